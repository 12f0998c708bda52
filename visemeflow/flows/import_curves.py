"""The `import_curves` flow: captured facial animation (Live Link Face CSV, per-frame channel CSV or NPY) with its
audio into the store, as utterances with curves of source `captured` (training targets from real speech).

Each take is one cached task (`import_curves[<utterance id>]`), keyed on its files' content hashes, the channel
table, the ARKit-to-viseme table's digest and the config: running the flow again on unchanged takes is all cache
hits; a changed file recomputes only its take; a take whose curves were deleted is imported again. Bad input is a
reject of stage `import_curves` (discovery rejects too) naming the take and the file; the other takes go on.
"""

from __future__ import annotations

from dataclasses import asdict

from prefect import flow
from prefect.artifacts import create_markdown_artifact
from prefect.futures import as_completed

from visemeflow.flows.params import DEFAULT_STORE, ImportCurvesParams, ImportCurvesSettings  # noqa: F401 (re-exported)
from visemeflow.shapes.capture import load_arkit_to_visemes
from visemeflow.flows.common import StageRun, finished, replace_stage_rejects
from visemeflow.ingest.captured import discover_takes
from visemeflow.ingest.hints import reject_advice, reject_lines
from visemeflow.tasks.progress import Progress
from visemeflow.tasks.common import reject_row
from visemeflow.tasks.import_curves import SOURCE, STAGE, ingested_rows, take_task_for



def _markdown(rows: list[dict], summary: dict) -> str:
    lines = [f"### Captured curves ({summary['variant']})", "",
             "| take | frames | fps | drift (frames) | residual mean / median (moving frames) | bounded | unmapped "
             "channels that vary | cached |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r.get("rejected"):
            lines.append(f"| `{r['utterance_id']}` | rejected: {r['reject']['message']} |  |  |  |  |  |  |")
            continue
        lines.append(f"| `{r['utterance_id']}` | {r['frames']} | {r['fps']:g} | {r['drift_frames']:+.2f} | "
                     f"{r['residual_mean_moving']:.4f} / {r['residual_median_moving']:.4f} | {r['bounded_frames']} | "
                     f"{', '.join(r['unmapped_channels']) or '-'} | {'yes' if r['cached'] else 'no'} |")
    lines += ["", "Residual: ||D_vis x - D_arkit a|| / ||D_arkit a|| on the demo rig's vertices per frame "
                  "(visemeflow.shapes.capture); bounded: frames refitted with weights <= 1."]
    return "\n".join(lines) + "\n"


@flow(name="import_curves", flow_run_name="import_curves({params.takes})")
def import_curves_flow(params: ImportCurvesParams):
    """Import every take as an utterance with `captured` curves; unchanged takes are cache hits."""
    config = params.config
    run = StageRun(STAGE, params.store, ImportCurvesSettings(
        takes=str(params.takes.resolve()), n_shards=params.n_shards,
        channel_table=str(params.channel_table.resolve()) if params.channel_table else None,
        names=str(params.names.resolve()) if params.names else None, config=config))
    store, logger = run.store, run.logger
    found = discover_takes(params.takes, channel_table=params.channel_table, names=params.names, fps=config.fps)
    solver = load_arkit_to_visemes()
    takes = [asdict(t) for t in found.takes]
    ingested = ingested_rows(store, [t["utterance_id"] for t in takes]) if takes else {}
    rejected = run.rejected_before()
    futures = {
        take_task_for(store, take, config.variant, rejected).submit(
            str(store.root), params.n_shards, take, config, solver.digest,
            ingested[take["utterance_id"]]["audio_path"] if take["utterance_id"] in ingested else None,
        ): take for take in takes
    }
    rows, rejects, unexpected = [], [], 0
    rejects += [reject_row(r.utterance_id, STAGE, r.error_type, r.message, r.path) for r in found.rejects]
    with Progress(STAGE, len(futures), unit="takes") as line:
        for future in as_completed(list(futures)):
            take = futures[future]
            try:
                report = dict(future.result())
            except Exception as exc:  # a bug or an unexpected failure: the take fails, the others go on
                unexpected += 1
                logger.error("%s failed: %s: %s", take["utterance_id"], type(exc).__name__, exc)
                rejects.append(reject_row(take["utterance_id"], STAGE, type(exc).__name__,
                                          f"{take['utterance_id']}: {exc}", take["capture_path"]))
                line.advance(failed=True)
                continue
            report["cached"] = future.state.name == "Cached"
            if report.get("rejected"):
                rejects.append(report["reject"])
            rows.append(report)
            line.advance(failed=bool(report.get("rejected")))
    rows.sort(key=lambda r: r["utterance_id"])
    replace_stage_rejects(store, STAGE, rejects, params.n_shards)
    done = [r for r in rows if not r.get("rejected")]
    moving = sum(r["moving_frames"] for r in done)
    summary = {
        "variant": config.variant, "source": SOURCE, "takes": len(takes) + len(found.rejects),
        "imported": sum(not r["cached"] for r in done), "cached": sum(r["cached"] for r in done),
        "rejected": len(rejects), "frames": sum(r["frames"] for r in done),
        "residual_mean_moving": (sum(r["residual_mean_moving"] * r["moving_frames"] for r in done) / moving
                                 if moving else None),
        "bounded_frames": sum(r["bounded_frames"] for r in done),
        "takes_report": rows,
    }
    create_markdown_artifact(key="import-curves", markdown=_markdown(rows, summary),
                             description="captured takes imported as curves")
    logger.info("import_curves: %d takes, %d imported, %d cached, %d rejected", summary["takes"], summary["imported"],
                summary["cached"], summary["rejected"])
    if rejects and (unexpected or len(rejects) >= summary["takes"]):
        # a run that ends Failed: the command prints no list of its own, so the reasons and hints are logged here
        logger.warning("import_curves: %d rejected:\n%s", len(rejects),
                       "\n".join(reject_lines(rejects) + [f"hint: {a}" for a in reject_advice(rejects)]))
    return finished(STAGE, summary, len(rejects), summary["takes"], unexpected)
