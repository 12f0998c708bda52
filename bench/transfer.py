"""Benchmark: deformation transfer of the demo rig's 16 visemes (visemeflow/authoring/transfer.py) onto new faces.

Run:  .venv/bin/python bench/transfer.py [--sheet docs/transfer_contact_sheet.png] [--size 180] [--targets self,auto]

Prints, never asserts (exit 0 whatever the figures). Targets, all built from the shipped demo rig
(`load_demo_rig()`, 21,984 vertices, 43,393 triangles, centimetres) and its identity modes (ict_identities.npz):

1. self: the template onto its own neutral (same topology): largest vertex error against the template's shapes.
2. identity: an ICT identity (modes 0..4 at +1, -1, +1, -0.5, +0.5 sigma), same topology.
3. remeshed: another identity (modes 0..2 at +0.8, +0.6, -0.7 sigma) cut to the ICT narrow face (vertices
   0..6705), Loop-subdivided once by trimesh (`remesh.subdivide_loop`: every vertex moves, 4 triangles for each, so
   no triangle is the template's), turned 20 degrees about y, scaled 1.15 and moved; its 68 landmarks are the
   nearest vertices (the markers). The target of tests/test_transfer.py too: one builder, `remeshed_face` in
   tests/factories.py.
4. remeshed, automatic markers: the same target with no markers given; FaceMesh on renders of both meshes finds
   the pairs (`visemeflow.authoring.automarkers`): how many, how far their target points lie from the true
   correspondence (the same ICT vertex moved with the face), and the transfer with them.
5. icp: the registration of target 3 (our `visemeflow.authoring.nricp`, the inputs the transfer gives it) side by
   side with trimesh's `nricp_amberg`, the peer it replaced, on the same inputs: time, the registered surface's RMS
   distance to the target and the markers' (both relative to the target's size), and how far apart the two are.

For each: time per stage (registration, factorisation, solve, total), the gradient residual, and the landmark
checks of the demo rig (tests/test_rig.py): inner-lip gap 62-66 of MBP (and of the neutral), AHH's gap and chin drop
(and whether they are the largest), mouth width 48-54 of UUU (narrowest?) and IEE (widest?). Times are one run on a
shared 2-core machine: noisy.

With --sheet, the 16 transferred visemes on the remeshed face are drawn with the project's renderer
(`synth.render.render_mesh`, the preview's camera `animation.preview.preview_camera`, framing "mouth") into a
4 x 4 contact sheet (PNG), the face turned back to frontal for the picture.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

# the remeshed target is built by the tests' builder, so that the figures printed here are of the face they check
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from factories import REMESHED_IDENTITY, ROTATION, identity_face, placed, remeshed_face  # noqa: E402

from visemeflow.rig.character import make_character  # noqa: E402
from visemeflow.animation.preview import preview_camera  # noqa: E402
from visemeflow.authoring.automarkers import automatic_markers  # noqa: E402
from visemeflow.authoring.transfer import transfer_visemes  # noqa: E402
from visemeflow.rig import load_demo_rig, rig_data_path  # noqa: E402
from visemeflow.render.raster import render_mesh  # noqa: E402
from visemeflow.visemes import VISEMES  # noqa: E402


def landmark_figures(character, landmark_ids, rotation=np.eye(3)) -> str:
    lm = np.concatenate([character.neutral[None], character.neutral[None] + character.deltas])[:, landmark_ids]
    lm = lm @ rotation
    gap = np.linalg.norm(lm[:, 62] - lm[:, 66], axis=1)
    width = np.linalg.norm(lm[:, 48] - lm[:, 54], axis=1)
    chin = lm[:, 8, 1]
    i = {v: 1 + VISEMES.index(v) for v in ("MBP", "AHH", "UUU", "IEE")}
    return (f"neutral gap {gap[0]:.3f} width {width[0]:.2f} | MBP gap {gap[i['MBP']]:.3f} "
            f"(smallest: {gap[1:].argmin() + 1 == i['MBP']}) | AHH gap {gap[i['AHH']]:.2f}, chin drop "
            f"{chin[0] - chin[i['AHH']]:.2f} (largest: {gap[1:].argmax() + 1 == i['AHH']}, "
            f"{chin[1:].argmin() + 1 == i['AHH']}) | UUU width {width[i['UUU']]:.2f} "
            f"(narrowest: {width[1:].argmin() + 1 == i['UUU']}) | IEE width {width[i['IEE']]:.2f} "
            f"(widest: {width[1:].argmax() + 1 == i['IEE']})")


def contact_sheet(character, path: Path, size: int) -> int:
    camera, pose = preview_camera(character, size, "mouth")
    panels = []
    for k, name in enumerate(character.shape_names):
        image = render_mesh(character.neutral + character.deltas[k], character.faces, character.vertex_colors,
                            camera, pose)
        image = np.ascontiguousarray(image[:, :, ::-1])
        cv2.putText(image, name, (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
        panels.append(image)
    rows = [np.concatenate(panels[r * 4:(r + 1) * 4], axis=1) for r in range(4)]
    sheet = np.concatenate(rows, axis=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), sheet, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return path.stat().st_size


TARGETS = ("self", "identity", "remeshed", "auto", "icp")
"""Targets 1-5 of the module's text, by the names `--targets` takes."""


def icp_side_by_side(demo, vertices, faces, landmarks) -> None:
    """Target 5: ours and trimesh's non-rigid ICP on the inputs the transfer of target 3 gives ours."""
    import trimesh
    from trimesh.registration import nricp_amberg

    from visemeflow.authoring import transfer as transfer_module
    from visemeflow.authoring.transfer import _closest

    calls = []
    ours = transfer_module.nricp

    def recorded(*args, **kwargs):
        start = time.perf_counter()
        out = ours(*args, **kwargs)
        calls.append((args, kwargs, out, time.perf_counter() - start))
        return out

    transfer_module.nricp = recorded
    try:
        transfer_visemes(demo, vertices, faces, target_landmarks=landmarks, name="remeshed")
    finally:
        transfer_module.nricp = ours
    (src_v, src_f, tgt_v, tgt_f), kw, got, ours_s = calls[0]
    start = time.perf_counter()
    peer = nricp_amberg(trimesh.Trimesh(src_v, src_f, process=False), trimesh.Trimesh(tgt_v, tgt_f, process=False),
                        source_landmarks=kw["landmarks"], target_positions=kw["landmark_positions"],
                        steps=kw["steps"], distance_threshold=kw["distance_threshold"], use_faces=False)
    peer_s = time.perf_counter() - start
    size = float(np.linalg.norm(np.ptp(tgt_v, axis=0)))

    def figures(x):
        surface = np.sqrt(np.mean(_closest(tgt_v, tgt_f, x)[1] ** 2)) / size
        marks = np.sqrt(np.mean(np.sum((x[kw["landmarks"]] - kw["landmark_positions"]) ** 2, axis=1))) / size
        return f"surface {surface:.5f}, markers {marks:.5f}"

    apart = np.sqrt(np.mean(np.sum((got - peer) ** 2, axis=1))) / size
    print(f"\n5. icp: the registration of target 3 ({len(src_v)} template vertices onto {len(tgt_v)}, "
          f"{sum(int(s[3]) for s in kw['steps'])} iterations at most), RMS relative to the target's size")
    print(f"   ours    {ours_s:6.2f} s  {figures(got)}")
    print(f"   trimesh {peer_s:6.2f} s  {figures(peer)}")
    print(f"   trimesh / ours: {peer_s / ours_s:.1f}x the time; the two registrations {apart:.5f} apart (RMS)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sheet", type=Path, default=None, help="write the contact sheet PNG here")
    parser.add_argument("--size", type=int, default=180, help="panel size in pixels")
    parser.add_argument("--targets", default=",".join(TARGETS),
                        help="which of the targets 1-5 to run, by name (a smoke run: self,auto)")
    args = parser.parse_args()
    targets = {t.strip() for t in args.targets.split(",") if t.strip()}
    if targets - set(TARGETS):
        parser.error(f"unknown targets: {', '.join(sorted(targets - set(TARGETS)))}; choose from {', '.join(TARGETS)}")
    if args.sheet is not None:   # the sheet draws target 3's visemes
        targets.add("remeshed")
    demo = load_demo_rig()
    modes = np.load(rig_data_path("ict_identities.npz"))["modes"].astype(np.float64)
    print(f"template: {demo.name}, {demo.n_vertices} vertices, {len(demo.faces)} triangles, 16 visemes")
    print("template: " + landmark_figures(make_character("t", demo.neutral, demo.faces, VISEMES, demo.deltas),
                                          demo.landmark_ids))

    if "self" in targets:
        start = time.perf_counter()
        result = transfer_visemes(demo, demo.neutral, demo.faces, name="self")
        wall = time.perf_counter() - start
        error = np.abs(result.character.deltas - demo.deltas).max()
        print(f"\n1. self (same topology), {wall:.2f} s wall: largest vertex error {error:.2e} cm "
              f"(the template moves up to {np.abs(demo.deltas).max():.2f} cm)")
        print("   " + "\n   ".join(result.report.lines()))

    if "identity" in targets:
        result = transfer_visemes(demo, identity_face(demo, modes, [1.0, -1.0, 1.0, -0.5, 0.5]), demo.faces,
                                  name="identity")
        print("\n2. identity (same topology)")
        print("   " + "\n   ".join(result.report.lines()))
        print("   landmarks: " + landmark_figures(result.character, result.landmark_ids))

    vertices, faces, landmarks = remeshed_face(demo, modes)
    sheet_result = None
    if "remeshed" in targets:
        result = transfer_visemes(demo, vertices, faces, target_landmarks=landmarks, name="remeshed")
        print(f"\n3. remeshed (different topology): target {len(vertices)} vertices, {len(faces)} triangles")
        print("   " + "\n   ".join(result.report.lines()))
        print("   landmarks: " + landmark_figures(result.character, result.landmark_ids, ROTATION))
        sheet_result = result

    if "auto" in targets:   # the same target without markers: pairs found by FaceMesh on renders of both meshes
        carried = np.union1d(demo.regions["mouth_interior"], demo.regions["eyes"])
        start = time.perf_counter()
        auto = automatic_markers(demo.neutral, demo.faces, vertices, faces, exclude=carried)
        found_s = time.perf_counter() - start
        truth = placed(identity_face(demo, modes, REMESHED_IDENTITY))
        error = np.linalg.norm(vertices[auto.pairs[:, 1]] - truth[auto.pairs[:, 0]], axis=1)
        result = transfer_visemes(demo, vertices, faces, name="remeshed-auto")
        landmark_gap = np.linalg.norm(vertices[result.landmark_ids] - vertices[landmarks], axis=1)
        print(f"\n4. remeshed, automatic markers ({found_s:.1f} s to find them): {len(auto.pairs)} pairs, target "
              f"points {np.median(error):.3f} cm from the true correspondence (median; 90th percentile "
              f"{np.percentile(error, 90):.3f}, largest {error.max():.3f}); the 68 landmarks it places "
              f"{np.median(landmark_gap):.3f} cm from the nearest-point truth (median)")
        print("   " + "\n   ".join(result.report.lines()))
        print("   landmarks: " + landmark_figures(result.character, result.landmark_ids, ROTATION))

    if "icp" in targets:
        icp_side_by_side(demo, vertices, faces, landmarks)

    if args.sheet is not None:
        c = sheet_result.character
        frontal = make_character(c.name, c.neutral @ ROTATION, c.faces, c.shape_names, c.deltas @ ROTATION,
                                 vertex_colors=c.vertex_colors)
        size = contact_sheet(frontal, args.sheet, args.size)
        print(f"\ncontact sheet: {args.sheet} ({size / 1000:.0f} kB)")


if __name__ == "__main__":
    main()
