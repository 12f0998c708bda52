"""Find the utterances of a corpus: a folder `<speaker>/<name>.wav` + alignment, or a manifest CSV."""

import csv
import hashlib
from dataclasses import dataclass, field, replace
from pathlib import Path

from visemeflow.schemas import InvalidIdError, validate_utterance_id

AUDIO_EXTS = (".wav", ".flac", ".ogg")
ALIGNMENT_EXTS = (".TextGrid", ".textgrid", ".align")
VIDEO_EXTS = (".mp4", ".avi", ".mpg", ".mov")
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


def hash_files(paths: list[str | None]) -> str:
    """blake2b of the bytes of the given files (None entries count as absent), as hex."""
    h = hashlib.blake2b(digest_size=16)
    for p in paths:
        h.update(b"\0" if p is None else b"\1")
        if p is not None:
            with open(p, "rb") as fh:
                while chunk := fh.read(1 << 20):
                    h.update(chunk)
            h.update(b"\0")
    return h.hexdigest()


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
        validate_utterance_id(only)
    if corpus.is_file():
        return _discover_manifest(corpus, only)
    manifest = corpus / "manifest.csv"
    if manifest.exists():
        return _discover_manifest(manifest, only)
    return _discover_folder(corpus, only)


def _with_hash(entry: CorpusEntry) -> CorpusEntry:
    digest = hash_files([entry.audio_path, entry.alignment_path, entry.video_path, entry.landmark_path])
    return replace(entry, content_hash=digest)


def _priority(filename: str) -> int:
    """Rank of a file among those of the same kind: earlier extensions in each list rank higher."""
    for exts in (AUDIO_EXTS, ALIGNMENT_EXTS, VIDEO_EXTS, LANDMARK_SUFFIXES):
        for rank, ext in enumerate(exts):
            if filename.endswith(ext):
                return len(exts) - rank
    return 0


def _discover_folder(root: Path, only: str | None = None) -> Discovery:
    entries: list[CorpusEntry] = []
    rejects: list[DiscoveryReject] = []
    if only is not None:
        speaker, name = only.split("/")
        speaker_dirs = [root / speaker] if (root / speaker).is_dir() else []
    else:
        speaker_dirs = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    for speaker_dir in speaker_dirs:
        files = {p.name: p for p in speaker_dir.iterdir() if p.is_file()}
        if only is not None:
            files = {n: p for n, p in files.items() if n.startswith(name + ".")}
        stems: dict[str, dict[str, Path]] = {}
        # Sorted by extension priority, highest last, so the choice does not depend on listing order:
        # a TextGrid wins over an .align, a .wav over a .flac, and so on.
        for name, path in sorted(files.items(), key=lambda item: _priority(item[0])):
            for kind, exts in (("audio", AUDIO_EXTS), ("alignment", ALIGNMENT_EXTS), ("video", VIDEO_EXTS)):
                for ext in exts:
                    if name.endswith(ext):
                        stems.setdefault(name[: -len(ext)], {})[kind] = path
            for suffix in LANDMARK_SUFFIXES:
                if name.endswith(suffix):
                    stems.setdefault(name[: -len(suffix)], {})["landmarks"] = path
        for stem, kinds in sorted(stems.items()):
            utterance_id = f"{speaker_dir.name}/{stem}"
            if only is not None and utterance_id != only:
                continue
            any_path = str(next(iter(kinds.values())))
            try:
                validate_utterance_id(utterance_id)
            except InvalidIdError as exc:
                rejects.append(DiscoveryReject(None, "InvalidId", f"{any_path}: {exc}", any_path))
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
            if only is not None and utterance_id != only:
                continue
            try:
                validate_utterance_id(utterance_id)
            except InvalidIdError as exc:
                rejects.append(DiscoveryReject(None, "InvalidId", f"{where}: {exc}", str(manifest)))
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
