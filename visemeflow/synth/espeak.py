"""Speech with exact per-phoneme timings from libespeak-ng, through ctypes.

The synthesiser knows where every phoneme starts because it generates them: with
`espeakINITIALIZE_PHONEME_EVENTS` the synth callback receives, next to each block of samples, a list of
events, and every phoneme event carries the index (`sample`) of the first sample of that phoneme in the
utterance. A phoneme ends where the next event starts; the last one ends with the audio. The alignment
therefore tiles [0, duration] exactly and needs no forced aligner. docs/espeak.md has the details.

Labels:
- English (and any other non-Mandarin voice): espeak's IPA phoneme names
  (`espeakINITIALIZE_PHONEME_IPA`), mapped under the `ipa` inventory. The few names our IPA table has no
  row for are rewritten by `IPA_TRANSLATIONS` (r-coloured vowels such as `ɑːɹ` become `ɑː` + `ɹ`, ...).
- Mandarin (`cmn` voices): pinyin initials and finals with tone digits, charsiu style (`zh e4`), found by
  grouping espeak's phoneme events by the input syllable they came from (`text_position`).
- espeak's pauses become `sil`.

libespeak-ng keeps one global state that carries over from one synthesis to the next, so the library is
initialised once per process and every synthesis runs in a forked child that starts from that state
(see "Determinism" below): results are then a pure function of the arguments, and concurrent calls from
threads cannot interfere.
"""

from __future__ import annotations

import atexit
import bisect
import ctypes
import ctypes.util
import os
import pickle
import re
import selectors
import shutil
import signal
import tempfile
import threading
import time
import unicodedata
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import numpy as np

from visemeflow.phonetics.inventory import inventory_symbols, map_phone
from visemeflow.phonetics.types import PhoneInterval, WordInterval

INSTALL_HINT: Final = (
    "install it with `apt-get install espeak-ng` (Debian/Ubuntu), `dnf install espeak-ng`, "
    "or `brew install espeak-ng`; set VISEMEFLOW_ESPEAK_LIBRARY to the library's path if it lives elsewhere"
)
SILENCE_LABEL: Final = "sil"

# --- the C API (speak_lib.h of espeak-ng 1.49-1.52) -------------------------------------------

_AUDIO_OUTPUT_SYNCHRONOUS = 2
_INITIALIZE_PHONEME_EVENTS = 0x0001
_INITIALIZE_PHONEME_IPA = 0x0002
_INITIALIZE_DONT_EXIT = 0x8000
_EVENT_LIST_TERMINATED, _EVENT_WORD, _EVENT_PHONEME = 0, 1, 7
_POS_CHARACTER = 1
_CHARS_UTF8 = 0x01
_PHONEMES = 0x100  # allow [[...]] phoneme input inside the text (GRID's letter "a" needs it)
_RATE, _PITCH = 1, 3
_EE_OK = 0
RATE_RANGE: Final = (80, 450)  # words per minute espeak-ng accepts
PITCH_RANGE: Final = (0, 100)


class _EventId(ctypes.Union):
    _fields_ = [("number", ctypes.c_int), ("name", ctypes.c_char_p), ("string", ctypes.c_char * 8)]


class _Event(ctypes.Structure):
    _fields_ = [
        ("type", ctypes.c_int),
        ("unique_identifier", ctypes.c_uint),
        ("text_position", ctypes.c_int),  # 1-based, in characters of the input text
        ("length", ctypes.c_int),
        ("audio_position", ctypes.c_int),  # milliseconds
        ("sample", ctypes.c_int),  # sample index in the utterance: what we use, exact
        ("user_data", ctypes.c_void_p),
        ("id", _EventId),
    ]


_SYNTH_CALLBACK = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_short), ctypes.c_int, ctypes.POINTER(_Event))


class EspeakUnavailableError(RuntimeError):
    """libespeak-ng (or its data) cannot be loaded on this machine."""


class EspeakError(RuntimeError):
    """espeak-ng failed, or its output could not be turned into an alignment."""


class EspeakLabelError(ValueError):
    """A phoneme espeak-ng emitted that our inventories do not map (see IPA_TRANSLATIONS)."""


# --- labels ------------------------------------------------------------------------------------

# espeak IPA phoneme names that `visemeflow/phonetics/data/ipa.csv` has no row for, rewritten as one or more
# symbols that it has, with relative shares of the phoneme's duration (vowel 2 : consonant or offglide 1,
# the weights docs/phonemes.md uses for compound pinyin finals). The table itself is not edited: these
# are espeak's spellings, not new phonemes. Found by synthesising CMUdict with every English voice.
IPA_TRANSLATIONS: Final[dict[str, tuple[tuple[str, float], ...]]] = {
    # r-coloured vowels written as one phoneme by the American/Scottish voices: vowel, then the r
    "ɑːɹ": (("ɑː", 2), ("ɹ", 1)),   # start
    "ɔːɹ": (("ɔː", 2), ("ɹ", 1)),   # north
    "oːɹ": (("oː", 2), ("ɹ", 1)),   # force
    "ɛɹ": (("ɛ", 2), ("ɹ", 1)),     # square
    "ɪɹ": (("ɪ", 2), ("ɹ", 1)),     # near
    "ʊɹ": (("ʊ", 2), ("ɹ", 1)),     # cure
    "ʌɹ": (("ʌ", 2), ("ɹ", 1)),     # en-gb-scotland nurse
    "əɹ": (("ə", 2), ("ɹ", 1)),     # en-gb-scotland letter
    "ʉɹ": (("ʉ", 2), ("ɹ", 1)),     # en-gb-scotland cure
    "aɪɚ": (("aɪ", 2), ("ɚ", 1)),   # fire (en-us)
    # triphthong and syllabic l: two articulations, kept in order
    "aɪə": (("aɪ", 2), ("ə", 1)),   # fire
    "əl": (("ə", 1), ("l", 2)),     # syllabic l of bottle: mostly the l
    # centring diphthongs of en-029: nucleus then schwa, like the table's ɪə and ʊə rows
    "oə": (("o", 2), ("ə", 1)),
    "ɔə": (("ɔ", 2), ("ə", 1)),
    "ɑə": (("ɑ", 2), ("ə", 1)),
    # other spellings of symbols the table has
    "iə": (("ɪə", 1),),             # near (en, en-gb-x-rp): the table's ɪə
    "ᵻ": (("ɨ", 1),),               # reduced high vowel of roses (en-us)
    "əɪ": (("aɪ", 1),),             # price (en-us-nyc): a raised aɪ
    "ʌʉ": (("aʊ", 1),),             # mouth (en-gb-scotland)
    "æʊ": (("aʊ", 1),),             # mouth (en-gb-x-gbclan, en-gb-x-gbcwmd)
    "ʌʊ": (("əʊ", 1),),             # goat (en-gb-x-gbcwmd)
    "əu": (("əʊ", 1),),             # goat (en-gb-x-gbcwmd)
    "ei": (("eɪ", 1),),             # face (en-gb-x-gbcwmd)
    "eiei": (("eɪ", 1),),           # Wii (en-gb-x-gbcwmd)
    "aa": (("aː", 1),),             # bath (en-029): long front a
}

# Mandarin: espeak names of the glides it writes for the zero initials y and w (yi: j i, yu: ʲ y, wu: w u)
_MANDARIN_GLIDES: Final = frozenset({"j", "w", "ʲ", "ɥ"})
_PINYIN_INITIALS: Final = ("zh", "ch", "sh", "b", "p", "m", "f", "d", "t", "n", "l", "g", "k", "h",
                           "j", "q", "x", "r", "z", "c", "s", "y", "w")


@dataclass(frozen=True, slots=True)
class PinyinSyllable:
    """One toned pinyin syllable split charsiu style: `zhe4` is initial `zh`, final `e`, tone 4.

    `initial` is "" for a syllable without one (`er2`, `ai4`); the zero initials `y` and `w` are kept as
    initials, and `final` is then the full final they stand for (`ya` -> y + ia, `wei` -> w + ui). `spelling`
    is the standard spelling espeak reads (ü as u after j/q/x/y, as v after n/l).
    """

    initial: str
    final: str
    tone: int
    spelling: str

    @property
    def labels(self) -> tuple[str, ...]:
        final = f"{self.final}{self.tone}"
        return (self.initial, final) if self.initial else (final,)


def parse_pinyin(syllable: str) -> PinyinSyllable:
    """Split a toned pinyin syllable (`zhong1`, `lv4`, `nü3`, `jue2`) into initial, final and tone."""
    text = unicodedata.normalize("NFC", syllable.strip()).lower().replace("ü", "v").replace("u:", "v")
    m = re.fullmatch(r"([a-z]+)([1-5])", text)
    if m is None:
        raise ValueError(f"not a toned pinyin syllable: {syllable!r} (expected letters then a tone digit 1-5, e.g. 'zhong1')")
    body, tone = m.group(1), int(m.group(2))
    initial = next((i for i in _PINYIN_INITIALS if body.startswith(i) and len(body) > len(i)), "")
    rest = body[len(initial):]
    if initial == "y":
        final = rest if rest.startswith("i") else ("v" + rest[1:] if rest.startswith(("u", "v")) else "i" + rest)
    elif initial == "w":
        final = rest if rest == "u" else "u" + rest
    elif initial in ("j", "q", "x"):
        final = "v" + rest[1:] if rest.startswith(("u", "v")) else rest
    elif initial in ("z", "c", "s") and rest == "i":
        final = "ii"
    elif initial in ("zh", "ch", "sh", "r") and rest == "i":
        final = "iii"
    else:
        final = rest
    final = {"iou": "iu", "uei": "ui", "uen": "un"}.get(final, final)
    if initial in ("n", "l") and final == "ue":  # nüe/lüe written without the dots
        final = "ve"
    if final not in inventory_symbols("pinyin") or final in _PINYIN_INITIALS:
        raise ValueError(f"not a pinyin syllable: {syllable!r} (final {final!r} after initial {initial!r} is unknown)")
    if initial in ("j", "q", "x", "y"):
        spelling = body.replace("v", "u")
    elif initial in ("n", "l"):
        spelling = initial + rest.replace("u", "v") if final.startswith("v") else body
    else:
        spelling = body
    return PinyinSyllable(initial, final, tone, f"{spelling}{tone}")


# --- the result ----------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)  # eq on numpy arrays is ambiguous; compare fields explicitly
class SynthResult:
    """Audio and its exact phone and word alignment.

    `audio` is float32 in [-1, 1] (the int16 samples / 32768), mono. `phones` tile [0, duration] with no
    gaps or overlaps, pauses labelled `sil`; every label maps under `inventory` ("ipa" or "pinyin").
    """

    audio: np.ndarray
    sample_rate: int
    phones: tuple[PhoneInterval, ...]
    words: tuple[WordInterval, ...]
    inventory: str

    @property
    def duration_s(self) -> float:
        return len(self.audio) / self.sample_rate

    @property
    def pcm16(self) -> np.ndarray:
        """The samples as espeak produced them (int16), e.g. for writing a PCM_16 wav byte for byte."""
        return np.round(self.audio * 32768.0).astype(np.int16)


# --- the library ---------------------------------------------------------------------------------
#
# Determinism: libespeak-ng keeps state from one synthesis to the next (the pitch-flutter index, the
# wave phase, the automatic gain, libc rand() for breathy voices), so the same call made twice in one
# process gives slightly different samples and phone times. Re-initialising does not help (espeak-ng
# 1.51 hangs in espeak_Synth for some voices after espeak_Terminate + espeak_Initialize). So the library
# is initialised once in this process and never used for synthesis here: each synthesis runs in a
# forked child, which starts from that same pristine state, sends back samples and events through a
# pipe, and exits. This costs several ms per call (100-120 GRID sentences/s instead of 550 in-process);
# the same inputs then give the same samples, byte for byte, in any order and in any process. Where os.fork does not exist (Windows) synthesis runs in-process
# under the lock and is only deterministic for the first call.

_LOCK = threading.RLock()
_ENGINE: _Engine | None = None
_LOAD_ERROR: EspeakUnavailableError | None = None
_FORK: Final = hasattr(os, "fork")
_CHILD_TIMEOUT_S: Final = 300.0
_ERRORS: Final[dict[str, type[Exception]]] = {}  # filled below: exception names a child may send back


def _find_library() -> str:
    override = os.environ.get("VISEMEFLOW_ESPEAK_LIBRARY")
    if override:
        return override
    found = ctypes.util.find_library("espeak-ng")
    if found:
        return found
    for candidate in ("/usr/lib/x86_64-linux-gnu/libespeak-ng.so.1", "/usr/lib/aarch64-linux-gnu/libespeak-ng.so.1",
                      "/usr/lib/libespeak-ng.so.1", "/usr/lib64/libespeak-ng.so.1", "/usr/local/lib/libespeak-ng.so.1",
                      "/opt/homebrew/lib/libespeak-ng.dylib", "/usr/local/lib/libespeak-ng.dylib"):
        if Path(candidate).exists():
            return candidate
    return "libespeak-ng.so.1"  # let the dynamic loader try its own search path


def _load_library() -> ctypes.CDLL:
    path = _find_library()
    try:
        lib = ctypes.CDLL(path)
    except OSError as exc:
        raise EspeakUnavailableError(f"libespeak-ng could not be loaded ({path}): {exc}; {INSTALL_HINT}") from exc
    lib.espeak_Initialize.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_char_p, ctypes.c_int]
    lib.espeak_Initialize.restype = ctypes.c_int
    lib.espeak_SetSynthCallback.argtypes = [_SYNTH_CALLBACK]
    lib.espeak_SetSynthCallback.restype = None
    lib.espeak_SetVoiceByName.argtypes = [ctypes.c_char_p]
    lib.espeak_SetVoiceByName.restype = ctypes.c_int
    lib.espeak_SetParameter.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int]
    lib.espeak_SetParameter.restype = ctypes.c_int
    lib.espeak_Synth.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_uint, ctypes.c_int, ctypes.c_uint,
                                 ctypes.c_uint, ctypes.POINTER(ctypes.c_uint), ctypes.c_void_p]
    lib.espeak_Synth.restype = ctypes.c_int
    lib.espeak_Synchronize.restype = ctypes.c_int
    lib.espeak_Info.argtypes = [ctypes.POINTER(ctypes.c_char_p)]
    lib.espeak_Info.restype = ctypes.c_char_p
    if hasattr(lib, "espeak_ng_GetSampleRate"):   # espeak-ng >= 1.49: the rate of the voice in use
        lib.espeak_ng_GetSampleRate.argtypes = []
        lib.espeak_ng_GetSampleRate.restype = ctypes.c_int
    return lib


def _initialise(lib: ctypes.CDLL, data_dir: str | None) -> tuple[int, str]:
    """espeak_Initialize (synchronous output, phoneme events with IPA names): (sample rate, data folder)."""
    options = _INITIALIZE_PHONEME_EVENTS | _INITIALIZE_PHONEME_IPA | _INITIALIZE_DONT_EXIT
    rate = lib.espeak_Initialize(_AUDIO_OUTPUT_SYNCHRONOUS, 0, data_dir.encode() if data_dir else None, options)
    if rate <= 0:
        where = f" at {data_dir}" if data_dir else ""
        raise EspeakUnavailableError(f"libespeak-ng could not load its data (espeak-ng-data{where}); {INSTALL_HINT}")
    path = ctypes.c_char_p()
    lib.espeak_Info(ctypes.byref(path))
    return rate, (path.value or b"").decode()


def _call_isolated(fn):
    """fn() in a forked child (see the note above); its result or its exception comes back pickled."""
    if not _FORK:
        return fn()
    read_fd, write_fd = os.pipe()
    with warnings.catch_warnings():  # Python 3.12+ warns about fork in threaded processes; the child only runs C code
        warnings.simplefilter("ignore", DeprecationWarning)
        pid = os.fork()
    if pid == 0:  # the child: compute, send, and leave without running any of the parent's exit handlers
        status = 0
        try:
            os.close(read_fd)
            try:
                payload = pickle.dumps((True, fn()), protocol=pickle.HIGHEST_PROTOCOL)
            except BaseException as exc:  # noqa: BLE001 - every failure is reported to the parent
                payload = pickle.dumps((False, (type(exc).__name__, str(exc))))
            view = memoryview(payload)
            while view:
                view = view[os.write(write_fd, view):]
        except BaseException:  # noqa: BLE001
            status = 1
        finally:
            os._exit(status)
    os.close(write_fd)
    chunks: list[bytes] = []
    selector = selectors.DefaultSelector()  # epoll/kqueue: no FD_SETSIZE limit in processes with many sockets
    try:
        selector.register(read_fd, selectors.EVENT_READ)
        deadline = time.monotonic() + _CHILD_TIMEOUT_S
        while True:
            if not selector.select(max(0.0, deadline - time.monotonic())):
                os.kill(pid, signal.SIGKILL)
                raise EspeakError(f"espeak-ng did not finish within {_CHILD_TIMEOUT_S:.0f} s")
            chunk = os.read(read_fd, 1 << 20)
            if not chunk:
                break
            chunks.append(chunk)
    finally:
        selector.close()
        os.close(read_fd)
        _, status = os.waitpid(pid, 0)
    if not chunks:
        raise EspeakError(f"the espeak-ng worker process died without an answer (wait status {status})")
    ok, value = pickle.loads(b"".join(chunks))
    if not ok:
        name, message = value
        raise _ERRORS.get(name, EspeakError)(message if name in _ERRORS else f"{name}: {message}")
    return value


class _Engine:
    """The initialised library, its callback and the buffers the callback fills."""

    def __init__(self, lib: ctypes.CDLL, data_dir: str | None) -> None:
        self.lib = lib
        self.sample_rate, self.data_dir = _initialise(lib, data_dir)
        self.private = data_dir is not None
        self.callback = _SYNTH_CALLBACK(self._on_synth)  # kept referenced: the library calls it later
        lib.espeak_SetSynthCallback(self.callback)
        self.chunks: list[bytes] = []
        self.events: list[tuple[int, int, int, str]] = []  # (type, text_position, sample, phoneme name)
        self.error: BaseException | None = None
        self.voice: str | None = None  # only used in-process (no fork)

    def _on_synth(self, wav, numsamples, events) -> int:
        try:
            if numsamples > 0 and wav:
                self.chunks.append(ctypes.string_at(wav, numsamples * 2))
            i = 0
            while events:
                ev = events[i]
                if ev.type == _EVENT_LIST_TERMINATED:
                    break
                if ev.type in (_EVENT_WORD, _EVENT_PHONEME):
                    name = ev.id.string.decode("utf-8", "ignore") if ev.type == _EVENT_PHONEME else ""
                    self.events.append((ev.type, ev.text_position, ev.sample, name))
                i += 1
            return 0
        except BaseException as exc:  # noqa: BLE001 - must not cross the C boundary; 1 aborts synthesis
            self.error = exc
            return 1

    def output_rate(self) -> int:
        """The sample rate of what the voice in use produces: espeak's own 22050 Hz, or an MBROLA voice's database
        rate (16000 Hz for mb-us1..3 and mb-en1), which espeak_Initialize's return value does not tell."""
        if hasattr(self.lib, "espeak_ng_GetSampleRate"):
            rate = int(self.lib.espeak_ng_GetSampleRate())
            if rate > 0:
                return rate
        return self.sample_rate

    def run(self, voices: Sequence[str], text: str, rate_wpm: int, pitch: int) -> tuple[str, bytes, list, int]:
        """Synthesise with the first of `voices` espeak knows: (voice used, int16 bytes, events, sample rate)."""
        if _FORK:
            _LIBC_SRAND(1)  # breathy variants draw noise from libc rand(): same seed in every child
        for name in voices:
            if name == self.voice or self.lib.espeak_SetVoiceByName(name.encode()) == _EE_OK:
                self.voice = name
                break
        else:
            self.voice = None
            raise ValueError(f"unknown espeak-ng voice {voices[0]!r} (`espeak-ng --voices` lists them)")
        self.lib.espeak_SetParameter(_RATE, int(rate_wpm), 0)
        self.lib.espeak_SetParameter(_PITCH, int(pitch), 0)
        self.chunks, self.events, self.error = [], [], None
        data = text.encode("utf-8") + b"\0"
        status = self.lib.espeak_Synth(data, len(data), 0, _POS_CHARACTER, 0, _CHARS_UTF8 | _PHONEMES, None, None)
        self.lib.espeak_Synchronize()
        if self.error is not None:
            raise EspeakError(f"the synth callback failed: {self.error!r}")
        if status != _EE_OK:
            raise EspeakError(f"espeak_Synth failed with status {status} for {text!r}")
        return name, b"".join(self.chunks), self.events, self.output_rate()


def _libc_srand():
    try:
        return ctypes.CDLL(None).srand
    except (OSError, AttributeError):
        return lambda seed: None


_LIBC_SRAND = _libc_srand()


def _engine() -> _Engine:
    """The process-wide engine, initialised on first use (never used for synthesis in this process)."""
    global _ENGINE, _LOAD_ERROR
    with _LOCK:
        if _ENGINE is None:
            if _LOAD_ERROR is not None:
                raise _LOAD_ERROR
            try:
                lib = _load_library()
                data_dir = None
                if _FORK:  # find the data folder in a throwaway child, so this process initialises once, right
                    system_dir = _call_isolated(lambda: _initialise(lib, None)[1])
                    force = os.environ.get("VISEMEFLOW_ESPEAK_PRIVATE_PINYIN", "") not in ("", "0")
                    if force or not _has_voice_file(system_dir, PINYIN_VOICE):
                        data_dir = _private_data_dir(system_dir)
                _ENGINE = _Engine(lib, data_dir)
            except EspeakUnavailableError as exc:
                _LOAD_ERROR = exc
                raise
        return _ENGINE


def espeak_available() -> bool:
    """True when libespeak-ng and its data load on this machine."""
    try:
        _engine()
        return True
    except EspeakUnavailableError:
        return False


# --- voices --------------------------------------------------------------------------------------

PINYIN_VOICE: Final = "cmn-latn-pinyin"
_PRIVATE_PINYIN_VOICE: Final = "visemeflow-cmn-pinyin"
_MANDARIN_BASES: Final = frozenset({"cmn", "zh", "zh-cmn", PINYIN_VOICE, _PRIVATE_PINYIN_VOICE})
# Our own voice file, used only when the installed espeak-ng has no cmn-latn-pinyin voice (older than
# 1.50): the cmn voice without `dictrules 1`, the rule that makes cmn read Latin letters as English.
# Without it the cmn dictionary reads them as pinyin syllables with tone digits.
_PINYIN_VOICE_FILE: Final = """name visemeflow Mandarin (pinyin input)
language cmn
phonemes cmn
dictionary cmn
words 1
pitch 80 118
dict_min 100000
"""


def is_mandarin(voice: str, language: str | None = None) -> bool:
    """True when (voice, language) asks for Mandarin; language wins when given."""
    if language is not None:
        return language.strip().lower().startswith(("zh", "cmn"))
    return voice.partition("+")[0].strip().lower() in _MANDARIN_BASES


def _has_voice_file(data_dir: str, name: str) -> bool:
    root = Path(data_dir)
    return any(p.name.lower() == name.lower() for sub in ("lang", "voices") if (root / sub).is_dir()
               for p in (root / sub).rglob("*"))


def _private_data_dir(system_dir: str) -> str:
    """A data folder mirroring the system one (symlinks) plus our pinyin voice; system files stay untouched."""
    root = Path(tempfile.mkdtemp(prefix="visemeflow-espeak-"))
    atexit.register(shutil.rmtree, root, True)
    system = Path(system_dir)
    for entry in system.iterdir():
        if entry.name != "voices":
            (root / entry.name).symlink_to(entry)
    (root / "voices").mkdir()
    if (system / "voices").is_dir():
        for entry in (system / "voices").iterdir():
            (root / "voices" / entry.name).symlink_to(entry)
    (root / "voices" / _PRIVATE_PINYIN_VOICE).write_text(_PINYIN_VOICE_FILE, encoding="utf-8")
    return str(root)


def _voice_candidates(engine: _Engine, voice: str, mandarin: bool) -> list[str]:
    """espeak names to try for `voice` (base plus optional `+variant`); ValueError when it cannot work."""
    base, plus, variant = voice.strip().partition("+")
    if base.lower().startswith(("mb-", "mb/")):
        raise ValueError(f"voice {voice!r} is an MBROLA voice: espeak-ng's phoneme events do not follow MBROLA's "
                         "timing (measured with mb-us2: each label lags the audio by about one phone, the closure of "
                         "a b sits under the vowel before it), so its alignments would be wrong; use an espeak-ng "
                         "voice (`espeak-ng --voices`)")
    if plus and not (variant and (Path(engine.data_dir) / "voices" / "!v" / variant).is_file()):
        raise ValueError(f"unknown espeak-ng voice variant {variant!r} in {voice!r}; see {engine.data_dir}/voices/!v")
    suffix = f"+{variant}" if plus else ""
    if mandarin:
        if base.lower() not in _MANDARIN_BASES:
            raise ValueError(f"voice {voice!r} is not a Mandarin voice; use 'cmn' or 'cmn+<variant>'")
        return [(_PRIVATE_PINYIN_VOICE if engine.private else PINYIN_VOICE) + suffix]
    if base.lower() in _MANDARIN_BASES:
        raise ValueError(f"voice {voice!r} is Mandarin; pass language='cmn' (or leave language unset)")
    return [base + suffix]


def _synth_raw(voice: str, mandarin: bool, text: str, rate_wpm: int, pitch: int) -> tuple[str, np.ndarray, list, int]:
    """(voice used, int16 samples, events, sample rate) of one synthesis, isolated in a child process."""
    engine = _engine()
    candidates = _voice_candidates(engine, voice, mandarin)
    if _FORK:
        name, pcm, events, rate = _call_isolated(lambda: engine.run(candidates, text, rate_wpm, pitch))
    else:
        with _LOCK:
            name, pcm, events, rate = engine.run(candidates, text, rate_wpm, pitch)
    return name, np.frombuffer(pcm, dtype=np.int16).copy(), events, rate


# --- synthesis -----------------------------------------------------------------------------------


def synthesize(text: str, voice: str = "en-us", rate_wpm: int = 160, pitch: int = 50,
               language: str | None = None, word_labels: Sequence[str] | None = None) -> SynthResult:
    """Speak `text` with espeak-ng and return the audio with its exact phone and word alignment.

    `voice` is an espeak-ng voice with an optional variant (`en-us`, `en-gb-x-rp`, `en+f3`, `cmn+m3`).
    `language` None takes it from the voice (`cmn...` is Mandarin, anything else English/IPA). Mandarin
    `text` is toned pinyin syllables separated by spaces (`ni3 hao3`). `word_labels`, one per
    whitespace-separated token of `text`, name the words tier instead of the text itself (useful when a
    token is espeak phoneme input such as `[['eI]]`). The same arguments give the same result, byte for byte.
    """
    if not RATE_RANGE[0] <= rate_wpm <= RATE_RANGE[1]:
        raise ValueError(f"rate_wpm must be within {RATE_RANGE}, got {rate_wpm}")
    if not PITCH_RANGE[0] <= pitch <= PITCH_RANGE[1]:
        raise ValueError(f"pitch must be within {PITCH_RANGE}, got {pitch}")
    mandarin = is_mandarin(voice, language)
    tokens = [(m.start() + 1, m.group()) for m in re.finditer(r"\S+", text)]  # 1-based, like text_position
    if not tokens:
        raise ValueError("nothing to synthesise: the text is empty")
    if word_labels is not None and len(word_labels) != len(tokens):
        raise ValueError(f"{len(word_labels)} word labels for {len(tokens)} tokens of {text!r}")
    syllables: list[PinyinSyllable] = []
    if mandarin:
        syllables = [parse_pinyin(tok) for _, tok in tokens]
        labels = list(word_labels) if word_labels is not None else [tok for _, tok in tokens]
        text = " ".join(s.spelling for s in syllables)
        tokens, pos = [], 1
        for s in syllables:
            tokens.append((pos, s.spelling))
            pos += len(s.spelling) + 1
    else:
        labels = list(word_labels) if word_labels is not None else [_clean_word(tok) for _, tok in tokens]
    voice_name, pcm, events, sample_rate = _synth_raw(voice, mandarin, text, rate_wpm, pitch)
    if pcm.size == 0:
        raise EspeakError(f"espeak-ng produced no audio for {text!r} with voice {voice_name!r}")
    segments = _phone_segments(events, pcm.size)
    token_starts = [p for p, _ in tokens]
    if mandarin:
        phones, words = _label_mandarin(segments, token_starts, syllables, labels, sample_rate)
        inventory = "pinyin"
    else:
        phones, words = _label_ipa(segments, events, token_starts, labels, sample_rate, voice_name)
        inventory = "ipa"
    audio = pcm.astype(np.float32) / np.float32(32768.0)
    return SynthResult(audio, sample_rate, phones, words, inventory)


def _clean_word(token: str) -> str:
    return token.strip(".,;:!?\"'()[]") or token


def _phone_segments(events, n_samples: int) -> list[tuple[int, int, str, int]]:
    """(start, end, espeak name or '' for a pause, text_position), tiling [0, n_samples) in samples."""
    starts: list[tuple[int, str, int]] = []
    last = 0
    for kind, text_pos, sample, name in events:
        if kind != _EVENT_PHONEME:
            continue
        last = min(max(sample, last), n_samples)  # never backwards, never past the audio
        starts.append((last, unicodedata.normalize("NFC", name.strip()), text_pos))
    if not starts or starts[0][0] > 0:
        starts.insert(0, (0, "", 0))
    out: list[tuple[int, int, str, int]] = []
    for i, (start, name, text_pos) in enumerate(starts):
        end = starts[i + 1][0] if i + 1 < len(starts) else n_samples
        if end <= start:
            continue  # zero-length event (e.g. two pause markers at one sample)
        if name == "" and out and out[-1][2] == "":
            out[-1] = (out[-1][0], end, "", out[-1][3])  # one sil for consecutive pauses
        else:
            out.append((start, end, name, text_pos))
    return out


def _split_samples(start: int, end: int, weights: Sequence[float]) -> list[tuple[int, int]]:
    total, acc, cuts = float(sum(weights)), 0.0, [start]
    for w in weights[:-1]:
        acc += w
        cuts.append(max(cuts[-1], min(end, start + int(round((end - start) * acc / total)))))
    cuts.append(end)
    return [(a, b) for a, b in zip(cuts[:-1], cuts[1:])]


def _word_of(text_pos: int, word_starts: Sequence[int]) -> int | None:
    i = bisect.bisect_right(word_starts, text_pos) - 1
    return i if i >= 0 else None


def _finish(pieces: list[tuple[int, int, str, int | None]], word_names: Mapping[int, str] | Sequence[str],
            sample_rate: int) -> tuple[tuple[PhoneInterval, ...], tuple[WordInterval, ...]]:
    """PhoneIntervals and WordIntervals from (start, end, label, word group) pieces in samples."""
    spans: dict[int, list[int]] = {}
    for a, b, _, group in pieces:
        if group is not None:
            span = spans.setdefault(group, [a, b])
            span[0], span[1] = min(span[0], a), max(span[1], b)
    order = sorted(spans, key=lambda g: spans[g][0])
    index = {g: i for i, g in enumerate(order)}
    words = tuple(WordInterval(word_names[g], spans[g][0] / sample_rate, spans[g][1] / sample_rate) for g in order)
    phones = tuple(
        PhoneInterval(label, a / sample_rate, b / sample_rate,
                      None if group is None else word_names[group], None if group is None else index[group])
        for a, b, label, group in pieces if b > a
    )
    return phones, words


def _label_ipa(segments, events, token_starts, labels, sample_rate, voice_name):
    """English: IPA names (translated where our table lacks them); words from espeak's word events.

    A word is the run of tokens from one espeak word event to the next, so a word espeak reads as one
    ("at a" in GRID is spoken as one word) is one interval named by both tokens.
    """
    groups = sorted({t for kind, pos, _, _ in events if kind == _EVENT_WORD
                     for t in [_word_of(pos, token_starts)] if t is not None})
    names = {g: " ".join(labels[g:(groups[i + 1] if i + 1 < len(groups) else len(labels))])
             for i, g in enumerate(groups)}
    pieces: list[tuple[int, int, str, int | None]] = []
    for a, b, name, text_pos in segments:
        if name == "":
            pieces.append((a, b, SILENCE_LABEL, None))
            continue
        token = _word_of(text_pos, token_starts)
        k = None if token is None else bisect.bisect_right(groups, token) - 1
        group = groups[k] if k is not None and k >= 0 else None
        parts = IPA_TRANSLATIONS.get(name, ((name, 1.0),))
        for (label, _), (pa, pb) in zip(parts, _split_samples(a, b, [w for _, w in parts])):
            try:
                map_phone(label, "ipa")
            except ValueError as exc:
                raise EspeakLabelError(
                    f"espeak-ng voice {voice_name!r} emitted the phoneme {name!r}, which the ipa table does not map; "
                    "add it to IPA_TRANSLATIONS in visemeflow/synth/espeak.py (see docs/espeak.md)"
                ) from exc
            pieces.append((pa, pb, label, group))
    return _finish(pieces, names, sample_rate)


def _label_mandarin(segments, token_starts, syllables, labels, sample_rate):
    """Mandarin: each syllable's espeak phonemes become its pinyin initial (the first one) and final (the rest)."""
    by_syllable: dict[int, list[tuple[int, int, str]]] = {}
    pieces: list[tuple[int, int, str, int | None]] = []
    for a, b, name, text_pos in segments:
        if name == "":
            pieces.append((a, b, SILENCE_LABEL, None))
            continue
        j = _word_of(text_pos, token_starts)
        if j is None:
            raise EspeakError(f"espeak-ng phoneme {name!r} at sample {a} belongs to no syllable")
        by_syllable.setdefault(j, []).append((a, b, name))
    for j, syl in enumerate(syllables):
        segs = by_syllable.get(j)
        if not segs:
            raise EspeakError(f"espeak-ng produced no phonemes for the syllable {labels[j]!r}")
        start, end = segs[0][0], segs[-1][1]
        final = f"{syl.final}{syl.tone}"
        if syl.initial and (syl.initial not in ("y", "w") or segs[0][2] in _MANDARIN_GLIDES):
            if len(segs) >= 2:
                cut = segs[1][0]
            else:  # one event for the whole syllable: give the initial a third of it
                cut = _split_samples(start, end, [1, 2])[0][1]
            parts = [(start, cut, syl.initial), (cut, end, final)]
        else:  # no initial, or a y/w syllable whose glide espeak folded into the vowel (yong: yu ŋ)
            parts = [(start, end, final)]
        # a pause inside the syllable's span stays a pause: cut the syllable's parts around it
        pauses = [(a, b) for a, b, lab, g in pieces if g is None and start < b and a < end]
        for pa, pb, label in parts:
            for cut_a, cut_b in _subtract(pa, pb, pauses):
                pieces.append((cut_a, cut_b, label, j))
    pieces.sort(key=lambda p: p[0])
    return _finish(pieces, labels, sample_rate)


def _subtract(a: int, b: int, holes: Sequence[tuple[int, int]]) -> list[tuple[int, int]]:
    out, cur = [], a
    for ha, hb in sorted(holes):
        if hb <= cur or ha >= b:
            continue
        if ha > cur:
            out.append((cur, ha))
        cur = max(cur, hb)
    if cur < b:
        out.append((cur, b))
    return out


_ERRORS.update({cls.__name__: cls for cls in (ValueError, EspeakError, EspeakLabelError, EspeakUnavailableError)})
