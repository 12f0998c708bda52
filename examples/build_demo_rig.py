"""Rebuild the shipped demo rig `visemeflow/rig/data/ict_visemes.npz` (package data; and `docs/rig_contact_sheet.png`)
from the ICT Face Model.

Run from the repository root:  .venv/bin/python examples/build_demo_rig.py [--ict DIR] [--out NPZ] [--sheet PNG | --no-sheet]

Input: `../shared/data/ict_facekit` (ICT-FaceKit, MIT): the neutral head mesh and the ARKit-style mouth/jaw/cheek/nose
shapes as gzipped OBJ, plus `vertex_indices.json`. The 16 visemes are weighted sums of shape deltas given by
`visemeflow/rig/data/ict_recipes.csv` (reasoning per row in docs/rig.md). The mesh is cropped to the parts a
frontal face camera sees (face, mouth socket, gums + tongue, teeth, eyeballs; ranges from the ICT-FaceKit README),
given vertex colours, and stored with float16 deltas.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from visemeflow.rig import (  # noqa: E402
    VisemeRig,
    combine_shapes,
    evaluate_rig,
    load_ict_recipes,
    load_rig_npz,
    read_obj,
    recipe_shapes,
    save_rig_npz,
    validate_rig,
)
from visemeflow.visemes import VISEMES  # noqa: E402

DEFAULT_ICT = REPO.parent / "shared" / "data" / "ict_facekit"
DEFAULT_OUT = REPO / "visemeflow" / "rig" / "data" / "ict_visemes.npz"  # package data, shipped in the wheel
DEFAULT_SHEET = REPO / "docs" / "rig_contact_sheet.png"

# Vertex ranges of the ICT Face Model (ICT-FaceKit README, end exclusive), in the order they are kept.
PARTS = {
    "face": (0, 9409),
    "mouth_socket": (11248, 13294),
    "gums_tongue": (14062, 17039),
    "teeth": (17039, 21451),
    "eye_left": (21451, 23021),  # outer ball (sclera + cornea) 21451..22220, inner ball (iris) 22221..23020
    "eye_right": (23021, 24591),
}

SKIN = np.array([0.86, 0.66, 0.55])
LIPS = np.array([0.70, 0.38, 0.37])
BROWS = np.array([0.36, 0.25, 0.18])
SOCKET = np.array([0.12, 0.035, 0.035])
GUMS_TONGUE = np.array([0.42, 0.16, 0.16])
TEETH = np.array([0.93, 0.91, 0.83])
SCLERA = np.array([0.90, 0.88, 0.85])
IRIS_COLOUR = np.array([0.30, 0.22, 0.14])
PUPIL = np.array([0.04, 0.03, 0.03])


def read_ict(ict: Path, shapes: list[str]) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray], np.ndarray]:
    """Neutral vertices, triangles, the named shapes' deltas (full mesh) and the 68 landmark vertex ids."""
    neutral = read_obj(ict / "generic_neutral_mesh.obj.gz")
    deltas = {}
    for shape in shapes:
        mesh = read_obj(ict / "shapes_mouth_jaw_cheek_nose" / f"{shape}.obj.gz")
        if mesh.vertices.shape != neutral.vertices.shape:
            raise SystemExit(f"{shape}: {len(mesh.vertices)} vertices, neutral has {len(neutral.vertices)}")
        deltas[shape] = mesh.vertices - neutral.vertices
    landmarks = np.array(json.loads((ict / "vertex_indices.json").read_text())["idx_to_landmark_verts"], np.int64)
    return neutral.vertices, neutral.faces, deltas, landmarks


def _smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _inside_distance(points_xy: np.ndarray, polygon_xy: np.ndarray) -> np.ndarray:
    """Signed distance of 2-D points to a closed polygon (positive inside), in the points' units."""
    import cv2

    scale = 1000.0  # cv2.pointPolygonTest works in float32 pixels; scale centimetres up for precision
    contour = (polygon_xy * scale).astype(np.float32).reshape(-1, 1, 2)
    return np.array([cv2.pointPolygonTest(contour, (float(x), float(y)), True) for x, y in points_xy * scale]) / scale


def _polyline_distance(points_xy: np.ndarray, polyline_xy: np.ndarray) -> np.ndarray:
    """Distance of 2-D points to an open polyline."""
    best = np.full(len(points_xy), np.inf)
    for a, b in zip(polyline_xy[:-1], polyline_xy[1:]):
        ab = b - a
        t = np.clip(((points_xy - a) @ ab) / (ab @ ab), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(points_xy - (a + t[:, None] * ab), axis=1))
    return best


def colour_vertices(vertices: np.ndarray, parts: dict[str, np.ndarray], landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) RGB in [0, 1] for the cropped mesh and the face-vertex ids counted as lips."""
    colors = np.tile(SKIN, (len(vertices), 1))
    face = parts["face"]
    xy = vertices[face, :2]
    lm = vertices[landmarks]

    lip_depth = _inside_distance(xy, lm[48:60, :2])
    lip_weight = _smoothstep(-0.12, 0.10, lip_depth)
    colors[face] = colors[face] * (1 - lip_weight[:, None]) + LIPS * lip_weight[:, None]
    # face vertices rolling back into the mouth behind the lips darken toward the socket colour
    front = lm[48:68, 2].min()
    inner = _smoothstep(0.3, 1.6, front - vertices[face, 2]) * (lip_depth > 0)
    colors[face] = colors[face] * (1 - inner[:, None]) + SOCKET * inner[:, None]

    brow_distance = np.minimum(_polyline_distance(xy, lm[17:22, :2]), _polyline_distance(xy, lm[22:27, :2]))
    above_eyes = vertices[face, 1] > lm[36:48, 1].max()
    brow_weight = (1 - _smoothstep(0.25, 0.5, brow_distance)) * above_eyes * 0.85
    colors[face] = colors[face] * (1 - brow_weight[:, None]) + BROWS * brow_weight[:, None]

    # fake ambient occlusion in the mouth: the deeper, the darker
    interior = np.concatenate([parts["mouth_socket"], parts["gums_tongue"], parts["teeth"]])
    depth = vertices[interior, 2]
    occlusion = 0.2 + 0.8 * _smoothstep(depth.min(), depth.max(), depth)
    colors[parts["mouth_socket"]] = SOCKET
    colors[parts["gums_tongue"]] = GUMS_TONGUE
    colors[parts["teeth"]] = TEETH
    colors[interior] *= occlusion[:, None]

    # both eye parts are closed balls (the outer one with the corneal bulge); paint iris and pupil on by the angle
    # from the gaze axis, ball centre -> corneal apex (anatomical sizes: iris about 30 degrees, pupil 11)
    for eye in ("eye_left", "eye_right"):
        ids = parts[eye]
        centre = (vertices[ids].min(axis=0) + vertices[ids].max(axis=0)) / 2.0
        gaze = vertices[ids[np.argmax(vertices[ids, 2])]] - centre
        gaze /= np.linalg.norm(gaze)
        radial = vertices[ids] - centre
        angle = np.degrees(np.arccos(np.clip((radial @ gaze) / np.linalg.norm(radial, axis=1), -1.0, 1.0)))
        iris = 1 - _smoothstep(26.0, 31.0, angle)
        pupil = 1 - _smoothstep(9.0, 12.0, angle)
        rgb = SCLERA * (1 - iris[:, None]) + IRIS_COLOUR * iris[:, None]
        colors[ids] = rgb * (1 - pupil[:, None]) + PUPIL * pupil[:, None]
    lips = face[lip_weight > 0.5]
    return np.clip(colors, 0.0, 1.0).astype(np.float32), lips


def build_rig(ict: Path) -> VisemeRig:
    recipes = load_ict_recipes()
    vertices, faces, shape_deltas, landmarks = read_ict(ict, recipe_shapes(recipes))
    kept = np.concatenate([np.arange(start, end) for start, end in PARTS.values()])
    new_id = np.full(len(vertices), -1, np.int64)
    new_id[kept] = np.arange(len(kept))
    faces = new_id[faces]
    faces = faces[(faces >= 0).all(axis=1)].astype(np.int32)
    if (new_id[landmarks] < 0).any():
        raise SystemExit("a landmark vertex lies outside the kept parts")
    landmark_ids = new_id[landmarks]

    parts = {name: new_id[np.arange(start, end)] for name, (start, end) in PARTS.items()}
    neutral = vertices[kept]
    colors, lips = colour_vertices(neutral, parts, landmark_ids)
    deltas = combine_shapes({name: d[kept] for name, d in shape_deltas.items()}, recipes)
    regions = {
        "face": parts["face"],
        "lips": lips,
        "mouth_interior": np.concatenate([parts["mouth_socket"], parts["gums_tongue"], parts["teeth"]]),
        "teeth": parts["teeth"],
        "eyes": np.concatenate([parts["eye_left"], parts["eye_right"]]),
    }
    rig = VisemeRig(
        name="ict_visemes",
        neutral=neutral.astype(np.float32),
        deltas=deltas,
        faces=faces,
        landmark_ids=landmark_ids,
        vertex_colors=colors,
        regions={k: v.astype(np.int64) for k, v in regions.items()},
    )
    validate_rig(rig)
    return rig


def contact_sheet(rig: VisemeRig, path: Path, tile: tuple[int, int] = (256, 192)) -> Path:
    """A 4x4 grid of the 16 visemes at weight 1, framed on the lower face, labelled; written as PNG."""
    import cv2

    from visemeflow.render.raster import Camera, frontal_pose, render_mesh

    camera = Camera.default(*tile, fov_deg=20.0)
    lower_face = rig.neutral[rig.landmark_ids[np.r_[2:15, 29:68]]]
    pose = frontal_pose(lower_face, camera, fill=0.95)
    meshes = evaluate_rig(rig, np.eye(len(VISEMES), dtype=np.float32)).numpy()
    tiles = []
    for name, mesh in zip(VISEMES, meshes):
        image = cv2.cvtColor(render_mesh(mesh, rig.faces, rig.vertex_colors, camera, pose), cv2.COLOR_RGB2BGR)
        for colour, thickness in (((0, 0, 0), 4), ((255, 255, 255), 2)):
            cv2.putText(image, name, (8, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.8, colour, thickness, cv2.LINE_AA)
        tiles.append(image)
    rows = [np.concatenate(tiles[r * 4 : r * 4 + 4], axis=1) for r in range(4)]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(rows, axis=0), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ict", type=Path, default=DEFAULT_ICT, help="ICT-FaceKit copy (default ../shared/data/ict_facekit)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="rig npz to write")
    parser.add_argument("--sheet", type=Path, default=DEFAULT_SHEET, help="contact sheet PNG to write")
    parser.add_argument("--no-sheet", action="store_true", help="do not draw the contact sheet")
    args = parser.parse_args(argv)
    rig = build_rig(args.ict)
    save_rig_npz(rig, args.out)
    shutil.copyfile(args.ict / "LICENSE", args.out.parent / "LICENSE")
    print(f"{args.out}: {rig.n_vertices} vertices, {len(rig.faces)} triangles, {args.out.stat().st_size / 1e6:.2f} MB")
    if not args.no_sheet:
        print(contact_sheet(load_rig_npz(args.out), args.sheet))  # the shipped, float16 rig
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
