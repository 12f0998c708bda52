"""The `animate` flow: stored curves put on characters and exported for engines and DCC tools (paper 6), one cached
task per (utterance, character); and `speak`: audio files to talking characters in one go (predict, then animate).

Files go to `<store>/animations/<character>/<speaker>/<name>/<name>.{glb,usd,livelink.csv,web.json,wav,...}`, or
under `out` in the same layout. A character that cannot be loaded, an utterance without curves or with curves that
are NaN or outside [0, 1], unreadable audio: each is a reject row (stage `animate`) naming the utterance and file,
and the rest of the batch goes on.
"""

from __future__ import annotations

import json
from pathlib import Path

from prefect import flow, get_run_logger
from prefect.artifacts import create_markdown_artifact
from prefect.states import Failed

from visemeflow.logs import SUMMARISED
from visemeflow.flows.params import DEFAULT_STORE, SOURCES, AnimateParams, AnimateSettings, PreviewParams, SpeakParams  # noqa: F401 (re-exported)
from visemeflow.location import input_digest, input_exists, is_url, local_input
from visemeflow.rig.character import CharacterError
from visemeflow.dashboards.records import record_packages
from visemeflow.flows.errors import RerunError, StageFailed
from visemeflow.flows.common import StageRun, collect_utterance_results, replace_stage_rejects
from visemeflow.flows.runners import cpu_thread_pool
from visemeflow.atomic import atomic_path
from visemeflow.hashing import file_hash, stable_hash
from visemeflow.schemas import C, CurveSource, validate_name
from visemeflow.storage import Store
from visemeflow.tasks.animate import STAGE, AnimateError, animate_one, bound_character, \
    character_keys, claim_character_folder, content_hash, outputs_present, package_inputs
from visemeflow.tasks.common import reject_row, result_storage





def _last_written(store: Store, source: str) -> str | None:
    """The variant the stage that makes `source` curves wrote last (its run record), if any."""
    stage = {"tracked": "track", "procedural": "procedural"}.get(source)
    run = store.read_run_config(stage) if stage else None
    return run and (run.get("variant") or (run.get("config") or {}).get("variant"))


def resolve_variant(store: Store, source: str, variant: str | None) -> str:
    """The variant of `source` curves to animate: as given, the only one stored, or the one the stage last wrote."""
    if variant:
        return validate_name(variant, "variant")
    variants = store.curve_variants(source)
    if len(variants) == 1:
        return variants[0]
    last = _last_written(store, source)
    if last in variants:
        return last
    raise LookupError(f"{store.root}: {len(variants)} variants of {source} curves "
                      f"({', '.join(variants) or 'none; run the stage that makes them first'}); name one")


def variant_plan(store: Store, source: str, variant: str | None,
                 utterances: list[str] | None) -> list[tuple[str, list[str]]]:
    """Which variant of `source` curves each utterance is animated from: [(variant, utterance ids)], in order.

    `variant` is one name or several, comma-separated, in order of preference; none: every stored variant, the one
    the stage last wrote first (a tracked corpus holds `guided-fast` curves for aligned videos and
    `unguided-fast` for the others: both are animated, each utterance once). An utterance is animated from the
    first variant that has its curves; one that none has goes with the first (its task rejects it: no curves).
    """
    stored = store.curve_variants(source)
    if variant:
        order = list(dict.fromkeys(validate_name(v.strip(), "variant") for v in variant.split(",") if v.strip()))
    else:
        last = _last_written(store, source)
        order = ([last] if last in stored else []) + [v for v in stored if v != last]
    if not order:
        raise LookupError(f"{store.root}: no {source} curves; run the stage that makes them first")
    present = {v: set(store.curve_ids(source, v)) if v in stored else set() for v in order}
    wanted = utterances if utterances is not None else sorted(set().union(*present.values()))
    groups: dict[str, list[str]] = {}
    for uid in dict.fromkeys(wanted):
        groups.setdefault(next((v for v in order if uid in present[v]), order[0]), []).append(uid)
    return [(v, groups[v]) for v in order if v in groups] or [(order[0], [])]


def _phones(store: Store, utterance_ids: list[str]) -> dict[str, list[tuple[float, float, str]]]:
    table = store.read_table("phones", utterance_ids=utterance_ids) if utterance_ids else None
    out: dict[str, list] = {}
    if table is None or not table.num_rows:
        return out
    for row in table.select([C.UTTERANCE_ID, C.START_S, C.END_S, C.PHONEME]).to_pylist():
        out.setdefault(row[C.UTTERANCE_ID], []).append((row[C.START_S], row[C.END_S], row[C.PHONEME] or ""))
    return out


def phones_beside(audio: str | Path) -> list[tuple[float, float, str]] | None:
    """(start, end, label) of the phones of the alignment file lying beside a local `audio` file (`take.TextGrid`
    beside `take.wav`, as a corpus has them), or of its transcript (`take.txt`, `take.lab` without times)
    forced-aligned in English as `ingest` aligns one, for the lips count of what `speak` made of it; None where
    there is none or it cannot be read or aligned (another language, a word the dictionary lacks): the count is
    only left out."""
    from visemeflow.ingest import IngestConfig, IngestError
    from visemeflow.ingest.corpus import discover_corpus
    from visemeflow.ingest.utterance import read_alignment

    if is_url(str(audio)) or not Path(audio).is_file():
        return None
    try:
        entries = discover_corpus(Path(audio)).entries
        entry = entries[0] if entries else None
        if entry is None or not entry.alignment_path or entry.alignment_format in (None, "none"):
            return None
        alignment = read_alignment(entry, IngestConfig())
    except (IngestError, OSError, ValueError):
        return None
    return [(float(p.start_s), float(p.end_s), p.label) for p in alignment.phones] or None


def _markdown(rows: list[dict]) -> str:
    lines = ["### Animations", "", "| utterance | character | convention | frames | fps | cached | files |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        files = ", ".join(f"`{Path(p).name}`" for p in r["files"].values())
        lines.append(f"| `{r['utterance_id']}` | {r['character']} | {r['convention']} | {r['frames']} | "
                     f"{r['fps']:g} | {'yes' if r['cached'] else 'no'} | {files} |")
    return "\n".join(lines) + "\n"


@flow(name="animate", flow_run_name="animate({params.source})", task_runner=cpu_thread_pool())
def animate_flow(params: AnimateParams):
    """Export every (utterance, character) of the chosen curves; bad input becomes rejects, the rest goes on."""
    plan = variant_plan(Store(params.store), params.source, params.variant, params.utterances)
    variants = [v for v, _ in plan]
    variant_of = {uid: v for v, uids in plan for uid in uids}
    label = ", ".join(variants)
    mapping = str(params.mapping.resolve()) if params.mapping else None
    mapping_hash = file_hash(params.mapping) if params.mapping and params.mapping.is_file() else None
    run = StageRun(STAGE, params.store, AnimateSettings(
        characters=[str(p.resolve()) for p in params.characters], source=params.source, variant=variants[0],
        variants=variants, mapping=mapping, out=str(params.out) if params.out else None, n_shards=params.n_shards,
        config=params.config))
    store, logger = run.store, run.logger
    ids = list(variant_of)
    utterances = {r[C.UTTERANCE_ID]: r for r in store.read_table("utterances", utterance_ids=ids)
                  .select([C.UTTERANCE_ID, C.AUDIO_PATH]).to_pylist()} if ids else {}
    phones = _phones(store, ids)   # the lips report counts the b/p/m closed on the mesh (and the preview shows them)
    for uid, audio in params.audio.items():   # `speak`: an alignment beside the audio file counts them too
        if uid in variant_of and uid not in phones and (beside := phones_beside(audio)):
            phones[uid] = beside
    per_utterance = {}  # uid -> (audio path, its content hash, the curves' provenance): once, for every character
    for uid in ids:
        audio = params.audio.get(uid) or (utterances.get(uid) or {}).get(C.AUDIO_PATH)
        audio = str(audio) if audio and input_exists(audio) else None   # a URL stays one: its task reads it
        per_utterance[uid] = (audio, input_digest(audio) if audio else None,
                              store.curves_provenance(params.source, variant_of[uid], uid) or "")
    out = str(params.out) if params.out else None
    rejects, futures, choices = [], {}, []
    paths = [str(Path(character).resolve()) for character in params.characters]
    root = package_root(store, out)
    for path, key in zip(paths, character_keys(paths, root)):
        try:
            if mapping and not params.mapping.is_file():
                raise CharacterError(f"{params.mapping}: no such mapping CSV")
            character_hash = content_hash(path)
            loaded, _ = bound_character(path, character_hash, params.config.convention, mapping, mapping_hash,
                                        params.config.meshes)
            choices.append(loaded.describe())
            logger.info("animate: %s", choices[-1])
        except (CharacterError, OSError, MemoryError) as exc:  # the character is unusable: one reject, next one
            rejects.append(reject_row(None, STAGE, type(exc).__name__, str(exc), path))
            logger.warning("animate: %s", exc, extra=SUMMARISED)
            continue
        if root is not None:   # this character's folder now: a later run of another file of its name gets another
            claim_character_folder(root, key, path, store)
        for uid in ids:
            audio, audio_hash, provenance = per_utterance[uid]
            variant = variant_of[uid]
            inputs = package_inputs(uid, params.source, variant, provenance, character_hash, mapping_hash,
                                    params.config, audio_hash, phones.get(uid))
            present = outputs_present(store, out, key, uid, params.config, audio is not None, inputs)
            future = animate_one.with_options(result_storage=result_storage(store.root),
                                              refresh_cache=not present).submit(
                str(store.root), uid, params.source, variant, provenance, path, character_hash, key, mapping,
                mapping_hash, params.config, audio, audio_hash, out, phones.get(uid))
            futures[future] = (uid, path)
    reports, package_rejects, unexpected = collect_utterance_results(futures, STAGE, AnimateError, logger,
                                                                     unit="packages")
    rejects += package_rejects
    if out:  # packages outside the store: recorded in it, so the dashboard can list them
        record_packages(store, reports, {uid: audio for uid, (audio, _, _) in per_utterance.items()})
    with store.locked("animate-rejects"):   # two runs at once (speak batches): neither loses the other's rejects
        kept = []
        if params.utterances:   # a run of some utterances (speak, `animate ID`): the others' rejects stay until theirs
            covered = set(ids)
            kept = [r for r in store.read_table("rejects", STAGE).to_pylist()
                    if r[C.UTTERANCE_ID] is not None and r[C.UTTERANCE_ID] not in covered]
        replace_stage_rejects(store, STAGE, rejects + kept, params.n_shards)
    summary = {"packages": len(futures), "written": sum(not r["cached"] for r in reports),
               "cached": sum(r["cached"] for r in reports), "rejected": len(rejects),
               "frames": sum(r["frames"] for r in reports)}
    if reports:
        create_markdown_artifact(key="animations", markdown=_markdown(reports),
                                 description="animation packages: files per utterance and character")
    # a character that could not be loaded fails every utterance it was asked for
    lost = sum(1 for r in rejects if r[C.UTTERANCE_ID] is None) * max(len(ids), 1)
    failed = sum(1 for r in rejects if r[C.UTTERANCE_ID] is not None) + lost
    # several variants (guided and unguided tracking): the summary line names them, with how many utterances each
    used = {"variants": ", ".join(f"{v}: {len(u)}" for v, u in plan)} if len(plan) > 1 else {}
    return run.finish(summary, failed, len(futures) + lost, unexpected=unexpected,
                      title=f"animate ({params.source}/{label})", reasons=[r[C.MESSAGE] for r in rejects],
                      extra={"source": params.source, "variant": label, "characters": len(params.characters)},
                      result={**summary, "source": params.source, "variant": label, **used,
                              "characters": len(params.characters),
                              "packages_written": reports, "character_choices": choices})


@flow(name="speak", flow_run_name="speak({params.model})")
def speak_flow(params: SpeakParams):
    """Audio to talking characters: the `predict` flow, then the `animate` flow on its curves (both cached). An
    audio file `predict` rejects is left out (`audio_rejected`, `rejects`); the others are animated."""
    from visemeflow.flows.predict import PredictParams, predict_flow

    state = predict_flow(PredictParams(store=params.store, model=params.model, audio=params.audio,
                                       fps=params.fps), return_state=True)
    if state.is_failed():   # every file rejected, or an unexpected error: predict's one-line reasons, no traceback
        failure = state.result(raise_on_failure=False)
        return Failed(message=state.message, data=StageFailed(state.message, getattr(failure, "summary", {})))
    predicted = state.result()
    rows = predicted["predictions"]
    animated = animate_flow(AnimateParams(
        store=params.store, characters=params.characters, source=CurveSource.PREDICTED, variant=params.model,
        utterances=[r["utterance_id"] for r in rows], audio={r["utterance_id"]: Path(r["audio"]) for r in rows},
        mapping=params.mapping, config=params.config, out=params.out))
    return {**animated, "audio_files": predicted["files"], "audio_rejected": predicted["rejected"],
            "rejects": predicted["rejects"], "audio_of": {r["utterance_id"]: r["audio"] for r in rows}}


def preview_sources(store: Store, uid: str, sources) -> tuple[list[tuple[str, str, str]], list[str]]:
    """((spec, source, variant) of each of `sources` whose curves `uid` has, why each other one is left out): what
    the preview draws, found before it renders (the CLI asks first, so that an ambiguous variant is one line)."""
    found, skipped = [], []
    for spec in sources:
        source, _, variant = spec.partition(":")
        try:
            found.append((spec, source, _variant_of_utterance(store, source, variant or None, uid)))
        except LookupError as exc:
            skipped.append(f"{spec}: {exc}")
    return found, skipped


def _variant_of_utterance(store: Store, source: str, variant: str | None, uid: str) -> str:
    """The variant of one utterance's `source` curves: as given, its only one, or the one the stage last wrote."""
    variants = store.curve_variants(source, uid)
    if variant:
        if variant not in variants:
            raise LookupError(f"no {source} curves of variant {variant!r}")
        return variant
    if len(variants) == 1:
        return variants[0]
    if not variants:
        raise LookupError(f"no {source} curves")
    try:
        return resolve_variant(store, source, None)
    except LookupError:
        raise LookupError(f"{len(variants)} variants ({', '.join(variants)}); name one as {source}:VARIANT") from None


@flow(name="preview", flow_run_name="preview({params.utterance_id})")
def preview_flow(params: PreviewParams) -> dict:
    """Render one utterance's preview MP4: the character driven by each source side by side, labelled, the phone
    under way written under them, the audio muxed (H.264 + AAC)."""
    from visemeflow.animation.apply import check_curves, resample_visemes
    from visemeflow.animation.package import bone_rig
    from visemeflow.articulation import close_lips
    from visemeflow.animation.preview import BoneSource, render_preview, video_source
    from visemeflow.ingest.audio import read_audio
    from visemeflow.tasks.animate import curves_and_fps, fresh_work_dir, package_dir, upload_file
    from visemeflow.tasks.track import landmark_file

    store = Store(params.store)
    uid = params.utterance_id
    path = str(params.character.resolve())
    character_hash = content_hash(path)
    mapping = str(params.mapping.resolve()) if params.mapping else None
    found, skipped = preview_sources(store, uid, params.sources)
    root = package_root(store, None)
    (key,) = character_keys([path], root)
    if root is not None and not params.out:
        claim_character_folder(root, key, path, store)
    folder = package_dir(store, None, key, uid)
    out = params.out or folder / f"{folder.name}.preview.mp4"
    recorded = not (store.remote and not params.out)   # a local MP4 gets a record of what it was made from
    inputs = _preview_inputs(store, params, character_hash, file_hash(mapping) if mapping else None, found) \
        if recorded else None
    record = _preview_record(Path(out)) if recorded and not params.force else {}
    if record and Path(out).is_file() and record.get("inputs") == inputs:
        get_run_logger().info("preview %s: %s kept (made from the same inputs)", uid, out)
        return {**record["result"], "reused": True}
    character, binding = bound_character(path, character_hash, None, mapping,
                                         file_hash(mapping) if mapping else None, tuple(params.meshes))
    panels, rate, tracked = {}, None, False
    for spec, source, variant in found:
        try:
            curves, fps, curve_file = curves_and_fps(store, uid, source, variant)
        except LookupError as exc:
            skipped.append(f"{spec}: {exc}")
            continue
        tracked = tracked or source == "tracked"
        rate = rate or fps
        curves = resample_visemes(check_curves(curves, f"{uid} ({source}/{variant} curves, {curve_file})"), fps, rate)
        if params.closure_rule:
            curves = close_lips(curves)
        label = f"{source.replace('_', ' ')} ({variant})"
        if params.mode != "bones":
            panels[label] = binding.weights(curves)
        if params.mode != "blendshape":
            rig = bone_rig(character, binding, params.bones)
            panels[f"{source.replace('_', ' ')}, {params.bones} bones"] = BoneSource(rig, curves)
    if not panels:
        raise LookupError(f"{uid}: none of the sources {', '.join(params.sources)} has curves in {store.root} "
                      f"({'; '.join(skipped)})")
    rows = store.read_table("utterances", utterance_ids=[uid]).select(
        [C.UTTERANCE_ID, C.AUDIO_PATH, C.VIDEO_PATH, C.LANDMARK_PATH, C.FPS]).to_pylist()
    audio = read_audio(local_input(rows[0][C.AUDIO_PATH])) if rows and rows[0][C.AUDIO_PATH] else None
    # tracked curves are judged against the footage they came from: its face crop as the first panel
    video = video_source(local_input(rows[0][C.VIDEO_PATH]), landmark_file(store, rows[0]), rows[0][C.FPS]) \
        if tracked and rows and rows[0][C.VIDEO_PATH] else None
    phones = _phones(store, [uid]).get(uid)
    # a store on object storage: rendered into a local work folder, then uploaded in one PUT
    work = fresh_work_dir(store, folder) if store.remote and not params.out else None
    report = render_preview(work / out.name if work else out, character, panels, rate, audio=audio, phones=phones,
                            title=f"{uid} - {character.name}", size=params.size, video=video)
    if work is not None:
        out = upload_file(store, work / out.name, work, folder)
    get_run_logger().info("preview %s: %s (%d frames, %s); left out: %s", uid, out, report.frames,
                          ", ".join(panels), "; ".join(skipped) or "nothing")
    result = {"utterance_id": uid, "path": str(out), "sources": (["video"] if video is not None else []) + list(panels),
              "skipped": skipped, "character": character.describe(),
              "frames": report.frames, "fps": rate, "frames_per_second": report.frames_per_second}
    if recorded:   # the next call with these inputs keeps the MP4
        with atomic_path(_preview_record_path(Path(out))) as tmp:
            tmp.write_text(json.dumps({"inputs": inputs, "result": result}, sort_keys=True), encoding="utf-8")
    return result


def _preview_record_path(out: Path) -> Path:
    """Where `visemeflow preview` records what an MP4 was made from: a hidden file beside it."""
    return out.with_name(f".{out.name}.inputs.json")


def _preview_record(out: Path) -> dict:
    """The record beside a preview MP4 (`_preview_record_path`), {} when there is none or it is unreadable."""
    try:
        return json.loads(_preview_record_path(out).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


def _preview_inputs(store: Store, params: PreviewParams, character_hash: str, mapping_hash: str | None,
                    found: list[tuple[str, str, str]]) -> dict:
    """What decides a preview MP4: each source's curves (their provenance), the utterance's files (its content hash:
    audio, alignment, video and the landmark file beside it), its phones, the landmarks the `landmarks` stage stored,
    the character and mapping files, the settings and the code that renders."""
    from visemeflow.tasks.code_version import code_digest

    uid = params.utterance_id
    rows = store.read_table("utterances", utterance_ids=[uid]).select([C.CONTENT_HASH]).to_pylist()
    landmarks = file_hash(store.local_file(store.landmark_path(uid))) if store.has_landmarks(uid) else None

    def curves(source: str, variant: str) -> str:   # what made them, else (written without one) their bytes
        return store.curves_provenance(source, variant, uid) or \
            file_hash(store.local_file(store.curve_path(source, variant, uid)))

    return {"utterance": uid, "content": rows[0][C.CONTENT_HASH] if rows else None,
            "sources": [[spec, source, variant, curves(source, variant)] for spec, source, variant in found],
            "phones": stable_hash(_phones(store, [uid]).get(uid)),
            "landmarks": landmarks, "character": character_hash, "mapping": mapping_hash,
            "settings": stable_hash([params.size, params.mode, params.bones, list(params.meshes), params.closure_rule]),
            "code": code_digest("visemeflow.animation.preview")}


def rerun_variant(store: Store, uid: str, last: AnimateSettings | None) -> str:
    """The curve variant a rerun of `uid` animates; RerunError (one line) when there is no animate run to repeat or
    the utterance has no such curves. The command asks before it starts the flow."""
    if last is None:
        raise RerunError(f"{store.root} has no animate run to repeat; run `visemeflow animate` first")
    variants = list(dict.fromkeys([last.variant, *last.variants]))
    variant = next((v for v in variants if store.has_curves(last.source, v, uid)), None)
    if variant is None:
        raise RerunError(f"{uid} has no {last.source} curves of variant {' or '.join(map(repr, variants))} "
                         f"in {store.root}")
    return variant


def package_root(store: Store, out: str | None):
    """The folder holding the character folders of packages (`--out`, else the store's `animations`, a `UPath` on
    object storage), where each records the file it holds (`tasks.animate.claim_character_folder`); None for an
    `--out` URL."""
    if out:
        return None if is_url(out) else Path(out)
    return store.root / "animations"


def rerun_one(store: Store, uid: str, last: AnimateSettings | None, force: bool) -> dict:
    """Every character of the last animate run, for one utterance; AnimateError for bad input."""
    from visemeflow.tasks.animate import character_keys

    variant = rerun_variant(store, uid, last)
    rows = store.read_table("utterances", utterance_ids=[uid]).select([C.AUDIO_PATH]).to_pylist()
    audio = rows[0][C.AUDIO_PATH] if rows and input_exists(rows[0][C.AUDIO_PATH]) else None
    mapping = last.mapping
    phones = _phones(store, [uid]).get(uid)   # as `animate` gives them: the lips count, the same package inputs
    task = animate_one.with_options(result_storage=result_storage(store.root), refresh_cache=force)
    packages = [task(str(store.root), uid, last.source, variant,
                     store.curves_provenance(last.source, variant, uid) or "", path, content_hash(path),
                     key, mapping, file_hash(mapping) if mapping else None, last.config, audio,
                     input_digest(audio) if audio else None, last.out, phones)
                for path, key in zip(last.characters, character_keys(last.characters, package_root(store, last.out)))
                if Path(path).exists()]
    # what the viewer will miss, as `animate` lists it (the command prints these; Prefect's console leaves them out)
    warnings = [f"{uid} -> {p['character']}: {w}" for p in packages for w in p.get("warnings") or ()]
    return {"packages": len(packages), "files": sum(len(p["files"]) for p in packages), "warnings": warnings}
