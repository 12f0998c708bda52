"""Benchmark: MediaPipe FaceMesh landmark detection (visemeflow.tracking.facemesh) on one core, and agreement
with MediaPipe's reference landmark files.

Run:  .venv/bin/python bench/landmarks.py [--repeats R] [--no-pin] [--clips N] [--frame docs/landmarks_frame.png]

Prints tables and never asserts; the exit status is 0 whatever the figures are. The process is pinned to one CPU
(os.sched_setaffinity, so MediaPipe's and FFmpeg's own threads share it too) and OMP/MKL/OpenBLAS to one thread.

Clips: ../shared/data/grid_s1/video/*.mpg (10 clips, 360x288, 25 fps, 75 frames each) and
../shared/data/talking_heads/{1,4}.mp4 (700x700; 1.mp4 variable frame rate, 135 frames; 4.mp4 30 fps, 199 frames),
with the reference files <clip>.mediapipe478.csv (MediaPipe FaceMesh 0.10.21, refine_landmarks=True,
max_num_faces=1, video mode from frame 0; the same model and wheel as ours).

Table 1, detection frames/s. Each clip is decoded once beforehand (`read_timed_frames`), then `detect_frames`
runs over its frames with each configuration; best of R runs (default 2) per clip, summed over the set:
  one face + probe   the default FaceMeshConfig(): max_num_faces=1 and a face-detector probe every 10 frames
                     (a second face would rerun the clip with max_faces=4).
  multi-face         FaceMeshConfig(probe_every=0): max_num_faces=4 from the first frame; FaceMesh then runs its
                     face detector on every frame (it follows fewer faces than it may).
each with refine_landmarks on (478 points, the iris model) and off (468). Columns: frames/s over whole clips
(graph start included: one FaceMesh graph per clip) by wall clock and by the process's CPU time (all its threads,
on the one core it is pinned to: on a machine shared with other jobs the wall clock also counts their turns on
that core, the CPU time does not), and by CPU time without the graph start (the mean CPU cost of starting and
closing the graphs a clip needs, measured separately, subtracted). Then end to end: `detect_video` on the files
(frames and their presentation times from one decoding pass, detection, graph start), default config, best of R.
The whole path video -> tracked curves (decoding, detection, identity fit, optical flow, solver) is timed by
bench/end_to_end.py.

Table 2, agreement with the reference files (default config, refine on; refine off for its 468 points): pixel
distance per (frame, point) pooled over the set's frames, median and 95th percentile, on the 40 lip vertices
(`LIP_IDS`, MediaPipe's FACEMESH_LIPS) and on all points; the share of frames detected by both.

--frame PATH also saves a frame with our 478 points drawn (the 40 lip vertices in red) as a palette PNG
(docs/landmarks_frame.png in the README): the ICT demo rig rendered by our synthetic-take renderer, not GRID or
talking_heads footage (GRID has no clear license, talking_heads is third-party footage that stays in ../shared).
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

from cpu import pin_one_core  # noqa: E402  (bench/, this script's folder)

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from visemeflow.tracking.facemesh import (  # noqa: E402
    LIP_IDS,
    N_MESH_UNREFINED,
    FaceMeshConfig,
    detect_frames,
    detect_video,
    draw_landmarks,
    read_mediapipe478,
)
from visemeflow.tracking.video import read_timed_frames  # noqa: E402

DATA = REPO.parent / "shared" / "data"
SETS = {
    "GRID 360x288": sorted((DATA / "grid_s1" / "video").glob("*.mpg")),
    "talking_heads 700x700": [DATA / "talking_heads" / "1.mp4", DATA / "talking_heads" / "4.mp4"],
}
CONFIGS = {
    "one face + probe, refine on": FaceMeshConfig(),
    "one face + probe, refine off": FaceMeshConfig(refine_landmarks=False),
    "multi-face, refine on": FaceMeshConfig(probe_every=0),
    "multi-face, refine off": FaceMeshConfig(refine_landmarks=False, probe_every=0),
}


def reference_of(video: Path) -> Path:
    if video.parent.name == "video":
        return video.parent.parent / "landmarks" / f"{video.stem}.mediapipe478.csv"
    return video.with_name(f"{video.stem}.mediapipe478.csv")


def graph_start_s(config: FaceMeshConfig, repeats: int = 3) -> float:
    """Mean CPU seconds to start and close the MediaPipe graphs one clip needs with `config`."""
    from mediapipe.python.solutions import face_detection, face_mesh

    times = []
    for _ in range(repeats):
        t = time.process_time()
        mesh = face_mesh.FaceMesh(static_image_mode=False, refine_landmarks=config.refine_landmarks,
                                  max_num_faces=1 if config.probe_every else config.max_faces)
        probe = face_detection.FaceDetection(model_selection=0) if config.probe_every else None
        mesh.close()
        if probe is not None:
            probe.close()
        times.append(time.process_time() - t)
    return float(np.mean(times))


def pooled(errors: list[np.ndarray]) -> tuple[float, float]:
    e = np.concatenate([x.ravel() for x in errors])
    e = e[np.isfinite(e)]
    return float(np.median(e)), float(np.percentile(e, 95))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--no-pin", action="store_true")
    parser.add_argument("--frame", type=Path, default=None, help="save a GRID frame with our landmarks drawn")
    parser.add_argument("--clips", type=int, default=None, help="only the first N clips of each set (a smoke run)")
    args = parser.parse_args()
    if args.clips is not None:
        for name in SETS:
            SETS[name] = SETS[name][:max(1, args.clips)]
    missing = [p for clips in SETS.values() for p in clips if not p.is_file() or not reference_of(p).is_file()]
    if missing or not SETS["GRID 360x288"]:
        sys.exit(f"missing benchmark data: {missing or DATA / 'grid_s1'}")
    print("landmarks bench:", "not pinned" if args.no_pin else pin_one_core())

    decoded = {name: [(p, *read_timed_frames(p)) for p in clips] for name, clips in SETS.items()}
    references = {p: read_mediapipe478(reference_of(p)) for clips in SETS.values() for p in clips}
    detect_frames(decoded["GRID 360x288"][0][1][:5], fps=25)   # warm-up: MediaPipe's first-use costs

    print("\nTable 1: detection frames/s on one core (frames decoded beforehand; best of "
          f"{args.repeats} runs per clip)")
    header = (f"{'set':<22} {'configuration':<30} {'frames':>6} {'fps wall':>9} {'fps CPU':>8} "
              f"{'CPU excl. start':>16} {'CPU ms/frame':>13}")
    print(header)
    print("-" * len(header))
    results: dict[tuple[str, str], list] = {}
    for name, clips in decoded.items():
        for label, config in CONFIGS.items():
            start = graph_start_s(config)
            wall, cpu, frames, tracks = 0.0, 0.0, 0, []
            for path, images, times in clips:
                best_wall = best_cpu = np.inf
                for _ in range(args.repeats):
                    t, c = time.perf_counter(), time.process_time()
                    track = detect_frames(images, times, name=path.name, config=config)
                    best_wall = min(best_wall, time.perf_counter() - t)
                    best_cpu = min(best_cpu, time.process_time() - c)
                wall += best_wall
                cpu += best_cpu
                frames += len(images)
                tracks.append((path, track))
            results[(name, label)] = tracks
            steady = max(cpu - start * len(clips), 1e-9)
            print(f"{name:<22} {label:<30} {frames:>6} {frames / wall:>9.1f} {frames / cpu:>8.1f} "
                  f"{frames / steady:>16.1f} {1000 * cpu / frames:>13.2f}")
    print("\nend to end, detect_video (decode with presentation times in one pass + detection), default config:")
    for name, clips in SETS.items():
        wall, cpu, frames = 0.0, 0.0, 0
        for p in clips:
            best_wall = best_cpu = np.inf
            for _ in range(args.repeats):
                t, c = time.perf_counter(), time.process_time()
                n = detect_video(p).n_frames
                best_wall = min(best_wall, time.perf_counter() - t)
                best_cpu = min(best_cpu, time.process_time() - c)
            wall += best_wall
            cpu += best_cpu
            frames += n
        print(f"  {name:<22} {frames} frames: {frames / wall:.1f} frames/s wall, {frames / cpu:.1f} frames/s of CPU "
              f"time ({1000 * cpu / frames:.2f} ms/frame)")

    print("\nTable 2: agreement with MediaPipe's reference files (pixels; pooled over frames and points)")
    header = (f"{'set':<22} {'configuration':<30} {'lips median':>11} {'lips p95':>9} {'all median':>10} "
              f"{'all p95':>8} {'all max':>8} {'detected':>9}")
    print(header)
    print("-" * len(header))
    for name in SETS:
        for label in ("one face + probe, refine on", "one face + probe, refine off"):
            lips, every, both, n = [], [], 0, 0
            n_points = N_MESH_UNREFINED if "off" in label else 478
            for path, track in results[(name, label)]:
                ref = references[path]
                err = np.linalg.norm(track.points[:, :n_points] - ref.points[:, :n_points], axis=-1)
                lips.append(err[:, list(LIP_IDS)])
                every.append(err)
                both += int((track.detected & ref.detected).sum())
                n += track.n_frames
            lm, lp = pooled(lips)
            am, ap = pooled(every)
            mx = max(float(np.nanmax(e)) for e in every)
            print(f"{name:<22} {label:<30} {lm:>11.4f} {lp:>9.4f} {am:>10.4f} {ap:>8.4f} {mx:>8.4f} "
                  f"{both:>4}/{n:<4}")

    if args.frame is not None:
        save_frame(args.frame)


def save_frame(out: Path) -> None:
    """A rendered frame of the ICT demo rig (our synthetic renderer, `synth.take`: no third-party footage in the
    repository) with the points FaceMesh finds on it: the frame of a short take with the widest inner-lip gap
    (vertices 13/14), cropped around the face."""
    from PIL import Image

    from visemeflow.phonetics.types import VisemeSegment
    from visemeflow.rig import demo_rig_path, load_rig
    from visemeflow.synth.take import SynthConfig, make_take, render_take

    rig = load_rig(demo_rig_path())
    segments = [VisemeSegment("MBP", 0.0, 0.2), VisemeSegment("AAA", 0.2, 0.5), VisemeSegment("OHH", 0.5, 0.8)]
    take = make_take(rig, segments, 20, "demo", "demo/landmarks", SynthConfig(width=560, height=560, fill=0.9))
    images = np.stack(list(render_take(rig, take)))
    track = detect_frames(images, fps=25, name="ICT demo take")
    frame = int(np.nanargmax(track.points[:, 14, 1] - track.points[:, 13, 1]))
    pts = track.points[frame]
    scale = 1
    h, w = images.shape[1:3]
    big = np.asarray(Image.fromarray(images[frame]).resize((w * scale, h * scale), Image.Resampling.LANCZOS))
    drawn = draw_landmarks(big, pts * scale, color=(60, 255, 60), highlight=LIP_IDS, radius=2, highlight_radius=3)
    x0, y0 = np.nanmin(pts, axis=0) * scale
    x1, y1 = np.nanmax(pts, axis=0) * scale
    pad = 24 * scale
    x0, y0 = max(0, int(x0) - pad), max(0, int(y0) - pad)
    x1, y1 = min(drawn.shape[1], int(x1) + pad), min(drawn.shape[0], int(y1) + pad)
    crop = Image.fromarray(drawn[y0:y1, x0:x1])
    out.parent.mkdir(parents=True, exist_ok=True)
    crop.quantize(colors=128, method=Image.Quantize.MEDIANCUT).save(out, optimize=True)
    print(f"\nsaved {out} ({crop.width}x{crop.height}, {out.stat().st_size / 1024:.0f} KB): the ICT demo rig rendered "
          f"at {w}x{h}, frame {frame} of a 20-frame take (face on {int(track.detected.sum())} of 20), our 478 points "
          f"(the 40 lip vertices red)")


if __name__ == "__main__":
    main()
