"""What every task shares: the cache policy, result storage and serializer, and reject rows."""

import functools
import logging
import os
import re
import stat
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from prefect import get_run_logger
from prefect.cache_policies import INPUTS, TASK_SOURCE, CachePolicy
from prefect.context import TaskRunContext
from prefect.filesystems import LocalFileSystem, RemoteFileSystem

from visemeflow import logs
from visemeflow.schemas import C
from visemeflow.storage import Store
from visemeflow.storage.store import RESULTS_DIR, cap_message
from visemeflow.tasks.code_version import code_digest
from visemeflow.tasks.results import (
    MAX_RECORD_BYTES,
    StoreJSONSerializer,
    UntrustedResultError,
    check_result_bytes,
    check_result_record,
)

# Every persisted task writes its result as JSON data; `DataOnlyCache` keeps Prefect from reading anything else.
RESULT_SERIALIZER = StoreJSONSerializer()


@dataclass
class DataOnlyCache(CachePolicy):
    """`policy`'s cache key, with the record stored at that key checked to be a JSON record of ours first.

    Prefect decodes a cached record with the serializer named in the record itself, inside its cache lookup, so
    the check has to come before the lookup: here, once the key is known. A refused record (a pickle planted in a
    copied store, a record of another serializer) is deleted with a warning naming it, never decoded; the task then
    runs and writes a JSON record in its place, as after `visemeflow clean results`.
    """

    policy: CachePolicy = field(default_factory=lambda: INPUTS + TASK_SOURCE)

    def __post_init__(self) -> None:
        if isinstance(self.key_storage, CachePolicy):
            raise TypeError("the policy to wrap is passed as DataOnlyCache(policy=...), not as the key storage")
        if self.key_storage is not None or self.policy.key_storage is not None:
            raise ValueError("DataOnlyCache checks the records in a task's result storage; a policy with its own "
                             "key storage would be read unchecked")
        self.isolation_level = self.policy.isolation_level
        self.lock_manager = self.policy.lock_manager

    def compute_key(self, task_ctx: TaskRunContext, inputs: dict[str, Any], flow_parameters: dict[str, Any],
                    **kwargs: Any) -> str | None:
        key = self.policy.compute_key(task_ctx, inputs, flow_parameters, **kwargs)
        if key is not None:
            discard_untrusted_record(task_ctx.result_store.result_storage, key, get_run_logger())
        return key

    # Combining must keep the check outermost: it checks the record of the final key.
    def __add__(self, other: CachePolicy) -> "DataOnlyCache":
        return DataOnlyCache(policy=self.policy + other)

    def __sub__(self, other: str) -> "DataOnlyCache":
        return DataOnlyCache(policy=self.policy - other)


def discard_untrusted_record(storage: object, key: str, logger: logging.Logger | logging.LoggerAdapter) -> bool:
    """Delete the record at `key` in `storage` unless it is a JSON record of ours; whether one was refused."""
    if isinstance(storage, RemoteFileSystem):
        return _discard_untrusted_object(storage, key, logger)
    if not isinstance(storage, LocalFileSystem):
        raise TypeError(f"cached results are checked in a local folder; {type(storage).__name__} storage is not "
                        "supported")
    path = Path(storage.basepath or ".").expanduser() / key
    if not os.path.lexists(path):
        return False
    try:
        check_result_record(path)
    except UntrustedResultError as exc:
        logger.warning("refused a cached result, the task runs again and replaces it: %s", exc)
        if not stat.S_ISDIR(os.lstat(path).st_mode):
            path.unlink()
        return True
    return False


def _discard_untrusted_object(storage: Any, key: str, logger: logging.Logger | logging.LoggerAdapter) -> bool:
    """`discard_untrusted_record` for results on object storage (a store at a URL): the same check of the bytes
    (an object has no links or special files to refuse)."""
    path = f"{storage.basepath.rstrip('/')}/{key}"
    fs = storage.filesystem
    try:
        data = fs.cat_file(path, start=0, end=MAX_RECORD_BYTES + 1)   # one ranged GET: never more than that
    except FileNotFoundError:
        return False
    return _refused_object(fs, path, data, logger)


def _refused_object(fs: Any, path: str, data: bytes, logger: logging.Logger | logging.LoggerAdapter) -> bool:
    """Check the bytes of the record object at `path` (read with at most one byte more than a record holds) as
    `check_result_record` checks a file; a refused one is deleted, with a warning. Whether it was refused."""
    try:
        if len(data) > MAX_RECORD_BYTES:
            raise UntrustedResultError(f"{path}: more than the {MAX_RECORD_BYTES} bytes a cached result record "
                                       "holds")
        check_result_bytes(path, data)
    except UntrustedResultError as exc:
        logger.warning("refused a cached result, the task runs again and replaces it: %s", exc)
        try:
            fs.rm_file(path)
        except FileNotFoundError:
            pass
        return True
    return False


@dataclass
class CodeDigest(CachePolicy):
    """The digest of the code a task runs (`code_version.code_digest` of its module): `TASK_SOURCE` sees the task's
    own lines only, and a task is a thin wrapper of the domain functions that decide its outputs."""

    def compute_key(self, task_ctx: TaskRunContext, inputs: dict[str, Any], flow_parameters: dict[str, Any],
                    **kwargs: Any) -> str:
        return code_digest(task_ctx.task.fn.__module__)


CODE = CodeDigest()

# Deterministic tasks are keyed on their inputs (content hashes, configs, ids) and the code they run.
CACHE_POLICY = DataOnlyCache(policy=INPUTS + TASK_SOURCE + CODE)


MADE_FROM_KEY = b"visemeflow.made_from"
"""File metadata of a shard's output: a digest (`hashing.stable_hash`) of the task inputs that wrote it."""


def made_from(store: Store, table: str, shard: int, stage: str | None, digest: str) -> bool:
    """Whether a shard's output file was written from the inputs of `digest`. A task's cache record says what a
    call once returned, not what the store holds now: after an input changes and changes back (A, B, A) the record
    of A is found while the files hold B's output, so a flow runs a cached shard again unless this holds."""
    metadata = store.shard_metadata(table, shard, stage)
    return metadata is not None and metadata.get(MADE_FROM_KEY, b"").decode() == digest


def result_storage(store_root: str | Path) -> Any:
    """Where Prefect keeps the persisted task results and cache records: inside the store. A folder (`Path`) for a
    local store; for a store on object storage a `RemoteFileSystem` at the same place (`<url>/.prefect-results`),
    so that a cache hit works from any machine that reaches the store."""
    store = Store(store_root)
    if store.remote:
        return _saved_remote_storage(f"{store.url}/{RESULTS_DIR}")
    return store.results_dir()


@functools.cache
def _saved_remote_storage(basepath: str) -> Any:
    """A `RemoteFileSystem` block at `basepath`, saved on the Prefect API (a task accepts only saved storage blocks),
    under a name made from the path, so every process and machine of a run saves and uses the same one. The block
    holds no credentials: each machine's fsspec reads them from its environment."""
    import hashlib

    name = "visemeflow-results-" + hashlib.blake2b(basepath.encode(), digest_size=6).hexdigest()
    block = RemoteFileSystem(basepath=basepath)
    try:
        block.save(name, overwrite=True)
    except Exception:   # another process saved it at the same moment (a name conflict): use the saved one
        block = RemoteFileSystem.load(name)
        if block.basepath != basepath:
            raise
    return block


def results_of(store_root: str | Path) -> Any:
    """Prefect's result store (`prefect.results.ResultStore`) of a visemeflow store (`result_storage`), with our
    JSON serializer: what a persisted task of this package reads its cached records from and writes them to."""
    from prefect.results import ResultStore

    store = Store(store_root)
    storage = (RemoteFileSystem(basepath=f"{store.url}/{RESULTS_DIR}") if store.remote
               else LocalFileSystem(basepath=str(store.results_dir())))
    return ResultStore(result_storage=storage, serializer=RESULT_SERIALIZER)


def fetch_records(results: Any, keys: list[str], logger: logging.Logger | logging.LoggerAdapter) -> dict[str, Any]:
    """The result records at `keys` of a result store on object storage, fetched together (one GET each, all in
    flight at once), each checked as `discard_untrusted_record` checks it (a refused one is deleted, with a warning)
    and then decoded as Prefect's `ResultStore.read` decodes it; absent and refused keys are left out."""
    from prefect.results import ResultRecord

    storage = results.result_storage
    fs = storage.filesystem
    base = fs._strip_protocol(storage.basepath.rstrip("/"))
    paths = {f"{base}/{key}": key for key in keys}
    # ranged GETs, as `_discard_untrusted_object`: a planted giant object is never read whole
    blobs = fs.cat(list(paths), on_error="return", start=0, end=MAX_RECORD_BYTES + 1) if paths else {}
    found = {}
    for path, key in paths.items():
        data = blobs.get(path)
        if isinstance(data, bytes) and not _refused_object(fs, path, data, logger):
            found[key] = ResultRecord.deserialize(data, backup_serializer=results.serializer)
    return found


def cache_key_of(task: Any, results: Any, *args: Any, checked: bool = True) -> str | None:
    """The cache key `task`'s cache policy gives the call `task(*args)`, as Prefect computes it when the task runs
    (the policies read the task, its inputs and its result storage; none of them the flow's parameters). A flow that
    does the work of several such calls in one task writes each result under its call's key (`results_of(...).
    write`), so that the call itself is then a cache hit, and reruns and `rerun` of one utterance stay as they were.
    `results`: the store's `results_of`, made once by a caller that keys many calls. `checked=False`: the key without
    `DataOnlyCache`'s check of the record at it, for a caller that checks the records itself (`fetch_records`)."""
    from types import SimpleNamespace

    from prefect.utilities.callables import get_call_parameters

    context = SimpleNamespace(task=task, result_store=results)
    policy = task.cache_policy
    if not checked and isinstance(policy, DataOnlyCache):   # the caller checks the records itself (`fetch_records`)
        policy = policy.policy
    return policy.compute_key(task_ctx=context, inputs=get_call_parameters(task.fn, args, {}),
                                         flow_parameters={})


class _RejectsInOneLine(logging.Filter):
    """Prefect logs every failed task run at ERROR with its traceback, about 30 lines. A task that fails on bad
    input raises an error naming its reject (`error_type`: TrackError, LandmarksError, ...): the stage records it
    in the rejects table and says so in one line, so here it is one WARNING line, without the trace. Any other
    error keeps its trace."""

    _FINISHED = re.compile(r"encountered an exception (\w+):")

    def __init__(self) -> None:
        super().__init__()
        self.expected: set[str] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        error = record.exc_info[1] if record.exc_info else None
        if error is not None and hasattr(error, "error_type"):
            self.expected.add(type(error).__name__)
            record.exc_info, record.exc_text, record.stack_info = None, None, None
            record.levelno, record.levelname = logging.WARNING, "WARNING"
            logs.mark(record)   # the stage's rejects, which a command prints itself (`visemeflow.logs`)
        elif error is None and record.levelno >= logging.ERROR:
            match = self._FINISHED.search(record.getMessage())
            if match and match[1] in self.expected:
                record.levelno, record.levelname = logging.WARNING, "WARNING"
                logs.mark(record)
        return True


def quiet_rejects(logger_name: str = "prefect.task_runs") -> None:
    """Put `_RejectsInOneLine` on Prefect's task-run logger, once (again after Prefect reconfigured logging), and
    `logs.SummarisedOffConsole` on Prefect's console handler."""
    from prefect.logging.handlers import PrefectConsoleHandler

    logger = logging.getLogger(logger_name)
    if not any(isinstance(f, _RejectsInOneLine) for f in logger.filters):
        logger.addFilter(_RejectsInOneLine())
    logs.keep_summarised_off([h for h in logging.getLogger().handlers if isinstance(h, PrefectConsoleHandler)])


quiet_rejects()


def reject_row(utterance_id: str | None, stage: str, error_type: str, message: str, path: str | None) -> dict[str, object]:
    """One row of the rejects table; the message capped as the store caps it, so the logs that quote the row stay
    bounded too (an entity-expanding XML file made a 30 MB message)."""
    return {
        C.UTTERANCE_ID: utterance_id, C.STAGE: stage, C.ERROR_TYPE: error_type, C.MESSAGE: cap_message(message),
        C.PATH: path, C.TIME: datetime.now(timezone.utc),
    }
