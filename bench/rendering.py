"""Benchmark: the ground-truth renderer and rig evaluation on the shipped ICT demo rig, on one CPU core.

Run:  .venv/bin/python bench/rendering.py [--frames N]

Prints one table (metric, value, target, met?) and never asserts; the exit status is 0 whatever the figures are.
Threads are pinned to one (OMP/MKL/OpenBLAS env set before numpy is imported, torch.set_num_threads(1)).

1. Rendering at 360x288 (the GRID video size), face framed as the synthetic corpus frames it (landmark span = 45% of
   the image height, so the head fills about 60%): N frames of the rig under random viseme weights (one weight
   set per frame, meshes evaluated beforehand and not timed), each rendered by
     fast       `render_mesh`: all triangles' bounding-box pixels enumerated at once in numpy, np.maximum.at z-buffer;
     reference  `render_mesh(..., reference=True)`: the plain per-triangle loop with a running z-buffer (same
                pixels; it is the faithful path the fast one is tested against), on a few frames only.
   Split of the fast path: rasterisation (`rasterize_fragments`) and shading (vertex normals + Lambert) alone.
   Also 640x480 and a close-up (landmark span = 90% of the height), where more pixels are covered, and the same
   frames textured (`MeshTexture`: UVs projected from the front, a 1024-px image, as previews of a glTF avatar draw
   it) against vertex colours. And the head in front of a static 20,000-triangle sheet (a body, hair): drawn as one
   mesh every frame against drawn over the sheet's backdrop, rendered once (`render_backdrop`, as previews draw a
   glTF avatar's meshes no target moves); the images must be identical.
2. Rig evaluation for 1,000 frames of weights: the 68 landmark vertices (`evaluate_rig(rig, w, rig.landmark_ids)`,
   what a tracker's landmark loss needs per iteration) against the full mesh; best of repeats, the tensors cache
   warm; the cold first call (which builds the cached torch tensors) is shown apart.
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_name] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from visemeflow.rig import evaluate_rig, load_demo_rig  # noqa: E402
from visemeflow.rig.model import VisemeRig  # noqa: E402
from visemeflow.render.raster import (  # noqa: E402
    MeshTexture,
    Camera,
    frontal_pose,
    rasterize_fragments,
    render_backdrop,
    render_mesh,
    shade_vertices,
    to_camera,
)


def best_of(fn, repeats: int) -> float:
    """Smallest wall time of `repeats` calls, seconds."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def per_frame(fn, meshes: np.ndarray) -> float:
    """Mean seconds per frame of fn(mesh) over all meshes (one warm-up call first)."""
    fn(meshes[0])
    start = time.perf_counter()
    for mesh in meshes:
        fn(mesh)
    return (time.perf_counter() - start) / len(meshes)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100, help="frames rendered per fast-path row")
    parser.add_argument("--reference-frames", type=int, default=3)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    rig: VisemeRig = load_demo_rig()
    rng = np.random.default_rng(0)
    weights = (rng.uniform(0, 1, (args.frames, 16)) * (rng.uniform(0, 1, (args.frames, 16)) < 0.2)).astype(np.float32)
    meshes = evaluate_rig(rig, weights).numpy()
    print(f"rig {rig.name}: {rig.n_vertices} vertices, {len(rig.faces)} triangles; torch threads {torch.get_num_threads()}")

    rows: list[tuple[str, str, str, str]] = []

    def add(metric: str, value: str, target: str = "", met: bool | None = None) -> None:
        rows.append((metric, value, target, "" if met is None else ("yes" if met else "NO")))

    views = {}
    for label, (width, height, fill) in {
        "360x288": (360, 288, 0.45),
        "640x480": (640, 480, 0.45),
        "360x288 close-up": (360, 288, 0.9),
    }.items():
        camera = Camera.default(width, height)
        views[label] = (camera, frontal_pose(rig.neutral[rig.landmark_ids], camera, fill=fill))

    camera, pose = views["360x288"]
    fast = per_frame(lambda m: render_mesh(m, rig.faces, rig.vertex_colors, camera, pose), meshes)
    reference = per_frame(
        lambda m: render_mesh(m, rig.faces, rig.vertex_colors, camera, pose, reference=True),
        meshes[: args.reference_frames],
    )
    raster = per_frame(lambda m: rasterize_fragments(m, rig.faces, camera, pose), meshes)
    shade = per_frame(lambda m: shade_vertices(to_camera(m, pose), rig.faces, rig.vertex_colors), meshes)
    covered = rasterize_fragments(meshes[0], rig.faces, camera, pose).pixel.size
    add("render 360x288, fast path (frames/s)", f"{1 / fast:.1f}", ">= 30", 1 / fast >= 30)
    add("render 360x288, per-triangle reference (frames/s)", f"{1 / reference:.2f}")
    add("  fast / reference speed-up", f"{reference / fast:.0f}x")
    add("  of which rasterisation (ms/frame)", f"{raster * 1e3:.1f}")
    add("  of which vertex normals + shading (ms/frame)", f"{shade * 1e3:.1f}")
    add("  face pixels covered", f"{covered} ({covered / (camera.width * camera.height):.0%})")
    # a textured mesh (`MeshTexture`, what previews of a glTF avatar draw): UVs projected from the front, a 1024-px
    # image (the preview's largest), against the same frames in vertex colours
    lo, hi = rig.neutral[:, :2].min(axis=0), rig.neutral[:, :2].max(axis=0)
    uv = ((rig.neutral[:, :2] - lo) / (hi - lo)).astype(np.float32)
    uv[:, 1] = 1 - uv[:, 1]
    image = rng.integers(0, 256, (1024, 1024, 3), dtype=np.uint8)
    texture = MeshTexture(uv=uv, face_image=np.zeros(len(rig.faces), np.int64),
                          face_color=np.ones((len(rig.faces), 3)), images=(image,))
    textured = per_frame(lambda m: render_mesh(m, rig.faces, rig.vertex_colors, camera, pose, texture=texture),
                         meshes)
    add("render 360x288, textured 1024-px image (frames/s)", f"{1 / textured:.1f}")
    add("  textured / vertex colours, time", f"{textured / fast:.2f}x")
    # a scene's static meshes (a body, hair: here a 20,000-triangle sheet through the back of the head) drawn once as a
    # backdrop (`render_backdrop`, what previews of a glTF avatar do) against drawing them with the head every frame
    lo3, hi3 = rig.neutral.min(axis=0), rig.neutral.max(axis=0)
    xs, ys = np.meshgrid(np.linspace(lo3[0] - 5, hi3[0] + 5, 101), np.linspace(lo3[1] - 8, hi3[1] + 3, 101))
    sheet = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, lo3[2] + 0.3 * (hi3[2] - lo3[2]))], 1)
    cells = np.arange(100 * 100).reshape(100, 100)
    corner = (cells // 100) * 101 + cells % 100
    quads = np.stack([corner, corner + 1, corner + 102, corner + 101], -1).reshape(-1, 4)
    sheet_faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    both_faces = np.concatenate([rig.faces, sheet_faces + len(rig.neutral)])
    both_colors = np.concatenate([rig.vertex_colors, np.full((len(sheet), 3), 0.4)])
    one_mesh = per_frame(lambda m: render_mesh(np.concatenate([m, sheet]), both_faces, both_colors, camera, pose),
                         meshes)
    backdrop = render_backdrop(sheet, sheet_faces, both_colors[len(rig.neutral):], camera, pose)
    layered = per_frame(lambda m: render_mesh(m, rig.faces, rig.vertex_colors, camera, pose, backdrop=backdrop),
                        meshes)
    same = all(np.array_equal(render_mesh(np.concatenate([m, sheet]), both_faces, both_colors, camera, pose),
                              render_mesh(m, rig.faces, rig.vertex_colors, camera, pose, backdrop=backdrop))
               for m in meshes[:5])
    add("render 360x288, head + 20,000-triangle static sheet as one mesh (frames/s)", f"{1 / one_mesh:.1f}")
    add("render 360x288, head over the sheet's backdrop (frames/s)", f"{1 / layered:.1f}")
    add("  one mesh / backdrop, time", f"{one_mesh / layered:.2f}x; images {'identical' if same else 'DIFFER'}")
    for label in ("640x480", "360x288 close-up"):
        cam, view = views[label]
        seconds = per_frame(lambda m: render_mesh(m, rig.faces, rig.vertex_colors, cam, view), meshes[:30])
        add(f"render {label}, fast path (frames/s)", f"{1 / seconds:.1f}")

    frames = rng.uniform(0, 1, (1000, 16)).astype(np.float32)
    tensor = torch.from_numpy(frames)
    fresh = VisemeRig(rig.name, rig.neutral, rig.deltas, rig.faces, rig.landmark_ids)
    start = time.perf_counter()
    evaluate_rig(fresh, tensor, fresh.landmark_ids)
    cold = time.perf_counter() - start
    landmarks = best_of(lambda: evaluate_rig(rig, tensor, rig.landmark_ids), 20)
    full = best_of(lambda: evaluate_rig(rig, tensor), 3)
    add("rig eval, 68 landmarks x 1,000 frames (ms)", f"{landmarks * 1e3:.3f}", "< 10", landmarks < 0.010)
    add("rig eval, full mesh x 1,000 frames (ms)", f"{full * 1e3:.1f}")
    add("  full / landmarks", f"{full / landmarks:.0f}x")
    add("rig eval, landmarks, first call incl. tensor cache (ms)", f"{cold * 1e3:.1f}")

    width = max(len(r[0]) for r in rows)
    print(f"{'metric':<{width}}  {'value':>16}  {'target':>7}  met?")
    for metric, value, target, met in rows:
        print(f"{metric:<{width}}  {value:>16}  {target:>7}  {met}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
