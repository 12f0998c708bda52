"""The `sweep` flow: one preset trained on nested subsets of the training set (paper 5.2, Fig. 5)."""

import math
import zlib
from pathlib import Path

from prefect import flow, get_run_logger
from prefect.artifacts import create_table_artifact

from visemeflow.atomic import atomic_write
from visemeflow.dashboards import plots
from visemeflow.flows.params import SweepParams
from visemeflow.flows.train import resolve_variant, training_rows
from visemeflow.flows.runners import cpu_thread_pool, on_requested_runner, run_on_runner
from visemeflow.hashing import file_hash, stable_hash
from visemeflow.learning.device import check_device_here
from visemeflow.learning.train import TrainConfig
from visemeflow.schemas import C
from visemeflow.storage import Store
from visemeflow.tasks.train import training_task_for


def nested_subsets(rows: list[dict], sizes: list[int]) -> dict[int, list[dict]]:
    """For each size, the first `size` training rows in a fixed pseudo-random order: every subset contains the smaller ones."""
    order = sorted(rows, key=lambda r: (zlib.crc32(r[C.UTTERANCE_ID].encode()), r[C.UTTERANCE_ID]))
    return {size: order[:size] for size in sorted(set(sizes)) if 0 < size <= len(order)}


def data_digest(store: Store, lineage: dict, rows: list[dict], val: list[dict]) -> str:
    """Digest of what a model is trained and judged on: the curves (`lineage`: source, variant, each utterance's
    curves' provenance, or the curve file's own hash where none was recorded) and each utterance's input files."""
    curves = {split: {uid: provenance or file_hash(store.local_file(store.curve_path(lineage["source"],
                                                                                      lineage["variant"], uid)))
                      for uid, provenance in lineage[split].items()} for split in ("train", "val")}
    audio = [[r[C.UTTERANCE_ID], r[C.CONTENT_HASH]] for r in rows + val]
    return stable_hash(lineage["source"], lineage["variant"], curves, audio)


def sweep_model_name(config: TrainConfig, size: int, data: str) -> str:
    """`sweep-<preset>-n<size>-<digest of the config and data>`: a sweep of another config or other data trains
    models (and checkpoints, in the model's folder) of its own, and a sweep run again finds its own."""
    return f"sweep-{config.preset}-n{size}-{stable_hash(config, data, size=4)}"


def plot_sweep(points: list[tuple[int, float]], path: Path, title: str) -> Path:
    """A Fig. 5-style PNG at `path`: validation L1 x 100 against training-set size (log x axis), drawn with
    matplotlib like every other chart (`dashboards.plots.sweep_figure`), written atomically."""
    png = plots.sweep_figure(points, title)
    return atomic_write(path, lambda tmp: tmp.write_bytes(png), keep_suffix=True)


@flow(name="sweep", flow_run_name="sweep({params.config.preset})", task_runner=cpu_thread_pool())
def sweep_flow(params: SweepParams) -> dict:
    """Train the preset on each nested subset (in parallel tasks) at an equal budget of steps; plot L1 x 100 by size.

    The budget counts utterances: with `config.batch_size` B, a size trains ceil(steps / size) epochs of
    ceil(size / B) optimisation steps. `params.device`/`precision`: as in the `train` flow (all sizes share it).
    """
    check_device_here(params.device, params.precision)  # one line, before anything runs
    if not on_requested_runner(params):  # e.g. a deployment run asking for Dask: run on it as a subflow
        return run_on_runner(sweep_flow, params)
    store = Store(params.store)
    variant = resolve_variant(store, params.source, params.variant)
    train, val, lineage = training_rows(store, params.source, variant)
    if not val:
        raise LookupError(f"no validation utterance in {store.root}: the sweep is judged on the 'val' split")
    subsets = nested_subsets(train, params.sizes)
    if not subsets:
        raise LookupError(f"none of the sizes {params.sizes} fits the {len(train)} training utterances")
    futures = {}
    for size, rows in subsets.items():
        epochs = max(1, math.ceil(params.steps / size))  # equal iteration budget, one utterance per step
        config = params.config.model_copy(update={"epochs": epochs})
        ids = {r[C.UTTERANCE_ID] for r in rows}
        sub_lineage = {**lineage, "train": {k: v for k, v in lineage["train"].items() if k in ids},
                       "config": config.model_dump(mode="json")}
        name = sweep_model_name(config, size, data_digest(store, sub_lineage, rows, val))
        futures[size] = training_task_for(store, name).submit(
            str(store.root), name, rows, val, params.source, variant, sub_lineage, config, params.device,
            params.precision, None if params.encoder_cache_dir is None else str(params.encoder_cache_dir),
        )
    results = {size: future.result() for size, future in futures.items()}
    points = [(size, float(r["val_l1_x100"])) for size, r in sorted(results.items())]
    title = f"{params.config.preset}: validation L1 x 100 by training size ({params.steps} steps each)"
    plot = store.write_file(store.report_path(f"sweep-{params.config.preset}.png"),
                            lambda tmp: plot_sweep(points, tmp, title), keep_suffix=True)
    create_table_artifact(
        key=f"sweep-{params.config.preset.replace('_', '-')}",
        table=[{"train_utterances": s, "val_l1_x100": round(v, 3)} for s, v in points],
        description=f"Fig. 5-style sweep; plot at {plot}",
    )
    get_run_logger().info("sweep %s: %s", params.config.preset, points)
    return {"points": points, "plot": str(plot), "validation_utterances": len(val)}
