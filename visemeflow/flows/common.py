"""Helpers the flows share: shard grouping, waiting with progress, failure accounting."""

import traceback
from collections import defaultdict
from collections.abc import Iterable

from prefect.artifacts import create_progress_artifact, update_progress_artifact
from prefect.futures import PrefectFuture, as_completed
from prefect.states import Completed, Failed, State

from visemeflow.flows.errors import StageFailed
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


def finished(stage: str, summary: dict, failed: int, total: int, unexpected: int = 0) -> State:
    """The flow's final state, with a message saying how many of the stage's utterances failed.

    Completed (the summary as its result) while failures are bad input of some utterances: each is a reject row
    with its reason and the rest of the corpus went on. Failed, raising `StageFailed` to a caller, when all of
    `total` utterances failed or `unexpected` of them failed with an error that is not a known bad-input class.
    """
    if unexpected:
        message = (f"{stage}: {unexpected} of {total} utterances failed with an unexpected error (tracebacks in the "
                   f"run's logs; reasons in the rejects table); {failed} failed in all")
        return Failed(message=message, data=StageFailed(message, summary))
    if total and failed >= total:
        message = f"{stage}: all {total} utterances failed (see the rejects table)"
        return Failed(message=message, data=StageFailed(message, summary))
    if failed:
        message = f"{stage}: {failed} of {total} utterances failed (see the rejects table); the others are done"
    else:
        message = f"{stage}: all {total} utterances done"
    return Completed(message=message, data=summary)


def collect_utterance_results(
    futures: dict, stage: str, expected: type[Exception], logger, work: dict | None = None, work_unit: str = "frames",
) -> tuple[list, list, int]:
    """Wait for per-utterance task futures (future -> utterance id) with a progress artifact and a progress line on
    the terminal: (reports with their `cached` flag, reject rows, count of unexpected errors). `expected` errors
    (with `error_type` and `path`) are rejects; any other exception is a bug met on one utterance: logged with its
    trace and rejected too, so the others still go on and the flow can end Failed.

    `work` (future -> e.g. frames of its utterance) makes the line's rate and ETA count `work_unit`s, not
    utterances: a corpus of short and long videos is then estimated by its length, not by its count.
    """
    from visemeflow.tasks.common import reject_row

    progress = create_progress_artifact(0.0, description=f"{stage}: utterances done") if futures else None
    reports, rejects, unexpected = [], [], 0
    work = work or {}
    with Progress(stage, len(futures), work_total=sum(work.values()) or None, work_unit=work_unit) as line:
        for done, future in enumerate(as_completed(list(futures)), start=1):
            uid = futures[future]
            try:
                report = dict(future.result())
                report["cached"] = int(future.state.name == "Cached")
                reports.append(report)
            except expected as exc:
                rejects.append(reject_row(uid, stage, exc.error_type, str(exc), exc.path))
            except Exception as exc:
                trace = "".join(traceback.format_exception(exc))
                logger.error("%s[%s]: unexpected %s\n%s", stage, uid, type(exc).__name__, trace)
                rejects.append(reject_row(uid, stage, type(exc).__name__, f"{uid}: {exc}\n{trace}", None))
                unexpected += 1
            line.advance(work=work.get(future, 0), failed=len(rejects) > line.failed)
            if progress is not None:
                update_progress_artifact(progress, 100.0 * done / len(futures))
    return reports, rejects, unexpected
