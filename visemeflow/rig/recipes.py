"""Viseme recipes: each of the 16 visemes as a weighted sum of ARKit-style expression shapes.

A recipe table has rows `viseme,shape,weight`; the viseme's delta is sum_k weight_k (shape_k - neutral). The ICT
Face Model recipes ship in `rig/data/ict_recipes.csv` (the reasoning for each row is in docs/rig.md).
"""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping
from importlib import resources

import numpy as np

from visemeflow.rig.model import RigError
from visemeflow.visemes import N_VISEMES, VISEMES

Recipes = dict[str, dict[str, float]]
"""viseme -> {shape name: weight}."""


def parse_recipes(text: str, source: str = "recipes") -> Recipes:
    """Recipe table text (CSV, header `viseme,shape,weight`) -> recipes; every viseme must have a row."""
    reader = csv.DictReader(io.StringIO(text))
    if reader.fieldnames is None or [f.strip() for f in reader.fieldnames] != ["viseme", "shape", "weight"]:
        raise RigError(f"{source}: expected the header 'viseme,shape,weight', got {reader.fieldnames}")
    recipes: Recipes = {v: {} for v in VISEMES}
    for line, row in enumerate(reader, start=2):
        viseme, shape = row["viseme"].strip(), row["shape"].strip()
        if viseme not in recipes:
            raise RigError(f"{source} line {line}: unknown viseme {viseme!r}; expected one of {', '.join(VISEMES)}")
        try:
            weight = float(row["weight"])
        except (TypeError, ValueError):
            raise RigError(f"{source} line {line}: weight {row['weight']!r} is not a number") from None
        if not np.isfinite(weight):
            raise RigError(f"{source} line {line}: weight must be finite")
        if shape in recipes[viseme]:
            raise RigError(f"{source} line {line}: {viseme} lists {shape!r} twice")
        recipes[viseme][shape] = weight
    empty = [v for v, r in recipes.items() if not r]
    if empty:
        raise RigError(f"{source}: no recipe row for viseme(s) {', '.join(empty)}")
    return recipes


def load_ict_recipes() -> Recipes:
    """The shipped recipes for the ICT Face Model's ARKit-style shapes."""
    text = resources.files("visemeflow.rig").joinpath("data", "ict_recipes.csv").read_text("utf-8")
    return parse_recipes(text, "visemeflow/rig/data/ict_recipes.csv")


def recipe_shapes(recipes: Recipes) -> list[str]:
    """Every shape name the recipes use, sorted."""
    return sorted({shape for recipe in recipes.values() for shape in recipe})


def combine_shapes(shape_deltas: Mapping[str, np.ndarray], recipes: Recipes) -> np.ndarray:
    """(16, V, 3) float32 viseme deltas from per-shape deltas {name: (V, 3)} (shape - neutral) and the recipes."""
    missing = [s for s in recipe_shapes(recipes) if s not in shape_deltas]
    if missing:
        raise RigError(f"recipes use shape(s) not provided: {', '.join(missing)}")
    first = np.asarray(next(iter(shape_deltas.values())))
    out = np.zeros((N_VISEMES,) + first.shape, np.float64)
    for i, viseme in enumerate(VISEMES):
        for shape, weight in recipes[viseme].items():
            out[i] += weight * np.asarray(shape_deltas[shape], np.float64)
    return out.astype(np.float32)
