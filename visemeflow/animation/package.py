"""One utterance's animation package for one character: the curves checked, resampled to the export rate if asked,
bound to the character's shapes and written in every requested format into one folder, the audio beside them.

| format        | file                  | for                                                          |
|---------------|-----------------------|--------------------------------------------------------------|
| `glb`         | `<stem>.glb`          | Blender, three.js / web, Unity (glTFast, UniVRM), Godot       |
| `usd`         | `<stem>.usd`          | Omniverse, Maya USD, Houdini (UsdSkel, as Audio2Face exports) |
| `usdz`        | `<stem>.usdz`         | the same stage with a glTF character's textures packed in      |
| `livelink`    | `<stem>.livelink.csv` | Unreal / MetaHuman (Live Link Face CSV, ARKit 52)             |
| `json`        | `<stem>.web.json`     | web avatars (TalkingHead's `dt`/`vs` animation layout)        |
| `curves-csv`  | `<stem>.curves.csv`   | the 16 viseme curves, one row per frame                      |
| `curves-json` | `<stem>.curves.json`  | the 16 viseme curves, one list per viseme                    |

The `glb` of a character read from a glTF scene is that whole scene with the clip added (`gltf_asset`); of other
characters, a new single-mesh GLB (`gltf.write_glb`). Its `usd` / `usdz` carry the scene's other meshes, UVs and
materials as well (`usd_scene`).

Bone mode (`AnimateConfig.mode = "bones"`, `visemeflow animate --mode bones --bones N`): the character's visemes become
N SSDR bones (`visemeflow.animation.bones`, solved once per character, binding and bone count in a process and
reused by every utterance of the run), and `glb` / `usd` are written as bone animation instead of blendshapes:

| format      | file               | for                                                                       |
|-------------|--------------------|---------------------------------------------------------------------------|
| `glb`       | `<stem>.bones.glb` | skinned glTF: joints, inverse bind matrices, LINEAR joint TRS channels    |
| `usd`       | `<stem>.bones.usd` | UsdSkel SkelAnimation with joints                                         |
| `pose-csv`  | `<stem>.poses.csv` | per viseme per bone quaternion + translation (an engine's own Pose Asset) |
| `pose-json` | `<stem>.poses.json`| the same as JSON                                                          |

The other formats (Live Link CSV, web JSON, curves) are the same in both modes.

glTF carries no audio: the utterance's audio goes beside the files as `<stem>.wav` (16-bit PCM at its own rate).
Every file has exactly the frames and rate of the (resampled) curves: frame k at k / fps. The Live Link CSV holds
ARKit weights whatever the character's convention (`conventions.arkit_weights`); the other character formats hold
the character's own shapes.
"""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import soundfile as sf

from visemeflow.animation.apply import check_curves, resample_visemes
from visemeflow.animation.config import DEFAULT_FORMATS, AnimateConfig  # noqa: F401 (re-exported here)
from visemeflow.animation.formats import (  # noqa: F401 (re-exported here: the table of formats)
    EXPORTERS,
    Exporter,
    ExportTarget,
    bone_only_formats,
    export_formats,
    register_exporter,
)
from visemeflow.articulation import close_lips
from visemeflow.animation.bones import BONE_FORMATS, BONE_SUFFIXES, DEFAULT_BONES, BoneRig, solve_bones, \
    write_pose_table
from visemeflow.rig.character import Character
from visemeflow.shapes.conventions import Binding
from visemeflow.atomic import atomic_path

class ExportWriteError(Exception):
    """An export file that could not be written (disk full, no permission, ...): names that file, not the inputs."""

    def __init__(self, path: str, fmt: str, reason: str):
        super().__init__(f"{path}: the {fmt} export cannot be written ({reason})")
        self.path, self.fmt, self.reason = str(path), fmt, reason

    def __reduce__(self):  # picklable with its three-argument constructor (Prefect ships exceptions)
        return (type(self), (self.path, self.fmt, self.reason))


@contextmanager
def _writing(path: Path, fmt: str) -> Iterator[None]:
    """Turn an OSError met while writing `path` into an ExportWriteError naming it (an error from the write
    itself, ENOSPC at the flush, names no file or only the temporary one)."""
    try:
        yield
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise ExportWriteError(str(path), fmt, reason.removeprefix(f"{path}: ")) from exc


@dataclass
class AnimationPackage:
    """What `export_animation` wrote."""

    files: dict[str, str]
    """format (and "audio") -> path."""
    frames: int
    fps: float
    source_fps: float
    resampled: bool
    binding: dict = field(default_factory=dict)
    curves: np.ndarray | None = None
    """(frames, 16) the curves the files play: resampled to `fps`, through the closure rule when it is on."""
    weights: np.ndarray | None = None
    """(frames, S) those curves in the character's own shapes (`binding.weights(curves)`)."""


def export_paths(out_dir: Path, stem: str, formats: tuple[str, ...] | list[str],
                 mode: str = "blendshape") -> dict[str, Path]:
    """Where each format of one package goes (bone mode writes glb/usd as `.bones.glb`/`.bones.usd`)."""
    def suffix(fmt: str) -> str:
        e = EXPORTERS[fmt]
        return e.bone_suffix if mode == "bones" and e.bone_suffix else e.suffix
    return {fmt: Path(out_dir) / f"{stem}{suffix(fmt)}" for fmt in formats}


def package_file_names(stem: str) -> set[str]:
    """Every file name a package of `stem` can hold: each format's (blendshape and bone modes), the audio and the
    preview. What a new package of that stem did not write is an earlier one's, left over (`stale_package_files`)."""
    from visemeflow.animation.bones import BONE_SUFFIXES

    suffixes = {e.suffix for e in EXPORTERS.values()} | {e.bone_suffix for e in EXPORTERS.values() if e.bone_suffix}
    return {f"{stem}{s}" for s in suffixes | set(BONE_SUFFIXES.values()) | {".wav", ".mp4"}}


def stale_package_files(folder: Path, stem: str, written: list[str]) -> list[Path]:
    """Files of an earlier package of `stem` in `folder` that this one (`written`) did not replace: a format or a
    preview no longer asked for. Only names a package can have; anything else in the folder is not ours."""
    kept = {Path(p).name for p in written}
    return sorted(Path(folder) / n for n in package_file_names(stem) - kept if (Path(folder) / n).is_file())


_RIGS: dict[str, object] = {}
_RIG_LOCKS: dict[str, threading.Lock] = {}
_RIGS_GUARD = threading.Lock()


def bone_rig(character: Character, binding: Binding, bone_count: int):
    """The character's SSDR bone rig for this binding and bone count, solved once per process (tens of seconds) and
    shared by every utterance animated in it; threads asking for the same rig wait for the one solve. More bones than
    the character's vertices support (`bones.max_bones`: 32, the default, for teeth of 48 vertices) are that many
    (`bone_count_note` says so)."""
    from visemeflow.animation.bones import max_bones

    bone_count = min(int(bone_count), max(max_bones(character.n_vertices), 1))
    digest = hashlib.sha256()
    for part in (character.neutral, character.faces, character.deltas, binding.matrix):
        digest.update(np.ascontiguousarray(part).tobytes())
    key = f"{digest.hexdigest()}:{bone_count}"
    with _RIGS_GUARD:
        lock = _RIG_LOCKS.setdefault(key, threading.Lock())
    with lock:
        if key not in _RIGS:
            _RIGS[key] = solve_bones(character, bone_count, binding=binding)
        return _RIGS[key]


def bone_count_note(character: Character, bone_count: int) -> str | None:
    """A line when `bone_rig` makes fewer bones than asked because the character's vertices support no more."""
    from visemeflow.animation.bones import max_bones

    most = max(max_bones(character.n_vertices), 1)
    if int(bone_count) <= most:
        return None
    return (f"{character.where()}: {bone_count} bones asked, at most {most} made: its {character.n_vertices} "
            "vertices support no more (each bone moves at least 3)")


def write_wav(path: Path, samples: np.ndarray, rate: int) -> Path:
    """16-bit PCM WAV, atomically (what every DCC and engine imports); ExportWriteError naming `path` if the disk
    refuses it."""
    with _writing(path, "audio"), atomic_path(path, keep_suffix=True) as tmp:
        sf.write(tmp, np.clip(np.asarray(samples, np.float32), -1.0, 1.0), int(rate), subtype="PCM_16", format="WAV")
    return path


def export_animation(out_dir: str | Path, stem: str, character: Character, binding: Binding, curves: np.ndarray,
                     fps: float, config: AnimateConfig, *, utterance_id: str, where: str | None = None,
                     audio: tuple[np.ndarray, int] | None = None) -> AnimationPackage:
    """Check `curves` (T, 16) at `fps`, resample to `config.fps`, and write each format of `config` into `out_dir`.

    CurvesError (naming `where`, default the utterance) for non-finite curves or values outside [0, 1];
    ExportWriteError naming the output file that the disk refused (full, read-only, no permission)."""
    out_dir = Path(out_dir)
    curves = check_curves(curves, where or utterance_id)
    rate = float(config.fps or fps)
    curves = resample_visemes(curves, float(fps), rate)
    if config.closure_rule:
        curves = close_lips(curves)
    weights = binding.weights(curves)
    paths = export_paths(out_dir, stem, config.formats, config.mode)
    files: dict[str, str] = {}
    bone_formats = [f for f in config.formats if EXPORTERS[f].bone_suffix] if config.mode == "bones" else []
    if bone_formats:
        rig = bone_rig(character, binding, config.bones)
        written = export_bone_animation(character, curves, rate, bone_formats, out_dir, stem=stem, rig=rig)
        files.update({fmt: str(path) for fmt, path in zip(bone_formats, written)})
    for fmt, path in paths.items():
        if fmt in bone_formats:
            continue
        with _writing(path, fmt):
            EXPORTERS[fmt].write(ExportTarget(path, character, curves, weights, rate, stem, utterance_id))
        files[fmt] = str(path)
    if config.audio and audio is not None:
        files["audio"] = str(write_wav(out_dir / f"{stem}.wav", *audio))
    return AnimationPackage(files, len(curves), rate, float(fps), abs(rate - fps) > 1e-9, binding.summary(), curves,
                            weights)


def export_bone_animation(character: Character, curves, fps: float, formats, out_dir, bone_count: int = DEFAULT_BONES,
                          audio: tuple[np.ndarray, int] | None = None, *, stem: str | None = None,
                          rig: BoneRig | None = None, binding=None) -> list:
    """Solve the character's bones (or use `rig`), blend them by (T, 16) `curves` at `fps` and write each of
    `formats` (any of `BONE_FORMATS`) into `out_dir` as `<stem><suffix>` (`BONE_SUFFIXES`; stem: the character's
    name), the audio beside as `<stem>.wav` when given ((samples, rate)). Returns the paths written, in order.

    CurvesError for non-finite curves or values outside [0, 1]; ValueError for an unknown format; BoneError as
    `solve_bones`."""
    formats = tuple(dict.fromkeys([formats] if isinstance(formats, str) else formats))
    unknown = [f for f in formats if f not in BONE_FORMATS]
    if unknown or not formats:
        raise ValueError(f"unknown bone export format(s) {', '.join(unknown) or '(none given)'}; known: "
                         f"{', '.join(BONE_FORMATS)}")
    curves = check_curves(curves, stem or character.name)
    fps = float(fps)
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"frames per second must be a positive number, got {fps}")
    if rig is None:
        rig = solve_bones(character, bone_count, binding=binding)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = stem or "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in character.name)
    written = []
    for fmt in formats:
        path = out_dir / f"{stem}{BONE_SUFFIXES[fmt]}"
        with _writing(path, fmt):
            if fmt == "glb":
                from visemeflow.animation.skinned_asset import is_gltf_asset, write_asset_bones_glb
                from visemeflow.animation.skinned_gltf import write_skinned_glb

                if is_gltf_asset(character):     # the user's whole avatar, the face bones in its skeleton
                    write_asset_bones_glb(path, character, rig, curves, fps, name=stem)
                else:
                    write_skinned_glb(path, rig, curves, fps, name=stem)
            elif fmt == "usd":
                from visemeflow.animation.usd_skel import write_usd_skel

                from visemeflow.animation.skinned_asset import is_gltf_asset

                write_usd_skel(path, rig, curves, fps, name=stem,
                               character=character if is_gltf_asset(character) else None)
            else:
                write_pose_table(path, rig, fmt.removeprefix("pose-"))
        written.append(path)
    if audio is not None:
        written.append(write_wav(out_dir / f"{stem}.wav", *audio))
    return written
