"""Peak memory of the optical-flow step of tracking on a 4K clip: the faithful path (every frame decoded and held,
flows at full resolution, as `track` did before) against the bounded one (frames decoded one at a time, only the face
crop kept, shrunk to FlowConfig.max_roi_px), side by side, each in a fresh process (its own VmHWM).

    .venv/bin/python bench/memory_tracking.py [--seconds 2] [--side 2160]

The clip: the first seconds of ../shared/data/talking_heads/4.mp4 (third-party footage, read from there, never
copied) scaled from 700 x 700 to side x side, written to a temporary H.264 file; its MediaPipe landmarks are scaled
alike. Printed: peak memory, seconds, and how far the two paths' flow correspondences at the landmarks are apart (median
and 95th percentile, pixels, where both are valid) and how often they agree on validity. Figures, never asserted.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from memory import peak_mb  # bench/memory.py: this script's folder is on sys.path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
CLIP = ROOT.parent / "shared" / "data" / "talking_heads" / "4.mp4"
MARKS = CLIP.with_name("4.mediapipe478.csv")


def child(mode: str, video: str, points_file: str, out: str) -> None:
    from visemeflow.tracking.optical_flow import FlowConfig, estimate_optical_flow, roi_around
    from visemeflow.tracking.video import iter_timed_frames, read_timed_frames

    points = np.load(points_file)                      # (T, N, 2) image pixels
    started = time.perf_counter()
    if mode == "whole":
        frames, _ = read_timed_frames(video)
        h, w = frames.shape[1:3]
        roi = roi_around(points.reshape(-1, 2), w, h, margin=0.15)
        flow = estimate_optical_flow(frames, FlowConfig(max_roi_px=None), roi)
    else:
        it = (f for f, _ in iter_timed_frames(video))
        first = next(it)
        h, w = first.shape[:2]
        roi = roi_around(points.reshape(-1, 2), w, h, margin=0.15)
        flow = estimate_optical_flow((f for g in ([first], it) for f in g), FlowConfig(), roi)
    seconds = time.perf_counter() - started
    q = [flow.correspondences(j, points[j - 1]) for j in range(1, flow.n_frames)]
    u = np.stack([c[0] for c in q])
    u[~np.stack([c[1] for c in q])] = np.nan   # not valid (outside the ROI or failing the checks)
    np.save(out, u)
    peak = peak_mb()
    print(json.dumps({"seconds": seconds, "peak_mb": peak, "frames": flow.n_frames, "size": [w, h],
                      "roi": list(flow.roi), "flow_mb": flow.nbytes / 2**20}))


def make_clip(tmp: Path, seconds: float, side: int) -> tuple[Path, Path]:
    import cv2

    from visemeflow.tracking.landmarks import read_landmarks
    from visemeflow.tracking.video import iter_timed_frames, write_video

    frames = []
    for f, t in iter_timed_frames(CLIP):
        if t >= seconds:
            break
        frames.append(cv2.resize(f, (side, side), interpolation=cv2.INTER_CUBIC))
    video = write_video(tmp / "4k.mp4", frames, 30.0)
    track = read_landmarks(MARKS)
    pts = np.asarray(track.points[: len(frames)], np.float64) * (side / 700.0)
    np.save(tmp / "points.npy", np.nan_to_num(pts, nan=side / 2))
    return video, tmp / "points.npy"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--side", type=int, default=2160)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        video, points = make_clip(Path(tmp), args.seconds, args.side)
        runs = {}
        for mode in ("whole", "streamed"):
            done = subprocess.run([sys.executable, __file__, "--child", mode, str(video), str(points),
                                   str(Path(tmp) / f"{mode}.npy")], capture_output=True, text=True)
            if done.returncode:
                print(done.stderr[-2000:])
                return 1
            runs[mode] = json.loads(done.stdout.strip().splitlines()[-1])
        a, b = np.load(Path(tmp) / "whole.npy"), np.load(Path(tmp) / "streamed.npy")
        both = np.isfinite(a).all(-1) & np.isfinite(b).all(-1)
        d = np.linalg.norm(a[both] - b[both], axis=-1)
        agree = (np.isfinite(a).all(-1) == np.isfinite(b).all(-1)).mean()
    w, s = runs["whole"], runs["streamed"]
    print(f"{w['frames']} frames of {w['size'][0]}x{w['size'][1]}, face ROI {w['roi'][2]}x{w['roi'][3]} px")
    print("| path | peak MB | flows MB | seconds |\n|---|---|---|---|")
    print(f"| whole clip, full-size flows | {w['peak_mb']:.0f} | {w['flow_mb']:.0f} | {w['seconds']:.1f} |")
    print(f"| frame by frame, ROI <= 480 px | {s['peak_mb']:.0f} | {s['flow_mb']:.0f} | {s['seconds']:.1f} |")
    print(f"peak ratio {w['peak_mb'] / s['peak_mb']:.1f}x, time ratio {w['seconds'] / s['seconds']:.1f}x; "
          f"correspondences at the landmarks apart by median {np.median(d):.3f} px, 95th percentile "
          f"{np.percentile(d, 95):.3f} px (image pixels) where both are valid; validity agrees at {agree:.1%}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(*sys.argv[2:6])
        sys.exit(0)
    sys.exit(main())
