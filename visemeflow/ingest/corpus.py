"""Find the utterances of a corpus: a folder `<speaker>/<name>.wav` + alignment, or a manifest CSV.

Utterance ids are `<speaker folder>/<file stem>` (or the manifest's `utterance_id`), NFC-normalised, in any
script (`Speaker One/take 1`, `张三/一`; rules in `schemas.ids`). Nothing outside the corpus folder is read:
a manifest path that leaves its folder and a symlink that points outside the corpus are rejects naming the file.
"""

import csv
import unicodedata
from dataclasses import dataclass, field, replace
from pathlib import Path

from visemeflow.hashing import files_hash
from visemeflow.ingest.audio import AUDIO_EXTS, VIDEO_EXTS
from visemeflow.schemas import InvalidIdError, make_utterance_id, normalize_utterance_id

ALIGNMENT_EXTS = (".TextGrid", ".textgrid", ".align")
LANDMARK_SUFFIXES = (".landmarks.csv", ".landmarks.parquet", ".mediapipe478.csv", ".openface.csv")
MANIFEST_COLUMNS = ("utterance_id", "audio", "alignment", "video", "landmarks", "language", "split")


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

    @property
    def speaker(self) -> str:
        return self.utterance_id.split("/")[0]

    @property
    def alignment_format(self) -> str:
        return "word_align" if self.alignment_path.endswith(".align") else "textgrid"


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


def _inside(path: Path, root: Path) -> bool:
    try:
        path.resolve().relative_to(root.resolve())
        return True
    except ValueError:
        return False


def discover_corpus(corpus: Path | str, only: str | None = None) -> Discovery:
    """Entries of a corpus folder (layout `<speaker>/<name>.*`) or of a manifest CSV file.

    With `only`, just that utterance is looked up (and hashed), as a rerun of one utterance needs.
    """
    corpus = Path(corpus)
    if not corpus.exists():
        raise FileNotFoundError(f"corpus {corpus} does not exist")
    if only is not None:
        only = normalize_utterance_id(only)
    if corpus.is_file():
        return _discover_manifest(corpus, only)
    manifest = corpus / "manifest.csv"
    if manifest.exists():
        return _discover_manifest(manifest, only)
    return _discover_folder(corpus, only)


def _with_hash(entry: CorpusEntry) -> CorpusEntry:
    digest = files_hash([entry.audio_path, entry.alignment_path, entry.video_path, entry.landmark_path])
    return replace(entry, content_hash=digest)


def _priority(filename: str) -> int:
    """Rank of a file among those of the same kind: earlier extensions in each list rank higher."""
    for exts in (AUDIO_EXTS, ALIGNMENT_EXTS, VIDEO_EXTS, LANDMARK_SUFFIXES):
        for rank, ext in enumerate(exts):
            if filename.endswith(ext):
                return len(exts) - rank
    return 0


def _nfc(name: str) -> str:
    return unicodedata.normalize("NFC", name)


def _discover_folder(root: Path, only: str | None = None) -> Discovery:
    entries: list[CorpusEntry] = []
    rejects: list[DiscoveryReject] = []
    real_root = root.resolve()
    speaker_dirs = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    if only is not None:
        speaker, name = only.split("/")
        # compared NFC-normalised: a folder name may be stored decomposed (macOS) yet is the same speaker
        speaker_dirs = [p for p in speaker_dirs if _nfc(p.name) == speaker]
    for speaker_dir in speaker_dirs:
        files = {p.name: p for p in speaker_dir.iterdir() if p.is_file()}
        if only is not None:
            files = {n: p for n, p in files.items() if _nfc(n).startswith(name + ".")}
        stems: dict[str, dict[str, Path]] = {}
        # Sorted by extension priority, highest last, so the choice does not depend on listing order:
        # a TextGrid wins over an .align, a .wav over a .flac, and so on.
        for filename, path in sorted(files.items(), key=lambda item: _priority(item[0])):
            for kind, exts in (("audio", AUDIO_EXTS), ("alignment", ALIGNMENT_EXTS), ("video", VIDEO_EXTS)):
                for ext in exts:
                    if filename.endswith(ext):
                        stems.setdefault(filename[: -len(ext)], {})[kind] = path
            for suffix in LANDMARK_SUFFIXES:
                if filename.endswith(suffix):
                    stems.setdefault(filename[: -len(suffix)], {})["landmarks"] = path
        for stem, kinds in sorted(stems.items()):
            any_path = str(next(iter(kinds.values())))
            try:
                utterance_id = make_utterance_id(speaker_dir.name, stem)
            except InvalidIdError as exc:
                if only is None:
                    rejects.append(DiscoveryReject(None, "InvalidId", f"{any_path}: {exc}", any_path))
                continue
            if only is not None and utterance_id != only:
                continue
            outside = next((p for p in kinds.values() if not _inside(p, real_root)), None)
            if outside is not None:
                rejects.append(DiscoveryReject(
                    utterance_id, "PathOutsideCorpus",
                    f"{utterance_id}: {outside} is a link to {outside.resolve()}, outside the corpus folder "
                    f"{real_root}; copy the file into the corpus", str(outside)))
                continue
            if "alignment" not in kinds:
                rejects.append(DiscoveryReject(utterance_id, "MissingAlignment",
                                               f"{utterance_id}: no .TextGrid or .align file next to {any_path}", any_path))
                continue
            if "audio" not in kinds and "video" in kinds:
                kinds["audio"] = kinds["video"]  # the audio track inside the video (GRID .mpg)
            if "audio" not in kinds:
                rejects.append(DiscoveryReject(utterance_id, "MissingAudio",
                                               f"{utterance_id}: no {'/'.join(AUDIO_EXTS)} file next to {kinds['alignment']}",
                                               str(kinds["alignment"])))
                continue
            entries.append(_with_hash(CorpusEntry(
                utterance_id, str(kinds["audio"].resolve()), str(kinds["alignment"].resolve()),
                str(kinds["video"].resolve()) if "video" in kinds else None,
                str(kinds["landmarks"].resolve()) if "landmarks" in kinds else None,
            )))
    return Discovery(tuple(entries), tuple(rejects))


def _discover_manifest(manifest: Path, only: str | None = None) -> Discovery:
    """Entries of a manifest CSV; relative paths are relative to its folder, and may not leave it."""
    root = manifest.parent.resolve()
    entries: list[CorpusEntry] = []
    rejects: list[DiscoveryReject] = []
    with open(manifest, newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        missing = {"utterance_id", "audio", "alignment"} - set(reader.fieldnames or [])
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
            if bad is None and (paths["audio"] is None or paths["alignment"] is None):
                bad = DiscoveryReject(utterance_id, "MissingInput", f"{where}: {utterance_id}: audio and alignment are required", str(manifest))
            if bad is not None:
                rejects.append(bad)
                continue
            entries.append(_with_hash(CorpusEntry(
                utterance_id, paths["audio"], paths["alignment"], paths["video"], paths["landmarks"],
                (row.get("language") or "").strip() or None, (row.get("split") or "").strip() or None,
            )))
    return Discovery(tuple(entries), tuple(rejects))
