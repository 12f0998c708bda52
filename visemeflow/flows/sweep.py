"""The `sweep` flow: one preset trained on nested subsets of the training set (paper 5.2, Fig. 5)."""

import math
import zlib
from pathlib import Path

import cv2
import numpy as np
from prefect import flow, get_run_logger
from prefect.artifacts import create_table_artifact

from visemeflow.atomic import atomic_write
from visemeflow.flows.params import SweepParams
from visemeflow.flows.train import resolve_variant, training_rows
from visemeflow.flows.runners import cpu_thread_pool, on_requested_runner, run_on_runner
from visemeflow.schemas import C
from visemeflow.storage import Store
from visemeflow.tasks.train import training_task_for


def nested_subsets(rows: list[dict], sizes: list[int]) -> dict[int, list[dict]]:
    """For each size, the first `size` training rows in a fixed pseudo-random order: every subset contains the smaller ones."""
    order = sorted(rows, key=lambda r: (zlib.crc32(r[C.UTTERANCE_ID].encode()), r[C.UTTERANCE_ID]))
    return {size: order[:size] for size in sorted(set(sizes)) if 0 < size <= len(order)}


def plot_sweep(points: list[tuple[int, float]], path: Path, title: str) -> Path:
    """A Fig. 5-style PNG: validation L1 x 100 against training-set size (log x axis), drawn with OpenCV."""
    width, height, margin = 640, 420, 60
    image = np.full((height, width, 3), 255, np.uint8)
    xs = np.log10([p[0] for p in points])
    ys = np.array([p[1] for p in points])
    x_lo, x_hi = xs.min() - 0.1, xs.max() + 0.1
    y_lo, y_hi = 0.0, max(ys.max() * 1.15, 1e-6)

    def to_px(x: float, y: float) -> tuple[int, int]:
        u = margin + (x - x_lo) / (x_hi - x_lo) * (width - 2 * margin)
        v = height - margin - (y - y_lo) / (y_hi - y_lo) * (height - 2 * margin)
        return int(round(u)), int(round(v))

    cv2.rectangle(image, (margin, margin), (width - margin, height - margin), (0, 0, 0), 1)
    pixels = [to_px(x, y) for x, y in zip(xs, ys)]
    for a, b in zip(pixels, pixels[1:]):
        cv2.line(image, a, b, (180, 80, 20), 2, cv2.LINE_AA)
    for (size, value), p in zip(points, pixels):
        cv2.circle(image, p, 5, (180, 80, 20), -1, cv2.LINE_AA)
        cv2.putText(image, f"{value:.2f}", (p[0] + 6, p[1] - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(image, str(size), (p[0] - 10, height - margin + 20), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1,
                    cv2.LINE_AA)
    cv2.putText(image, title, (margin, 35), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(image, "training utterances (log scale)", (width // 2 - 120, height - 15), cv2.FONT_HERSHEY_SIMPLEX,
                0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(image, "val L1 x 100", (5, margin - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    def write(tmp: Path) -> None:
        if not cv2.imwrite(str(tmp), image):
            raise OSError(f"cannot write the sweep plot {path}")

    return atomic_write(path, write, keep_suffix=True)  # cv2 picks the format by the suffix


@flow(name="sweep", flow_run_name="sweep[{params.config.preset}]", task_runner=cpu_thread_pool())
def sweep_flow(params: SweepParams) -> dict:
    """Train the preset on each nested subset (in parallel tasks) at an equal budget of steps; plot L1 x 100 by size."""
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
        name = f"sweep-{params.config.preset}-n{size}"
        ids = {r[C.UTTERANCE_ID] for r in rows}
        sub_lineage = {**lineage, "train": {k: v for k, v in lineage["train"].items() if k in ids},
                       "config": config.model_dump(mode="json")}
        futures[size] = training_task_for(store, name).submit(
            str(store.root), name, rows, val, params.source, variant, sub_lineage, config
        )
    results = {size: future.result() for size, future in futures.items()}
    points = [(size, float(r["val_l1_x100"])) for size, r in sorted(results.items())]
    plot = plot_sweep(points, store.report_path(f"sweep-{params.config.preset}.png"),
                      f"{params.config.preset}: validation L1 x 100 by training size ({params.steps} steps each)")
    create_table_artifact(
        key=f"sweep-{params.config.preset.replace('_', '-')}",
        table=[{"train_utterances": s, "val_l1_x100": round(v, 3)} for s, v in points],
        description=f"Fig. 5-style sweep; plot at {plot}",
    )
    get_run_logger().info("sweep %s: %s", params.config.preset, points)
    return {"points": points, "plot": str(plot), "validation_utterances": len(val)}
