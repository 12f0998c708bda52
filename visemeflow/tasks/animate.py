"""Animation task: one utterance's curves put on one character and exported (GLB, USD, Live Link CSV, web JSON,
curve CSV/JSON, the audio beside them, optionally a preview MP4), into one folder.

Cached on what decides the files: the curves' provenance, the character file's and mapping CSV's content hashes,
the audio's content hash, the export config and the output folder. Each package records those inputs in
`.inputs.json` beside its files, written last: a cache hit is used only while every file is there and that record
matches (a package another character of the same name wrote since, or one a kill left half written, recomputes).

The preview of an utterance with a video (tracked curves of a video utterance, or any other source of one) shows
the source video's face crop beside the character, as `visemeflow preview` does (`preview_video`); its cache key
then also holds the utterance's content hash (which covers the video and a landmark file beside it) and the
provenance of the landmarks the `landmarks` stage stored, when the crop comes from those (`PreviewVideoKey`). A video
that cannot be read leaves the preview to the character alone, with a warning in the report (`warnings`).
"""

from __future__ import annotations

import functools
import json
import logging
import re
import shutil
from collections import defaultdict
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from prefect import get_run_logger, task
from prefect.cache_policies import TASK_SOURCE, CachePolicy, Inputs
from prefect.context import TaskRunContext

from visemeflow.logs import SUMMARISED
from visemeflow.animation.apply import CurvesError
from visemeflow.animation.bones import BoneError
from visemeflow.atomic import atomic_write_text
from visemeflow.location import local_input
from visemeflow.rig.character import Character, CharacterError
from visemeflow.animation.gltf import GLTF_SUFFIXES
from visemeflow.animation.load import load_bound_character
from visemeflow.shapes.conventions import Binding
from visemeflow.animation.package import (
    AnimateConfig,
    ExportWriteError,
    bone_rig,
    export_animation,
    export_paths,
    stale_package_files,
)
from visemeflow.atomic import atomic_path
from visemeflow.animation.lips import closure_report
from visemeflow.hashing import file_hash, stable_hash
from visemeflow.ingest.audio import AudioError, read_audio
from visemeflow.schemas import C, readable_path_parts
from visemeflow.storage import Store
from visemeflow.tasks.code_version import code_digest
from visemeflow.tasks.common import CODE, RESULT_SERIALIZER, DataOnlyCache
from visemeflow.tasks.progress import StepLog, step_log

STAGE = "animate"
INPUTS_FILE = ".inputs.json"
NO_VIDEO_KEY = "no video"


def _video_row(store: Store, utterance_id: str) -> dict | None:
    """The utterance's row (id, content hash, video, landmark file, fps) when it has a video; None otherwise (no
    row: an audio file `speak` predicted from)."""
    rows = store.read_table("utterances", utterance_ids=[utterance_id]).select(
        [C.UTTERANCE_ID, C.CONTENT_HASH, C.VIDEO_PATH, C.LANDMARK_PATH, C.FPS]).to_pylist()
    return rows[0] if rows and rows[0][C.VIDEO_PATH] else None


def preview_video_key(store: Store, utterance_id: str) -> str:
    """What the preview's video panel is made from: the utterance's content hash (its video, and a landmark file
    beside it) and the provenance of the stored landmarks when the crop comes from those; `NO_VIDEO_KEY` without
    a video."""
    row = _video_row(store, utterance_id)
    if row is None:
        return NO_VIDEO_KEY
    stored = None if row[C.LANDMARK_PATH] else store.landmarks_provenance(utterance_id)
    return stable_hash(row[C.CONTENT_HASH], stored)


@dataclass
class PreviewVideoKey(CachePolicy):
    """The animate task's key part for the preview's video panel (`preview_video_key`); a constant without a
    preview, so only packages that render one read the utterances table for it."""

    def compute_key(self, task_ctx: TaskRunContext, inputs: dict[str, Any], flow_parameters: dict[str, Any],
                    **kwargs: Any) -> str:
        config = inputs.get("config")
        if not getattr(config, "preview", False):
            return "no preview"
        return preview_video_key(Store(inputs["store_root"]), inputs["utterance_id"])


# keyed on content hashes, not on where the character, mapping and audio files lie
ANIMATE_CACHE_POLICY = Inputs(exclude=["character_path", "mapping_path", "audio_path"]) + TASK_SOURCE + CODE \
    + PreviewVideoKey()


class AnimateError(ValueError):
    """An (utterance, character) that cannot be animated; names the utterance, the file and the reason."""

    def __init__(self, utterance_id: str | None, path: str | None, error_type: str, reason: str):
        where = ": ".join(p for p in (utterance_id, path) if p)
        super().__init__(f"{where}: {reason}" if where else reason)
        self.utterance_id, self.path, self.error_type, self.reason = utterance_id, path, error_type, reason

    def __reduce__(self):
        return (type(self), (self.utterance_id, self.path, self.error_type, self.reason))


@functools.lru_cache(maxsize=4)
def bound_character(path: str, character_hash: str, convention: str | None, mapping: str | None,
                    mapping_hash: str | None, meshes: tuple[str, ...] = ()) -> tuple[Character, Binding]:
    """The character of `path` bound to the 16 visemes (one load per run; the hashes key a changed file apart).

    `meshes`: the meshes of a glTF scene to drive (default: chosen by their target names, a mapping CSV's shapes
    counting as usable names)."""
    return load_bound_character(path, convention, mapping, meshes)


def curves_and_fps(store: Store, utterance_id: str, source: str, variant: str) -> tuple[np.ndarray, float, str]:
    """(T, 16) curves, their frame rate (as the writer recorded it) and the file they came from."""
    curves = store.load_curves(utterance_id, source, variant)
    return curves.values, curves.fps, str(store.curve_path(source, variant, utterance_id))


def content_hash(path: str | Path) -> str:
    """Content hash of a character file, or of a character folder (its files, by name and content)."""
    path = Path(path)
    if path.is_file():
        return file_hash(path)
    if not path.is_dir():
        raise CharacterError(f"{path}: no such character file or folder")
    return stable_hash(sorted((p.name, file_hash(p)) for p in path.iterdir() if p.is_file()))


def character_key(path: str | Path) -> str:
    """The folder name of a character's packages: its file's stem with characters a store name cannot hold as `_`."""
    stem = Path(path).name
    for suffix in (*GLTF_SUFFIXES, ".npz"):
        stem = stem.removesuffix(suffix)
    return re.sub(r"[^A-Za-z0-9_.-]", "_", stem).lstrip(".") or "character"


CHARACTER_OWNER = ".character"   # in a character's package folder: the resolved path of the file it holds


def character_keys(paths: list[str], root: Any = None) -> list[str]:
    """The package folder name of each character of one run: its `character_key`, unless different files (by
    resolved path) share one, as `a/good.glb` and `b/good.glb`, or (`root`: the folder of the character folders,
    `--out` or the store's `animations`, on object storage too) its folder there holds another file's packages, as
    its `.character` says (`claim_character_folder`): then it gets `-<8 hex digits>` of its resolved path, so no run
    overwrites another character's packages and the same file gets the same folder again."""
    keys = [character_key(p) for p in paths]
    resolved = [str(Path(p).resolve()) for p in paths]
    owners: dict[str, set[str]] = defaultdict(set)
    for key, where in zip(keys, resolved):
        owners[key].add(where)
    out = []
    for key, where in zip(keys, resolved):
        owner = _folder_owner(_base(root) / key) if root is not None else None
        out.append(f"{key}-{stable_hash(where, size=4)}" if len(owners[key]) > 1 or owner not in (None, where)
                   else key)
    return out


def _base(root: Any) -> Any:
    """A local folder as a Path; a store's folder on object storage (a `UPath`) as it is."""
    return Path(root) if isinstance(root, str) else root


def _folder_owner(folder: Any) -> str | None:
    try:
        return (folder / CHARACTER_OWNER).read_text(encoding="utf-8").strip() or None
    except (OSError, UnicodeDecodeError, ValueError):   # none yet (a folder of an earlier version, or a new one)
        return None


def claim_character_folder(root: Any, key: str, path: str, store: Store | None = None) -> None:
    """Record in `root/<key>/.character` that the folder holds the packages of the character file `path` (resolved),
    unless it says so already (see `character_keys`). `root`: a local folder, or the store's `animations` on object
    storage (written through `store`)."""
    folder = _base(root) / key
    where = str(Path(path).resolve())
    if _folder_owner(folder) == where:
        return
    if store is not None and store.remote:
        store.write_file(folder / CHARACTER_OWNER, lambda tmp: Path(tmp).write_text(where + "\n", encoding="utf-8"))
        return
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(folder / CHARACTER_OWNER, where + "\n")


def package_inputs(utterance_id: str, source: str, variant: str, provenance: str, character_hash: str,
                   mapping_hash: str | None, config: AnimateConfig, audio_hash: str | None,
                   phones: list | None) -> dict:
    """What one package is made from, as its `.inputs.json` records it (content hashes, not paths), and the code."""
    return {"utterance_id": utterance_id, "source": source, "variant": variant, "curves": provenance,
            "character": character_hash, "mapping": mapping_hash, "audio": audio_hash,
            "config": stable_hash(config), "phones": stable_hash(phones) if phones else None,
            "code": code_digest(__name__)}


def preview_video(store: Store, utterance_id: str):
    """(the `VideoSource` of the package preview's video panel, or None; why there is none, or None): the
    utterance's video cropped to the face by its landmarks, the panel `visemeflow preview` shows (`video_source`).
    (None, None) for an utterance without a video; (None, reason) for one whose video cannot be read, so the preview
    shows the character alone rather than a panel that says so."""
    row = _video_row(store, utterance_id)
    if row is None:
        return None, None
    from visemeflow.animation.preview import video_problem, video_source

    problem = video_problem(local_input(row[C.VIDEO_PATH]))
    if problem:
        return None, f"the preview shows the character alone: {problem}"
    # the tracker's landmarks (`tasks.track.landmark_file`'s rule; not imported: its module would put the solver's
    # code in this task's digest): the file beside the video, else the `landmarks` stage's
    stored = store.local_file(store.landmark_path(utterance_id)) if store.has_landmarks(utterance_id) else None
    return video_source(local_input(row[C.VIDEO_PATH]), local_input(row[C.LANDMARK_PATH]) or stored, row[C.FPS]), None


def fresh_work_dir(store: Store, target: Path) -> Path:
    """An empty local folder to write the package of the store folder `target` (on object storage) into."""
    folder = store.local_work_dir(target)
    for old in folder.iterdir():
        shutil.rmtree(old) if old.is_dir() else old.unlink()
    return folder


def upload_file(store: Store, local: Path, folder: Path, target: Path) -> Path:
    """The file `local` (in the work folder `folder`) uploaded into the store folder `target`, in one PUT."""
    path = target / local.relative_to(folder)
    data = local.read_bytes()
    return store.write_file(path, lambda tmp: Path(tmp).write_bytes(data), keep_suffix=True)


def package_dir(store: Store, out: str | None, character: str, utterance_id: str) -> Path:
    """The folder of one (utterance, character) package: under `out` if given, named as the id reads
    (`out/<character>/my voice/take 1/take 1.glb`), else in the store (ASCII, percent-encoded)."""
    folder = store.animation_dir(character, utterance_id)   # checks the character name too
    if not out:
        return folder
    speaker, name = readable_path_parts(utterance_id)
    return Path(out) / character / speaker / name


def _step_log(name: str) -> StepLog:
    """Progress lines of one long step: on the run's logger in a Prefect run (terminal and UI), else this module's
    (`tasks.progress.step_log`: on stderr where the logger hides them)."""
    from prefect.exceptions import MissingContextError

    try:
        logger = get_run_logger()
    except MissingContextError:
        logger = logging.getLogger(__name__)
    return step_log(name, logger)


def _bone_closure(character: Character, rig, lips: dict) -> list[str]:
    """Puts the bone mesh's MBP lip gap in the package's lip report (`bones_mbp_gap_mm`); a warning when it stays
    open."""
    from visemeflow.animation.bones import mbp_gap_mm
    from visemeflow.articulation import CLOSED_MM

    gap = mbp_gap_mm(character, rig)
    if gap is None:
        return []
    lips["bones_mbp_gap_mm"] = round(gap, 2)
    if gap < CLOSED_MM:
        return []
    more = f"more bones (--bones {2 * rig.n_bones}) may close them" if rig.n_bones < 64 else \
        "more bones will hardly close them"
    blendshapes = "" if "warning" in lips else "; --mode blendshape does"   # its own MBP shape closes
    return [f"{character.where()}: its {rig.n_bones} bones leave MBP's lips {gap:.1f} mm apart (closed is below "
            f"{CLOSED_MM} mm); {more}{blendshapes}"]


def animate(store: Store, utterance_id: str, source: str, variant: str, character_path: str, character_hash: str,
            mapping_path: str | None, mapping_hash: str | None, config: AnimateConfig, audio_path: str | None,
            out: str | None, phones: list[tuple[float, float, str]] | None = None,
            character_name: str | None = None) -> dict:
    """Export one utterance for one character into the folder of `character_name` (default: its
    `character_key`); AnimateError naming the utterance and file for bad input."""
    try:
        character, binding = bound_character(character_path, character_hash, config.convention, mapping_path,
                                             mapping_hash, config.meshes)
    except CharacterError as exc:
        raise AnimateError(utterance_id, character_path, "CharacterError",
                           str(exc).removeprefix(f"{character_path}: ")) from exc
    try:
        curves, fps, curve_file = curves_and_fps(store, utterance_id, source, variant)
    except LookupError as exc:
        raise AnimateError(utterance_id, None, "NoCurves", str(exc).removeprefix(f"{utterance_id}: ")) from exc
    audio = None
    if audio_path and config.audio:
        try:
            audio = read_audio(local_input(audio_path))
        except AudioError as exc:
            raise AnimateError(utterance_id, audio_path, "AudioError", exc.reason) from exc
    target = package_dir(store, out, character_name or character_key(character_path), utterance_id)
    stem = target.name
    # a store on object storage: the package is written into a local work folder, then uploaded file by file
    folder = fresh_work_dir(store, target) if store.remote and not out else target
    started = time.perf_counter()
    try:
        package = export_animation(folder, stem, character, binding, curves, fps, config, utterance_id=utterance_id,
                                   where=f"{source}/{variant} curves", audio=audio)
    except CurvesError as exc:
        raise AnimateError(utterance_id, curve_file, "CurvesError", str(exc)) from exc
    except ExportWriteError as exc:   # the output's disk, not the character, is at fault: name the output file
        raise AnimateError(utterance_id, exc.path, "ExportWriteError", str(exc).removeprefix(f"{exc.path}: ")) \
            from exc
    except (CharacterError, BoneError) as exc:   # bones it cannot have (too many, a skeleton scaled unevenly)
        raise AnimateError(utterance_id, character_path, type(exc).__name__,
                           str(exc).removeprefix(f"{character.source}: ")) from exc
    files = dict(package.files)
    played = package.curves   # the preview and the lip report show what the exports play
    lips = closure_report(character, binding, package.weights, package.fps, phones)
    warnings = binding.warnings()   # a closure or contact the character's shapes cannot make
    if config.mode == "bones":
        from visemeflow.animation.package import bone_count_note

        warnings += [note] if (note := bone_count_note(character, config.bones)) else []
        if lips:   # the viewer sees the bones' mesh: do their MBP lips meet?
            warnings += _bone_closure(character, bone_rig(character, binding, config.bones), lips)
    if config.preview or {"glb", "usd", "usdz"} & set(config.formats):   # what its exports cannot show as its file
        from visemeflow.animation.textures import appearance_notes

        warnings += list(appearance_notes(character))
    if config.mode == "bones" and "glb" in config.formats:   # what the face bones in the avatar's skeleton leave out
        from visemeflow.animation.skinned_asset import asset_bone_notes

        warnings += list(asset_bone_notes(character, bone_rig(character, binding, config.bones)))
    if config.preview:
        from visemeflow.animation.preview import BoneSource, render_preview

        panels = {f"{source} ({variant})": package.weights}
        if config.mode == "bones":   # what the bone exports play, beside the blendshapes they approximate
            rig = bone_rig(character, binding, config.bones)    # its bones as made (Dem Bones may leave some empty)
            panels = {"blendshapes": panels[f"{source} ({variant})"],
                      f"{rig.n_bones} bones": BoneSource(rig, played)}
        video, why = preview_video(store, utterance_id)   # the footage beside the character, when there is one
        warnings += [why] if why else []
        path = folder / f"{stem}.mp4"
        shown = render_preview(path, character, panels, package.fps, audio=audio, phones=phones,
                               title=f"{utterance_id} - {character.label}", video=video,
                               progress=_step_log(f"animate[{utterance_id}]"))
        warnings += [f"the preview's video panel: {shown.video_problem}"] if shown.video_problem else []
        files["preview"] = str(path)
    if folder == target:   # an earlier package's format or preview that this one lacks would pass for this one's
        for stale in stale_package_files(target, stem, list(files.values())):
            stale.unlink(missing_ok=True)
    else:   # every file the export wrote (a glTF's buffers, a USD's layers too), one PUT each
        uploaded = {str(p): str(upload_file(store, p, folder, target)) for p in sorted(folder.rglob("*")) if p.is_file()}
        files = {kind: uploaded.get(str(Path(local)), local) for kind, local in files.items()}
    seconds = time.perf_counter() - started
    return {"utterance_id": utterance_id, "character": character.label, "convention": binding.convention,
            "meshes": [part.name for part in character.parts],
            "folder": str(target), "files": files, "frames": package.frames, "fps": package.fps,
            "resampled_from": package.source_fps if package.resampled else None, "seconds": round(seconds, 4),
            "lips": lips, "warnings": warnings}


@task(cache_policy=DataOnlyCache(policy=ANIMATE_CACHE_POLICY), persist_result=True, result_serializer=RESULT_SERIALIZER,
      task_run_name="animate[{utterance_id}:{character_name}]")
def animate_one(store_root: str, utterance_id: str, source: str, variant: str, provenance: str, character_path: str,
                character_hash: str, character_name: str, mapping_path: str | None, mapping_hash: str | None,
                config: AnimateConfig, audio_path: str | None, audio_hash: str | None, out: str | None,
                phones: list | None = None) -> dict:
    """One (utterance, character) package; `provenance` and the hashes key the cache (see the module)."""
    report = animate(Store(store_root), utterance_id, source, variant, character_path, character_hash, mapping_path,
                     mapping_hash, config, audio_path, out, [tuple(p) for p in phones] if phones else None,
                     character_name)
    inputs = package_inputs(utterance_id, source, variant, provenance, character_hash, mapping_hash, config,
                            audio_hash, phones)
    text = json.dumps(inputs, sort_keys=True)
    if out is None:   # in the store (a folder or object storage), after the package's files
        store = Store(store_root)
        store.write_file(store.animation_dir(character_name, utterance_id) / INPUTS_FILE,
                         lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
    else:
        with atomic_path(Path(report["folder"]) / INPUTS_FILE) as tmp:
            tmp.write_text(text, encoding="utf-8")
    logger = get_run_logger()
    logger.info("%s -> %s: %d frames at %g fps, %s", utterance_id, character_name, report["frames"], report["fps"],
                ", ".join(report["files"]))
    for warning in report["warnings"]:
        logger.warning("%s -> %s: %s", utterance_id, character_name, warning, extra=SUMMARISED)
    return report


def outputs_present(store: Store, out: str | None, character_name: str, utterance_id: str, config: AnimateConfig,
                    with_audio: bool, inputs: dict) -> bool:
    """Whether every file a package of this config would write is on disk and the package records `inputs`
    (`package_inputs`) as what it was made from: a deleted file, or a package made from other inputs under the same
    folder, recomputes."""
    folder = package_dir(store, out, character_name, utterance_id)
    names = export_paths(Path(), folder.name, config.formats, config.mode).values()   # a UPath on object storage
    paths = [folder / name.name for name in names]
    paths += [folder / f"{folder.name}.wav"] if with_audio and config.audio else []
    paths += [folder / f"{folder.name}.mp4"] if config.preview else []
    return all(p.is_file() for p in paths) and _recorded_inputs(folder) == inputs


def _recorded_inputs(folder: Path) -> dict | None:
    try:
        return json.loads((folder / INPUTS_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):   # none, or unreadable: the package is made again
        return None
