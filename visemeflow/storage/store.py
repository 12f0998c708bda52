"""The Parquet store: paths, atomic writes, reads.

Layout under the root folder:
    tables/<table>/shard-NNNN.parquet                  utterances, phones (one file per shard)
    tables/rejects/<stage>/shard-NNNN.parquet          rejects of a stage, per shard
    curves/<source>/<variant>/<speaker>/<name>.parquet one file per (source, variant, utterance)

Every file is written to a hidden temporary file in its folder and renamed over the target, so a
killed writer never leaves a half file and readers see the old or the new file whole. Shard files
that are read, changed and written back (a rerun of one utterance) are updated under a lock file so
two writers cannot lose each other's rows.
"""

import errno
import fcntl
import json
import os
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.dataset as ds
import pyarrow.parquet as pq

from visemeflow.schemas import (
    CURVES,
    METRICS,
    TABLE_SCHEMAS,
    TRACKING_FRAMES,
    C,
    split_utterance_id,
    validate_name,
)

PROVENANCE_KEY = b"visemeflow.provenance"
# Curve files are small and many: dictionary-encode only the constant id columns and keep statistics only
# where dataset scans prune files by them (a third less write time, a quarter smaller files).
CURVE_FILE_OPTIONS = {
    "use_dictionary": [C.UTTERANCE_ID, C.SOURCE, C.VARIANT],
    "write_statistics": [C.UTTERANCE_ID, C.SOURCE, C.VARIANT, C.FRAME],
}
FPS_KEY = b"visemeflow.fps"


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


class StoreError(OSError):
    """The store cannot be written or read; the message names the path and the reason."""


def _read_whole(path: Path) -> pa.Table:
    """One Parquet file read through a single open handle.

    `pq.read_table(path)` opens the path more than once (footer, then pages); a writer renaming a new
    file over it in between makes the read fail ("Page was smaller than expected"). One handle keeps
    the read on one version of the file.
    """
    with open(path, "rb") as fh:
        return pq.read_table(fh)


class Store:
    """A local Parquet store rooted at one folder."""

    def __init__(self, root: Path | str):
        self.root = Path(root).resolve()

    def __repr__(self) -> str:
        return f"Store({str(self.root)!r})"

    # ---- paths -------------------------------------------------------------------------------
    def table_dir(self, table: str, stage: str | None = None) -> Path:
        if table not in TABLE_SCHEMAS:
            raise ValueError(f"unknown table {table!r}; tables are {sorted(TABLE_SCHEMAS)}")
        folder = self.root / "tables" / table
        return folder / validate_name(stage, "stage") if stage else folder

    def shard_path(self, table: str, shard: int, stage: str | None = None) -> Path:
        return self.table_dir(table, stage) / f"shard-{shard:04d}.parquet"

    def curve_path(self, source: str, variant: str, utterance_id: str) -> Path:
        speaker, name = split_utterance_id(utterance_id)
        return (
            self.root / "curves" / validate_name(source, "curve source") / validate_name(variant, "variant")
            / speaker / f"{name}.parquet"
        )

    def tracking_frames_path(self, variant: str, utterance_id: str) -> Path:
        speaker, name = split_utterance_id(utterance_id)
        return self.root / "tracking_frames" / validate_name(variant, "variant") / speaker / f"{name}.parquet"

    def model_dir(self, model: str) -> Path:
        """Folder of a trained model: weights, config and lineage, checkpoints."""
        return self.root / "models" / validate_name(model, "model name")

    def augmented_audio_path(self, augmentation: str, augmented_id: str) -> Path:
        """An augmented copy of an utterance's audio (float WAV), in the folder of one augmentation set."""
        speaker, name = split_utterance_id(augmented_id)
        return self.root / "augmented" / validate_name(augmentation, "augmentation") / speaker / f"{name}.wav"

    def metrics_path(self, model: str, run: str) -> Path:
        return self.root / "metrics" / validate_name(model, "model name") / f"{validate_name(run, 'run name')}.parquet"

    # ---- writes ------------------------------------------------------------------------------
    def _write_atomic(self, table: pa.Table, path: Path, **parquet_options: object) -> Path:
        tmp = path.parent / f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp"
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(table, tmp, compression="zstd", **parquet_options)
            os.replace(tmp, path)
        except BaseException as exc:  # any failure (also ArrowInvalid, Ctrl-C) removes the temporary file
            try:
                tmp.unlink(missing_ok=True)
            except OSError:
                pass  # the folder itself is unusable, so there is no temporary file
            if not isinstance(exc, OSError):
                raise
            reason = "disk full" if exc.errno == errno.ENOSPC else (exc.strerror or str(exc))
            raise StoreError(exc.errno or 0, f"cannot write {path}: {reason}; stored data is unchanged") from exc
        return path

    def write_shard(
        self, table_name: str, shard: int, table: pa.Table, stage: str | None = None,
        metadata: dict[bytes, bytes] | None = None,
    ) -> Path:
        """Replace one shard file of a table with `table` (cast to the table's schema) and file metadata."""
        table = table.cast(TABLE_SCHEMAS[table_name])
        if metadata:
            table = table.replace_schema_metadata(metadata)
        return self._write_atomic(table, self.shard_path(table_name, shard, stage))

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
        meta = {PROVENANCE_KEY: provenance.encode()}
        if fps is not None:
            meta[FPS_KEY] = repr(float(fps)).encode()
        table = table.replace_schema_metadata(meta)
        return self._write_atomic(table, self.curve_path(sources[0], variants[0], ids[0]), **CURVE_FILE_OPTIONS)

    def write_tracking_frames(self, table: pa.Table) -> Path:
        """Per-frame tracking diagnostics of one (variant, utterance), replacing what was stored."""
        table = table.cast(TRACKING_FRAMES)
        ids = table.column(C.UTTERANCE_ID).unique().to_pylist()
        variants = table.column(C.VARIANT).unique().to_pylist()
        if len(ids) != 1 or len(variants) != 1:
            raise ValueError(f"a tracking_frames file holds one utterance and variant; got {ids[:3]}, {variants[:3]}")
        return self._write_atomic(table, self.tracking_frames_path(variants[0], ids[0]))

    def read_tracking_frames(self, variant: str | None = None, utterance_ids: list[str] | None = None) -> pa.Table:
        """Stored tracking diagnostics (of one variant, some utterances) as one table."""
        folder = self.root / "tracking_frames"
        if variant:
            folder = folder / validate_name(variant, "variant")
        files = self._files(folder)
        if not files or utterance_ids == []:
            return TRACKING_FRAMES.empty_table()
        dataset = ds.dataset(files, schema=TRACKING_FRAMES, format="parquet")
        flt = pc.field(C.UTTERANCE_ID).isin(utterance_ids) if utterance_ids is not None else None
        return dataset.to_table(filter=flt)

    def write_metrics(self, model: str, run: str, table: pa.Table) -> Path:
        """The metrics rows of one (model, run), replacing what that run wrote before."""
        return self._write_atomic(table.cast(METRICS), self.metrics_path(model, run))

    def read_metrics(self, model: str | None = None) -> pa.Table:
        folder = self.root / "metrics"
        if model:
            folder = folder / validate_name(model, "model name")
        files = self._files(folder)
        return ds.dataset(files, schema=METRICS, format="parquet").to_table() if files else METRICS.empty_table()

    @contextmanager
    def locked(self, name: str) -> Iterator[None]:
        """Hold an exclusive lock named `name` (a file under the store) for a read-modify-write."""
        lock_path = self.root / ".locks" / f"{validate_name(name, 'lock name')}.lock"
        try:
            lock_path.parent.mkdir(parents=True, exist_ok=True)
            fh = open(lock_path, "a")
        except OSError as exc:
            raise StoreError(exc.errno or 0, f"cannot lock {lock_path}: {exc.strerror or exc}") from exc
        with fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)

    def replace_utterance_rows(
        self, table_name: str, shard: int, utterance_id: str, rows: pa.Table, stage: str | None = None
    ) -> Path:
        """In one shard file, replace the rows of `utterance_id` with `rows`, under the shard's lock."""
        lock = f"{table_name}-{stage or 'all'}-{shard:04d}"
        with self.locked(lock):
            path = self.shard_path(table_name, shard, stage)
            schema = TABLE_SCHEMAS[table_name]
            old = _read_whole(path) if path.exists() else schema.empty_table()
            kept = old.filter(pc.invert(pc.equal(old.column(C.UTTERANCE_ID), utterance_id)))
            new = pa.concat_tables([kept.cast(schema), rows.cast(schema)])
            # Keep the file's metadata (e.g. the config hash that lets later runs reuse these rows).
            return self._write_atomic(new.replace_schema_metadata(old.schema.metadata), path)

    def stale_temporary_files(self, min_age_s: float = 3600.0) -> list[Path]:
        """Temporary files left by killed writers.

        A temporary file is stale when the process that wrote it (its pid is in the name) no longer runs
        on this machine, or when it is older than `min_age_s` (a pid may have been reused).
        """
        if not self.root.exists():
            return []
        stale, now = [], time.time()
        for tmp in self.root.rglob(".*.tmp"):
            if tmp.parent.name == ".prefect-results":
                continue
            try:
                pid = int(tmp.name.rsplit(".", 3)[-3])
            except (ValueError, IndexError):
                continue
            try:
                if not _pid_alive(pid) or now - tmp.stat().st_mtime > min_age_s:
                    stale.append(tmp)
            except FileNotFoundError:
                continue
        return stale

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

    # ---- reads -------------------------------------------------------------------------------
    def _files(self, folder: Path) -> list[str]:
        if not folder.exists():
            return []
        return sorted(str(p) for p in folder.rglob("*.parquet") if not p.name.startswith("."))

    def read_table(self, table_name: str, stage: str | None = None, utterance_ids: list[str] | None = None) -> pa.Table:
        """All rows of a table (of one stage for rejects; all stages when None), optionally for some ids."""
        schema = TABLE_SCHEMAS[table_name]
        files = self._files(self.table_dir(table_name, stage))
        if not files:
            return schema.empty_table()
        dataset = ds.dataset(files, schema=schema, format="parquet")
        flt = pc.field(C.UTTERANCE_ID).isin(pa.array(utterance_ids, pa.string())) if utterance_ids is not None else None
        return dataset.to_table(filter=flt)

    def read_shard(self, table_name: str, shard: int, stage: str | None = None) -> pa.Table:
        path = self.shard_path(table_name, shard, stage)
        return _read_whole(path).cast(TABLE_SCHEMAS[table_name]) if path.exists() else TABLE_SCHEMAS[table_name].empty_table()

    def has_curves(self, source: str, variant: str, utterance_id: str) -> bool:
        return self.curve_path(source, variant, utterance_id).exists()

    def curves_provenance(self, source: str, variant: str, utterance_id: str) -> str | None:
        """What made the stored curves (as given to `write_curves`), or None when there are none."""
        path = self.curve_path(source, variant, utterance_id)
        if not path.exists():
            return None
        meta = pq.read_schema(path).metadata or {}
        return meta.get(PROVENANCE_KEY, b"").decode()

    def read_curves(self, utterance_id: str, source: str, variant: str | None = None) -> pa.Table:
        """Curves of one utterance from one source; `variant` may be omitted when only one exists."""
        if variant is None:
            variants = self.curve_variants(source, utterance_id)
            if len(variants) != 1:
                raise LookupError(
                    f"{utterance_id}: {len(variants)} variants of {source} curves ({', '.join(variants) or 'none'}); name one"
                )
            variant = variants[0]
        path = self.curve_path(source, variant, utterance_id)
        if not path.exists():
            raise LookupError(f"{utterance_id}: no {source} curves of variant {variant!r} in {self.root}")
        return _read_whole(path).cast(CURVES)

    def curve_variants(self, source: str, utterance_id: str | None = None) -> list[str]:
        folder = self.root / "curves" / validate_name(source, "curve source")
        if not folder.exists():
            return []
        variants = sorted(p.name for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))
        if utterance_id is None:
            return variants
        return [v for v in variants if self.curve_path(source, v, utterance_id).exists()]

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
        dataset = ds.dataset(files, schema=CURVES, format="parquet")
        flt = pc.field(C.UTTERANCE_ID).isin(pa.array(utterance_ids, pa.string())) if utterance_ids is not None else None
        return dataset.to_table(columns=columns, filter=flt)

    # ---- run configs -------------------------------------------------------------------------
    def write_run_config(self, stage: str, config: dict) -> Path:
        """Remember the settings a stage last ran with (a rerun of one utterance uses them)."""
        path = self.root / "configs" / f"{validate_name(stage, 'stage')}.json"
        tmp = path.parent / f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp"
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(json.dumps(config, indent=2, sort_keys=True, default=str))
            os.replace(tmp, path)
        except OSError as exc:
            try:
                tmp.unlink(missing_ok=True)
            except OSError:
                pass  # the folder itself is unusable, so there is no temporary file
            raise StoreError(exc.errno or 0, f"cannot write {path}: {exc.strerror or exc}") from exc
        return path

    def read_run_config(self, stage: str) -> dict | None:
        path = self.root / "configs" / f"{validate_name(stage, 'stage')}.json"
        return json.loads(path.read_text()) if path.exists() else None
