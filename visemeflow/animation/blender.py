"""`visemeflow blender FILE`: run Blender on an animation we wrote with `blender_open.py` (the file's frame rate and
frame range, its wav in the sequencer, played in sync with the audio), in Blender's window or into a .blend.

Which Blender: `--blender`, else $VISEMEFLOW_BLENDER, else `blender` on PATH. It may be the Blender program (run as
`blender [--background --factory-startup] --python blender_open.py -- ARGS`) or a Python that has the `bpy` module
(PyPI `bpy`, Blender as a module; run as `python blender_open.py ARGS`, always without a window).
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
from dataclasses import dataclass
from pathlib import Path

from visemeflow.animation import blender_open

SCRIPT = Path(blender_open.__file__)
INSTALL_HINT = ("install Blender (Debian/Ubuntu: apt install blender; or from blender.org) and put `blender` on PATH, "
                "or name it with --blender or $VISEMEFLOW_BLENDER (a Python with the bpy module works too: "
                "`python -m venv bpy-venv && bpy-venv/bin/pip install bpy==5.0.1`, in a venv of its own, since bpy "
                "pins NumPy 1.26); or run the script inside Blender yourself: blender --python "
                f"{SCRIPT} -- FILE")


class BlenderError(RuntimeError):
    """No Blender to run, a file it cannot open, or Blender failing on it."""


@dataclass(frozen=True)
class BlenderRun:
    """What Blender reported (`blender_open.main`'s dict), and the command that ran."""

    report: dict
    command: list[str]


def find_blender(explicit: str | os.PathLike | None = None) -> str:
    """The Blender to run (see the module doc); BlenderError with how to get one."""
    wanted = explicit or os.environ.get("VISEMEFLOW_BLENDER")
    if wanted:
        found = shutil.which(str(wanted))
        if found is None:
            raise BlenderError(f"no Blender at {wanted}: " + INSTALL_HINT)
        return found
    found = shutil.which("blender")
    if found is None:
        raise BlenderError("no Blender found: " + INSTALL_HINT)
    return found


def animation_fps(path: Path) -> float:
    """The frame rate a file we wrote plays at: a glTF's key times, a USD stage's timeCodesPerSecond."""
    suffix = path.suffix.lower()
    if suffix in blender_open.GLTF_SUFFIXES:
        try:
            fps = blender_open.gltf_fps(path)
        except (OSError, ValueError, KeyError, IndexError, TypeError, AttributeError, struct.error) as exc:
            # not JSON, a GLB cut short, an animation sampler naming no accessor or one without min/max
            raise BlenderError(f"{path}: not a glTF whose animation can be read ({type(exc).__name__}: {exc})") \
                from None
        if fps is None:
            raise BlenderError(f"{path}: no animation in it (a glTF with at least two key times)")
        return fps
    from pxr import Usd

    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise BlenderError(f"{path}: USD cannot open it")
    return float(stage.GetTimeCodesPerSecond())


def is_python(executable: str) -> bool:
    return Path(executable).name.startswith("python")


def blender_command(executable: str, animation: Path, *, save: Path | None = None, wav: Path | None = None
                    ) -> list[str]:
    """The command that opens `animation` (absolute) in `executable`: in its window, or into `save` in the
    background."""
    args = [str(animation), "--fps", repr(animation_fps(animation))]
    if wav is not None:
        args += ["--wav", str(wav.resolve())]
    if save is not None:
        args += ["--save", str(save.resolve())]
    if is_python(executable):
        return [executable, str(SCRIPT), *args]
    head = [executable, "--background", "--factory-startup"] if save is not None else [executable]
    return [*head, "--python", str(SCRIPT), "--", *args]


def open_in_blender(animation: str | os.PathLike, *, save: str | os.PathLike | None = None,
                    wav: str | os.PathLike | None = None, blender: str | os.PathLike | None = None,
                    timeout: float | None = 600.0) -> BlenderRun:
    """Open `animation` (a GLB or USD we wrote) in Blender, ready to play; with `save`, write the scene as that
    .blend without a window (a Python with bpy always runs without one, so it needs `save`)."""
    path = Path(animation).resolve()
    if not path.is_file():
        raise BlenderError(f"{animation}: no such file")
    if path.suffix.lower() not in blender_open.GLTF_SUFFIXES + blender_open.USD_SUFFIXES:
        raise BlenderError(f"{animation}: not a GLB, glTF or USD file (what `animate` and `speak` write with "
                           "--format glb, usd or usdz)")
    if wav is not None and not Path(wav).is_file():
        raise BlenderError(f"--wav {wav}: no such file")
    executable = find_blender(blender)
    if save is None and is_python(executable):
        raise BlenderError(f"{executable} is a Python with bpy, which has no window: give --save FILE.blend")
    if save is not None:
        Path(save).resolve().parent.mkdir(parents=True, exist_ok=True)
    command = blender_command(executable, path, save=Path(save) if save else None, wav=Path(wav) if wav else None)
    if save is None:   # Blender's window: the user's session, its output on the terminal
        done = subprocess.run(command, timeout=None)
        if done.returncode != 0:
            raise BlenderError(f"Blender exited {done.returncode} on {path}")
        return BlenderRun({"file": str(path)}, command)
    done = subprocess.run(command, capture_output=True, text=True, timeout=timeout)
    lines = [line for line in done.stdout.splitlines() if line.startswith("blender_open: ")]
    if done.returncode != 0 or not lines:
        tail = (done.stdout + done.stderr).strip().splitlines()[-8:]
        raise BlenderError(f"Blender exited {done.returncode} on {path}:\n" + "\n".join(tail))
    return BlenderRun(json.loads(lines[-1].removeprefix("blender_open: ")), command)
