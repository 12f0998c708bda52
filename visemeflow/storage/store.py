"""The Parquet store: paths, atomic writes, reads.

Layout under the root folder:
    tables/<table>/shard-NNNN.parquet                  utterances, phones (one file per shard)
    tables/rejects/<stage>/shard-NNNN.parquet          rejects of a stage, per shard
    curves/<source>/<variant>/<speaker>/<name>.parquet one file per (source, variant, utterance)
    tracking_frames/<variant>/<speaker>/<name>.parquet per-frame tracking diagnostics
    landmarks/<speaker>/<name>.mediapipe478.parquet    FaceMesh 478 points per video frame (landmarks stage)
    models/<model>/model.pt, checkpoints/              trained models
    metrics/<model>/<run>.parquet                      metrics of a model's runs
    augmented/<set>/<speaker>/<name>.wav               augmented validation audio of `evaluate`
    reports/<name>                                     tables and plots (robustness.md, sweep-*.png)
    configs/<stage>.json                               the settings each stage last ran with
    .prefect-results/                                  Prefect's persisted task results
    .locks/                                            lock files of read-modify-write updates

<speaker>/<name> are the utterance id's parts percent-encoded (`schemas.ids.id_path_parts`): ASCII ids of
letters, digits and `_ - .` appear as they are, others (`张三/一`, `Speaker One/a`) reversibly encoded.

Every file goes through this class: flows, tasks and operations ask it for paths and listings and let it
write and delete. Every file is written with `visemeflow.atomic` (a uniquely named hidden temporary file in
its folder, fsync, rename over the target), so a killed writer never leaves a half file and readers see the
old or the new file whole. Shard files that are read, changed and written back (a rerun of one utterance)
are updated under a lock file so two writers cannot lose each other's rows. Curves and metrics are checked
before they are written: a NaN or infinite value is refused with the utterance and the first bad value named.
Reject messages are capped where they are written (`write_shard`, `replace_utterance_rows`): the head and
how many characters were cut.

The root may also be a URL on object storage (`s3://bucket/prefix`, `visemeflow.location`): the same layout, each
file uploaded whole in one PUT from a local temporary file, the locks and the shard rewrites conditional PUTs (no
rename, flock or pid), listings uncached; docs/reference.md, "A store on object storage".
"""

import errno
import fcntl
import json
import os
import re
import secrets
import shutil
import socket
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import timezone
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from visemeflow.atomic import atomic_path, is_temporary_name, temporary_writer, this_machine
from visemeflow.location import object_copy, parse_root, private_folder, remote_root
from visemeflow.schemas import (
    CURVES,
    METRICS,
    TABLE_SCHEMAS,
    TRACKING_FRAMES,
    C,
    id_path_parts,
    utterance_id_from_path_parts,
    validate_name,
)
from visemeflow.schemas.curves import FPS_KEY, PROVENANCE_KEY, Curves
from visemeflow.timebase import DEFAULT_FPS
from visemeflow.visemes import VISEMES

# Curve files are small and many: dictionary-encode only the constant id columns and keep statistics only
# where dataset scans prune files by them (a third less write time, a quarter smaller files).
CURVE_FILE_OPTIONS = {
    "use_dictionary": [C.UTTERANCE_ID, C.SOURCE, C.VARIANT],
    "write_statistics": [C.UTTERANCE_ID, C.SOURCE, C.VARIANT, C.FRAME],
}



def _dataset(*args, **kwargs):
    """`pyarrow.dataset.dataset`, imported on first use: the module pulls in pandas (0.3 s), which a command that
    reads no table (a cached `predict`) does not need."""
    import pyarrow.dataset as ds

    return ds.dataset(*args, **kwargs)

def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _conform(table: pa.Table, schema: pa.Schema) -> pa.Table:
    """`table` with exactly `schema`'s columns, in its order: missing ones null (a file an older version wrote), extra
    ones dropped; as a pyarrow dataset with that schema reads the file."""
    columns = [table.column(f.name).cast(f.type) if f.name in table.column_names
               else pa.nulls(table.num_rows, f.type) for f in schema]
    return pa.Table.from_arrays(columns, schema=schema.remove_metadata())


class StoreError(OSError):
    """The store cannot be written or read; the message names the path and the reason."""


def damaged_curves(path, utterance_id: str, source: str, exc: Exception) -> "StoreError":
    """The error of a curve file that does not read as Parquet (cut short by a copy or a full disk)."""
    again = {"procedural": "procedural", "tracked": "track"}.get(source)
    how = (f"`visemeflow rerun {utterance_id} --stage {again}` (or the pipeline) makes it again" if again else
           "make it again with the command that made it")
    return StoreError(errno.EIO, f"{path}: the {source} curves of {utterance_id} are damaged, not a whole Parquet "
                                 f"file ({str(exc).splitlines()[0]}); {how}")


class NonFiniteValueError(ValueError):
    """Curves or metrics holding NaN or an infinite value: refused before anything is written."""


RESULTS_DIR = ".prefect-results"
_SHARD_FILE = re.compile(r"^shard-([0-9]{4,})\.parquet$")
MAX_REJECT_MESSAGE_CHARS = 4000
"""Longest reject message stored, note included. Real reasons are a few hundred characters; an input can make them
megabytes (an XML entity expanded into the value an error quotes), which would then fill the `rejects` output and
every dashboard page."""


def cap_message(message: str, limit: int = MAX_REJECT_MESSAGE_CHARS) -> str:
    """`message` itself when it has at most `limit` characters, else its head and "... [N characters cut]", `limit`
    characters in all (so a capped message is never cut again)."""
    if len(message) <= limit:
        return message
    head = limit - len("... [ characters cut]") - len(str(len(message)))  # the count has at most that many digits
    return f"{message[:head]}... [{len(message) - head} characters cut]"


def _cap_messages(table: pa.Table) -> pa.Table:
    """The rejects `table` with each message capped (`cap_message`)."""
    column = table.column(C.MESSAGE)
    if table.num_rows == 0 or pc.max(pc.utf8_length(column)).as_py() <= MAX_REJECT_MESSAGE_CHARS:
        return table
    capped = [cap_message(m) for m in column.to_pylist()]  # the column is not nullable
    return table.set_column(table.schema.get_field_index(C.MESSAGE), table.schema.field(C.MESSAGE),
                            pa.array(capped, column.type))


def _first_non_finite(table: pa.Table, columns: list[str]) -> tuple[int, str, object, int] | None:
    """(row, column, value, number of bad values) of the first NaN, infinite or null value in `columns`."""
    if all(table.column(c).null_count == 0 and np.isfinite(table.column(c).to_numpy()).all() for c in columns):
        return None  # the common case, checked column by column without copies
    values = np.stack([table.column(c).to_numpy(zero_copy_only=False).astype(np.float64, copy=False)
                       for c in columns], axis=1) if table.num_rows else np.zeros((0, len(columns)))
    bad = ~np.isfinite(values)
    if not bad.any():
        return None
    row = int(np.flatnonzero(bad.any(axis=1))[0])
    col = int(np.flatnonzero(bad[row])[0])
    value = table.column(columns[col])[row].as_py()
    return row, columns[col], value, int(bad.sum())


def _read_whole(path: Path) -> pa.Table:
    """One Parquet file read through a single open handle.

    `pq.read_table(path)` opens the path more than once (footer, then pages); a writer renaming a new
    file over it in between makes the read fail ("Page was smaller than expected"). One handle keeps
    the read on one version of the file. The handle is Arrow's own (`pa.OSFile`), not a Python file: buffers
    read through a Python file are Python objects, and an Arrow I/O thread that drops the last one while the
    interpreter exits must take the GIL, is ended by Python and aborts the process (`visemeflow predict` exited
    with SIGABRT after its work was done).
    """
    if not isinstance(path, Path):   # an object of a store on object storage: one GET, one version
        return pq.read_table(pa.BufferReader(path.fs.cat_file(path.path)))
    with pa.OSFile(str(path)) as fh:
        return pq.read_table(fh)


def _parquet_tail_ok(path: Path) -> bool:
    """A local file that ends as a whole Parquet file does: a footer length that fits, then the magic `PAR1`."""
    try:
        with open(path, "rb") as fh:
            size = fh.seek(0, os.SEEK_END)
            if size < 12:
                return False
            fh.seek(size - 8)
            tail = fh.read(8)
    except (FileNotFoundError, NotADirectoryError, IsADirectoryError):   # a file where a folder would be, or none
        return False
    footer = int.from_bytes(tail[:4], "little")
    return tail[4:] == b"PAR1" and 0 < footer <= size - 12


def _read_schema(path: Path) -> pa.Schema:
    """The Arrow schema (with the file's metadata) of one Parquet file, read through one handle (`_read_whole`)."""
    if not isinstance(path, Path):
        return pq.read_schema(pa.BufferReader(path.fs.cat_file(path.path)))   # small files; one GET, one version
    with pa.OSFile(str(path)) as fh:
        return pq.read_schema(fh)


LOCK_LEASE_S = float(os.environ.get("VISEMEFLOW_LOCK_LEASE_S", "600"))
"""A lock object of a store on object storage older than this is taken for a dead holder's and removed (no pid can
be checked across machines). The locked sections are short (one shard file read and written back). Its age is
judged on the object store's clock (`Store._server_clock_skew`), not the machines'."""


def _lock_file(lock_path: Path):
    """The local lock file `lock_path` opened for reading and appending (made with its folder when missing); a
    StoreError naming it when it cannot be."""
    try:
        lock_path.parent.mkdir(parents=True, exist_ok=True)
        return open(lock_path, "a+")
    except OSError as exc:
        raise StoreError(exc.errno or 0, f"cannot lock {lock_path}: {exc.strerror or exc}") from exc


def _timestamp(moment) -> float:
    """POSIX seconds of an object's date (fsspec gives datetimes, naive ones in UTC)."""
    return moment.timestamp() if moment.tzinfo else moment.replace(tzinfo=timezone.utc).timestamp()


@dataclass(frozen=True)
class PartialUpload:
    """An unfinished multipart upload under a store on object storage (`Store.stale_uploads`)."""

    path: Path        # the store path it would have written
    key: str          # its object key in the bucket
    upload_id: str
    started: float    # POSIX seconds, the server's clock
    n_bytes: int      # of the parts uploaded so far


def _server_time(response: Mapping) -> float | None:
    """POSIX seconds of an S3 answer's `Date` header: the server's clock when it answered, or None without one."""
    from email.utils import parsedate_to_datetime

    date = response.get("ResponseMetadata", {}).get("HTTPHeaders", {}).get("date")
    try:
        return _timestamp(parsedate_to_datetime(date)) if date else None
    except (TypeError, ValueError):
        return None


def _private_folder(kind: str, what: str) -> Path:
    """`location.private_folder`, its refusal a StoreError as every other of the store's."""
    try:
        return private_folder(kind, what)
    except PermissionError as exc:
        raise StoreError(exc.errno, exc.strerror) from exc


class Store:
    """A Parquet store rooted at one folder, or at a prefix on object storage (`s3://bucket/prefix`: see
    `visemeflow.location`). `root` is a `Path` for a folder and a `upath.UPath` for a URL; the paths the methods give
    are of the same kind, with the same `/`, `name`, `parent`, `exists()`, `read_bytes()`."""

    def __init__(self, root: Path | str):
        parsed = parse_root(root)
        self.remote = isinstance(parsed, str)
        self.url: str | None = parsed if self.remote else None
        self.root = remote_root(parsed) if self.remote else Path(parsed).resolve()

    def __repr__(self) -> str:
        return f"Store({str(self.root)!r})"

    @property
    def location(self) -> str:
        """The root as text for messages and task arguments: the folder, or the URL."""
        return self.url or str(self.root)

    # ---- paths -------------------------------------------------------------------------------
    def table_dir(self, table: str, stage: str | None = None) -> Path:
        if table not in TABLE_SCHEMAS:
            raise ValueError(f"unknown table {table!r}; tables are {sorted(TABLE_SCHEMAS)}")
        folder = self.root / "tables" / table
        return folder / validate_name(stage, "stage") if stage else folder

    def shard_path(self, table: str, shard: int, stage: str | None = None) -> Path:
        return self.table_dir(table, stage) / f"shard-{shard:04d}.parquet"

    def curve_path(self, source: str, variant: str, utterance_id: str) -> Path:
        speaker, name = id_path_parts(utterance_id)
        return (
            self.root / "curves" / validate_name(source, "curve source") / validate_name(variant, "variant")
            / speaker / f"{name}.parquet"
        )

    def tracking_frames_path(self, variant: str, utterance_id: str) -> Path:
        speaker, name = id_path_parts(utterance_id)
        return self.root / "tracking_frames" / validate_name(variant, "variant") / speaker / f"{name}.parquet"

    def landmark_path(self, utterance_id: str) -> Path:
        """FaceMesh landmarks the `landmarks` stage detected on an utterance's video: the columns of a
        `.mediapipe478.csv` (frame, time_s, detected, x_i, y_i, z_i) in Parquet; `read_landmarks` reads it."""
        speaker, name = id_path_parts(utterance_id)
        return self.root / "landmarks" / speaker / f"{name}.mediapipe478.parquet"

    def has_landmarks(self, utterance_id: str) -> bool:
        return self.landmark_path(utterance_id).is_file()

    def landmarks_provenance(self, utterance_id: str) -> str | None:
        """What made an utterance's stored landmarks (as given to `write_landmarks`), or None when there are none."""
        path = self.landmark_path(utterance_id)
        if not path.is_file():
            return None
        return (_read_schema(path).metadata or {}).get(PROVENANCE_KEY, b"").decode()

    def local_file(self, path: Path) -> str:
        """A local path holding the store file `path`, for readers that take only a local path (the tracker's
        landmark reader): `path` itself in a folder store. From object storage the file is downloaded once per
        version (its ETag names the copy) into this machine's temporary folder, so repeated reads cost one HEAD."""
        if not self.remote:
            return str(path)
        try:
            return object_copy(self.root.fs, path.path, str(path))
        except PermissionError as exc:   # the private folder refused (or the server: fsspec's 403), as the store's
            raise StoreError(exc.errno or errno.EACCES, exc.strerror or f"{path}: {exc}") from exc

    @staticmethod
    def utterance_id_of(path: str | Path) -> str:
        """The utterance id of a per-utterance file of the store (`.../<speaker>/<name>.<ext>`)."""
        path = Path(path)
        return utterance_id_from_path_parts(path.parent.name, path.name.removesuffix(path.suffix))

    def model_dir(self, model: str) -> Path:
        """Folder of a trained model: weights, config and lineage, checkpoints."""
        return self.root / "models" / validate_name(model, "model name")

    def model_path(self, model: str) -> Path:
        """The file of a trained model (weights, config, lineage), written when its training finished."""
        return self.model_dir(model) / "model.pt"

    def checkpoint_dir(self, model: str) -> Path:
        """Folder of a model's training checkpoints (an interrupted training resumes from them)."""
        return self.model_dir(model) / "checkpoints"

    def local_file_at(self, location: str) -> str:
        """`local_file` of a store file given as text (a path, or a URL this store's methods made, as task results
        carry them); ValueError when it is not inside the store."""
        path = remote_root(location) if self.remote else Path(location)
        return self.local_file(self._inside(path))

    def model_file(self, model: str) -> str:
        """A local path holding the trained model's file, for `torch.load` and hashing: the file itself in a folder
        store; from object storage a copy named by the object's version (`local_file`)."""
        return self.local_file(self.model_path(model))

    def local_work_dir(self, path: Path) -> Path:
        """A local folder to work in for the store folder `path` (a training's checkpoints): `path` itself in a
        folder store; on object storage a folder of this user's under the machine's temporary folder, named by the
        store path, which the caller uploads from (`write_file`)."""
        if not self.remote:
            return path
        import hashlib

        digest = hashlib.blake2b(str(path).encode(), digest_size=12).hexdigest()
        local = _private_folder("work", "the local work folders of a store on object storage") / f"{digest}-{path.name}"
        local.mkdir(mode=0o700, exist_ok=True)
        return local

    def install_model(self, model: str, source: Path) -> Path:
        """Copy a trained model file (e.g. the package's default model) into the store as `model`, atomically."""
        data = Path(source).read_bytes()
        return self._replace(self.model_path(model), lambda tmp: Path(tmp).write_bytes(data))

    def has_model(self, model: str) -> bool:
        return self.model_path(model).is_file()

    def model_names(self) -> list[str]:
        """Names of the trained models (those whose training finished), sorted."""
        folder = self.root / "models"
        if not folder.is_dir():
            return []
        return sorted(d.name for d in folder.iterdir()
                      if d.is_dir() and not d.name.startswith(".") and (d / "model.pt").is_file())

    def finished_checkpoint_dirs(self) -> list[Path]:
        """Checkpoint folders of models whose training finished (nothing resumes from them any more)."""
        return [self.checkpoint_dir(m) for m in self.model_names() if self.checkpoint_dir(m).is_dir()]

    def augmented_audio_path(self, augmentation: str, augmented_id: str) -> Path:
        """An augmented copy of an utterance's audio (float WAV), in the folder of one augmentation set."""
        speaker, name = id_path_parts(augmented_id)
        return self.root / "augmented" / validate_name(augmentation, "augmentation") / speaker / f"{name}.wav"

    def has_augmented_audio(self, augmentation: str, augmented_id: str) -> bool:
        return self.augmented_audio_path(augmentation, augmented_id).is_file()

    def augmented_sets(self) -> list[Path]:
        """Folders of the stored augmentation sets (`augmented/<condition>-s<seed>`), sorted."""
        folder = self.root / "augmented"
        return sorted(p for p in folder.iterdir() if p.is_dir()) if folder.is_dir() else []

    def metrics_path(self, model: str, run: str) -> Path:
        return self.root / "metrics" / validate_name(model, "model name") / f"{validate_name(run, 'run name')}.parquet"

    def has_metrics(self, model: str, run: str) -> bool:
        return self.metrics_path(model, run).is_file()

    def animation_dir(self, character: str, utterance_id: str) -> Path:
        """Folder of one utterance's animation files for one character (`animations/<character>/<speaker>/<name>/`)."""
        speaker, name = id_path_parts(utterance_id)
        return self.root / "animations" / validate_name(character, "character name") / speaker / name

    def animation_dirs(self) -> list[Path]:
        """Folders of stored animation packages (`animations/<character>/<speaker>/<name>/`), sorted."""
        folder = self.root / "animations"
        if not folder.is_dir():
            return []
        return sorted(p for p in folder.glob("*/*/*") if p.is_dir() and not p.name.startswith("."))

    def report_path(self, name: str) -> Path:
        """A report file (`robustness.md`, `sweep-<preset>.png`) in the store's `reports` folder."""
        return self.root / "reports" / validate_name(name, "report name")

    def report_files(self, prefix: str = "", suffix: str = "") -> list[Path]:
        """Stored report files whose names start with `prefix` and end with `suffix`, sorted."""
        folder = self.root / "reports"
        if not folder.is_dir():
            return []
        return sorted(p for p in folder.iterdir() if p.is_file() and not is_temporary_name(p.name)
                      and not p.name.startswith(".") and p.name.startswith(prefix) and p.name.endswith(suffix))

    def results_dir(self) -> Path:
        """Folder of Prefect's persisted task results and cache records (see `tasks.common.result_storage`)."""
        return self.root / RESULTS_DIR

    # ---- writes ------------------------------------------------------------------------------
    def _inside(self, path: Path) -> Path:
        if self.remote:
            text, root = str(path), str(self.root)
            if type(path) is not type(self.root) or ".." in text.split("/") or not (
                    text == root or text.startswith(root + "/")):
                raise ValueError(f"{path} is not inside the store {root}")
            return path
        path = Path(path)
        resolved = path.resolve()
        if resolved != self.root and self.root not in resolved.parents:
            raise ValueError(f"{path} is not inside the store {self.root}")
        return path

    def write_file(self, path: Path, writer: Callable[[Path], object], *, keep_suffix: bool = False) -> Path:
        """Replace the store file `path` with what `writer(temporary_path)` writes, atomically.

        For files not written by a method of their own (augmented audio, a plot): `writer` gets a hidden
        temporary path in the same folder (ending in `path`'s suffix when `keep_suffix`, for writers that pick
        the format by it). A failing writer leaves the previous file in place; an OSError becomes a StoreError
        naming `path`.
        """
        return self._replace(self._inside(path), writer, keep_suffix)

    def _replace(self, path: Path, writer: Callable[[Path], object], keep_suffix: bool = False) -> Path:
        """`write_file` for a path this class made (inside the store by construction: no check on the hot path)."""
        if self.remote:
            return self._upload(path, writer, keep_suffix)
        try:
            with atomic_path(path, keep_suffix=keep_suffix) as tmp:
                writer(tmp)
        except OSError as exc:  # any other failure (ArrowInvalid, Ctrl-C) propagates as it is
            reason = "disk full" if exc.errno == errno.ENOSPC else (exc.strerror or str(exc))
            raise StoreError(exc.errno or 0, f"cannot write {path}: {reason}; stored data is unchanged") from exc
        return path

    def _upload(self, path: Path, writer: Callable[[Path], object], keep_suffix: bool,
                put: Callable[[Path], object] | None = None) -> Path:
        """`_replace` on object storage: `writer` writes a local temporary file, which is then uploaded in one PUT
        (a multipart upload, completed only when whole, for a large file), so the object appears whole or not at
        all and a writer that fails or is killed uploads nothing. `put(local_file)` replaces the upload (a
        conditional PUT)."""
        suffix = path.suffix if keep_suffix else ""
        try:
            with tempfile.TemporaryDirectory(prefix="visemeflow-put-") as folder:
                tmp = Path(folder) / f".{path.name}.tmp{suffix}"
                writer(tmp)
                if put is not None:
                    put(tmp)
                else:
                    self.root.fs.put_file(str(tmp), path.path)
        except FileExistsError:
            raise   # a conditional PUT refused (`replace_utterance_rows` reads again)
        except OSError as exc:
            reason = "disk full" if exc.errno == errno.ENOSPC else (exc.strerror or str(exc))
            raise StoreError(exc.errno or 0, f"cannot write {path}: {reason}; stored data is unchanged") from exc
        return path

    def _write_atomic(self, table: pa.Table, path: Path, **parquet_options: object) -> Path:
        options = {"compression": "zstd", **parquet_options}
        return self._replace(path, lambda tmp: pq.write_table(table, tmp, **options))

    def write_shard(
        self, table_name: str, shard: int, table: pa.Table, stage: str | None = None,
        metadata: dict[bytes, bytes] | None = None, keep: Callable[[pa.Table], pa.Table] | None = None,
    ) -> Path:
        """Replace one shard file of a table with `table` (cast to the table's schema) and file metadata; reject
        messages are capped (`MAX_REJECT_MESSAGE_CHARS`).

        Under the shard's lock, as `replace_utterance_rows` writes, so that one utterance's rows replaced by a rerun
        or an import are never lost to a whole shard's write that read the shard before them: `keep(stored)`
        gives the rows of the shard as stored *now* that the new file keeps besides `table` (read under the lock,
        and on S3 written back only if unchanged since)."""
        schema = TABLE_SCHEMAS[table_name]
        table = table.cast(schema)

        def new(stored: pa.Table) -> pa.Table:
            out = table if keep is None else pa.concat_tables([table, keep(stored).cast(schema)])
            if table_name == "rejects":
                out = _cap_messages(out)
            return out.replace_schema_metadata(metadata) if metadata else out

        return self._rewrite(table_name, shard, stage, new, read=keep is not None)

    def write_curves(
        self, table: pa.Table, *, provenance: str = "", fps: float | None = None
    ) -> Path:
        """Write the curves of one (source, variant, utterance); `provenance` records what made them."""
        table = table.cast(CURVES)
        ids = table.column(C.UTTERANCE_ID).unique().to_pylist()
        sources = table.column(C.SOURCE).unique().to_pylist()
        variants = table.column(C.VARIANT).unique().to_pylist()
        if len(ids) != 1 or len(sources) != 1 or len(variants) != 1:
            raise ValueError(
                f"a curves file holds one utterance, source and variant; got {ids[:3]}, {sources}, {variants}"
            )
        path = self.curve_path(sources[0], variants[0], ids[0])  # validates the id before anything else
        what = f"{ids[0]} ({sources[0]}/{variants[0]})"
        bad = _first_non_finite(table, [C.TIME_S, *VISEMES])
        if bad is not None:
            row, column, value, n_bad = bad
            frame = table.column(C.FRAME)[row].as_py()
            raise NonFiniteValueError(
                f"refusing to write curves of {what}: frame {frame}, column {column} is {value} "
                f"({n_bad} NaN, infinite or missing values in all); nothing was written to {path}"
            )
        if fps is not None and not np.isfinite(fps):
            raise NonFiniteValueError(f"refusing to write curves of {what}: frame rate {fps} is not finite")
        meta = {PROVENANCE_KEY: provenance.encode()}
        if fps is not None:
            meta[FPS_KEY] = repr(float(fps)).encode()
        table = table.replace_schema_metadata(meta)
        return self._write_atomic(table, path, **CURVE_FILE_OPTIONS)

    def write_tracking_frames(self, table: pa.Table) -> Path:
        """Per-frame tracking diagnostics of one (variant, utterance), replacing what was stored."""
        table = table.cast(TRACKING_FRAMES)
        ids = table.column(C.UTTERANCE_ID).unique().to_pylist()
        variants = table.column(C.VARIANT).unique().to_pylist()
        if len(ids) != 1 or len(variants) != 1:
            raise ValueError(f"a tracking_frames file holds one utterance and variant; got {ids[:3]}, {variants[:3]}")
        return self._write_atomic(table, self.tracking_frames_path(variants[0], ids[0]))

    def write_landmarks(self, utterance_id: str, table: pa.Table, *, provenance: str = "") -> Path:
        """An utterance's FaceMesh landmark table (`tracking.facemesh.mediapipe478_table`), replacing what was
        stored; `provenance` records what made it."""
        path = self.landmark_path(utterance_id)
        meta = dict(table.schema.metadata or {})
        meta[PROVENANCE_KEY] = provenance.encode()
        # 1,437 columns of noisy floats: no column statistics (nothing filters on them), no dictionaries and snappy
        # for zstd (neither shrinks these: a 75-frame GRID clip's file 894 -> 667 kB); its write 123 -> 26 ms, and
        # reading two of its columns 10.5 -> 5.0 ms (the footer a reader parses is the smaller)
        return self._write_atomic(table.replace_schema_metadata(meta), path, compression="snappy",
                                  use_dictionary=False, write_statistics=False)

    def read_tracking_frames(self, variant: str | None = None, utterance_ids: list[str] | None = None) -> pa.Table:
        """Stored tracking diagnostics (of one variant, some utterances) as one table."""
        files = self.tracking_frame_files(variant)
        if not files or utterance_ids == []:
            return TRACKING_FRAMES.empty_table()
        dataset = self._dataset(files, schema=TRACKING_FRAMES, format="parquet")
        flt = pc.field(C.UTTERANCE_ID).isin(utterance_ids) if utterance_ids is not None else None
        return dataset.to_table(filter=flt)

    def write_metrics(self, model: str, run: str, table: pa.Table) -> Path:
        """The metrics rows of one (model, run), replacing what that run wrote before.

        NaN and infinite values are refused (a missing per-viseme value is null, not NaN).
        """
        path = self.metrics_path(model, run)
        table = table.cast(METRICS)
        columns = [C.L1, C.L1_X100, *(C.L1_PREFIX + v for v in VISEMES)]
        values = table.select(columns)
        # nulls are allowed where the schema allows them: compare only the non-null values
        for column in columns:
            col = values.column(column)
            finite = pc.is_finite(col)
            if pc.any(pc.invert(pc.fill_null(finite, True))).as_py():
                row = int(np.flatnonzero(~np.asarray(pc.fill_null(finite, True)))[0])
                r = table.slice(row, 1).to_pylist()[0]
                raise NonFiniteValueError(
                    f"refusing to write metrics of model {model}, run {run}: row {row} (condition "
                    f"{r[C.CONDITION]}, utterance {r[C.UTTERANCE_ID] or 'all'}, epoch {r[C.EPOCH]}), column "
                    f"{column} is {r[column]}; nothing was written to {path}"
                )
        return self._write_atomic(table, path)

    def read_metrics(self, model: str | None = None) -> pa.Table:
        folder = self.root / "metrics"
        if model:
            folder = folder / validate_name(model, "model name")
        files = self._files(folder)
        return self._dataset(files, schema=METRICS, format="parquet").to_table() if files else METRICS.empty_table()

    @contextmanager
    def locked(self, name: str) -> Iterator[None]:
        """Hold an exclusive lock named `name` (a file under the store) for a read-modify-write.

        On object storage the lock is an object created only where none exists (`If-None-Match: *`), removed when
        the block ends; one older than `LOCK_LEASE_S` is taken for a dead holder's and removed."""
        lock_path = self.root / ".locks" / f"{validate_name(name, 'lock name')}.lock"
        if self.remote:
            with self._object_lock(lock_path):
                yield
            return
        with _lock_file(lock_path) as fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)

    @contextmanager
    def _object_lock(self, lock_path: Path) -> Iterator[None]:
        """`locked` on object storage (see there)."""
        fs, key = self.root.fs, lock_path.path
        token = f"{socket.gethostname()} {os.getpid()} {secrets.token_hex(8)}".encode()
        delay = 0.02
        skew: float | None = None      # the server's clock minus this machine's, learnt when a lock is met
        while True:
            try:
                fs.pipe_file(key, token, mode="create")
                break
            except FileExistsError:
                try:
                    stamp = _timestamp(fs.modified(key))
                except FileNotFoundError:
                    continue   # released between the two calls
                if skew is None:
                    try:
                        skew = self._server_clock_skew(lock_path)
                    except OSError as exc:
                        raise StoreError(exc.errno or 0, f"cannot lock {lock_path}: {exc}") from exc
                if time.time() + skew - stamp > LOCK_LEASE_S:
                    fs.rm_file(key)   # a dead holder's: whoever creates it next holds it
                    continue
                time.sleep(delay)
                delay = min(2 * delay, 0.5)
            except OSError as exc:
                raise StoreError(exc.errno or 0, f"cannot lock {lock_path}: {exc}") from exc
        try:
            yield
        finally:
            try:
                if fs.cat_file(key) == token:   # never another holder's (ours may have been broken as stale)
                    fs.rm_file(key)
            except FileNotFoundError:
                pass

    @contextmanager
    def held(self, name: str, what: str) -> Iterator[None]:
        """Hold the lease `name` (for `what`, named in the refusal) while the block runs, for hours if need be;
        StoreError (EBUSY) naming the holder when another holder's lease is live, on any machine.

        On object storage the lease is an object created only where none exists (`If-None-Match: *`), rewritten
        every `LOCK_LEASE_S` / 4 by a background thread while held (its date, the server's clock, is the
        heartbeat) and removed at the end. One not rewritten for `LOCK_LEASE_S` is a dead holder's and is taken
        over; its old holder, if it was only stalled, sees the object is no longer its own and stops renewing. In a
        folder it is an `flock`, which the kernel releases when its holder dies."""
        lock_path = self.root / ".locks" / f"{validate_name(name, 'lease name')}.lease"
        if not self.remote:
            with _lock_file(lock_path) as fh:
                try:
                    fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    fh.seek(0)
                    holder = fh.read().strip() or "another process"
                    raise StoreError(errno.EBUSY, f"{what} is held by {holder}") from None
                fh.seek(0)
                fh.truncate()
                fh.write(f"{this_machine()} pid {os.getpid()}")
                fh.flush()
                yield
            return
        fs, key = self.root.fs, lock_path.path
        holder = f"{socket.gethostname()} pid {os.getpid()}"
        token = f"{holder} {secrets.token_hex(8)}".encode()
        for _ in range(5):
            try:
                fs.pipe_file(key, token, mode="create")
                break
            except FileExistsError:
                try:
                    stamp, other = _timestamp(fs.modified(key)), fs.cat_file(key).decode("utf-8", "replace")
                except FileNotFoundError:
                    continue   # released between the calls
                try:
                    age = time.time() + self._server_clock_skew(lock_path) - stamp
                except OSError as exc:
                    raise StoreError(exc.errno or 0, f"cannot take the lease {lock_path}: {exc}") from exc
                if age > LOCK_LEASE_S:
                    fs.rm_file(key)   # a dead holder's
                    continue
                other = other.rsplit(" ", 1)[0] if " pid " in other else "another holder"
                raise StoreError(errno.EBUSY, f"{what} is held by {other} (renewed {age:.0f} s ago; a lease "
                                              f"not renewed for {LOCK_LEASE_S:.0f} s is taken for a dead one's)") from None
            except OSError as exc:
                raise StoreError(exc.errno or 0, f"cannot take the lease {lock_path}: {exc}") from exc
        else:
            raise StoreError(errno.EBUSY, f"{what}: its lease {lock_path} kept changing hands")
        stop = threading.Event()

        def renew() -> None:
            while not stop.wait(LOCK_LEASE_S / 4):
                try:
                    if fs.cat_file(key) != token:
                        return   # taken over as a dead holder's: never take it back
                    fs.pipe_file(key, token)
                except Exception:   # a missed renewal is retried; LOCK_LEASE_S allows three
                    continue

        renewer = threading.Thread(target=renew, name=f"lease-{name}", daemon=True)
        renewer.start()
        try:
            yield
        finally:
            stop.set()
            renewer.join(timeout=10)
            try:
                if fs.cat_file(key) == token:
                    fs.rm_file(key)
            except FileNotFoundError:
                pass

    def _server_clock_skew(self, lock_path: Path) -> float:
        """Seconds the object store's clock is ahead of this machine's: a lock's age is its object's date (the
        server's clock) against the server's now, so machines whose clocks disagree neither break a live lock
        nor wait on a dead one longer than the lease. Measured with one probe object (written, dated, removed)
        per contended lock; to the second, as S3 dates objects."""
        fs, key = self.root.fs, f"{lock_path.path}.clock-{secrets.token_hex(6)}"
        before = time.time()
        fs.pipe_file(key, b"")
        after = time.time()
        try:
            return _timestamp(fs.modified(key)) - 0.5 * (before + after)
        finally:
            try:
                fs.rm_file(key)
            except FileNotFoundError:
                pass

    def replace_utterance_rows(
        self, table_name: str, shard: int, utterance_id: str, rows: pa.Table, stage: str | None = None
    ) -> Path:
        """In one shard file, replace the rows of `utterance_id` with `rows`, under the shard's lock.

        On S3 the shard is also written back only if it is still the version read (`If-Match` its ETag, or
        `If-None-Match: *` where there was none), else read again: a writer whose lock was taken for a dead one's
        still loses no rows."""
        schema = TABLE_SCHEMAS[table_name]

        def merged(old: pa.Table) -> pa.Table:
            kept = old.filter(pc.invert(pc.equal(old.column(C.UTTERANCE_ID), utterance_id)))
            new = pa.concat_tables([kept.cast(schema), rows.cast(schema)])
            if table_name == "rejects":
                new = _cap_messages(new)
            # Keep the file's metadata (e.g. the config hash that lets later runs reuse these rows).
            return new.replace_schema_metadata(old.schema.metadata)

        return self._rewrite(table_name, shard, stage, merged)

    def _rewrite(self, table_name: str, shard: int, stage: str | None, merged: Callable[[pa.Table], pa.Table],
                 read: bool = True) -> Path:
        """Write `merged(stored)` over a shard file under the shard's lock (`stored`: the file as it is, or an empty
        table; with `read` False nothing is read and a replaced S3 object is not compared either)."""
        lock = f"{table_name}-{stage or 'all'}-{shard:04d}"
        path = self.shard_path(table_name, shard, stage)
        schema = TABLE_SCHEMAS[table_name]
        with self.locked(lock):
            if not read:
                return self._write_atomic(merged(schema.empty_table()), path)
            if not (self.remote and self.root.protocol in ("s3", "s3a")):
                old = _read_whole(path) if path.exists() else schema.empty_table()
                return self._write_atomic(merged(old), path)
            for _ in range(20):
                try:
                    etag = self.root.fs.info(path.path, refresh=True)["ETag"]
                    old = pq.read_table(pa.BufferReader(path.read_bytes()))
                except FileNotFoundError:
                    etag, old = None, schema.empty_table()
                condition = {"mode": "create"} if etag is None else {"IfMatch": etag}
                try:
                    return self._upload(path, lambda tmp, old=old: pq.write_table(merged(old), tmp, compression="zstd"),
                                        False, put=lambda tmp, c=condition: self.root.fs.pipe_file(
                                            path.path, tmp.read_bytes(), **c))
                except (FileExistsError, StoreError) as exc:
                    if isinstance(exc, StoreError) and "condition" not in str(exc).lower():
                        raise
                    continue   # changed since it was read: read it again
            raise StoreError(0, f"cannot write {path}: it kept changing while being rewritten; stored data is unchanged")

    def stale_temporary_files(self, min_age_s: float = 3600.0) -> list[Path]:
        """Temporary files left by killed writers (names of `visemeflow.atomic`), sorted.

        A temporary file is stale when the process that wrote it (its pid and machine are in the name) no longer
        runs on this machine, or when it is older than `min_age_s` (a pid may have been reused). A file another
        machine is writing (a store on a shared folder) is judged by its age alone: its pid means nothing here.
        Temporary files of older versions, whose names carry no pid, are stale when older than `min_age_s`.
        """
        if self.remote or not self.root.exists():
            return []   # object storage has no temporary objects: a write is one PUT of a local temporary file
        stale, now = [], time.time()
        for folder, dirs, files in os.walk(self.root):
            if Path(folder) == self.root:
                dirs[:] = [d for d in dirs if d != RESULTS_DIR]  # Prefect's own files
            for name in files:
                if not name.startswith(".") or not is_temporary_name(name):
                    continue
                tmp = Path(folder) / name
                writer = temporary_writer(name)
                mine = writer is not None and writer[1] in (None, this_machine())
                try:
                    if (mine and not _pid_alive(writer[0])) or now - tmp.stat().st_mtime > min_age_s:
                        stale.append(tmp)
                except FileNotFoundError:
                    continue
        return sorted(stale)

    def stale_uploads(self, min_age_s: float = 3600.0) -> list["PartialUpload"]:
        """Unfinished multipart uploads under a store on object storage that began more than `min_age_s` ago on the
        server's clock (its answer's `Date`, so listing writes nothing), sorted by path: what a writer killed while
        uploading a large file leaves. The bucket keeps (and bills) their parts until they are aborted
        (`abort_upload`), and nothing reads them. Younger ones may be a live writer's. A folder store has none."""
        if not self.remote:
            return []
        fs = self.root.fs
        bucket, base = self._bucket_and_base()
        found, page, now = [], {}, None
        try:
            while True:
                out = fs.call_s3("list_multipart_uploads", Bucket=bucket, Prefix=base, **page)
                now = _server_time(out) if now is None else now
                found += out.get("Uploads", [])
                if not out.get("IsTruncated"):
                    break
                page = {"KeyMarker": out["NextKeyMarker"], "UploadIdMarker": out["NextUploadIdMarker"]}
            if not found:
                return []
            if now is None:   # a server that sends no date: measure it with a probe object
                now = time.time() + self._server_clock_skew(self.root / ".uploads")
            stale = []
            for upload in found:
                started = _timestamp(upload["Initiated"])
                if now - started <= min_age_s:
                    continue
                key, upload_id = upload["Key"], upload["UploadId"]
                path = self.root.joinpath(*key[len(base):].split("/"))
                stale.append(PartialUpload(path, key, upload_id, started, self._upload_bytes(bucket, key, upload_id)))
        except OSError as exc:
            raise StoreError(exc.errno or 0, f"cannot list the unfinished uploads of {self.location}: {exc}") from exc
        return sorted(stale, key=lambda u: (str(u.path), u.started))

    def _bucket_and_base(self) -> tuple[str, str]:
        """The bucket of a store on object storage and the key prefix of its objects ('' at the bucket's root, else
        'prefix/')."""
        bucket, _, prefix = self.root.path.partition("/")
        prefix = prefix.strip("/")
        return bucket, f"{prefix}/" if prefix else ""

    def _upload_bytes(self, bucket: str, key: str, upload_id: str) -> int:
        total, page = 0, {}
        while True:
            try:
                out = self.root.fs.call_s3("list_parts", Bucket=bucket, Key=key, UploadId=upload_id, **page)
            except FileNotFoundError:   # finished or aborted meanwhile
                return total
            total += sum(int(part.get("Size", 0)) for part in out.get("Parts", []))
            if not out.get("IsTruncated"):
                return total
            page = {"PartNumberMarker": out["NextPartNumberMarker"]}

    def abort_upload(self, upload: "PartialUpload") -> None:
        """Abort an unfinished multipart upload of this store (`stale_uploads`): its parts are removed; an upload
        finished or aborted meanwhile is left as it is."""
        bucket, base = self._bucket_and_base()
        if not upload.key.startswith(base):
            raise ValueError(f"{upload.key} is not inside the store {self.location}")
        try:
            self.root.fs.call_s3("abort_multipart_upload", Bucket=bucket, Key=upload.key, UploadId=upload.upload_id)
        except FileNotFoundError:
            pass
        except OSError as exc:
            raise StoreError(exc.errno or 0, f"cannot abort the upload of {upload.path}: {exc}") from exc

    def sweep_temporary_files(self, min_age_s: float = 3600.0) -> int:
        """Remove the stale temporary files (`stale_temporary_files`); returns how many were removed."""
        removed = 0
        for tmp in self.stale_temporary_files(min_age_s):
            try:
                tmp.unlink()
                removed += 1
            except FileNotFoundError:
                continue
        return removed

    def delete_shard(self, table_name: str, shard: int, stage: str | None = None) -> None:
        self.shard_path(table_name, shard, stage).unlink(missing_ok=True)

    def shards(self, table_name: str, stage: str | None = None) -> list[int]:
        """Numbers of the stored shard files of a table (of one stage for rejects), sorted."""
        folder = self.table_dir(table_name, stage)
        if not folder.is_dir():
            return []
        return sorted(int(m[1]) for p in folder.iterdir() if (m := _SHARD_FILE.match(p.name)))

    def delete_shards_except(self, table_name: str, keep: set[int], stage: str | None = None) -> list[int]:
        """Delete the shard files of a table whose numbers are not in `keep`; returns the deleted numbers."""
        gone = [shard for shard in self.shards(table_name, stage) if shard not in keep]
        for shard in gone:
            self.delete_shard(table_name, shard, stage)
        return gone

    def replace_stage_rejects(self, stage: str, tables: Mapping[int, pa.Table]) -> list[int]:
        """Make a stage's rejects exactly `tables` ({shard: rows}); returns the shard numbers deleted.

        The given shards are written first, each atomically, and only then are the stage's other shard files
        deleted: a run killed in between leaves the stage's rejects readable (old shards not yet deleted, or
        new ones), never none.
        """
        with self.locked(f"rejects-{validate_name(stage, 'stage')}"):
            for shard, table in sorted(tables.items()):
                self.write_shard("rejects", shard, table, stage=stage)
            return self.delete_shards_except("rejects", set(tables), stage)

    def delete_path(self, path: Path) -> None:
        """Remove a file or folder of the store (what `visemeflow clean` reclaims)."""
        path = self._inside(path)
        if str(path) == str(self.root):
            raise ValueError(f"refusing to delete the whole store {self.root}")
        if self.remote:
            try:
                self.root.fs.rm(path.path, recursive=True)
            except FileNotFoundError:
                pass
            return
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)

    def disk_usage(self, path: Path) -> int:
        """Bytes of a file of the store, or of every file under a folder of it."""
        path = self._inside(path)
        if self.remote:
            return int(self.root.fs.du(path.path)) if path.exists() else 0
        if path.is_file():
            return path.stat().st_size
        total = 0
        for p in path.rglob("*"):
            try:
                if p.is_file():
                    total += p.stat().st_size
            except FileNotFoundError:
                continue
        return total

    # ---- reads -------------------------------------------------------------------------------
    def _files(self, folder: Path) -> list[str]:
        if self.remote:   # one recursive listing (no per-folder calls); the names as URLs
            protocol = str(self.root).split("://", 1)[0]
            try:
                found = self.root.fs.find(folder.path)
            except FileNotFoundError:
                return []
            return sorted(f"{protocol}://{f}" for f in found
                          if f.endswith(".parquet") and not f.rsplit("/", 1)[-1].startswith("."))
        if not folder.exists():
            return []
        return sorted(str(p) for p in folder.rglob("*.parquet") if not p.name.startswith("."))

    def _dataset(self, files: list[str], *, schema: pa.Schema, **kwargs: object):
        """A pyarrow dataset of some of the store's Parquet files (`_files`) read as `schema`.

        On object storage the files are fetched at once, one GET each, all in flight together (`fs.cat`), and
        the dataset is built in memory: a pyarrow dataset over fsspec asks for each file's size and footer before
        its data, three or more requests a file, one after the other (a cached pipeline rerun on 25 utterances
        made 380 requests to the tables alone)."""
        if not self.remote:
            return _dataset(files, schema=schema, **kwargs)
        import pyarrow.dataset as ds

        fs = self.root.fs
        paths = [fs._strip_protocol(f) for f in files]
        blobs = fs.cat(paths)   # a list: a dict of them, each fetched by one GET, all in flight together
        tables = [_conform(pq.read_table(pa.BufferReader(blobs[p])), schema) for p in paths]
        return ds.dataset(tables, schema=schema.remove_metadata())

    def read_table(self, table_name: str, stage: str | None = None, utterance_ids: list[str] | None = None) -> pa.Table:
        """All rows of a table (of one stage for rejects; all stages when None), optionally for some ids."""
        schema = TABLE_SCHEMAS[table_name]
        files = self._files(self.table_dir(table_name, stage))
        if not files:
            return schema.empty_table()
        dataset = self._dataset(files, schema=schema, format="parquet")
        flt = pc.field(C.UTTERANCE_ID).isin(pa.array(utterance_ids, pa.string())) if utterance_ids is not None else None
        return dataset.to_table(filter=flt)

    def has_shard(self, table_name: str, shard: int, stage: str | None = None) -> bool:
        return self.shard_path(table_name, shard, stage).is_file()

    def shard_metadata(self, table_name: str, shard: int, stage: str | None = None) -> dict[bytes, bytes] | None:
        """The file metadata written with a shard (`write_shard(metadata=...)`), or None when there is no shard."""
        path = self.shard_path(table_name, shard, stage)
        if not self.remote and not path.is_file():
            return None
        try:
            return dict(_read_schema(path).metadata or {})
        except FileNotFoundError:
            return None

    def read_shard(self, table_name: str, shard: int, stage: str | None = None) -> pa.Table:
        path = self.shard_path(table_name, shard, stage)
        if self.remote:   # one GET, no HEAD first
            try:
                return _read_whole(path).cast(TABLE_SCHEMAS[table_name])
            except FileNotFoundError:
                return TABLE_SCHEMAS[table_name].empty_table()
        return _read_whole(path).cast(TABLE_SCHEMAS[table_name]) if path.exists() else TABLE_SCHEMAS[table_name].empty_table()

    def has_curves(self, source: str, variant: str, utterance_id: str) -> bool:
        """Whether the curve file is there and whole: not empty (a file renamed inside `atomic.group_sync` can come
        back empty after a power loss) and ending as a Parquet file does, its footer's length then `PAR1` (a file
        cut short, by a copy or a full disk, does not). One open and an 8-byte read, so a stage's check of thousands
        stays cheap; a stage remakes a file that is not whole. On object storage, where a file is uploaded whole or
        not at all, its size (one request)."""
        path = self.curve_path(source, variant, utterance_id)
        if self.remote:
            try:
                return path.stat().st_size > 0
            except (FileNotFoundError, NotADirectoryError):
                return False
        return _parquet_tail_ok(path)

    def curves_present(self, source: str, variant: str, utterance_ids: list[str]) -> set[str]:
        """Those of `utterance_ids` whose curve file is there and not empty (`has_curves` of each). On object
        storage one listing of the variant's folder (1,000 objects a request) instead of a request per utterance."""
        if not self.remote:
            return {uid for uid in utterance_ids if self.has_curves(source, variant, uid)}
        folder = self.root / "curves" / validate_name(source, "curve source") / validate_name(variant, "variant")
        try:
            listing = self.root.fs.find(folder.path, detail=True)
        except FileNotFoundError:
            return set()
        stored = {self.utterance_id_of(key) for key, info in listing.items()
                  if key.endswith(".parquet") and not key.rsplit("/", 1)[-1].startswith(".") and info.get("size")}
        return stored & set(utterance_ids)

    def curves_provenances(self, source: str, variant: str, utterance_ids: list[str]) -> dict[str, str | None]:
        """`curves_provenance` of each of `utterance_ids`; on object storage their files are fetched together (one
        GET each, all in flight at once)."""
        if not self.remote or len(utterance_ids) < 2:
            return {uid: self.curves_provenance(source, variant, uid) for uid in utterance_ids}
        paths = {self.curve_path(source, variant, uid).path: uid for uid in utterance_ids}
        blobs = self.root.fs.cat(list(paths), on_error="return")
        found: dict[str, str | None] = {}
        for key, uid in paths.items():
            blob = blobs.get(key)
            try:
                if not isinstance(blob, bytes):
                    raise FileNotFoundError(key)
                meta = pq.read_schema(pa.BufferReader(blob)).metadata or {}
                found[uid] = meta.get(PROVENANCE_KEY, b"").decode()
            except (pa.ArrowInvalid, OSError):
                found[uid] = None
        return found

    def curves_provenance(self, source: str, variant: str, utterance_id: str) -> str | None:
        """What made the stored curves (as given to `write_curves`), or None when there are none, or when the file's
        Parquet footer cannot be read (empty or cut short by a crash inside `atomic.group_sync`): a stage that
        compares provenances then writes it again."""
        path = self.curve_path(source, variant, utterance_id)
        if not self.remote and not path.exists():
            return None
        try:
            meta = _read_schema(path).metadata or {}
        except (pa.ArrowInvalid, OSError):   # FileNotFoundError (one GET on object storage, no HEAD first) too   # no footer (ArrowInvalid), a footer that does not parse (OSError)
            return None
        return meta.get(PROVENANCE_KEY, b"").decode()

    def _stored_curve_path(self, utterance_id: str, source: str, variant: str | None) -> Path:
        """The file of one utterance's curves from one source; `variant` may be omitted when only one exists."""
        if variant is None:
            variants = self.curve_variants(source, utterance_id)
            if len(variants) > 1:
                raise LookupError(f"{utterance_id}: {len(variants)} variants of {source} curves "
                                  f"({', '.join(variants)}); name one with --variant")
            if not variants:
                raise LookupError(self._no_curves(utterance_id, source))
            variant = variants[0]
        path = self.curve_path(source, variant, utterance_id)
        if not path.exists():
            variants = self.curve_variants(source, utterance_id)
            raise LookupError(f"{utterance_id}: no {source} curves of variant {variant!r} in {self.location}; its "
                              f"variants: {', '.join(variants)}" if variants else self._no_curves(utterance_id, source))
        return path

    def _no_curves(self, utterance_id: str, source: str) -> str:
        others = sorted({s for s, v in self.curve_sets() if s != source and self.curve_path(s, v, utterance_id).exists()})
        hint = f"; it has {', '.join(others)} curves (--source {others[0]})" if others else ""
        return f"{utterance_id}: no {source} curves in {self.location}{hint}"

    def read_curves(self, utterance_id: str, source: str, variant: str | None = None) -> pa.Table:
        """Curves of one utterance from one source; `variant` may be omitted when only one exists. A file that is
        not a whole Parquet file is a StoreError naming it (`damaged_curves`)."""
        path = self._stored_curve_path(utterance_id, source, variant)
        try:
            return _read_whole(path).cast(CURVES)
        except pa.ArrowInvalid as exc:
            raise damaged_curves(path, utterance_id, source, exc) from None

    def load_curves(self, utterance_id: str, source: str, variant: str | None = None,
                    default_fps: float = DEFAULT_FPS) -> Curves:
        """The stored curves of one utterance as a :class:`Curves` value, with the rate and provenance the writer
        recorded (``default_fps`` only for a one-frame file of a writer that recorded no rate)."""
        path = self._stored_curve_path(utterance_id, source, variant)
        try:
            table = _read_whole(path)
        except pa.ArrowInvalid as exc:
            raise damaged_curves(path, utterance_id, source, exc) from None
        return Curves.from_table(table, default_fps)

    def save_curves(self, curves: Curves) -> Path:
        """Write a :class:`Curves` value (its rate and provenance in the file's metadata), replacing what was there."""
        return self.write_curves(curves.to_table(), provenance=curves.provenance, fps=curves.fps)

    def curve_variants(self, source: str, utterance_id: str | None = None) -> list[str]:
        folder = self.root / "curves" / validate_name(source, "curve source")
        if not folder.exists():
            return []
        variants = sorted(p.name for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))
        if utterance_id is None:
            return variants
        return [v for v in variants if self.curve_path(source, v, utterance_id).exists()]

    def curve_sets(self) -> list[tuple[str, str]]:
        """(source, variant) of every stored set of curves, sorted."""
        folder = self.root / "curves"
        if not folder.is_dir():
            return []
        return [(src.name, var) for src in sorted(folder.iterdir())
                if src.is_dir() and not src.name.startswith(".") for var in self.curve_variants(src.name)]

    def curve_ids(self, source: str, variant: str) -> list[str]:
        """Utterance ids with stored curves of (source, variant), from the file listing (no file is opened)."""
        return sorted(self.utterance_id_of(f) for f in self.curve_files(source, variant))

    def tracking_variants(self) -> list[str]:
        folder = self.root / "tracking_frames"
        return sorted(p.name for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")) \
            if folder.is_dir() else []

    def tracking_frame_files(self, variant: str | None = None) -> list[str]:
        """Stored tracking-diagnostics files (of one variant), sorted; `utterance_id_of` names their utterance."""
        folder = self.root / "tracking_frames"
        if variant:
            folder = folder / validate_name(variant, "variant")
        return self._files(folder)

    def curve_files(self, source: str | None = None, variant: str | None = None) -> list[str]:
        folder = self.root / "curves"
        if source:
            folder = folder / validate_name(source, "curve source")
            if variant:
                folder = folder / validate_name(variant, "variant")
        return self._files(folder)

    def scan_curves(
        self, source: str | None = None, variant: str | None = None, columns: list[str] | None = None,
        utterance_ids: list[str] | None = None,
    ) -> pa.Table:
        """All stored curves (optionally of one source/variant and some utterances) as one table."""
        files = self.curve_files(source, variant)
        if not files:
            return CURVES.empty_table() if columns is None else CURVES.empty_table().select(columns)
        dataset = self._dataset(files, schema=CURVES, format="parquet")
        flt = pc.field(C.UTTERANCE_ID).isin(pa.array(utterance_ids, pa.string())) if utterance_ids is not None else None
        return dataset.to_table(columns=columns, filter=flt)

    # ---- run configs -------------------------------------------------------------------------
    def write_run_config(self, stage: str, config: dict) -> Path:
        """Remember the settings a stage last ran with (a rerun of one utterance uses them)."""
        path = self.root / "configs" / f"{validate_name(stage, 'stage')}.json"
        return self.write_text(path, json.dumps(config, indent=2, sort_keys=True, default=str))

    def write_text(self, path: Path, text: str) -> Path:
        """Replace the store file `path` with UTF-8 `text`, atomically."""
        return self.write_file(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))

    def write_report_text(self, name: str, text: str) -> Path:
        """Replace the report `name` (`robustness.md`, ...) with `text`, atomically."""
        return self.write_text(self.report_path(name), text)

    def write_report(self, name: str, writer: Callable[[Path], object]) -> Path:
        """Replace the report `name` with what `writer(path)` writes (a plot; the temporary path keeps the suffix)."""
        return self.write_file(self.report_path(name), writer, keep_suffix=True)

    def read_run_config(self, stage: str) -> dict | None:
        path = self.root / "configs" / f"{validate_name(stage, 'stage')}.json"
        return json.loads(path.read_text()) if path.exists() else None
