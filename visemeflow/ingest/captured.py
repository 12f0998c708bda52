"""Captured facial animation as takes of our 16 viseme curves: take readers, discovery, import (the channel
tables they use: `visemeflow.ingest.channels`).

A **take** is one utterance's audio plus a file of per-frame captured weights in one of three formats:

- `livelink`: a Live Link Face CSV (Epic's iOS app; `shapes.livelink.read_livelink_csv`), the 52 ARKit weights
  by name. Its frame rate comes from the timecodes (`HH:MM:SS:FF.fff`, frames counted at the timecode rate: the
  rate is the standard one, of those above the largest `FF`, that spaces the rows most evenly; the capture rate is
  1 / the median spacing), or is given. Rows missing from the timecode grid (dropped frames) are filled by linear
  interpolation, so frame k is at k / fps from the first row.
- `csv`: a CSV whose header names the channels, one row per frame; columns named `frame`, `time`, `time_s`,
  `timestamp` or `timecode` are not channels (`time`/`time_s` in seconds give the frame rate when none is given).
- `npy`: a (frames, channels) array (no pickles: `allow_pickle=False`) with a names file: an `.npy` of strings or a
  text file with one name per line.

Channels become ARKit-52 weights through a **channel table** (CSV or `.xlsx`), in one of two forms:

- `arkit,expression[,status]`: each ARKit name from an expression of channels, `name` or `max(a, b, ...)`; rows whose
  status is `invalid` (any case) and rows without an expression drive nothing (FACEGOOD's
  `Voice2Face_blendshape2ARkit.xlsx` is this form; `examples/facegood/voice2face_arkit.csv` is it as CSV);
- `channel,arkit,weight`: each ARKit weight is the sum of weight x channel over its rows.
Without a table, channels must be ARKit names themselves (matched ignoring case). ARKit names in a table are matched
ignoring case too (`browDownleft` is `browDownLeft`). A channel the table names that the file lacks, a channel name
that is neither in the table nor ARKit when there is none, a duplicate channel, a NaN or infinite value and an
array of the wrong shape are `CaptureReadError`s naming the file (and the line, frame or channel). Channels the table
does not use are ignored; those that vary are listed (`CapturedTake.unmapped`), since their motion is lost.

`import_take` reads a take, checks its frame count against the audio (within `max_drift_frames_per_s` frames per
second of audio, at least one frame), fits the viseme curves (`shapes.capture`) and returns the `utterances` row
(no alignment: `alignment_format` "none", `alignment_path` "") with the curves. Takes are found in a manifest CSV
(`utterance_id,audio,capture,format,channels,names,fps,language,split`, paths relative to it and inside its folder)
or a folder `<speaker>/<name>.wav` + `<name>.livelink.csv` | `<name>.capture.csv` | `<name>.capture.npy`.
"""

from __future__ import annotations

import csv
import io
import math
import statistics
import unicodedata
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from visemeflow.shapes.capture import ArkitToVisemes, CaptureError, VisemeFit, fit_visemes
from visemeflow.shapes.conventions import ARKIT_52
from visemeflow.shapes.livelink import arkit_from_livelink, is_number, parse_timecode, read_livelink_csv
from visemeflow.hashing import files_hash
from visemeflow.ingest.config import CaptureConfig
from visemeflow.ingest.audio import AUDIO_EXTS, VIDEO_EXTS, is_video_file
from visemeflow.ingest.channels import (  # the readers of a take's table, re-exported (__all__)
    _canonical_arkit,
    CaptureReadError,
    ChannelTable,
    ExpressionRow,
    read_channel_table,
    read_expression_rows,
    read_xlsx_rows,
    write_expression_csv,
)
from visemeflow.ingest.corpus import CorpusEntry, DiscoveryReject
from visemeflow.ingest.utterance import IngestError, assign_split, read_audio_info
from visemeflow.schemas import C, InvalidIdError, make_utterance_id, normalize_utterance_id
from visemeflow.schemas.tables import NO_ALIGNMENT

__all__ = [
    "BAD_INPUT_ERRORS",
    "CAPTURE_FORMATS",
    "CAPTURED_ALIGNMENT_FORMAT",
    "CaptureConfig",
    "CaptureReadError",
    "CapturedTake",
    "ChannelTable",
    "ExpressionRow",
    "ImportedTake",
    "Take",
    "TakeDiscovery",
    "detect_format",
    "discover_takes",
    "import_take",
    "livelink_frame_rate",
    "read_channel_csv",
    "read_channel_npy",
    "read_channel_table",
    "read_expression_rows",
    "read_livelink_take",
    "read_take",
    "read_xlsx_rows",
    "write_expression_csv",
]

CAPTURE_FORMATS = ("livelink", "csv", "npy")
CAPTURED_ALIGNMENT_FORMAT = NO_ALIGNMENT
"""`alignment_format` of the `utterances` rows of captured takes (they have no alignment; `alignment_path` is "")."""
TAKE_MANIFEST = "takes.csv"
MANIFEST_COLUMNS = ("utterance_id", "audio", "capture", "format", "channels", "names", "fps", "language", "split")
CAPTURE_SUFFIXES = {".livelink.csv": "livelink", ".capture.csv": "csv", ".capture.npy": "npy"}
INDEX_COLUMNS = frozenset({"frame", "time", "time_s", "timestamp", "timecode"})
TIMECODE_RATES = (24.0, 25.0, 30.0, 48.0, 50.0, 60.0, 72.0, 90.0, 100.0, 120.0, 240.0)
VARYING = 1e-3
"""A channel whose values span more than this varies (unused varying channels are reported)."""
# ---- take readers ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CapturedTake:
    """One captured file as ARKit-52 weights on a regular frame grid."""

    path: str
    format: str
    arkit: np.ndarray = field(repr=False)
    """(T, 52) float32 in `ARKIT_52` order."""
    fps: float
    channels: tuple[str, ...] = ()
    """The file's channel names (the ARKit names for Live Link)."""
    unmapped: tuple[str, ...] = ()
    """Channels that vary but drive no ARKit shape, most varying first (their motion is lost)."""
    filled_frames: int = 0
    """Frames missing from the file's clock (Live Link timecodes), filled by interpolation."""

    @property
    def n_frames(self) -> int:
        return len(self.arkit)


def _fps_or_error(fps, path: Path) -> float:
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not math.isfinite(fps) or fps <= 0:
        raise CaptureReadError(str(path), "MissingFrameRate",
                               f"the capture frame rate must be a positive number, got {fps!r}")
    return float(fps)


def _snap_rate(rate: float, base: float) -> float:
    """`rate` as base / k when within 0.5% of one (60 / 2 = 30), else rounded to 3 decimals."""
    k = max(1, round(base / rate))
    return base / k if abs(base / k - rate) <= 0.005 * rate else round(rate, 3)


def livelink_frame_rate(timecodes: list[str], path: str | Path = "Live Link CSV") -> tuple[float, float, np.ndarray]:
    """(timecode rate, capture frame rate, seconds of each row from the first) of Live Link timecodes.

    The timecode rate is the standard rate above the largest frame field that spaces the rows most evenly; the
    capture rate is 1 / the median spacing (snapped to the timecode rate / k when within 0.5%)."""
    path = Path(path)
    if len(timecodes) < 2:
        raise CaptureReadError(str(path), "MissingFrameRate",
                               f"{len(timecodes)} frame(s): too few to read a frame rate; give the fps")
    frames = [int(tc.split(":")[3].split(".")[0]) for tc in timecodes]
    best = None
    for rate in (r for r in TIMECODE_RATES if r > max(frames)):
        times = np.array([parse_timecode(tc, rate) for tc in timecodes])
        steps = np.diff(times)
        if (steps <= 0).any():
            continue
        spread = float(np.std(steps) / np.median(steps))
        if best is None or spread < best[0] - 1e-9:
            best = (spread, rate, times - times[0])
    if best is None:
        rate = next((r for r in TIMECODE_RATES if r > max(frames)), None)
        if rate is None:
            raise CaptureReadError(str(path), "BadTimecode", f"frame field {max(frames)} is beyond every timecode rate")
        times = np.array([parse_timecode(tc, rate) for tc in timecodes])
        line = int(np.flatnonzero(np.diff(times) <= 0)[0]) + 3  # header is line 1, row k is line k + 2
        raise CaptureReadError(str(path), "BadTimecode",
                               f"line {line}: timecode {timecodes[line - 2]} does not come after {timecodes[line - 3]}")
    _, rate, times = best
    return rate, _snap_rate(1.0 / float(np.median(np.diff(times))), rate), times


def _regular_grid(values: np.ndarray, times: np.ndarray, fps: float) -> tuple[np.ndarray, int]:
    """Values on the grid k / fps (linear interpolation where rows are missing) and how many frames were filled."""
    n = int(round(times[-1] * fps)) + 1
    if n == len(values) and np.abs(times - np.arange(n) / fps).max() < 0.25 / fps:
        return values, 0
    grid = np.arange(n) / fps
    out = np.stack([np.interp(grid, times, values[:, j]) for j in range(values.shape[1])], axis=1)
    return out.astype(values.dtype), max(0, n - len(values))


def read_livelink_take(path: str | Path, fps: float | None = None) -> CapturedTake:
    """A Live Link Face CSV as ARKit weights; the frame rate from its timecodes unless `fps` is given."""
    path = Path(path)
    try:
        _, values, timecodes = read_livelink_csv(path)
    except ValueError as exc:
        raise CaptureReadError(str(path), "BadLiveLink", str(exc).removeprefix(f"{path}: ").removeprefix(f"{path}, "))
    if not len(values):
        raise CaptureReadError(str(path), "EmptyCapture", "no frames")
    arkit = arkit_from_livelink(values).astype(np.float32)
    if fps is not None:
        return CapturedTake(str(path), "livelink", arkit, _fps_or_error(fps, path), tuple(ARKIT_52))
    _, rate, times = livelink_frame_rate(timecodes, path)
    arkit, filled = _regular_grid(arkit, times, rate)
    return CapturedTake(str(path), "livelink", arkit, rate, tuple(ARKIT_52), filled_frames=filled)


def _channels_to_arkit(names: tuple[str, ...], values: np.ndarray, table: ChannelTable | None, path: Path,
                       fps: float, fmt: str) -> CapturedTake:
    """Check a (frames, channels) array and its names, map it to ARKit weights."""
    where = str(path)
    if values.ndim != 2:
        raise CaptureReadError(where, "BadShape", f"expected a (frames, channels) array, got shape {values.shape}")
    if values.shape[1] != len(names):
        raise CaptureReadError(where, "BadShape", f"{values.shape[1]} channels but {len(names)} channel names")
    if not len(values):
        raise CaptureReadError(where, "EmptyCapture", "no frames")
    seen: dict[str, int] = {}
    for i, name in enumerate(names):
        if not name:
            raise CaptureReadError(where, "BadChannelName", f"channel {i + 1} has no name")
        if name in seen:
            raise CaptureReadError(where, "DuplicateChannel", f"channel {name!r} appears twice (columns {seen[name] + 1} "
                                                              f"and {i + 1})")
        seen[name] = i
    bad = ~np.isfinite(values)
    if bad.any():
        frame, column = map(int, np.argwhere(bad)[0])
        raise CaptureReadError(where, "NonFiniteCapture", f"channel {names[column]!r} is {values[frame, column]} at "
                                                          f"frame {frame} ({int(bad.sum())} NaN or infinite values)")
    if table is None:
        mapping = {n: _canonical_arkit(n) for n in names}
        unknown = [n for n, a in mapping.items() if a is None]
        if unknown:
            raise CaptureReadError(where, "UnknownChannel",
                                   f"channel(s) {', '.join(map(repr, unknown[:12]))}{' ...' if len(unknown) > 12 else ''}"
                                   " are not ARKit-52 names; give a channel table (arkit,expression or "
                                   "channel,arkit,weight)")
        first: dict[str, str] = {}
        for n, a in mapping.items():
            if a in first:
                raise CaptureReadError(where, "DuplicateChannel", f"channels {first[a]!r} and {n!r} both read as {a}")
            first[a] = n
        table = ChannelTable("ARKit names", tuple((a, "sum", ((n, 1.0),)) for n, a in mapping.items()))
    missing = [c for c in table.channels if c not in seen]
    if missing:
        shown = ", ".join(names[:20]) + (" ..." if len(names) > 20 else "")
        raise CaptureReadError(where, "UnknownChannel",
                               f"the channel table {table.source} names channel(s) {', '.join(map(repr, missing))} "
                               f"that this file lacks; its {len(names)} channels: {shown}")
    used = set(table.channels)
    spans = values.max(axis=0) - values.min(axis=0)
    unmapped = tuple(names[i] for i in np.argsort(-spans, kind="stable") if names[i] not in used and spans[i] > VARYING)
    arkit = table.apply(tuple(names), values.astype(np.float64))
    return CapturedTake(where, fmt, arkit, fps, tuple(names), unmapped)


def read_channel_csv(path: str | Path, table: ChannelTable | None = None, fps: float | None = None) -> CapturedTake:
    """A CSV of channels (header = names, one row per frame) as ARKit weights through `table`."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise CaptureReadError(str(path), "UnreadableCapture", f"cannot read ({exc})") from None
    reader = csv.reader(io.StringIO(text, newline=""))
    header = next(reader, None)
    if not header:
        raise CaptureReadError(str(path), "EmptyCapture", "no header of channel names")
    header = [h.strip() for h in header]
    keep = [i for i, h in enumerate(header) if h.lower() not in INDEX_COLUMNS]
    time_col = next((i for i, h in enumerate(header) if h.lower() in ("time", "time_s")), None)
    rows, times = [], []
    for line, row in enumerate(reader, start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise CaptureReadError(str(path), "BadShape", f"line {line}: {len(row)} fields, the header has {len(header)}")
        try:
            rows.append([float(row[i]) for i in keep])
            if time_col is not None:
                times.append(float(row[time_col]))
        except ValueError:
            bad = next(i for i in keep + ([time_col] if time_col is not None else []) if not is_number(row[i]))
            raise CaptureReadError(str(path), "BadValue",
                                   f"line {line}: column {header[bad]!r} holds {row[bad]!r}, not a number") from None
    values = np.array(rows, dtype=np.float64).reshape(len(rows), len(keep))
    if fps is None:
        if time_col is None or len(times) < 2:
            raise CaptureReadError(str(path), "MissingFrameRate",
                                   "no time column (time or time_s, in seconds) to read the frame rate from; give the fps")
        steps = np.diff(times)
        if not np.isfinite(steps).all() or (steps <= 0).any():
            raise CaptureReadError(str(path), "BadTimecode", "the time column does not increase from row to row")
        fps = round(1.0 / statistics.median(steps.tolist()), 3)
    return _channels_to_arkit(tuple(header[i] for i in keep), values, table, path, _fps_or_error(fps, path), "csv")


def _load_npy(path: Path) -> np.ndarray:
    try:
        with warnings.catch_warnings():  # files written by Python 2 need extra header parsing; numpy warns
            warnings.simplefilter("ignore", UserWarning)
            return np.load(path, allow_pickle=False, encoding="latin1")
    except ValueError as exc:
        if "allow_pickle" in str(exc):
            raise CaptureReadError(str(path), "PickledArray", "holds Python objects (a pickle), which are not loaded; "
                                                              "save it as a numeric or string array") from None
        raise CaptureReadError(str(path), "UnreadableCapture", f"not a .npy array ({exc})") from None
    except OSError as exc:
        raise CaptureReadError(str(path), "UnreadableCapture", f"cannot read ({exc})") from None


def _read_names(path: Path) -> tuple[str, ...]:
    if path.suffix.lower() == ".npy":
        names = _load_npy(path)
        if names.ndim != 1 or names.dtype.kind not in "US":
            raise CaptureReadError(str(path), "BadShape", f"channel names must be a 1-D array of strings, got "
                                                          f"{names.dtype} {names.shape}")
        return tuple(unicodedata.normalize("NFC", n.decode("latin1") if isinstance(n, bytes) else str(n)).strip()
                     for n in names.tolist())
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise CaptureReadError(str(path), "UnreadableCapture", f"cannot read the channel names ({exc})") from None
    return tuple(line.strip() for line in text.splitlines() if line.strip())


def read_channel_npy(path: str | Path, names: str | Path, table: ChannelTable | None = None,
                     fps: float | None = None) -> CapturedTake:
    """A (frames, channels) .npy with its channel names (.npy of strings or text, one per line) as ARKit weights."""
    path, names = Path(path), Path(names)
    if fps is None:
        raise CaptureReadError(str(path), "MissingFrameRate", "an .npy capture has no clock; give its fps")
    values = _load_npy(path)
    if values.dtype.kind not in "fiu":
        raise CaptureReadError(str(path), "BadShape", f"expected numbers, got an array of {values.dtype}")
    channel_names = _read_names(names)
    if values.ndim == 2 and values.shape[1] != len(channel_names):
        raise CaptureReadError(str(path), "BadShape", f"{values.shape[1]} channels but the names file {names} lists "
                                                      f"{len(channel_names)}")
    return _channels_to_arkit(channel_names, values.astype(np.float64), table, path, _fps_or_error(fps, path), "npy")


def detect_format(path: str | Path) -> str:
    """`npy` for .npy files; for CSV files `livelink` when the header has Timecode and BlendShapeCount, else `csv`."""
    path = Path(path)
    if path.suffix.lower() == ".npy":
        return "npy"
    if path.suffix.lower() != ".csv":
        raise CaptureReadError(str(path), "UnknownFormat", f"cannot tell the capture format of {path.name}: expected "
                                                           f"a .csv or .npy file, or a format ({', '.join(CAPTURE_FORMATS)})")
    try:
        with open(path, encoding="utf-8-sig", newline="") as fh:
            header = {h.strip().lower() for h in next(csv.reader(fh), [])}
    except (OSError, UnicodeDecodeError) as exc:
        raise CaptureReadError(str(path), "UnreadableCapture", f"cannot read ({exc})") from None
    return "livelink" if {"timecode", "blendshapecount"} <= header else "csv"


def read_take(path: str | Path, fmt: str | None = None, *, table: ChannelTable | None = None,
              names: str | Path | None = None, fps: float | None = None) -> CapturedTake:
    """Read one captured file in `fmt` (detected from the file when None)."""
    path = Path(path)
    if not path.is_file():
        raise CaptureReadError(str(path), "MissingCapture", "captured file not found")
    fmt = fmt or detect_format(path)
    if fmt == "livelink":
        return read_livelink_take(path, fps)
    if fmt == "csv":
        return read_channel_csv(path, table, fps)
    if fmt == "npy":
        if names is None:
            raise CaptureReadError(str(path), "MissingNames", "an .npy capture needs a channel names file")
        return read_channel_npy(path, names, table, fps)
    raise CaptureReadError(str(path), "UnknownFormat", f"unknown capture format {fmt!r}; expected one of "
                                                       f"{', '.join(CAPTURE_FORMATS)}")


# ---- takes: discovery and import -------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Take:
    """One take's files (absolute paths) and settings; `content_hash` covers every file."""

    utterance_id: str
    audio_path: str
    capture_path: str
    format: str | None = None
    table_path: str | None = None
    names_path: str | None = None
    fps: float | None = None
    language: str | None = None
    split: str | None = None
    content_hash: str = ""

    @property
    def speaker(self) -> str:
        return self.utterance_id.split("/")[0]


@dataclass(frozen=True, slots=True)
class TakeDiscovery:
    takes: tuple[Take, ...]
    rejects: tuple[DiscoveryReject, ...] = ()


def _inside(path: Path, root: Path) -> bool:
    try:
        path.resolve().relative_to(root.resolve())
        return True
    except ValueError:
        return False


def _hashed(take: Take) -> Take:
    return replace(take, content_hash=files_hash([take.audio_path, take.capture_path, take.table_path,
                                                  take.names_path]))


def discover_takes(root: str | Path, *, channel_table: str | Path | None = None, names: str | Path | None = None,
                   fps: float | None = None) -> TakeDiscovery:
    """Takes of a manifest CSV (or a folder holding `takes.csv`), else of a folder `<speaker>/<name>.<audio>` +
    `<name>.livelink.csv | .capture.csv | .capture.npy`, or the one take of such a capture file (`<speaker>/<name>`,
    its audio beside it). `channel_table`, `names` and `fps` are the defaults of takes that give none. Bad rows are
    rejects naming the file; nothing outside the manifest's folder is read."""
    root = Path(root)
    check_takes(root)
    defaults = {"table_path": str(Path(channel_table).resolve()) if channel_table else None,
                "names_path": str(Path(names).resolve()) if names else None, "fps": fps}
    if root.is_file() and _capture_suffix(root.name):   # absolute: `take.livelink.csv` in its own folder has one
        return _takes_from_folder(root.absolute().parent.parent, defaults, only=root.absolute())
    if root.is_file():
        return _takes_from_manifest(root, defaults)
    if (root / TAKE_MANIFEST).is_file():
        return _takes_from_manifest(root / TAKE_MANIFEST, defaults)
    return _takes_from_folder(root, defaults)


def check_takes(root: str | Path) -> None:
    """What can be told of `takes` without reading a take (the CLI asks before any flow starts): ValueError
    (FileNotFoundError) naming it when it is missing, or a manifest without the columns a manifest needs."""
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"takes {root} do not exist")
    manifest = root / TAKE_MANIFEST if root.is_dir() else root
    if not manifest.is_file() or _capture_suffix(manifest.name):
        return
    try:
        with open(manifest, encoding="utf-8-sig", newline="") as fh:
            fields = {f.strip() for f in next(csv.reader(fh), [])}
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"manifest {manifest}: cannot read ({exc})") from None
    missing = {"utterance_id", "audio", "capture"} - fields
    if missing:
        raise ValueError(f"manifest {manifest}: missing column(s) {sorted(missing)}; expected {MANIFEST_COLUMNS} (or "
                         f"give one take, `<speaker>/<name>{'|'.join(CAPTURE_SUFFIXES)}` with its audio beside it, or "
                         "a folder of them)")


def _capture_suffix(name: str) -> str | None:
    return next((s for s in CAPTURE_SUFFIXES if name.endswith(s)), None)


def _takes_from_folder(root: Path, defaults: dict, only: Path | None = None) -> TakeDiscovery:
    """The takes of the speaker folders in `root`; `only`: that one capture file's take (its folder the speaker)."""
    takes, rejects = [], []
    real_root = root.resolve()
    speakers = [only.parent] if only is not None else sorted(
        p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    for speaker_dir in speakers:
        files = sorted(p for p in speaker_dir.iterdir() if p.is_file() and not p.name.startswith("."))
        audio: dict[str, Path] = {}
        for ext in reversed(AUDIO_EXTS + VIDEO_EXTS):  # the first extension of each list wins
            for p in files:
                if p.name.endswith(ext):
                    audio[p.name[: -len(ext)]] = p
        for p in files:
            suffix = _capture_suffix(p.name)
            if suffix is None or (only is not None and p.name != only.name):
                continue
            stem = p.name[: -len(suffix)]
            try:
                uid = make_utterance_id(speaker_dir.name, stem)
            except InvalidIdError as exc:
                rejects.append(DiscoveryReject(None, "InvalidId", f"{p}: {exc}", str(p)))
                continue
            outside = next((q for q in (p, audio.get(stem)) if q is not None and not _inside(q, real_root)), None)
            if outside is not None:
                rejects.append(DiscoveryReject(uid, "PathOutsideCorpus", f"{uid}: {outside} is a link to "
                                               f"{outside.resolve()}, outside the takes folder {real_root}", str(outside)))
                continue
            if stem not in audio:
                rejects.append(DiscoveryReject(uid, "MissingAudio", f"{uid}: no {'/'.join(AUDIO_EXTS)} (or video) file "
                                               f"next to {p}", str(p)))
                continue
            takes.append(_hashed(Take(uid, str(audio[stem].resolve()), str(p.resolve()), CAPTURE_SUFFIXES[suffix],
                                      **defaults)))
    return TakeDiscovery(tuple(takes), tuple(rejects))


def _takes_from_manifest(manifest: Path, defaults: dict) -> TakeDiscovery:
    root = manifest.parent.resolve()
    takes, rejects, seen = [], [], set()
    try:
        text = manifest.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"manifest {manifest}: cannot read ({exc})") from None
    reader = csv.DictReader(io.StringIO(text, newline=""))
    fields = [f.strip() for f in reader.fieldnames or []]
    reader.fieldnames = fields
    # its columns were checked by `check_takes`
    for line, row in enumerate(reader, start=2):
        where = f"{manifest}:{line}"
        try:
            uid = normalize_utterance_id((row.get("utterance_id") or "").strip())
        except InvalidIdError as exc:
            rejects.append(DiscoveryReject(None, "InvalidId", f"{where}: {exc}", str(manifest)))
            continue
        if uid in seen:
            rejects.append(DiscoveryReject(uid, "DuplicateId", f"{where}: {uid} listed twice", str(manifest)))
            continue
        seen.add(uid)
        paths, bad = {}, None
        for col in ("audio", "capture", "channels", "names"):
            value = (row.get(col) or "").strip()
            if not value:
                paths[col] = None
                continue
            path = (root / value).resolve()
            if not _inside(path, root):
                bad = DiscoveryReject(uid, "PathOutsideCorpus",
                                      f"{where}: {uid}: {col} path {value!r} leaves the manifest's folder {root}", value)
            elif not path.is_file():
                bad = DiscoveryReject(uid, f"Missing{col.capitalize()}",
                                      f"{where}: {uid}: {col} file {path} does not exist", str(path))
            if bad:
                break
            paths[col] = str(path)
        fmt = (row.get("format") or "").strip().lower() or None
        if bad is None and (paths["audio"] is None or paths["capture"] is None):
            bad = DiscoveryReject(uid, "MissingInput", f"{where}: {uid}: audio and capture are required", str(manifest))
        if bad is None and fmt is not None and fmt not in CAPTURE_FORMATS:
            bad = DiscoveryReject(uid, "UnknownFormat", f"{where}: {uid}: format {fmt!r} is not one of "
                                  f"{', '.join(CAPTURE_FORMATS)}", str(manifest))
        fps_text = (row.get("fps") or "").strip()
        fps = defaults["fps"]
        if bad is None and fps_text:
            try:
                fps = float(fps_text)
                if not (math.isfinite(fps) and fps > 0):
                    raise ValueError
            except ValueError:
                bad = DiscoveryReject(uid, "BadFrameRate", f"{where}: {uid}: fps {fps_text!r} is not a positive "
                                      "number", str(manifest))
        if bad is not None:
            rejects.append(bad)
            continue
        takes.append(_hashed(Take(
            uid, paths["audio"], paths["capture"], fmt, paths["channels"] or defaults["table_path"],
            paths["names"] or defaults["names_path"], fps, (row.get("language") or "").strip() or None,
            (row.get("split") or "").strip() or None)))
    return TakeDiscovery(tuple(takes), tuple(rejects))


@dataclass(frozen=True)
class ImportedTake:
    """A take's `utterances` row, its fitted curves at `fps`, and what the reading and the fit found."""

    utterance: dict[str, object]
    curves: np.ndarray = field(repr=False)
    fps: float
    fit: VisemeFit = field(repr=False)
    capture: CapturedTake = field(repr=False)
    drift_frames: float


def import_take(take: Take, config: CaptureConfig, solver: ArkitToVisemes | None = None) -> ImportedTake:
    """Read a take's audio header and captured file, check their lengths agree, fit the viseme curves.

    Raises `CaptureReadError` (naming the take's file) or `ingest.IngestError` (the audio) for bad input."""
    uid = take.utterance_id
    video = take.audio_path if is_video_file(take.audio_path) else None
    entry = CorpusEntry(uid, take.audio_path, "", video_path=video, content_hash=take.content_hash)
    sample_rate, duration = read_audio_info(entry)
    table = read_channel_table(take.table_path) if take.table_path else None
    capture = read_take(take.capture_path, take.format, table=table, names=take.names_path, fps=take.fps)
    n, fps = capture.n_frames, capture.fps
    drift = n - duration * fps
    allowed = max(1.0, config.max_drift_frames_per_s * duration)
    if abs(drift) > allowed:
        raise CaptureReadError(take.capture_path, "CaptureAudioMismatch",
                               f"{n} frames at {fps:g} fps ({n / fps:.3f} s) but the audio {take.audio_path} lasts "
                               f"{duration:.3f} s ({duration * fps:.1f} frames): {abs(drift):.1f} frames apart, more "
                               f"than the {allowed:.1f} allowed ({config.max_drift_frames_per_s:g} per second of audio)")
    try:
        fit = fit_visemes(capture.arkit, solver, where=take.capture_path)
    except CaptureError as exc:
        raise CaptureReadError(take.capture_path, "BadCapture", str(exc).removeprefix(f"{take.capture_path}: ")) from exc
    utterance = {
        C.UTTERANCE_ID: uid, C.SPEAKER: take.speaker, C.LANGUAGE: take.language, C.INVENTORY: None,
        C.AUDIO_PATH: take.audio_path, C.VIDEO_PATH: video, C.ALIGNMENT_PATH: "",
        C.ALIGNMENT_FORMAT: CAPTURED_ALIGNMENT_FORMAT, C.LANDMARK_PATH: None, C.SAMPLE_RATE: sample_rate,
        C.DURATION_S: duration, C.FPS: fps, C.N_FRAMES: n, C.CONTENT_HASH: take.content_hash,
        C.SPLIT: take.split or assign_split(uid, config.val_fraction),
    }
    return ImportedTake(utterance, fit.curves, fps, fit, capture, float(drift))


BAD_INPUT_ERRORS = (CaptureReadError, IngestError)
"""The bad-input errors of `import_take` (a reject each)."""
