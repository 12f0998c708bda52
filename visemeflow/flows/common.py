"""Helpers the flows share: shard grouping, waiting with progress, failure accounting."""

import traceback
from collections import defaultdict
from collections.abc import Callable, Iterable
from contextvars import ContextVar

from prefect import get_run_logger
from prefect.artifacts import create_progress_artifact, update_progress_artifact
from prefect.futures import PrefectFuture, as_completed
from prefect.states import Completed, Failed, State

from visemeflow.flows.errors import StageFailed
from visemeflow.flows.params import SETTINGS, StageSettings
from visemeflow.tasks.progress import Progress
from visemeflow.schemas import shard_of


def group_by_shard(items: Iterable[dict], key: str, n_shards: int) -> dict[int, list[dict]]:
    groups: dict[int, list[dict]] = defaultdict(list)
    for item in items:
        groups[shard_of(item[key] or "", n_shards)].append(item)  # rows of no utterance (a bad character): shard of ""
    return dict(sorted(groups.items()))


def replace_stage_rejects(store, stage: str, rejects: list[dict], n_shards: int) -> None:
    """A stage's reject rows as its rejects table, sharded by utterance id; new shards first, then the stale ones
    go (a kill in between never loses the stage's rejects)."""
    from visemeflow.schemas import REJECTS, C, table_from_rows

    store.replace_stage_rejects(stage, {shard: table_from_rows(rows, REJECTS)
                                        for shard, rows in group_by_shard(rejects, C.UTTERANCE_ID, n_shards).items()})


def collect(
    futures: list[PrefectFuture], stage: str, kept_when_cached: tuple[str, ...] = ("shard", "utterances"),
    cached_key: str = "cached_shards", unit: str = "tasks",
) -> tuple[list[dict], list[str]]:
    """Wait for all futures, updating a progress artifact; (reports of the ones that worked, errors).

    A cache hit returns the report of the run that computed it, though this run did no work: only the
    `kept_when_cached` fields of such a report are kept, and `cached_key` says whether it was one. `unit` names
    what a task is on the terminal's progress line (shards, utterances).
    """
    progress_id = create_progress_artifact(progress=0.0, description=f"{stage}: tasks done") if futures else None
    reports, errors = [], []
    with Progress(stage, len(futures), unit=unit) as line:
        for done, future in enumerate(as_completed(futures), start=1):
            try:
                report = dict(future.result())
            except Exception as exc:  # a failed task: count it, let the others finish
                errors.append(f"{type(exc).__name__}: {exc}")
            else:
                if future.state.name == "Cached":
                    reports.append({**{k: report[k] for k in kept_when_cached if k in report}, cached_key: 1})
                else:
                    reports.append({**report, cached_key: 0})
            line.advance(failed=len(errors) > line.failed)
            if progress_id is not None:
                update_progress_artifact(progress_id, progress=100.0 * done / len(futures))
    return sorted(reports, key=lambda r: r.get("shard", 0)), errors


def totals(reports: list[dict]) -> dict[str, int]:
    out: dict[str, int] = defaultdict(int)
    for r in reports:
        for k, v in r.items():
            if k != "shard":
                out[k] += v
    out["shards"] = len(reports)
    return dict(out)


def _shortened(text: str, limit: int = 300) -> str:
    return text if len(text) <= limit else text[:limit - 3] + "..."


def finished(stage: str, summary: dict, failed: int, total: int, unexpected: int = 0,
             reasons: Iterable[str] = ()) -> State:
    """The flow's final state, with a message saying how many of the stage's utterances failed.

    Completed (the summary as its result) while failures are bad input of some utterances: each is a reject row
    with its reason and the rest of the corpus went on. Failed, raising `StageFailed` to a caller, when all of
    `total` utterances failed or `unexpected` of them failed with an error that is not a known bad-input class;
    when all failed, the message gives the first lines of the first three of `reasons` (this run's rejects), so
    that a run of one file says why it failed, not only that it did.
    """
    if unexpected:
        message = (f"{stage}: {unexpected} of {total} utterances failed with an unexpected error (tracebacks in the "
                   f"run's logs; reasons in the rejects table); {failed} failed in all")
        return Failed(message=message, data=StageFailed(message, summary))
    every = "its one utterance" if total == 1 else f"all {total} utterances"
    if total and failed >= total:
        reasons = sorted(_shortened(r.split("\n", 1)[0]) for r in reasons if r)   # one order, whatever finished first
        why = "; ".join(reasons[:3]) + (f"; and {len(reasons) - 3} more" if len(reasons) > 3 else "")
        message = f"{stage}: {every} failed" + (f": {why}" if why else "") + " (see the rejects table)"
        return Failed(message=message, data=StageFailed(message, summary))
    if failed:
        message = f"{stage}: {failed} of {total} utterances failed (see the rejects table); the others are done"
    else:
        message = f"{stage}: {every} done"
    return Completed(message=message, data=summary)


def collect_utterance_results(
    futures: dict, stage: str, expected: type[Exception], logger, work: dict | None = None, work_unit: str = "frames",
    unit: str = "utterances",
) -> tuple[list, list, int]:
    """Wait for per-utterance task futures (future -> utterance id, or (utterance id, input path) where one
    utterance has several tasks, e.g. a package per character) with a progress artifact and a progress line on the
    terminal: (reports with their `cached` flag, reject rows, count of unexpected errors). `expected` errors (with
    `error_type` and `path`) are rejects; any other exception is a bug met on one task: logged with its trace and
    rejected too, so the others still go on and the flow can end Failed.

    `work` (future -> e.g. frames of its utterance) makes the line's rate and ETA count `work_unit`s, not
    `unit`s: a corpus of short and long videos is then estimated by its length, not by its count.
    """
    from visemeflow.tasks.common import reject_row

    progress = create_progress_artifact(0.0, description=f"{stage}: {unit} done") if futures else None
    reports, rejects, unexpected = [], [], 0
    work = work or {}
    with Progress(stage, len(futures), unit=unit, work_total=sum(work.values()) or None, work_unit=work_unit) as line:
        for done, future in enumerate(as_completed(list(futures)), start=1):
            uid, path = futures[future] if isinstance(futures[future], tuple) else (futures[future], None)
            where = f"{uid}, {path}" if path else uid
            try:
                report = dict(future.result())
                report["cached"] = int(future.state.name == "Cached")
                reports.append(report)
            except expected as exc:
                rejects.append(reject_row(uid, stage, exc.error_type, str(exc), exc.path))
            except Exception as exc:
                trace = "".join(traceback.format_exception(exc))
                logger.error("%s[%s]: unexpected %s\n%s", stage, where, type(exc).__name__, trace)
                message = f"{uid}: {path}: {exc}\n{trace}" if path else f"{uid}: {exc}\n{trace}"
                rejects.append(reject_row(uid, stage, type(exc).__name__, message, path))
                unexpected += 1
            line.advance(work=work.get(future, 0), failed=len(rejects) > line.failed)
            if progress is not None:
                update_progress_artifact(progress, 100.0 * done / len(futures))
    return reports, rejects, unexpected


def read_cached(stage: str, task, store_root, calls: list[tuple[str, tuple, bool]],
                logger) -> tuple[list[dict], list]:
    """Split per-utterance calls `(uid, args, present)` of a persisted `task` into the reports of those that would
    be cache hits (their record under the key Prefect computes, `tasks.common.cache_key_of`, and `present`: their
    output still in the store), read from the records without a task run, each with `cached` 1; and the calls
    left to run, `(uid, args, key)`. A task run costs Prefect 15-60 ms even as a cache hit: 24,000 of them, one per
    utterance at the paper's scale, were most of a rerun's time (bench/track_tasks.py)."""
    from visemeflow.storage import Store
    from visemeflow.tasks.common import cache_key_of, fetch_records, results_of

    results = results_of(store_root)
    remote = Store(store_root).remote
    # on object storage every record is fetched at once (one GET each, all in flight) and checked there, not one
    # key at a time through the cache policy's check and Prefect's reads (four requests an utterance)
    keyed = [(uid, args, present, cache_key_of(task, results, *args, checked=not remote))
             for uid, args, present in calls]
    records = fetch_records(results, [k for _, _, present, k in keyed if present and k is not None], logger) \
        if remote else {}
    reports, left = [], []
    for uid, args, present, key in keyed:
        if remote and key in records:
            reports.append({**records[key].result, "cached": 1})
            continue
        if not remote and key is not None and present and results.exists(key):
            try:
                reports.append({**results.read(key).result, "cached": 1})
                continue
            except Exception as exc:    # an unreadable record: the task runs again and writes it anew
                logger.warning("%s[%s]: its cached result could not be read (%s); running it again",
                               stage, uid, exc)
        left.append((uid, args, key))
    if reports:
        logger.info("%s: %d utterances cached (read from their cached results, no task run)", stage, len(reports))
    return reports, left


# Set while a served (confined) flow runs (`ops.serve.flat_flow`): it checks the paths in settings read from the
# store (`last_settings`), which the served run's own parameters do not show, against serve's folders.
recorded_settings_check: ContextVar[Callable[[str, StageSettings], None] | None] = ContextVar(
    "visemeflow_recorded_settings_check", default=None)


def last_settings(store, stage: str) -> StageSettings | None:
    """What `stage` last ran with in `store` (typed: `flows.params.SETTINGS`), None when it never ran there; in a
    served run, checked by `recorded_settings_check` (a rerun by hand writes where the stage last wrote)."""
    data = store.read_run_config(stage)
    settings = None if data is None else SETTINGS[stage].model_validate(data)
    check = recorded_settings_check.get()
    if settings is not None and check is not None:
        check(stage, settings)
    return settings


class StageRun:
    """What every stage flow does around its tasks, written once: the store opened and cleared of the temporary
    files killed runs left, the settings recorded (what `rerun` repeats), and at the end the summary and the
    stage's rejects published as artifacts and logged, and the run's final state (`finished`)."""

    def __init__(self, stage: str, store_root, settings: StageSettings | None = None) -> None:
        from visemeflow.storage import Store

        self.stage = stage
        self.store = Store(store_root)
        self.logger = get_run_logger()
        swept = self.store.sweep_temporary_files()
        if swept:
            self.logger.info("removed %d temporary files left by killed runs", swept)
        if settings is not None:
            self.store.write_run_config(stage, settings.model_dump(mode="json"))

    def rejected_before(self) -> set[str]:
        """Utterances the stage's rejects table names now (their missing outputs are no reason to recompute)."""
        from visemeflow.schemas import C

        return set(self.store.read_table("rejects", self.stage).column(C.UTTERANCE_ID).to_pylist())

    def finish(self, summary: dict, failed: int, total: int, *, extra: dict | None = None, unexpected: int = 0,
               rejects=None, result: dict | None = None, title: str | None = None,
               reasons: Iterable[str] | None = None) -> State:
        """Publish `summary` (with `extra`, figures that are not counts) and the rejects (the stage's table unless
        given), log them, and end the run: `finished` over `result` (default: summary and extra), with `reasons`
        (default: the messages of the given `rejects`, this run's)."""
        from visemeflow.schemas import C

        from visemeflow.dashboards.artifacts import publish_rejects, publish_stage_summary

        publish_stage_summary(self.stage, summary, extra)
        publish_rejects(self.stage, rejects if rejects is not None else self.store.read_table("rejects", self.stage))
        self.logger.info("%s: %s", title or self.stage, summary)
        if reasons is None:
            reasons = rejects.column(C.MESSAGE).to_pylist() if rejects is not None else ()
        return finished(self.stage, result if result is not None else {**summary, **(extra or {})}, failed, total,
                        unexpected, reasons)
