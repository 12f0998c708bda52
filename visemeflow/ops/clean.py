"""Reclaim disk in a store: only what the flows can make again, never curves, tables, models or metrics.

Kinds of reclaimable data:
  temporary    files left by writers that were killed (their process is gone, or they are over an hour old); on
               object storage, multipart uploads a killed writer left unfinished, begun over an hour ago by the
               server's clock (their parts are kept and billed until aborted)
  augmented    the augmented validation audio of `evaluate` (`augmented/<condition>-s<seed>/`): the next
               `evaluate` that needs a set writes it again
  checkpoints  `models/<name>/checkpoints/` of models whose training finished (`model.pt` exists): only
               an interrupted training resumes from them
  results      Prefect's persisted task results and cache records (`.prefect-results/`): the next run of every
               stage recomputes its tasks once (same outputs) and records them again

Run it while no flow writes to the store: a flow that is evaluating while its augmented audio is removed fails
that model's task (run it again).
"""

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from visemeflow.storage import Store
from visemeflow.storage.store import PartialUpload

KINDS = ("temporary", "augmented", "checkpoints", "results")


@dataclass
class Reclaimable:
    kind: str
    paths: list[Path] = field(default_factory=list)
    n_bytes: int = 0
    uploads: list[PartialUpload] = field(default_factory=list)   # unfinished uploads on object storage (temporary)

    @property
    def count(self) -> int:
        return len(self.paths) + len(self.uploads)


def _paths(store: Store, kind: str) -> list[Path]:
    if kind == "temporary":
        return store.stale_temporary_files()
    if kind == "augmented":
        return store.augmented_sets()
    if kind == "checkpoints":
        return store.finished_checkpoint_dirs()
    if kind == "results":
        folder = store.results_dir()
        return [folder] if folder.is_dir() else []
    raise ValueError(f"unknown kind {kind!r}; known: {', '.join(KINDS)}")


def reclaimable(store: Store, kinds: Iterable[str] = KINDS) -> list[Reclaimable]:
    """What each kind would remove from `store`, with its size."""
    found = []
    for kind in kinds:
        paths = _paths(store, kind)
        uploads = store.stale_uploads() if kind == "temporary" else []
        found.append(Reclaimable(kind, paths, sum(store.disk_usage(p) for p in paths) + sum(u.n_bytes for u in uploads),
                                 uploads))
    return found


def clean(store: Store, kinds: Iterable[str]) -> list[Reclaimable]:
    """Remove the reclaimable data of `kinds` from `store`; returns what was removed."""
    removed = reclaimable(store, kinds)
    for item in removed:
        for path in item.paths:
            store.delete_path(path)
        for upload in item.uploads:
            store.abort_upload(upload)
    return removed


def human_bytes(n: int) -> str:
    if n < 1024:
        return f"{n} B"
    size = float(n)
    for unit in ("KiB", "MiB", "GiB"):
        size /= 1024
        if size < 1024 or unit == "GiB":
            break
    return f"{size:.1f} {unit}"
