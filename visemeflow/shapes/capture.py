"""Captured ARKit animation as our 16 viseme curves: a per-frame non-negative least-squares fit through a face that
has both conventions.

The ICT Face Model carries ARKit-style shapes and the shipped demo rig holds our 16 visemes on the same vertices.
For ARKit weights a (52, `ARKIT_52` order) of one frame, the viseme weights x (16) minimise the distance between the
two deformations of that face:

    ||D_vis x - D_arkit a||^2 = x'Gx - 2x'Ba + a'Ca    over x >= 0,

with D_vis (3V, 16) the viseme offsets and D_arkit (3V, 52) the ARKit offsets on all the demo rig's vertices (ARKit
shapes ICT lacks, eyes, brows, tongue, are zero columns: they contribute nothing), G = D_vis'D_vis, B = D_vis'D_arkit
and C = D_arkit'D_arkit. Only these inner products are needed, so the shipped table
(`shapes/data/arkit_to_visemes.csv`, measured by `examples/build_arkit_to_visemes.py`) is their 48 x 48 Gram
matrix M (16 visemes + the 32 ARKit shapes ICT has), a few kilobytes.

Solving: with G = LL' (Cholesky), x'Gx - 2x'Ba = ||L'x - L^-1 Ba||^2 - const, so each frame is a 16 x 16 NNLS
(`scipy.optimize.nnls`) on the whitened system. Vectorised around it: repeated frames are solved once, frames with
B a <= 0 everywhere (nothing of the mouth moves, e.g. a pure eye blink) are 0 at once (x = 0 meets the optimality
conditions), frames whose unconstrained solution already lies in [0, 1] take it. A frame whose NNLS weight goes past
1 is fitted again with 0 <= x <= 1 (bounded-variable least squares), so curves are in [0, 1] by the fit rather than
by clipping; `VisemeFit.bounded` counts those frames.

The relative residual of a frame is ||D_vis x - D_arkit a|| / ||D_arkit a|| (0 when the frame moves none of the
ARKit shapes the face has). What it cannot tell: G is nearly singular (the demo visemes are recipes over fewer ARKit
shapes than 16, e.g. SCHWA is almost a third of AHH), so some visemes come back as an equivalent mix (AHH 0.8 as AHH
0.74 + SCHWA 0.19) with the same face; the deformation is recovered, the split between such visemes is not unique.

Pure: numpy and scipy; the table is package data.
"""

from __future__ import annotations

import csv
import functools
import io
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
from scipy.linalg import cho_solve, solve_triangular
from scipy.optimize import lsq_linear, nnls

from visemeflow.shapes.conventions import ARKIT_52
from visemeflow.hashing import new_hasher
from visemeflow.visemes import N_VISEMES, VISEMES

__all__ = [
    "CHECK_TOLERANCE",
    "TABLE_FILE",
    "ArkitToVisemes",
    "CaptureError",
    "VisemeFit",
    "arkit_to_visemes",
    "curve_shares",
    "fit_visemes",
    "gram_table_text",
    "load_arkit_to_visemes",
    "parse_gram_table",
]

TABLE_FILE = "arkit_to_visemes.csv"
CHECK_TOLERANCE = 1e-9
"""`examples/build_arkit_to_visemes.py --check` accepts differences up to this share of the largest entry."""
_SILENT = 1e-12
"""A frame whose ||D_arkit a||^2 is below this share of the largest ARKit shape's squared norm moves nothing."""
_NNLS_MAXITER = 50 * N_VISEMES
_N_ARKIT = len(ARKIT_52)
_ARKIT_INDEX = {name: i for i, name in enumerate(ARKIT_52)}


class CaptureError(ValueError):
    """ARKit weights or a conversion table that cannot be used; the message names the source."""


@dataclass(frozen=True)
class ArkitToVisemes:
    """The Gram matrix of the 16 viseme offsets and the measured ARKit shapes' offsets on one face, and what the
    per-frame fit derives from it."""

    names: tuple[str, ...]
    """The 16 visemes (in `VISEMES` order), then the ARKit shapes the face has."""
    matrix: np.ndarray = field(repr=False)
    """(len(names), len(names)) float64: inner products of the offsets (squared centimetres for ICT)."""
    n_vertices: int = 0
    source: str = ""
    gram: np.ndarray = field(init=False, repr=False)
    """G (16, 16)."""
    cross: np.ndarray = field(init=False, repr=False)
    """B (16, 52), ARKit columns in `ARKIT_52` order; zero for shapes the face lacks."""
    arkit_gram: np.ndarray = field(init=False, repr=False)
    """C (52, 52)."""
    cholesky: np.ndarray = field(init=False, repr=False)
    """Lower L with G = LL'."""
    digest: str = field(init=False)
    """A digest of the names and the matrix (provenance, cache keys)."""

    def __post_init__(self) -> None:
        where = self.source or "ARKit-to-viseme table"
        names, m = tuple(self.names), np.asarray(self.matrix, dtype=np.float64)
        if names[:N_VISEMES] != VISEMES:
            raise CaptureError(f"{where}: the first {N_VISEMES} shapes must be the visemes {', '.join(VISEMES)} in "
                               f"that order, got {', '.join(names[:N_VISEMES])}")
        arkit = names[N_VISEMES:]
        unknown = [n for n in arkit if n not in _ARKIT_INDEX]
        if unknown:
            raise CaptureError(f"{where}: {', '.join(map(repr, unknown))} not ARKit blendshape name(s)")
        if len(set(arkit)) != len(arkit) or not arkit:
            raise CaptureError(f"{where}: the ARKit shapes must be distinct and at least one, got {arkit}")
        if m.shape != (len(names), len(names)):
            raise CaptureError(f"{where}: the matrix must be {len(names)} x {len(names)}, got {m.shape}")
        if not np.isfinite(m).all():
            raise CaptureError(f"{where}: the matrix holds NaN or infinite values")
        scale = float(np.abs(m).max())
        if float(np.abs(m - m.T).max()) > CHECK_TOLERANCE * scale:
            raise CaptureError(f"{where}: the matrix is not symmetric")
        gram = m[:N_VISEMES, :N_VISEMES]
        try:
            chol = np.linalg.cholesky(gram)
        except np.linalg.LinAlgError:
            raise CaptureError(f"{where}: the visemes' Gram matrix is not positive definite (a viseme without "
                               "motion, or two identical visemes)") from None
        columns = np.array([_ARKIT_INDEX[n] for n in arkit])
        cross = np.zeros((N_VISEMES, _N_ARKIT))
        cross[:, columns] = m[:N_VISEMES, N_VISEMES:]
        arkit_gram = np.zeros((_N_ARKIT, _N_ARKIT))
        arkit_gram[np.ix_(columns, columns)] = m[N_VISEMES:, N_VISEMES:]
        h = new_hasher()
        h.update("\0".join(names).encode())
        h.update(np.ascontiguousarray(m).tobytes())
        for key, value in (("names", names), ("matrix", m), ("gram", gram), ("cross", cross),
                           ("arkit_gram", arkit_gram), ("cholesky", chol), ("digest", h.hexdigest())):
            object.__setattr__(self, key, value)

    @classmethod
    def from_gram(cls, names, gram, *, n_vertices: int = 0, source: str = "") -> "ArkitToVisemes":
        return cls(tuple(names), np.asarray(gram, dtype=np.float64), n_vertices, source)

    @property
    def arkit_names(self) -> tuple[str, ...]:
        """The ARKit shapes the face has (the others move nothing)."""
        return self.names[N_VISEMES:]


def gram_table_text(table: ArkitToVisemes, notes: list[str] | tuple[str, ...] = ()) -> str:
    """The CSV text of a table: `#` comment lines (`# vertices: N` is read back), a header `shape,<names>`, then one
    row per shape with the matrix at full float64 precision (shortest round-trip text)."""
    lines = ["# Inner products of the demo rig's 16 viseme offsets and the ICT Face Model's ARKit-style shape offsets",
             "# (squared centimetres summed over the rig's vertices), measured by examples/build_arkit_to_visemes.py;",
             "# read by visemeflow.shapes.capture (per-frame NNLS: ARKit weights -> viseme weights).",
             f"# vertices: {table.n_vertices}"]
    lines += [f"# {note}" for note in notes]
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(("shape",) + table.names)
    for name, row in zip(table.names, table.matrix):
        writer.writerow([name] + [repr(float(v)) for v in row])
    return "\n".join(lines) + "\n" + out.getvalue()


def parse_gram_table(text: str, source: str) -> ArkitToVisemes:
    """A table written by `gram_table_text`; CaptureError naming `source` (and the line) otherwise."""
    n_vertices = 0
    body = []
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("#"):
            key, _, value = stripped.lstrip("#").partition(":")
            if key.strip() == "vertices" and value.strip().isdigit():
                n_vertices = int(value)
            continue
        if stripped:
            body.append(line)
    rows = list(csv.reader(body))
    if not rows or not rows[0] or rows[0][0].strip() != "shape":
        raise CaptureError(f"{source}: expected a header 'shape,AAA,...', got {rows[0][:3] if rows else 'nothing'}")
    names = tuple(n.strip() for n in rows[0][1:])
    if len(rows) - 1 != len(names):
        raise CaptureError(f"{source}: {len(names)} shapes in the header but {len(rows) - 1} rows")
    matrix = np.empty((len(names), len(names)))
    for i, row in enumerate(rows[1:]):
        if len(row) != len(names) + 1 or row[0].strip() != names[i]:
            raise CaptureError(f"{source}: row {i + 1} must be {names[i]!r} with {len(names)} values, got "
                               f"{row[0]!r} with {len(row) - 1}")
        try:
            matrix[i] = [float(v) for v in row[1:]]
        except ValueError as exc:
            raise CaptureError(f"{source}: row {names[i]!r}: {exc}") from None
    return ArkitToVisemes(names, matrix, n_vertices, source)


@functools.lru_cache(maxsize=1)
def _shipped() -> ArkitToVisemes:
    text = resources.files("visemeflow.shapes").joinpath("data", TABLE_FILE).read_text("utf-8")
    return parse_gram_table(text, f"visemeflow/shapes/data/{TABLE_FILE}")


def load_arkit_to_visemes(path: str | Path | None = None) -> ArkitToVisemes:
    """The shipped table (package data), or one written by `gram_table_text` at `path`."""
    if path is None:
        return _shipped()
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise CaptureError(f"{path}: cannot read the ARKit-to-viseme table ({exc})") from None
    return parse_gram_table(text, str(path))


@dataclass(frozen=True)
class VisemeFit:
    """The per-frame fit of (T, 52) ARKit weights."""

    curves: np.ndarray
    """(T, 16) float32 in [0, 1]."""
    residual: np.ndarray
    """(T,) float32: ||D_vis x - D_arkit a|| / ||D_arkit a||, 0 for frames that move none of the face's shapes."""
    moving: np.ndarray
    """(T,) bool: frames that move some of the face's ARKit shapes (the others are silent: curves and residual 0)."""
    bounded: int
    """Frames whose plain NNLS went above 1 somewhere and were fitted again with 0 <= x <= 1."""

    @property
    def silent(self) -> int:
        """How many frames move none of the face's ARKit shapes."""
        return int((~self.moving).sum())


def _check_arkit(arkit, where: str) -> np.ndarray:
    a = np.asarray(arkit)
    if a.ndim != 2 or a.shape[1] != _N_ARKIT:
        raise CaptureError(f"{where}: ARKit weights must be (frames, {_N_ARKIT}) in ARKIT_52 order, got {a.shape}")
    if not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating):
        raise CaptureError(f"{where}: ARKit weights must be real numbers, got {a.dtype}")
    a = a.astype(np.float64)
    bad = ~np.isfinite(a)
    if bad.any():
        frame, column = map(int, np.argwhere(bad)[0])
        raise CaptureError(f"{where}: {ARKIT_52[column]} is {a[frame, column]} at frame {frame} "
                           f"({int(bad.sum())} NaN or infinite values)")
    return a


def _solve_frame(lt: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, bool]:
    """min ||lt x - target|| over x >= 0, and over 0 <= x <= 1 when the first goes past 1; (x, bounded)."""
    try:
        x, _ = nnls(lt, target, maxiter=_NNLS_MAXITER)
    except RuntimeError:  # iteration limit (not seen on real data): the bounded solver converges
        x = np.full(N_VISEMES, 2.0)
    if x.max() <= 1.0:
        return x, False
    fit = lsq_linear(lt, target, bounds=(0.0, 1.0), method="bvls", tol=1e-12)
    return fit.x, True


def fit_visemes(arkit, table: ArkitToVisemes | None = None, where: str = "ARKit weights") -> VisemeFit:
    """(T, 52) ARKit weights (`ARKIT_52` order) -> the 16 viseme curves of each frame, by the NNLS fit on the face of
    `table` (the shipped one by default). CaptureError naming `where`, the frame and the shape for NaN or infinite
    weights or a wrong shape. Weights are used as given (captures may stray a little outside [0, 1])."""
    table = table or load_arkit_to_visemes()
    a = _check_arkit(arkit, where)
    n = len(a)
    if n == 0:
        return VisemeFit(np.zeros((0, N_VISEMES), np.float32), np.zeros(0, np.float32), np.zeros(0, bool), 0)
    rows, inverse = np.unique(a, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    counts = np.bincount(inverse, minlength=len(rows))
    ba = rows @ table.cross.T  # (U, 16): B a per distinct frame
    energy = np.einsum("ti,ij,tj->t", rows, table.arkit_gram, rows)  # ||D_arkit a||^2
    silent = energy <= _SILENT * float(np.diag(table.arkit_gram).max())
    x = np.zeros_like(ba)
    zero = silent | (ba <= 0).all(axis=1)  # x = 0 is optimal when B a <= 0 (the gradient points into x >= 0)
    free = cho_solve((table.cholesky, True), ba.T).T  # the unconstrained minimiser
    inside = ~zero & (free >= 0).all(axis=1) & (free <= 1).all(axis=1)
    x[inside] = free[inside]
    todo = np.flatnonzero(~zero & ~inside)
    bounded = 0
    if len(todo):
        lt = table.cholesky.T
        targets = solve_triangular(table.cholesky, ba[todo].T, lower=True).T
        for k, target in zip(todo, targets):
            x[k], was_bounded = _solve_frame(lt, target)
            bounded += int(counts[k]) if was_bounded else 0
    x = np.clip(x, 0.0, 1.0)
    r2 = np.einsum("ti,ij,tj->t", x, table.gram, x) - 2.0 * np.einsum("ti,ti->t", x, ba) + energy
    residual = np.where(silent, 0.0, np.sqrt(np.maximum(r2, 0.0) / np.where(silent, 1.0, energy)))
    return VisemeFit(x[inverse].astype(np.float32), residual[inverse].astype(np.float32), ~silent[inverse], bounded)


def arkit_to_visemes(arkit, table: ArkitToVisemes | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(T, 52) ARKit weights -> ((T, 16) float32 viseme curves in [0, 1], (T,) relative residual per frame)."""
    fit = fit_visemes(arkit, table)
    return fit.curves, fit.residual


def curve_shares(curves: np.ndarray, active: float = 0.1, open_threshold: float = 0.3) -> dict[str, object]:
    """How converted curves look: the share of frames where some viseme exceeds `active`, each viseme's share of
    being the top one among those frames, and the share of all frames with the jaw-open visemes AHH or AAA above
    `open_threshold`."""
    curves = np.asarray(curves, dtype=np.float32)
    if curves.ndim != 2 or curves.shape[1] != N_VISEMES:
        raise ValueError(f"curves must be (frames, {N_VISEMES}), got {curves.shape}")
    n = max(len(curves), 1)
    moving = curves.max(axis=1, initial=0.0) > active if len(curves) else np.zeros(0, bool)
    top = np.bincount(curves[moving].argmax(axis=1), minlength=N_VISEMES) if moving.any() else np.zeros(N_VISEMES)
    jaw = (curves[:, VISEMES.index("AHH")] > open_threshold) | (curves[:, VISEMES.index("AAA")] > open_threshold)
    return {
        "active_share": float(moving.sum() / n),
        "top_share": {v: float(top[i] / max(int(moving.sum()), 1)) for i, v in enumerate(VISEMES)},
        "jaw_open_share": float(jaw.sum() / n),
        "mean": {v: float(curves[:, i].mean()) if len(curves) else 0.0 for i, v in enumerate(VISEMES)},
    }

