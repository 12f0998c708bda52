"""`esx` of bench/encoders.py: espeak-ng voices speaking Dutch and Czech (and, on request, German and Polish),
with espeak's own exact phone timings as the alignment (`visemeflow.synth.espeak.synthesize`, the same engine,
voices, rates and TextGrid writer as `visemeflow espeak-corpus`).

Sentences: random sequences of 4-8 common words of the language (`WORDS`, written here from general knowledge of
the languages -- not from the Fish Fillets NG dialogs that bench/thirdlang.py judges), every second sentence forced
to hold at least two words with a b, p or m, so that most utterances close the lips. Voices: the language's
espeak-ng voice and its variants (`VARIANTS`), rates 130/160/200 wpm (`sentences.DEFAULT_RATES`), spread over the
utterances by `sentences.speaker_plan`.

Labels: espeak's IPA names under the `ipa` inventory. The names that `visemeflow/phonetics/data/ipa.csv` has no
row for are rewritten by `EXTRA_TRANSLATIONS` (long vowels and diphthongs to their vowels, the Czech fricative
trill to r, syllabic consonants to the consonant, ...), added to `espeak.IPA_TRANSLATIONS` only for the duration of
the synthesis in this process (`extra_translations`); any other unknown name stays an error (EspeakLabelError).
The corpus is written once under `bench/out/encoders/corpus-esx-<langs>-<n>-s<seed>/` (ignored by git).
"""

from __future__ import annotations

import contextlib
import itertools
import random
from pathlib import Path

import soundfile as sf

from visemeflow.synth import espeak as _espeak
from visemeflow.synth.sentences import DEFAULT_RATES, speaker_name, speaker_plan, textgrid_of

OUT = Path(__file__).resolve().parent / "out" / "encoders"

WORDS = {
    "nl": """
de het een en van in is dat op te zijn met voor niet aan er maar om ook als dan bij nog uit wat naar kan
door over wel zo al hij zij wij ik je we ze mijn zijn ons hun haar man vrouw kind huis water boom bloem
brood boter melk appel peer boek pen papier tafel stoel deur raam muur dak bed kamer keuken bad spiegel
mooi groot klein oud nieuw warm koud blauw paars bruin wit zwart rood groen geel snel langzaam
maken lopen praten spelen slapen eten drinken kopen betalen bellen brengen blijven beginnen openen
moeder vader broer zus oma opa baby mama papa meneer mevrouw buurman vriend
morgen middag maand jaar week dag avond nacht moment minuut uur tijd
bus boot trein fiets auto vliegtuig brug baan weg plein markt park bos berg strand zee meer
vis soep pasta patat koffie thee bier wijn taart pizza aardappel tomaat bonen
misschien samen bijna meestal altijd nooit vaak soms binnen buiten boven beneden hier daar
praten bouwen blazen poetsen pakken plukken breken missen meten mogen moeten
""",
    "cs": """
a v se na je že to s z do o k jak ale by já ty on ona my vy oni tak jen už ještě když pak kde
být mít moci chtít muset dělat jít přijít vidět slyšet mluvit psát pít spát platit prosit bydlet
máma táta bratr babička dědeček přítel pán paní muž žena dítě pes kočka myš ryba pták
dům byt okno stůl postel pokoj mapa papír pero kniha obraz zeď podlaha most město park pole les
moře břeh potok voda mléko pivo polévka chléb máslo sýr maso brambory jablko hruška bonbon
malý velký pěkný modrý bílý černý zelený žlutý starý nový první poslední dobrý špatný rychlý pomalý
mám máme můžeme budeme bude byl byla bylo pojď pomoc prosím proto potom pořád pozor mezi před po
ráno poledne večer noc den týden měsíc rok doba moment minuta hodina teď brzy později nikdy vždy
auto vlak autobus loď letadlo kolo cesta ulice náměstí obchod banka pošta škola nemocnice
krásný tam tady dnes zítra včera doma venku nahoře dole spolu hodně málo možná
""",
    "de": """
der die das und ist ein eine nicht mit von zu auf für im mir mich wir bitte danke aber immer manchmal
Mann Frau Kind Haus Baum Blume Brot Butter Milch Apfel Buch Papier Tisch Bett Zimmer Mutter Vater
Bruder Mittag Morgen Abend Monat Jahr Woche Bus Boot Bahn Brücke Berg Park Meer Wasser Bier Suppe
machen bauen bringen bleiben beginnen spielen kaufen bezahlen gehen kommen sprechen schlafen
groß klein blau braun weiß schwarz rot grün schön alt neu warm kalt schnell langsam oben unten hier
""",
    "pl": """
i w na z to się nie jest że do po jak ale tak co mi my mam mamy może bardzo proszę potem przed pod
mama tata brat babcia dziadek pan pani mąż żona dziecko pies kot mysz ryba ptak dom okno stół
pokój mapa papier pióro książka obraz most miasto park pole las morze woda mleko piwo chleb masło
mięso jabłko biały czarny zielony mały duży piękny dobry stary nowy pierwszy ostatni szybko powoli
być mieć móc pić płacić pisać pracować budować mówić spać pomagać rano wieczór miesiąc tydzień
""",
}
"""Common words of each language (a few hundred for nl and cs), many with b/p/m."""

VARIANTS = ("", "+f3", "+m3", "+f4", "+m2", "+f2")
"""espeak-ng voice variants spoken by each language's voice (`voices/!v`); "" is the language's own voice."""

EXTRA_TRANSLATIONS: dict[str, tuple[tuple[str, float], ...]] = {
    # long vowels: their vowel
    "aː": (("a", 1),), "eː": (("e", 1),), "iː": (("iː", 1),), "oː": (("o", 1),), "uː": (("uː", 1),),
    "ɛː": (("ɛ", 1),), "ɔː": (("ɔ", 1),), "øː": (("ø", 1),), "yː": (("y", 1),), "ɪː": (("ɪ", 1),),
    "ʏː": (("ʏ", 1),), "ɑː": (("ɑː", 1),), "ɐː": (("ɐ", 1),), "œː": (("œ", 1),),
    # diphthongs: nucleus then offglide (vowel 2 : glide 1, as espeak.IPA_TRANSLATIONS)
    "ɛɪ": (("ɛ", 2), ("ɪ", 1)), "œy": (("œ", 2), ("y", 1)), "ʌu": (("ʌ", 2), ("u", 1)),
    "ɑu": (("ɑ", 2), ("u", 1)), "aʊ": (("aʊ", 1),), "eʊ": (("e", 2), ("ʊ", 1)), "oʊ": (("oʊ", 1),),
    "aɪ": (("aɪ", 1),), "ɔø": (("ɔ", 2), ("ø", 1)), "ɔʏ": (("ɔʏ", 1),), "ou": (("o", 2), ("u", 1)),
    "au": (("a", 2), ("u", 1)), "eu": (("e", 2), ("u", 1)), "ɛu": (("ɛ", 2), ("u", 1)),
    "ai": (("a", 2), ("i", 1)), "ei": (("eɪ", 1),), "oi": (("o", 2), ("i", 1)), "ui": (("u", 2), ("i", 1)),
    "ɑi": (("ɑ", 2), ("i", 1)), "ɔi": (("ɔ", 2), ("i", 1)), "iu": (("i", 2), ("u", 1)), "ʏu": (("ʏ", 2), ("u", 1)),
    "oːi": (("o", 2), ("i", 1)), "aːi": (("a", 2), ("i", 1)), "eːu": (("e", 2), ("u", 1)),
    "iːu": (("iː", 2), ("u", 1)), "ɛi": (("ɛ", 2), ("i", 1)),
    # consonants spelled otherwise
    "ɡ": (("g", 1),), "r̝": (("r", 1),), "r̝̊": (("r", 1),), "ɦ": (("ɦ", 1),), "l̩": (("l", 1),), "r̩": (("r", 1),),
    "m̩": (("m", 1),), "n̩": (("n", 1),), "ɲ": (("ɲ", 1),), "tʃ": (("tʃ", 1),), "dʒ": (("dʒ", 1),),
    "ts": (("ts", 1),), "dz": (("dz", 1),), "tɕ": (("tɕ", 1),), "dʑ": (("dʑ", 1),), "ʂ": (("ʂ", 1),),
    "ʐ": (("ʐ", 1),), "tʂ": (("tʂ", 1),), "dʐ": (("dʐ", 1),), "ʋ": (("ʋ", 1),), "ɣ": (("ɣ", 1),),
    "pf": (("pf", 1),), "ɛ̃": (("ɛ", 1),), "ɔ̃": (("ɔ", 1),), "w̃": (("w", 1),), "j̃": (("j", 1),),
    "ɐ̯": (("ɐ", 1),), "ʊ̯": (("ʊ", 1),), "ɪ̯": (("ɪ", 1),), "i̯": (("i", 1),), "u̯": (("u", 1),),
    "ɾ": (("ɾ", 1),), "ʁ": (("ʁ", 1),), "ɵ": (("ɵ", 1),), "ɔː̃": (("ɔ", 1),),
}


@contextlib.contextmanager
def extra_translations():
    """espeak.IPA_TRANSLATIONS with EXTRA_TRANSLATIONS added (the package's own entries win), restored after."""
    saved = _espeak.IPA_TRANSLATIONS
    _espeak.IPA_TRANSLATIONS = {**EXTRA_TRANSLATIONS, **saved}
    try:
        yield
    finally:
        _espeak.IPA_TRANSLATIONS = saved


def has_bilabial(word: str) -> bool:
    return any(c in word.lower() for c in "bpm")


def sentences(lang: str, n: int, seed: int, min_words: int = 4, max_words: int = 8) -> list[tuple[str, ...]]:
    """`n` random word sequences of `lang`; every second one holds at least two words with b/p/m."""
    words = list(dict.fromkeys(WORDS[lang].split()))
    labial = [w for w in words if has_bilabial(w)]
    rng = random.Random(f"{lang}-{seed}")
    out = []
    for i in range(n):
        count = rng.randint(min_words, max_words)
        chosen = [rng.choice(words) for _ in range(count)]
        if i % 2 == 0:
            for k in rng.sample(range(count), 2):
                chosen[k] = rng.choice(labial)
        out.append(tuple(chosen))
    return out


def write_corpus(root: Path, langs: tuple[str, ...], n: int, seed: int = 0) -> list[str]:
    """`root/<speaker>/<lang><i>.wav` + `.TextGrid` for `n` utterances per language; returns their ids."""
    ids = []
    with extra_translations():
        for lang in langs:
            plan = itertools.cycle(speaker_plan([lang + v for v in VARIANTS], DEFAULT_RATES))
            for i, words in enumerate(sentences(lang, n, seed)):
                voice, rate = next(plan)
                result = _espeak.synthesize(" ".join(words), voice, rate, 50, lang)
                folder = root / speaker_name(voice, rate)
                folder.mkdir(parents=True, exist_ok=True)
                stem = folder / f"{lang}{i:05d}"
                sf.write(stem.with_suffix(".wav"), result.pcm16, result.sample_rate, subtype="PCM_16", format="WAV")
                stem.with_suffix(".TextGrid").write_text(textgrid_of(result), encoding="utf-8")
                ids.append(f"{folder.name}/{stem.name}")
    return ids


def ensure_corpus(langs: tuple[str, ...] = ("nl", "cs"), n: int = 200, seed: int = 0) -> Path:
    from learning_data import written_once

    return written_once(OUT / f"corpus-esx-{'-'.join(langs)}-{n}-s{seed}", f"espeak {'/'.join(langs)} corpus",
                        lambda root: write_corpus(root, langs, n, seed))
