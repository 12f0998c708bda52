"""Find the utterances of a corpus: a folder `<speaker>/<name>.wav` + alignment, or a manifest CSV.

Utterance ids are `<speaker folder>/<file stem>` (or the manifest's `utterance_id`), NFC-normalised, in any
script (`Speaker One/take 1`, `张三/一`; rules in `schemas.ids`). Names that differ only in their Unicode form
(`café` composed and decomposed) give one id: all of them are rejects (IdCollision) naming every file, never two
utterances under one id. Nothing outside the corpus folder is read:
a manifest path that leaves its folder and a symlink that points outside the corpus are rejects naming the file.
A manifest's `split` (train or val) and `language` (a tag: `en`, `zh-CN`) are checked: another value is a reject
naming the manifest line.

Alignments: a file next to the audio with the same stem, `.TextGrid` (Praat, any variant, binary too), `.xra`
(SPPAS), `.lab` (HTK label file) or `.align` (word spans, GRID), or an entry of an HTK master label file (`*.mlf`)
in the speaker's folder or in the corpus folder. When an utterance has several, the first of this order wins:
TextGrid, xra, lab, align, an MLF in its speaker folder, an MLF in the corpus folder (MLFs of one folder in name
order); a file made for one utterance says more about it than a corpus-wide list, and phones beat word spans. A
`.lab` that does not start with a `start end label` line is a transcript (as MFA's `.lab` files are), not an
alignment, and so is a `.txt` with the audio's stem: an utterance with a transcript and no alignment gets the
transcript (`alignment_format` "transcript"), which ingest forced-aligns in English
(`visemeflow.phonetics.forcealign`; `IngestConfig.align_transcripts`). An `.align` is read by what it holds: an HTK MLF (P2FA's output), a TextGrid, else
word spans. A label file beside its audio with its stem (`NAME.align` holding an MLF, `NAME.mlf`) belongs to that
audio whatever its one entry names (P2FA names a temporary file, `"/tmp/tmpab12/myl_26185.rec"`).

`check_corpus` says in one line, cheaply and before any flow, why a path is no corpus: an alignment file, a
binary or headerless file given as the manifest, a flat folder of wavs without speaker folders.

One audio or video file (`pipeline clip.mp4`, `ingest take.wav`) is a corpus of one utterance: the file with what a
corpus folder pairs with it beside it (its alignment or transcript, landmarks, the audio beside a video), id
`<its folder's name>/<its stem>` (`SINGLE_FILE_SPEAKER` where the folder's name is no valid speaker). The named file
is that utterance's audio (or video) even where another of its kind with its stem lies beside it.

An utterance with a video (and no alignment) is kept without one: its `alignment_path` is "" and its
`alignment_format` is `schemas.tables.NO_ALIGNMENT`; its audio is the video's audio track when no audio file is
beside it. Audio without video and without an alignment is a reject (MissingAlignment).
"""

import csv
import re
import unicodedata
from dataclasses import dataclass, field, replace
from pathlib import Path

from visemeflow.hashing import files_hash, stable_hash
from visemeflow.location import is_url, mirror, remote_root
from visemeflow.ingest.audio import AUDIO_EXTS, VIDEO_EXTS
from visemeflow.phonetics.htk import (
    MLF_HEADER,
    LabelFileError,
    MlfEntry,
    MlfIndex,
    load_mlf,
    looks_like_htk_label,
)
from visemeflow.schemas import InvalidIdError, make_utterance_id, normalize_utterance_id
from visemeflow.schemas.tables import NO_ALIGNMENT

ALIGNMENT_EXTS = (".TextGrid", ".textgrid", ".xra", ".lab", ".align")
"""Alignment files of one utterance, highest priority first."""
MLF_EXT = ".mlf"
ALIGNMENT_FORMATS = {".align": "word_align", ".xra": "xra", ".lab": "htk", ".mlf": "mlf"}
TRANSCRIPT_EXT = ".txt"
"""A transcript beside its audio (as a `.lab` without times): words, no timings."""
TRANSCRIPT_FORMAT = "transcript"
"""`alignment_format` by file suffix (lower case); any other suffix is a Praat TextGrid ("textgrid")."""
LANDMARK_SUFFIXES = (".landmarks.csv", ".landmarks.parquet", ".mediapipe478.csv", ".openface.csv")
MANIFEST_COLUMNS = ("utterance_id", "audio", "alignment", "video", "landmarks", "language", "split")
SPLITS = ("train", "val")
"""The splits a manifest may give (any case): training takes every utterance not in `val`, so another name (`test`,
`dev`) would silently be trained on."""
LANGUAGE_TAG = re.compile(r"[A-Za-z]{2,3}(?:[-_][A-Za-z0-9]{1,8}){0,4}")
"""A language tag as manifests write them: an ISO 639 code (`en`, `cmn`) with optional BCP 47 subtags (`zh-CN`,
`zh-Hans-CN`, `en_US`)."""


@dataclass(frozen=True, slots=True)
class CorpusEntry:
    """One utterance's input files (absolute paths) and what the manifest says about it."""

    utterance_id: str
    audio_path: str
    alignment_path: str
    video_path: str | None = None
    landmark_path: str | None = None
    language: str | None = None
    split: str | None = None
    content_hash: str = ""
    alignment_key: str | None = None
    """For an alignment file holding several utterances (an HTK MLF): `folder/stem`, what its entry is found by."""
    alignment_kind: str | None = None
    """The format found in the file's content where its suffix does not say it: an `.align` holding an HTK MLF
    (P2FA writes one) or a TextGrid; None: by the suffix."""

    @property
    def speaker(self) -> str:
        return self.utterance_id.split("/")[0]

    @property
    def alignment_format(self) -> str:
        """`textgrid`, `xra`, `htk`, `mlf` or `word_align` by the file's suffix, `transcript` for words without
        times; `NO_ALIGNMENT` without one."""
        if not self.alignment_path:
            return NO_ALIGNMENT
        if self.alignment_kind is not None:
            return self.alignment_kind
        return ALIGNMENT_FORMATS.get(Path(self.alignment_path).suffix.lower(), "textgrid")

    @property
    def has_alignment(self) -> bool:
        return bool(self.alignment_path)


@dataclass(frozen=True, slots=True)
class DiscoveryReject:
    utterance_id: str | None
    error_type: str
    message: str
    path: str


@dataclass(frozen=True, slots=True)
class Discovery:
    entries: tuple[CorpusEntry, ...]
    rejects: tuple[DiscoveryReject, ...] = field(default_factory=tuple)
    notes: tuple[str, ...] = ()
    """What was chosen where a folder offered more than one file of a kind for one utterance (`take.wav` beside
    `take.flac`): one line each, naming the file used and the ones left out."""


CORPUS_LAYOUT = ("a corpus is a folder of speaker folders, CORPUS/<speaker>/<name>.wav (or .flac, .mp3, ..., or a "
                 "video) with its alignment beside it (<name>.TextGrid, .lab, .align or .xra), one such audio or "
                 "video file, or a manifest CSV with columns utterance_id, audio, alignment")
"""What a corpus is, in the one line that every wrong-layout message ends with."""
SINGLE_FILE_SPEAKER = "speaker"
"""The speaker of a one-file corpus whose folder's name is no valid speaker (`/clip.mp4`, `.cache/take.wav`)."""
_SNIFF_BYTES = 8192


class CorpusError(ValueError):
    """A corpus path that is no corpus (a single audio file, a folder of the wrong layout, a binary file given as
    the manifest): one line saying what was found and what a corpus is."""


def check_corpus(path: Path | str) -> str | None:
    """Why `path` (which exists) cannot be a corpus, in one line, or None when it may be one. A URL
    (`s3://bucket/corpus`) is checked on its local mirror (`remote_corpus`), the message naming the URL.

    Cheap (a directory listing, the first bytes of a file), so that a command can call it before any flow starts:
    an alignment file, a file that is not a CSV, a manifest without an `utterance_id` column, or a folder holding no
    speaker folder with audio, video or alignment files (a flat folder of wavs). One audio or video file (by its
    extension, any case) is a corpus of one utterance (None), and so is a path that does not exist, left to the
    caller."""
    if is_url(path):
        try:
            remote = remote_corpus(str(path))
        except (OSError, ValueError) as exc:
            return f"cannot read the corpus {path}: {exc}"
        problem = check_corpus(remote.local)
        return None if problem is None else remote.to_url(problem)
    path = Path(path)
    if path.is_file() and _media_ext(path.name) is not None:
        return None  # one audio or video file: a corpus of one utterance, read by discovery
    if path.is_file():
        return _check_manifest_file(path)
    if not path.is_dir():
        return None
    if (path / "manifest.csv").is_file():
        return _check_manifest_file(path / "manifest.csv")
    known = AUDIO_EXTS + VIDEO_EXTS + ALIGNMENT_EXTS + (MLF_EXT,)
    try:
        children = [p for p in path.iterdir() if not p.name.startswith(".")]
    except OSError as exc:
        return f"cannot read the corpus folder {path}: {exc.strerror}"
    for child in children:
        if child.is_dir() and any(f.name.lower().endswith(known) for f in _files(child)):
            return None  # a speaker folder with input files: discovery says what each file lacks
    loose = sorted(p.name for p in children if p.is_file() and p.name.lower().endswith(known))
    folders = sum(p.is_dir() for p in children)
    if loose:
        shown = ", ".join(loose[:3]) + (f" and {len(loose) - 3} more" if len(loose) > 3 else "")
        return (f"no utterances in {path}: {len(loose)} audio/video/alignment file{'s' if len(loose) != 1 else ''} "
                f"({shown}) lie directly in it, not in a speaker folder; move them into one folder per speaker "
                f"({path / 'speaker1'}/...); {CORPUS_LAYOUT}")
    found = f"{folders} folder{'s' if folders != 1 else ''} without audio, video or alignment files" if folders \
        else "nothing" if not children else f"{len(children)} file{'s' if len(children) != 1 else ''} of other kinds"
    return f"no utterances in {path}: found {found}; {CORPUS_LAYOUT}"


def _files(folder: Path):
    """The files of a folder, lazily (a speaker folder may hold thousands; the first input file is enough)."""
    try:
        yield from (p for p in folder.iterdir() if p.is_file())
    except OSError:
        return


def _check_manifest_file(path: Path) -> str | None:
    """Why the file `path` is not a manifest CSV (an alignment file, binary, no utterance_id column), or None."""
    lower = path.name.lower()
    if lower.endswith(ALIGNMENT_EXTS + (MLF_EXT,)):
        return f"{path} is an alignment file, not a corpus: give its audio or video file instead; {CORPUS_LAYOUT}"
    try:
        with open(path, "rb") as fh:
            head = fh.read(_SNIFF_BYTES)
    except OSError as exc:
        return f"cannot read the manifest {path}: {exc.strerror}"
    head = head.removeprefix(b"\xef\xbb\xbf")
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as exc:  # text cut inside a character by the read is still text
        text = head[: exc.start].decode("utf-8") if exc.start > len(head) - 4 else None
    if text is None or "\x00" in text:
        what = "not a manifest CSV" if lower.endswith(".csv") else \
            f"neither an audio or video file ({', '.join(AUDIO_EXTS + VIDEO_EXTS)}) nor a manifest CSV"
        return f"{path} is {what} (it is not UTF-8 text): {CORPUS_LAYOUT}"
    header = [h.strip() for h in next(csv.reader([text.splitlines()[0] if text.strip() else ""]), [])]
    if "utterance_id" not in header:
        return (f"{path} is not a manifest CSV: its first line has no utterance_id column (columns: "
                f"{', '.join(MANIFEST_COLUMNS)}); {CORPUS_LAYOUT}")
    if not {"audio", "video"} & set(header):   # what discovery would refuse after the flow has started
        return (f"manifest {path}: no audio or video column (its columns: {', '.join(header)}; expected "
                f"{', '.join(MANIFEST_COLUMNS)}, with audio or video); {CORPUS_LAYOUT}")
    return None


def _inside(path: Path, root: Path) -> bool:
    try:
        path.resolve().relative_to(root.resolve())
        return True
    except ValueError:
        return False


@dataclass(frozen=True, slots=True)
class RemoteCorpus:
    """A corpus on object storage (`s3://bucket/corpus`, a manifest or one file there) as a local mirror of its
    folder (`location.mirror`): `local` is the corpus's path in the mirror, `folder` the mirror of the URL `url`."""

    local: Path
    folder: Path
    url: str

    def to_url(self, text: str) -> str:
        """`text` (a path, a message) with the mirror's paths written as the URLs they mirror."""
        return text.replace(str(self.folder), self.url)


def named_only(filename: str) -> bool:
    """Whether discovery reads the file `filename` of a corpus only by its name: audio, video and landmark files (the
    media). Of a corpus on object storage these are named in its mirror, not downloaded (`location.mirror`); their
    tasks read them. Alignments, transcripts, manifests and MLFs are read at discovery."""
    return _media_ext(filename) is not None or filename.lower().endswith(LANDMARK_SUFFIXES)


def remote_corpus(url: str) -> RemoteCorpus:
    """The local mirror of the corpus at `url`: a prefix is mirrored whole; one object (a manifest, one audio or
    video file) with the folder it lies in, where its relative paths and the files beside it are. The media are
    only named there (`named_only`), so an utterance's content hash covers its media objects' ETags and sizes
    (`location.object_identity`) and its alignment's bytes. FileNotFoundError when nothing lies at `url`."""
    url = url.rstrip("/")
    root = remote_root(url)
    if root.fs.isfile(root.path):
        folder_url, name = url.rsplit("/", 1)
        folder = mirror(folder_url, named_only)
        return RemoteCorpus(folder / name, folder, folder_url)
    if not root.fs.isdir(root.path):
        raise FileNotFoundError(f"corpus {url} does not exist")
    folder = mirror(url, named_only)
    return RemoteCorpus(folder, folder, url)


def _discover_remote(url: str, only: str | None) -> Discovery:
    """`discover_corpus` of a corpus on object storage: discovered in its local mirror (its media named, not
    downloaded: `remote_corpus`), every path and message then naming the object's URL, which the tasks read through
    `location.local_input` on whatever machine they run."""
    remote = remote_corpus(url)
    found = discover_corpus(remote.local, only)

    def back(value):
        return remote.to_url(value) if isinstance(value, str) else value

    entries = tuple(replace(e, audio_path=back(e.audio_path), alignment_path=back(e.alignment_path),
                            video_path=back(e.video_path), landmark_path=back(e.landmark_path))
                    for e in found.entries)
    rejects = tuple(replace(r, message=back(r.message), path=back(r.path)) for r in found.rejects)
    return Discovery(entries, rejects)


def discover_corpus(corpus: Path | str, only: str | None = None) -> Discovery:
    """Entries of a corpus folder (layout `<speaker>/<name>.*`) or of a manifest CSV file; a URL
    (`s3://bucket/corpus`) through its local mirror (`remote_corpus`), the entries naming the objects' URLs.

    With `only`, just that utterance is looked up (and hashed), as a rerun of one utterance needs.
    """
    if is_url(corpus):
        return _discover_remote(str(corpus), only)
    corpus = Path(corpus)
    if not corpus.exists():
        raise FileNotFoundError(f"corpus {corpus} does not exist")
    if only is not None:
        only = normalize_utterance_id(only)
    if corpus.is_file() and _media_ext(corpus.name) is not None:
        return _discover_file(corpus, only)
    if corpus.is_file():
        problem = _check_manifest_file(corpus)
        if problem is not None:
            raise CorpusError(problem)
        return _discover_manifest(corpus, only)
    manifest = corpus / "manifest.csv"
    if manifest.exists():
        return _discover_manifest(manifest, only)
    return _discover_folder(corpus, only)


def _with_hash(entry: CorpusEntry, mlf_entry: MlfEntry | None = None) -> CorpusEntry:
    """The entry with the digest of its files; of an MLF only the utterance's own entry counts, so editing
    another utterance's labels (or hashing a large MLF once per utterance) does not touch this one."""
    if mlf_entry is None:
        digest = files_hash([entry.audio_path, entry.alignment_path or None, entry.video_path, entry.landmark_path])
    else:
        files = files_hash([entry.audio_path, None, entry.video_path, entry.landmark_path])
        digest = stable_hash(files, "mlf", mlf_entry.pattern, mlf_entry.text)
    return replace(entry, content_hash=digest)


def _mlf_indexes(paths: list[Path], root: Path, rejects: list["DiscoveryReject"]) -> list[tuple[Path, MlfIndex]]:
    """The MLFs among `paths` (name order) that read; a malformed or outside one is a reject naming it."""
    out = []
    for path in sorted(paths, key=lambda p: p.name):
        if not _inside(path, root):
            rejects.append(DiscoveryReject(None, "PathOutsideCorpus",
                                           f"{path} is a link to {path.resolve()}, outside the corpus folder {root}; "
                                           "copy the file into the corpus", str(path)))
            continue
        try:
            out.append((path, load_mlf(path)))
        except LabelFileError as exc:
            rejects.append(DiscoveryReject(None, "BadAlignmentFile", str(exc), str(path)))
        except OSError as exc:
            rejects.append(DiscoveryReject(None, "UnreadableAlignment", f"{path}: cannot read: {exc.strerror}", str(path)))
    return out


def _find_in_mlfs(indexes: list[tuple[Path, MlfIndex]], folder: str, stem: str) -> tuple[Path, MlfEntry] | None:
    for path, index in indexes:
        entry = index.find(folder, stem) or index.find(_nfc(folder), _nfc(stem))
        if entry is not None:
            return path, entry
    return None


def _content_format(path: Path) -> str | None:
    """`mlf` or `textgrid` for an `.align` file whose content is an HTK MLF (P2FA writes its alignment so) or a
    Praat TextGrid; None for word spans (GRID's `start end word` lines) and for other suffixes, which say their
    format. Only the first bytes are read."""
    if path.suffix.lower() != ".align":
        return None
    try:
        with open(path, "rb") as fh:
            head = fh.read(64)
    except OSError:
        return None  # reading the alignment names the file and why it cannot be read
    if head.startswith((b"\xff\xfe", b"\xfe\xff")):  # UTF-16: Praat's text TextGrids, never word spans
        return "textgrid"
    head = head.removeprefix(b"\xef\xbb\xbf").lstrip()
    if head.startswith(MLF_HEADER.encode()):
        return "mlf"
    if head.startswith((b"File type", b"ooBinaryFile")):
        return "textgrid"
    return None


def _own_mlf_entry(path: Path, folder: str, stem: str) -> tuple[MlfEntry, str]:
    """(entry, `folder/stem` key that finds it) of an MLF beside one audio file with its stem (`NAME.align`,
    `NAME.mlf`). Such a file belongs to that audio whatever its entry names: P2FA's names the temporary file it
    aligned (`"/tmp/tmpab12/myl_26185.rec"`). An entry for the audio's own name wins; else a file of one entry
    gives that entry. LabelFileError when the file is malformed or holds several entries and none for the audio."""
    index = load_mlf(path)
    entry = index.find(folder, stem)
    if entry is not None:
        return entry, f"{folder}/{stem}"
    if len(index.entries) != 1:
        raise LabelFileError(f"{path}: {len(index.entries)} entries and none for {folder}/{stem}; a label file "
                             "beside one audio file should hold that file's labels alone")
    only = index.entries[0]
    parts = re.split(r"[/\\]", only.pattern)
    return only, f"{parts[-2] if len(parts) > 1 else ''}/{parts[-1].rsplit('.', 1)[0]}"


def _priority(filename: str) -> int:
    """Rank of a file among those of the same kind: earlier extensions in each list rank higher."""
    for exts in (AUDIO_EXTS, ALIGNMENT_EXTS, VIDEO_EXTS, LANDMARK_SUFFIXES):
        for rank, ext in enumerate(exts):
            if filename.lower().endswith(ext.lower()):
                return len(exts) - rank
    return 0


def _nfc(name: str) -> str:
    return unicodedata.normalize("NFC", name)


def _discover_folder(root: Path, only: str | None = None) -> Discovery:
    entries: list[CorpusEntry] = []
    rejects: list[DiscoveryReject] = []
    spellings: dict[str, list[list[Path]]] = {}  # id -> the files of each (folder, stem) spelling it
    real_root = root.resolve()
    notes: list[str] = []
    speaker_dirs = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    root_mlfs = _mlf_indexes([p for p in root.iterdir() if p.is_file() and p.name.lower().endswith(MLF_EXT)],
                             real_root, rejects)
    if only is not None:
        speaker, name = only.split("/")
        # compared NFC-normalised: a folder name may be stored decomposed (macOS) yet is the same speaker
        speaker_dirs = [p for p in speaker_dirs if _nfc(p.name) == speaker]
    for speaker_dir in speaker_dirs:
        # macOS leaves `._NAME` (AppleDouble metadata) beside each file it copies to a foreign disk: not media
        listing = [p for p in speaker_dir.iterdir() if not p.name.startswith("._")]
        files = {p.name: p for p in listing if p.is_file()}
        if only is None:
            rejects.extend(_nested_media(speaker_dir, listing))
        mlfs = _mlf_indexes([p for n, p in files.items() if n.lower().endswith(MLF_EXT)], real_root, rejects) \
            + root_mlfs
        if only is not None:
            files = {n: p for n, p in files.items() if _nfc(n).startswith(name + ".")}
        _discover_speaker(speaker_dir.name, speaker_dir.name, files, mlfs, real_root, only,
                          entries, rejects, spellings, notes=notes)
    return _without_id_collisions(entries, rejects, spellings, notes)


def _nested_media(speaker_dir: Path, listing: list[Path]) -> list["DiscoveryReject"]:
    """A reject for each folder inside a speaker folder that holds audio or video: a corpus is SPEAKER/UTTERANCE
    files, and files a level deeper (studio/speaker/take.wav) were left out without a word. Only that one level is
    looked at."""
    out = []
    for sub in sorted(p for p in listing if p.is_dir() and not p.name.startswith(".")):
        try:
            media = [p for p in sub.iterdir() if p.is_file() and not p.name.startswith(".") and _media_ext(p.name)]
        except OSError:
            continue
        if media:
            out.append(DiscoveryReject(
                None, "NestedFolder",
                f"{sub}: {len(media)} audio or video file{'s' if len(media) > 1 else ''} two folders deep, left out "
                f"(e.g. {media[0].name}); a corpus is SPEAKER/UTTERANCE files: point visemeflow at {speaker_dir} "
                "if its folders are the speakers, or move the files up a level", str(sub)))
    return out


def _discover_speaker(speaker: str, folder: str, files: dict[str, Path], mlfs: list[tuple[Path, MlfIndex]],
                      real_root: Path, only: str | None, entries: list[CorpusEntry], rejects: list[DiscoveryReject],
                      spellings: dict[str, list[list[Path]]], pinned: tuple[str, str, Path] | None = None,
                      notes: list[str] | None = None) -> None:
    """The entries and rejects of the files of one speaker folder (`files`: name -> path), added to `entries`,
    `rejects` and `spellings`. `speaker` is the id's first part, `folder` the folder's own name (what an MLF entry
    is found by). `pinned` (stem, kind, path): the file a user named, which is that utterance's audio or video
    whatever else of its kind lies beside it; then only that stem is read. `notes` gets a line for each utterance
    whose folder holds two files of one kind (the priority below chooses)."""
    stems: dict[str, dict[str, Path]] = {}
    passed_over: dict[tuple[str, str], list[Path]] = {}   # (stem, kind) -> files of that kind another outranked
    transcripts: dict[str, Path] = {}
    # Sorted by extension priority, highest last, so the choice does not depend on listing order:
    # a TextGrid wins over an .align, a .wav over a .flac, and so on.
    for filename, path in sorted(files.items(), key=lambda item: _priority(item[0])):
        lower = filename.lower()   # TAKE01.WAV, take01.TEXTGRID: what recorders and Windows tools write
        if lower.endswith(TRANSCRIPT_EXT):
            transcripts[filename[: -len(TRANSCRIPT_EXT)]] = path
        for kind, exts in (("audio", AUDIO_EXTS), ("alignment", ALIGNMENT_EXTS), ("video", VIDEO_EXTS)):
            for ext in exts:
                if lower.endswith(ext.lower()):
                    if ext == ".lab" and not looks_like_htk_label(path):
                        transcripts[filename[: -len(ext)]] = path  # a transcript, not an alignment
                        continue
                    found = stems.setdefault(filename[: -len(ext)], {})
                    if kind in found and found[kind] != path:
                        passed_over.setdefault((filename[: -len(ext)], kind), []).append(found[kind])
                    found[kind] = path
        for suffix in LANDMARK_SUFFIXES:
            if lower.endswith(suffix):
                stems.setdefault(filename[: -len(suffix)], {})["landmarks"] = path
    if pinned is not None:  # the named file, whatever else of its kind (a .wav beside an .mp3) lies beside it
        pinned_stem, pinned_kind, pinned_path = pinned
        stems = {pinned_stem: {**stems.get(pinned_stem, {}), pinned_kind: pinned_path}}
    for stem, kinds in sorted(stems.items()):
        any_path = str(pinned[2] if pinned is not None else next(iter(kinds.values())))
        try:
            utterance_id = make_utterance_id(speaker, stem)
        except InvalidIdError as exc:
            if only is None:   # every file of the name is left out: say so, not only of the first
                named = {*kinds.values(), *(p for (s, _), ps in passed_over.items() if s == stem for p in ps)}
                others = sorted(str(p) for p in named if str(p) != any_path)
                also = f"; left out with it: {', '.join(others)}" if others else ""
                rejects.append(DiscoveryReject(None, "InvalidId", f"{any_path}: {exc}{also}", any_path))
            continue
        if only is not None and utterance_id != only:
            continue
        spellings.setdefault(utterance_id, []).append(sorted(kinds.values()))
        outside = next((p for p in kinds.values() if not _inside(p, real_root)), None)
        if outside is not None:
            rejects.append(DiscoveryReject(
                utterance_id, "PathOutsideCorpus",
                f"{utterance_id}: {outside} is a link to {outside.resolve()}, outside the corpus folder "
                f"{real_root}; copy the file into the corpus", str(outside)))
            continue
        mlf_entry, key, kind, own_mlf = None, None, None, None
        if "alignment" in kinds:
            kind = _content_format(kinds["alignment"])
            own_mlf = kinds["alignment"] if kind == "mlf" else None
        else:
            found_in = _find_in_mlfs(mlfs, folder, stem)
            if found_in is not None:
                kinds["alignment"], mlf_entry = found_in
                key = f"{folder}/{stem}"
            elif any(path == files.get(stem + MLF_EXT) for path, _ in mlfs):  # NAME.mlf read, no entry named
                own_mlf = files[stem + MLF_EXT]
        if own_mlf is not None:  # NAME.align holding an MLF, or NAME.mlf: this utterance's own label file
            try:
                mlf_entry, key = _own_mlf_entry(own_mlf, folder, stem)
            except LabelFileError as exc:
                rejects.append(DiscoveryReject(utterance_id, "BadAlignmentFile", str(exc), str(own_mlf)))
                continue
            except OSError as exc:
                rejects.append(DiscoveryReject(utterance_id, "UnreadableAlignment",
                                               f"{own_mlf}: cannot read: {exc.strerror}", str(own_mlf)))
                continue
            kinds["alignment"] = own_mlf
        if "alignment" not in kinds and stem in transcripts and ("audio" in kinds or "video" in kinds):
            transcript = transcripts[stem]
            if not _inside(transcript, real_root):   # as the files above: never read a file outside the corpus
                rejects.append(DiscoveryReject(
                    utterance_id, "PathOutsideCorpus",
                    f"{utterance_id}: {transcript} is a link to {transcript.resolve()}, outside the corpus folder "
                    f"{real_root}; copy the file into the corpus", str(transcript)))
                continue
            kinds["alignment"], kind = transcript, TRANSCRIPT_FORMAT   # ingest aligns it
        if "audio" not in kinds and "video" in kinds:
            kinds["audio"] = kinds["video"]  # the audio track inside the video (GRID .mpg)
        if "alignment" not in kinds and "video" not in kinds:
            note = (f" ({transcripts[stem].name} is a transcript without times, not an alignment)"
                    if stem in transcripts else "")
            rejects.append(DiscoveryReject(
                utterance_id, "MissingAlignment",
                f"{utterance_id}: no alignment for {any_path}: no {', '.join(ALIGNMENT_EXTS)} file beside it and "
                f"no entry for it in an .mlf file{note}", any_path))
            continue
        if "audio" not in kinds:
            rejects.append(DiscoveryReject(utterance_id, "MissingAudio",
                                           f"{utterance_id}: no {'/'.join(AUDIO_EXTS)} file next to {kinds['alignment']}",
                                           str(kinds["alignment"])))
            continue
        if notes is not None:
            for what, chosen in kinds.items():
                left = passed_over.get((stem, what))
                if left and pinned is None:
                    notes.append(f"{utterance_id}: {chosen.name} is its {what}; "
                                 f"{', '.join(p.name for p in left)} beside it left out (an {what} file of the "
                                 "same name ranks lower: rename it if it is another take)")
        entries.append(_with_hash(CorpusEntry(
            utterance_id, str(kinds["audio"].resolve()),
            str(kinds["alignment"].resolve()) if "alignment" in kinds else "",
            str(kinds["video"].resolve()) if "video" in kinds else None,
            str(kinds["landmarks"].resolve()) if "landmarks" in kinds else None,
            alignment_key=key, alignment_kind=kind,
        ), mlf_entry))


def _media_ext(filename: str) -> str | None:
    """The audio or video extension `filename` ends with (any case), as the corpus reader knows them; else None."""
    lower = filename.lower()
    return next((ext for ext in AUDIO_EXTS + VIDEO_EXTS if lower.endswith(ext)), None)


def single_file_speaker(folder: str) -> str:
    """The speaker of a one-file corpus in `folder` (the name of the file's folder): that name, NFC-normalised, when
    it is a valid speaker (the rules of speaker folders, `schemas.ids`), else SINGLE_FILE_SPEAKER (a file in `/`, in
    a hidden folder, or in a folder whose name holds a control character)."""
    try:
        return make_utterance_id(folder, "x").split("/")[0]
    except InvalidIdError:
        return SINGLE_FILE_SPEAKER


def _discover_file(path: Path, only: str | None = None) -> Discovery:
    """One audio or video file as a corpus of one utterance: `<its folder's name>/<its stem>`, with what a corpus
    folder pairs with it beside it (alignment, transcript, landmarks, the audio beside a video, an entry of an MLF in
    its folder). The folder is the corpus folder: a file beside it that links outside it is a reject. The path is
    resolved first, as the flows do, so that a link gives the same id whichever way it is read."""
    path = path.resolve()
    folder = path.parent
    ext = _media_ext(path.name)
    stem = path.name[: -len(ext)]
    speaker = single_file_speaker(folder.name)
    try:
        utterance_id = make_utterance_id(speaker, stem)
    except InvalidIdError as exc:
        return Discovery((), () if only is not None else (
            DiscoveryReject(None, "InvalidId", f"{path}: {exc}", str(path)),))
    if only is not None and only != utterance_id:
        return Discovery(())
    try:
        beside = [p for p in folder.iterdir() if p.name.startswith(stem + ".") and p.is_file()]
        mlf_paths = [p for p in folder.iterdir() if p.name.lower().endswith(MLF_EXT) and p.is_file()]
    except OSError:  # a folder that may not be listed: the file alone
        beside, mlf_paths = [path], []
    files = {p.name: p for p in beside}
    files[path.name] = path
    entries: list[CorpusEntry] = []
    rejects: list[DiscoveryReject] = []
    mlf_rejects: list[DiscoveryReject] = []
    mlfs = _mlf_indexes(mlf_paths, folder, mlf_rejects)
    kind = "video" if ext in VIDEO_EXTS else "audio"
    _discover_speaker(speaker, folder.name, files, mlfs, folder, utterance_id, entries, rejects, {},
                      pinned=(stem, kind, path))
    # a broken MLF beside the file is named only where it may be why the file has no alignment
    return Discovery(tuple(entries), tuple(rejects + (mlf_rejects if not entries else [])))


def _without_id_collisions(entries: list[CorpusEntry], rejects: list[DiscoveryReject],
                           spellings: dict[str, list[list[Path]]], notes: list[str] | None = None) -> Discovery:
    """The discovery with every id that several spellings give (`café` composed and decomposed, in one folder or in
    two speaker folders) refused: one reject per spelling, naming all their files. Keeping either would be a guess,
    and keeping both would give two utterances one id, whose rows and phones then merge."""
    collided = {uid: groups for uid, groups in spellings.items() if len(groups) > 1}
    if not collided:
        return Discovery(tuple(entries), tuple(rejects), tuple(notes or ()))
    rejects = [r for r in rejects if r.utterance_id not in collided]
    for uid, groups in collided.items():
        files = ", ".join(str(p) for group in groups for p in group)
        for group in groups:
            rejects.append(DiscoveryReject(
                uid, "IdCollision",
                f"{uid}: {len(groups)} spellings of one name give this id (names equal after Unicode NFC "
                f"normalisation): {files}; rename the files so each utterance is spelled one way", str(group[0])))
    return Discovery(tuple(e for e in entries if e.utterance_id not in collided), tuple(rejects),
                     tuple(n for n in notes or () if n.split(":")[0] not in collided))


def _check_split_and_language(where: str, utterance_id: str, split: str | None, language: str | None,
                              manifest: Path) -> DiscoveryReject | None:
    """A reject for a manifest row whose split is not one of SPLITS or whose language is not a LANGUAGE_TAG."""
    if split is not None and split not in SPLITS:
        return DiscoveryReject(utterance_id, "BadSplit", f"{where}: {utterance_id}: split {split!r} is not one of "
                               f"{', '.join(SPLITS)} (or empty: chosen by a hash of the id)", str(manifest))
    if language is not None and LANGUAGE_TAG.fullmatch(language) is None:
        shown = language if len(language) <= 40 else language[:40] + "..."
        return DiscoveryReject(utterance_id, "BadLanguage", f"{where}: {utterance_id}: language {shown!r} is not a "
                               "language tag (expected e.g. en, zh-CN, cmn; or empty)", str(manifest))
    return None


def _discover_manifest(manifest: Path, only: str | None = None) -> Discovery:
    """Entries of a manifest CSV; relative paths are relative to its folder, and may not leave it. A manifest that
    is not UTF-8 is a CorpusError naming the line, never the undecodable bytes."""
    try:
        return _read_manifest(manifest, only)
    except UnicodeDecodeError as exc:
        raise CorpusError(f"{manifest} is not a manifest CSV: not UTF-8 text at byte {exc.start} "
                          f"({exc.reason}); {CORPUS_LAYOUT}") from None


def _read_manifest(manifest: Path, only: str | None) -> Discovery:
    root = manifest.parent.resolve()
    entries: list[CorpusEntry] = []
    rejects: list[DiscoveryReject] = []
    with open(manifest, newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        columns = set(reader.fieldnames or [])
        # the alignment column may be left out (rows with a video are kept without one), audio or video may not
        missing = {"utterance_id"} - columns
        if not columns & {"audio", "video"}:
            missing.add("audio or video")
        if missing:
            raise ValueError(f"manifest {manifest}: missing column(s) {sorted(missing)}; expected {MANIFEST_COLUMNS}")
        seen: set[str] = set()
        for lineno, row in enumerate(reader, start=2):
            where = f"{manifest}:{lineno}"
            utterance_id = (row.get("utterance_id") or "").strip()
            try:
                utterance_id = normalize_utterance_id(utterance_id)
            except InvalidIdError as exc:
                if only is None:
                    rejects.append(DiscoveryReject(None, "InvalidId", f"{where}: {exc}", str(manifest)))
                continue
            if only is not None and utterance_id != only:
                continue
            if utterance_id in seen:
                rejects.append(DiscoveryReject(utterance_id, "DuplicateId", f"{where}: {utterance_id} listed twice", str(manifest)))
                continue
            seen.add(utterance_id)
            paths: dict[str, str | None] = {}
            bad = None
            for col in ("audio", "alignment", "video", "landmarks"):
                value = (row.get(col) or "").strip()
                if not value:
                    paths[col] = None
                    continue
                path = (root / value).resolve()
                if not _inside(path, root):
                    bad = DiscoveryReject(utterance_id, "PathOutsideCorpus",
                                          f"{where}: {utterance_id}: {col} path {value!r} leaves the corpus folder {root}", value)
                    break
                if not path.is_file():
                    bad = DiscoveryReject(utterance_id, f"Missing{col.capitalize()}",
                                          f"{where}: {utterance_id}: {col} file {path} does not exist", str(path))
                    break
                paths[col] = str(path)
            if bad is None and paths["audio"] is None and paths["video"] is not None:
                paths["audio"] = paths["video"]  # the audio track inside the video
            if bad is None and (paths["audio"] is None or (paths["alignment"] is None and paths["video"] is None)):
                bad = DiscoveryReject(utterance_id, "MissingInput",
                                      f"{where}: {utterance_id}: audio and alignment are required (or a video, "
                                      "whose audio track is used and which may have no alignment)", str(manifest))
            mlf_entry, key, kind = None, None, None
            if bad is None and paths["alignment"] is not None:
                kind = _content_format(Path(paths["alignment"]))
            if bad is None and paths["alignment"] is not None and (kind == "mlf"
                                                                   or paths["alignment"].lower().endswith(MLF_EXT)):
                named = Path(paths["audio"])
                key = f"{named.parent.name}/{named.stem}"
                try:
                    if kind == "mlf":  # an .align holding an MLF is this utterance's own, whatever its entry names
                        mlf_entry, key = _own_mlf_entry(Path(paths["alignment"]), named.parent.name, named.stem)
                    else:
                        mlf_entry = load_mlf(paths["alignment"]).find(named.parent.name, named.stem)
                    if mlf_entry is None:
                        bad = DiscoveryReject(utterance_id, "MissingAlignment",
                                              f"{where}: {utterance_id}: {paths['alignment']} has no entry for {key}",
                                              paths["alignment"])
                except LabelFileError as exc:
                    bad = DiscoveryReject(utterance_id, "BadAlignmentFile", f"{where}: {utterance_id}: {exc}",
                                          paths["alignment"])
                except OSError as exc:
                    bad = DiscoveryReject(utterance_id, "UnreadableAlignment",
                                          f"{where}: {utterance_id}: {paths['alignment']}: cannot read: {exc.strerror}",
                                          paths["alignment"])
            language = (row.get("language") or "").strip() or None
            split = (row.get("split") or "").strip().lower() or None
            if bad is None:
                bad = _check_split_and_language(where, utterance_id, split, language, manifest)
            if bad is not None:
                rejects.append(bad)
                continue
            entries.append(_with_hash(CorpusEntry(
                utterance_id, paths["audio"], paths["alignment"] or "", paths["video"], paths["landmarks"],
                language, split, alignment_key=key, alignment_kind=kind,
            ), mlf_entry))
    return Discovery(tuple(entries), tuple(rejects))
