"""Blender as the programs that read our files see them: `probe` runs tests/blender_probe.py in the venv that
`make blender-deps` builds (Blender 5.0 as the PyPI `bpy` module; a test fails, never skips, without it) on a
GLB or USD and returns what Blender shows. Shared by tests/test_blender.py, test_bone_asset.py and
test_usd_joints.py."""

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from factories import REPO

BPY_PYTHON = REPO / ".venv-blender" / "bin" / "python"
PROBE = Path(__file__).with_name("blender_probe.py")
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])   # (x, y, z) -> (x, -z, y)


def bpy_python() -> Path:
    if not BPY_PYTHON.is_file():
        pytest.fail(f"{BPY_PYTHON} missing: `make blender-deps` builds it (Blender as the PyPI bpy module)")
    return BPY_PYTHON


def probe(path: Path, frames: list[int], out: Path, fps: float | None = 30.0) -> tuple[dict, dict[str, np.ndarray]]:
    """What Blender shows of `path` (see tests/blender_probe.py): its report and each mesh's world vertices."""
    request = {"path": str(path), "frames": frames, "out": str(out), "fps": fps}
    done = subprocess.run([str(bpy_python()), str(PROBE), json.dumps(request)], capture_output=True, text=True,
                          timeout=300)
    lines = [line for line in done.stdout.splitlines() if line.startswith("probe: ")]
    assert done.returncode == 0 and lines, (done.stdout + done.stderr)[-3000:]
    report = json.loads(lines[-1].removeprefix("probe: "))
    with np.load(out) as arrays:          # each mesh's vertices; its UVs and colours go in the report
        report["uv"] = {k.removesuffix(".uv"): arrays[k] for k in arrays.files if k.endswith(".uv")}
        report["color"] = {k.removesuffix(".color"): arrays[k] for k in arrays.files if k.endswith(".color")}
        return report, {k: arrays[k] for k in arrays.files if not k.endswith((".uv", ".color"))}
