"""The `track` flow: phoneme-guided viseme tracking of every utterance with a video.

With `TrackParams.joint_frames` (400, the default) the stage runs few tasks: an utterance whose own task would be a
cache hit is read from that cached record, without a task run (24,000 cached task runs would cost minutes of
Prefect at the paper's scale); the others are tracked in groups of about that many frames, one `track-joint[...]`
task and one joint solve per group (`tracking.solver.solve_fast_many`: each clip gets the curves of its own solve,
to float rounding, for a fraction of the solver's time), and each result is written as its utterance's task's
cached record, so a later run and a run with `joint_frames` 0 (one `track[...]` task per utterance, as
before) find it. An utterance that fails in a group is tracked by its own task, alone, and rejected there with its
whole message.

Utterances without an alignment are tracked unguided (variant `unguided-...`, see tasks/track.py); the summary
counts them (`unguided`) and says why (`unguided_why`).

With `TrackingConfig.speaker_identity` the face and camera of real video (no `<name>.camera.json`) are fitted once
per (speaker, image size) before the utterances' tasks, by a cached task on the neutral frames of the first
`identity_clips` clips by utterance id (`speaker_identities`), and handed to each utterance's task (part of its cache
key: a changed chosen clip re-tracks the speaker). Without it each clip is fitted on its own, as before."""

import logging
from pathlib import Path

from prefect import flow
from prefect.futures import as_completed

from visemeflow.flows.common import (
    StageRun,
    collect_utterance_results,
    last_settings,
    read_cached,
    replace_stage_rejects,
)
from visemeflow.flows.errors import RerunError
from visemeflow.flows.params import TrackParams, TrackSettings
from visemeflow.flows.runners import cpu_thread_pool, on_requested_runner, run_on_runner
from visemeflow.hashing import file_hash
from visemeflow.location import input_exists, is_url, remote_root
from visemeflow.rig import demo_rig_path
from visemeflow.schemas import C
from visemeflow.storage import Store
from visemeflow.tasks.progress import Progress
from visemeflow.tasks.common import result_storage
from visemeflow.tasks.procedural import SOURCE as PROCEDURAL
from visemeflow.tasks.procedural import default_variant
from visemeflow.tasks.track import (
    SOURCE,
    STAGE,
    TrackError,
    fit_speaker_identity_task,
    identity_clips,
    landmark_file,
    track_jointly,
    track_utterance,
    tracked_provenance,
    utterance_config,
)
from visemeflow.tracking.solver import TrackingConfig, joins
from visemeflow.tracking.utterance import CAMERA_SUFFIX, needs_identity, video_size

LANDMARKS_KEY = "stored_landmarks"
"""Key of the stored landmarks' provenance in a task's utterance row (part of the task's cache key)."""
TRACK_FIELDS = [C.UTTERANCE_ID, C.CONTENT_HASH, C.VIDEO_PATH, C.LANDMARK_PATH, C.AUDIO_PATH, C.ALIGNMENT_PATH,
                C.ALIGNMENT_FORMAT, C.FPS, C.N_FRAMES]


def rig_and_hash(rig: Path | None) -> tuple[Path, str]:
    path = (rig or demo_rig_path()).resolve()
    return path, file_hash(path)


def procedural_variant_of(store: Store, given: str | None) -> str:
    """The procedural curves that guide tracking: as given, else those the procedural stage last wrote."""
    if given:
        return given
    last = last_settings(store, "procedural")
    if last is not None and last.variant:
        return last.variant
    from visemeflow.procedural import ProceduralConfig

    return default_variant(ProceduralConfig())


def real_video(video: str) -> bool:
    """`needs_identity` of a video path or URL: no `<name>.camera.json` beside it (on S3 one HEAD; the video is
    not fetched)."""
    if not is_url(video):
        return needs_identity(video)
    folder, name = video.rsplit("/", 1)
    return not input_exists(f"{folder}/{name.rsplit('.', 1)[0]}{CAMERA_SUFFIX}")


def frame_size(video: str) -> tuple[int, int] | None:
    """`video_size` of a video path or URL; of an object only the header's bytes are fetched (ranged reads)."""
    if not is_url(video):
        return video_size(video)
    root = remote_root(video)
    try:
        with root.fs.open(root.path, "rb", block_size=HEADER_BLOCK) as fh:
            return video_size(fh)
    except OSError:
        return None


HEADER_BLOCK = 1 << 18
"""Bytes per ranged read of a video object whose header `frame_size` reads."""


def identity_groups(store: Store, rows: list[dict]) -> dict[tuple[str, int, int], list[dict]]:
    """The real-video utterances among `rows` (no `<name>.camera.json`) by (speaker, width, height): one speaker
    identity each. A video whose size cannot be read is in no group (tracked as without a speaker identity)."""
    ids = [r[C.UTTERANCE_ID] for r in rows]
    speakers = dict(zip(*store.read_table("utterances", utterance_ids=ids).select([C.UTTERANCE_ID, C.SPEAKER])
                        .to_pydict().values()))
    groups: dict[tuple[str, int, int], list[dict]] = {}
    for row in rows:
        if not real_video(row[C.VIDEO_PATH]):
            continue
        size = frame_size(row[C.VIDEO_PATH])
        if size is not None:
            groups.setdefault((speakers[row[C.UTTERANCE_ID]], *size), []).append(row)
    return groups


def identity_inputs(store: Store, members: list[dict], config: TrackingConfig) -> list[dict]:
    """The rows of the clips a group's identity is fitted on, with their landmark file (and the stored landmarks'
    provenance, part of the identity task's cache key)."""
    with_files = []
    for row in members:
        path = landmark_file(store, row)
        if path:
            extra = {} if row[C.LANDMARK_PATH] else {LANDMARKS_KEY: store.landmarks_provenance(row[C.UTTERANCE_ID])}
            with_files.append({C.UTTERANCE_ID: row[C.UTTERANCE_ID], C.CONTENT_HASH: row[C.CONTENT_HASH],
                               C.LANDMARK_PATH: path, C.FPS: row[C.FPS], **extra})
    return identity_clips(with_files, config.identity_clips)


def speaker_identities(store: Store, rows: list[dict], config: TrackingConfig, rig_path: Path, rig_hash: str,
                       logger, submit: bool = True) -> dict[str, dict | None]:
    """Utterance id -> its speaker's identity (`SpeakerIdentity.to_dict`; None: fitted per clip) of the real-video
    utterances in `rows`, one cached `fit_speaker_identity_task` per (speaker, image size); {} when
    `config.speaker_identity` is off. A group whose fit fails is tracked per clip (with a warning)."""
    if not config.speaker_identity:
        return {}
    groups = identity_groups(store, rows)
    task = fit_speaker_identity_task.with_options(result_storage=result_storage(store.root))
    runs = {}
    for key in sorted(groups):
        speaker, width, height = key
        args = (speaker, [width, height], identity_inputs(store, groups[key], config), str(rig_path), rig_hash,
                config.identity_frames)
        runs[key] = task.submit(*args) if submit else task(*args)
    out: dict[str, dict | None] = {}
    for key, run in runs.items():
        try:
            identity = run.result() if submit else run
        except Exception as exc:  # noqa: BLE001 - the clips are then fitted on their own, as without the option
            logger.warning("identity[%s %dx%d] failed, its clips are fitted one by one: %s: %s", *key,
                           type(exc).__name__, exc)
            identity = None
        out.update({row[C.UTTERANCE_ID]: identity for row in groups[key]})
    return out


def keyed_row(store: Store, row: dict) -> dict:
    """The utterance row a track task is given: with the provenance of the landmarks the `landmarks` stage stored
    for it, where it has no landmark file of its own (new landmarks then invalidate its cache)."""
    if row[C.LANDMARK_PATH]:
        return row
    return {**row, LANDMARKS_KEY: store.landmarks_provenance(row[C.UTTERANCE_ID])}


def unguided_why(unguided: list[dict]) -> str | None:
    """'N: reason; M: reason' over the reports of utterances tracked without phoneme guidance; None if none."""
    counts: dict[str, int] = {}
    for r in unguided:
        reason = r.get("unguided_reason") or "unknown"
        counts[reason] = counts.get(reason, 0) + 1
    return "; ".join(f"{n}: {reason}" for reason, n in sorted(counts.items())) or None


def joint_groups(calls: list, frames_each: int) -> list[list]:
    """`calls` (longest first) in groups of about `frames_each` frames: each group's frames reach it or it holds
    one call; a group's clips are then of like length."""
    groups, group, total = [], [], 0
    for call in calls:
        group.append(call)
        total += int(call[1][C.N_FRAMES] or 0)
        if total >= frames_each:
            groups.append(group)
            group, total = [], 0
    return groups + ([group] if group else [])


def track_in_groups(store: Store, calls: list, present: dict[str, bool], frames_each: int, logger,
                    device: str = "cpu") -> tuple[list[dict], list[dict], int, int]:
    """The track stage's work with joint solves: each utterance whose `track_utterance` call would be a cache hit
    (its record there and `present`: its curves stored, or it was rejected) is read from that record, without a
    task run; the others are tracked
    in groups of about `frames_each` frames, one `track_jointly` task and one joint solve each, which leave each
    result as its call's cached record. An utterance that fails in a group (or whose group meets a bug) then runs
    in its own `track_utterance` task, alone, and is rejected there with its whole message.
    (reports, reject rows, unexpected errors, utterances tracked jointly), as `collect_utterance_results`."""
    reports, left = read_cached(STAGE, track_utterance, store.root,
                                [(uid, args, present[uid]) for uid, _, args in calls], logger)
    misses = [(uid, args[1], args, key) for uid, args, key in left]
    groups = joint_groups(misses, frames_each)
    if groups:
        logger.info("track: %d utterances to track, in %d joint solve(s) of about %d frames", len(misses),
                    len(groups), frames_each)
    futures = {}
    for group in groups:
        label = group[0][0] if len(group) == 1 else f"{group[0][0]} +{len(group) - 1}"
        args = group[0][2]
        futures[track_jointly.submit(args[0], label, [row for _, row, _, _ in group], args[2], args[4], args[6],
                                     [a[7] for _, _, a, _ in group], [key for *_, key in group], device)] = group
    alone, jointly = [], 0
    work = sum(int(row[C.N_FRAMES] or 0) for _, row, _, _ in misses)
    with Progress(STAGE, len(misses), work_total=work or None, work_unit="frames") as line:
        for future in as_completed(list(futures)):
            group = futures[future]
            try:
                done = future.result()
            except Exception as exc:    # a bug met in one group: its utterances' own tasks run them alone
                logger.warning("track: a joint solve failed (%s: %s); its %d utterances are tracked one by one",
                               type(exc).__name__, exc, len(group))
                done = {}
            failed = [call for call in group if not isinstance(done.get(call[0]), dict)]
            alone += failed
            tracked = [done[uid] for uid, *_ in group if isinstance(done.get(uid), dict)]
            reports += [{**report, "cached": 0} for report in tracked]
            jointly += len(tracked)
            line.advance(len(tracked), work=sum(r["frames"] for r in tracked))
    own = {track_utterance.with_options(result_storage=result_storage(store.root), refresh_cache=True)
           .submit(*args): uid for uid, _, args, _ in alone}
    more, rejects, unexpected = collect_utterance_results(
        own, STAGE, TrackError, logger, work={f: int(row[C.N_FRAMES] or 0) for f, (_, row, _, _) in zip(own, alone)})
    return reports + more, rejects, unexpected, jointly


@flow(name="track", flow_run_name="track({params.store})", task_runner=cpu_thread_pool())
def track_flow(params: TrackParams) -> dict[str, object]:
    """Track every utterance that has a video; failures become rejects and the rest goes on."""
    if not on_requested_runner(params):  # e.g. a deployment run asking for Dask: run on it as a subflow
        return run_on_runner(track_flow, params)
    rig_path, rig_hash = rig_and_hash(params.rig)
    procedural_variant = procedural_variant_of(Store(params.store), params.procedural_variant)
    config = params.config
    run = StageRun(STAGE, params.store, TrackSettings(rig=str(rig_path), procedural_variant=procedural_variant,
                                                      n_shards=params.n_shards, config=config))
    store = run.store
    rows = [r for r in store.read_table("utterances").select(TRACK_FIELDS).to_pylist() if r[C.VIDEO_PATH]]
    # longest videos first: with n workers the run then ends on short utterances, not on one long one
    rows.sort(key=lambda r: (-(r[C.N_FRAMES] or 0), r[C.UTTERANCE_ID]))
    rejected_before = run.rejected_before()
    identities = speaker_identities(store, rows, config, rig_path, rig_hash, run.logger)
    calls = []          # each utterance's track_utterance call: (uid, row, its arguments)
    provenances = store.curves_provenances(PROCEDURAL, procedural_variant, [r[C.UTTERANCE_ID] for r in rows])
    for row in rows:
        uid = row[C.UTTERANCE_ID]
        provenance = provenances[uid] or ""
        row = keyed_row(store, row)
        calls.append((uid, row, (str(store.root), row, procedural_variant, provenance, str(rig_path), rig_hash,
                                 config, identities.get(uid))))
    # a cache hit must not hide deleted curves, nor curves another config wrote over (one variant folder holds the
    # curves of every flow region, preset, ...): recompute unless they are there as this call would write them (or
    # the utterance was rejected)
    variants = {uid: utterance_config(row, config).variant for uid, row, _ in calls}
    recorded = {}
    for v in set(variants.values()):
        recorded.update(store.curves_provenances(SOURCE, v, [u for u in variants if variants[u] == v]))
    present = {uid: recorded.get(uid) == tracked_provenance(row, config, identities.get(uid))
               or uid in rejected_before for uid, row, _ in calls}
    if params.joint_frames > 0 and joins(config):    # L_rgb or LM: one clip at a time, so one task each
        reports, rejects, unexpected, jointly = track_in_groups(store, calls, present, params.joint_frames,
                                                                run.logger, params.device)
    else:               # one task per utterance, each a cache hit or a solve of its own
        futures, frames = {}, {}
        for uid, row, args in calls:
            future = track_utterance.with_options(
                result_storage=result_storage(store.root), refresh_cache=not present[uid],
            ).submit(*args)
            futures[future] = uid
            frames[future] = int(row[C.N_FRAMES] or 0)
        reports, rejects, unexpected = collect_utterance_results(futures, STAGE, TrackError, run.logger, work=frames)
        jointly = 0
    replace_stage_rejects(store, STAGE, rejects, params.n_shards)
    errors = [r["mouth_error_px"] for r in reports if r.get("mouth_error_px") is not None]
    unguided = [r for r in reports if not r.get("guided", True)]
    summary = {
        "utterances": len(rows), "tracked": sum(1 for r in reports if not r["cached"]),
        "cached": sum(r["cached"] for r in reports), "rejected": len(rejects),
        "frames": sum(r["frames"] for r in reports), "unguided": len(unguided),
        "interpolated_frames": sum(r.get("interpolated_frames", 0) for r in reports),
    }
    extra = {"variant": config.variant, "jointly": jointly,
             "variants": ", ".join(sorted({r["variant"] for r in reports})) or None,
             "unguided_why": unguided_why(unguided),
             "mean_mouth_error_px": round(sum(errors) / len(errors), 3) if errors else None}
    return run.finish(summary, len(rejects), len(rows), extra=extra, unexpected=unexpected,
                      reasons=[r[C.MESSAGE] for r in rejects], title=f"track ({extra['variants'] or config.variant})")  # the modes used, not the one asked


def rerun_one(store: Store, uid: str, last: TrackSettings | None, force: bool) -> dict:
    """Track one utterance again, with the last track run's settings (else the defaults)."""
    rows = store.read_table("utterances", utterance_ids=[uid]).select(TRACK_FIELDS).to_pylist()
    if not rows:
        raise RerunError(f"{uid} is not ingested in {store.root}; see `visemeflow rejects` or rerun --stage ingest")
    if not rows[0][C.VIDEO_PATH]:
        raise RerunError(f"{uid} has no video in {store.root}: there is nothing to track")
    last = last or TrackSettings()
    rig_path, rig_hash = rig_and_hash(Path(last.rig) if last.rig else None)
    variant = procedural_variant_of(store, last.procedural_variant)
    provenance = store.curves_provenance(PROCEDURAL, variant, uid) or ""
    row, config = keyed_row(store, rows[0]), last.config      # the flow's row: the same cache key
    identity = None
    if config.speaker_identity and real_video(row[C.VIDEO_PATH]):
        # the speaker identity the track run used (cached), from the same clips of the same speaker and image size
        speaker = store.read_table("utterances", utterance_ids=[uid]).column(C.SPEAKER)[0].as_py()
        same = [r for r in store.read_table("utterances").select(TRACK_FIELDS + [C.SPEAKER]).to_pylist()
                if r[C.SPEAKER] == speaker and r[C.VIDEO_PATH]]
        peers = [{k: r[k] for k in TRACK_FIELDS} for r in same]
        identity = speaker_identities(store, peers, config, rig_path, rig_hash, logging.getLogger(__name__),
                                      submit=False).get(uid)
    task = track_utterance.with_options(result_storage=result_storage(store.root), refresh_cache=force)
    return task(str(store.root), row, variant, provenance, str(rig_path), rig_hash, config, identity)
