"""The `visemeflow` command."""

import contextlib
import os
import sys
import tempfile
from pathlib import Path
from typing import Annotated, Optional

# Analytics in embedded mode cause "database is locked" errors; set before Prefect is imported.
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
# The embedded server's first start migrates a fresh database; on a loaded 2-core machine that takes longer than
# Prefect's 20 s default (seen in CI: "Timed out while attempting to connect to ephemeral Prefect API server").
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")

import typer  # noqa: E402

from visemeflow.cli.options import Opt, stage_command  # noqa: E402
from visemeflow.flows.params import (  # noqa: E402 (torch-free configs: a wrong argument still fails in under a second)
    DEFAULT_STORE,
    AnimateParams,
    EvaluateParams,
    ImportCurvesParams,
    IngestParams,
    LandmarksParams,
    PipelineParams,
    PredictParams,
    PreviewParams,
    ProceduralParams,
    RerunParams,
    SpeakParams,
    SweepParams,
    SynthParams,
    TrackParams,
    TrainParams,
)
from visemeflow.location import is_url, parse_root, remote_problem  # noqa: E402

FIRST_COMMANDS = ("speak", "pipeline", "predict", "animate", "train", "evaluate", "serve", "rerun", "rejects")


class _CommandsInUseOrder(typer.core.TyperGroup):
    """`visemeflow --help` lists what a new user reaches for first (`speak`, then a corpus's `pipeline`), then the
    stages in the order they are defined."""

    def list_commands(self, ctx):
        names = super().list_commands(ctx)
        return [n for n in FIRST_COMMANDS if n in names] + [n for n in names if n not in FIRST_COMMANDS]


# plain help (click's): typer's boxed style labels every flag `<bool>` as if it took a value; 100 columns leave room
# for each command's first line
app = typer.Typer(help="Audio-driven viseme curves for 3D face animation, as Prefect flows.", no_args_is_help=True,
                  rich_markup_mode=None, pretty_exceptions_enable=False, cls=_CommandsInUseOrder,
                  context_settings={"max_content_width": 100})
curves_app = typer.Typer(help="Look at stored curves and export them.", no_args_is_help=True, rich_markup_mode=None,
                         pretty_exceptions_enable=False)
app.add_typer(curves_app, name="curves")


def _print_version(value: bool) -> None:
    if value:
        from importlib.metadata import PackageNotFoundError, version

        try:
            number = version("visemeflow")
        except PackageNotFoundError:   # run from a source tree that was never installed
            from visemeflow import __version__ as number
        typer.echo(f"visemeflow {number}")
        raise typer.Exit()


@app.callback()
def _options(version: Annotated[bool, typer.Option(
        "--version", callback=_print_version, is_eager=True, help="Print the version and exit.")] = False) -> None:
    """Audio-driven viseme curves for 3D face animation, as Prefect flows."""



def _existing_store(store: Path | str) -> None:
    """A command that only reads a store: a folder that does not exist is a mistyped path, one line, not an empty
    store (a URL store's bucket was checked by `_usable_store`)."""
    if not is_url(store) and not Path(store).is_dir():
        _fail(f"no store at {store}: give the folder a pipeline wrote with --store")


def _fail(message: str) -> None:
    """A wrong argument: one line on stderr and exit 2, before any flow (and Prefect, with its temporary server) starts."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(2)


# Whether this process is the `visemeflow` command (main()), not `app` called in-process (tests, CliRunner): only
# the command chooses the Prefect API, through the environment, before it imports Prefect.
_AS_COMMAND = False
# Commands that run no flow: they neither need a Prefect API nor look one up. `serve` finds or starts its own.
_NO_FLOW = frozenset({"blender", "serve", "rejects", "clean", "dashboard", "show", "export", "export-model", "transfer",
                      "espeak-corpus"})


def _usable_store(ctx: typer.Context, store: Path | str) -> Path | str:
    """Fail before any flow starts when the store cannot be a writable folder (no side effects). Run as the command,
    for a command that runs a flow, point Prefect at a server already up (PREFECT_API_URL, else a running
    `visemeflow serve --store STORE`), else start Prefect's temporary server now, while the command imports its
    libraries, rather than when the flow is called (`visemeflow.ops.connect`). A URL store (`s3://...`): its bucket
    must answer (one request; none while the shell completes words)."""
    store = parse_root(store)
    if is_url(store):
        if ctx.resilient_parsing:
            return store
        problem = remote_problem(store)
        if problem:
            _fail(problem)
    else:
        probe, problem = _unwritable(store)
        if problem == "a file":
            _fail(f"cannot use {store} as a store: {probe} is a file, not a folder")
        if problem:
            _fail(f"cannot write the store {store}: {problem} on {probe}")
    if _AS_COMMAND and ctx.info_name not in _NO_FLOW and not ctx.resilient_parsing and "prefect" not in sys.modules:
        from visemeflow.ops.connect import use_running_api

        use_running_api(store)
    return store


def _check_paths(value: Path | list[Path] | None, what: str, kind: str = "any") -> None:
    """Each path exists and is a folder (kind "dir"), a file ("file") or either ("any"); else one line `error: ...`
    and exit 2, before any flow starts (the flow would fail the same way, but after Prefect's server is up)."""
    for path in value if isinstance(value, (list, tuple)) else [] if value is None else [value]:
        if not path.exists():
            _fail(f"{what} {path} does not exist")
        if kind == "file" and path.is_dir():
            _fail(f"{what} {path} is a folder: give the files in it ({path / '*.wav'}, or the shell's other patterns)")
        if kind == "file" and not path.is_file():
            _fail(f"{what} {path} is not a file")
        if kind == "dir" and not path.is_dir():
            _fail(f"{what} {path} is not a folder")


AUDIO_CHECKED_UP_FRONT = 100
"""Files whose headers `speak` and `predict` read before the flow; a larger batch is left to the flow's rejects."""


def _check_audio_readable(paths: list[Path]) -> None:
    """When no given audio file can be read (each judged on its header), one line and exit 2 before the model
    loads; when some can, the flow rejects the others by name and does the rest."""
    from visemeflow.ingest.audio import unreadable_reason

    local = [p for p in paths if not is_url(str(p))]
    if not local or len(local) != len(paths) or len(local) > AUDIO_CHECKED_UP_FRONT:
        return
    reasons = [(path, unreadable_reason(path)) for path in local]
    if all(reason for _, reason in reasons):
        path, reason = reasons[0]
        others = len(reasons) - 1
        more = "" if not others else " (the other file too)" if others == 1 else f" (the other {others} files too)"
        _fail(f"audio file {path}: {reason}{more}")


def _must_exist(what: str, kind: str = "any"):
    """A callback running `_check_paths` on a Path option/argument (or each of a repeated one) while parsing."""
    def check(ctx: typer.Context, value):
        if not ctx.resilient_parsing:
            _check_paths(value, what, kind)
        return value
    return check


_corpus_exists = _must_exist("corpus (a folder, a manifest CSV or one audio or video file)")


def _corpus(ctx: typer.Context, value):
    """The corpus exists and has a corpus's layout: one line and exit 2 before any flow starts, else (a single
    video, a flat folder of wavs, a binary manifest)."""
    if value is None or ctx.resilient_parsing:
        return value
    try:
        value = parse_root(value)
    except ValueError as exc:
        _fail(str(exc))
    if is_url(value):   # on object storage: its bucket answers, then its layout as a folder's (on a local mirror)
        problem = remote_problem(value)
        if problem is not None:
            _fail(problem.replace("cannot use the store", "cannot read the corpus"))
    else:
        value = _corpus_exists(ctx, value)
    if value is not None:
        from visemeflow.ingest.corpus import check_corpus

        problem = check_corpus(value)
        if problem is not None:
            _fail(problem)
    return value


_character = _must_exist("character")
_file = _must_exist("file", "file")
_path = _must_exist("path")


def _known_model(store: Path, model: str) -> None:
    """A named model must be in the store (checked before --device loads torch and before the flow starts)."""
    if model in ("default", "default-fbank", "phones"):
        return
    from visemeflow.storage import Store

    s = Store(store)
    if not s.has_model(model):
        _fail(f"no model {model!r} in {s.root} ({s.model_path(model)} missing); train one with `visemeflow train`")



StoreOpt = Annotated[str, typer.Option("--store", help="Folder of the Parquet store (a URL such as s3://bucket/prefix "
                                      "for the commands that run on object storage).", callback=_usable_store)]


def _device(device: str, precision: str | None = None) -> str:
    """The --device word, checked on this machine before any flow starts: one line and exit 2 when it has no such
    device (e.g. cuda on a CPU-only torch), or no such precision."""
    from visemeflow.learning.device import DeviceError, check_device_here

    try:
        check_device_here(device, precision)
    except DeviceError as exc:
        _fail(str(exc))
    return device.strip().lower()


def _unjoined_heartbeats() -> None:
    """Run as the command, whose process ends with its flow: no waiting for Prefect's heartbeat thread (up to 1 s)
    when the run ends (`visemeflow.ops.connect.unjoined_heartbeats`)."""
    if _AS_COMMAND:
        from visemeflow.ops.connect import unjoined_heartbeats

        unjoined_heartbeats()


def _print_stage_rejects(rejects: list[dict], store: Path, stage: str) -> None:
    """A stage's rejects of this run, one line each on stderr, and exit 1: the command did not do all it was asked."""
    for r in rejects:   # each reason starts with the file it names
        typer.echo(f"rejected {r['reason'].splitlines()[0]}", err=True)
    if rejects:
        typer.echo(f"see `visemeflow rejects --store {store} --stage {stage}`", err=True)
        raise typer.Exit(1)


# Options several stage commands share (visemeflow.cli.options: type, default and help from the params models)
STORE = Opt("store", type=str, callback=_usable_store)
STRICT = Opt(None, "--strict", type=bool, default=False,
             help="Exit 1 when any utterance is rejected (for schedulers and CI); without it a corpus stage that "
                  "finishes with some rejects exits 0 and lists them.")
SHARDS = Opt("n_shards", "--shards")
RUNNER = (Opt("runner.kind", "--runner"), Opt("runner.dask_workers"), Opt("runner.dask_address"),
          Opt("runner.threads"))
CHARACTERS = Opt("characters", "--character", repeat=True, callback=_character)
ANIMATE_OPTIONS = (Opt("config.formats", "--format"), Opt("config.mode"), Opt("config.bones"),
                   Opt("config.closure_rule"), Opt("config.meshes", "--mesh", repeat=True))
TRAIN_AUGMENT = Opt(None, "--train-augment", type=float, default=0.0,
                    help="Share of training steps whose audio gets one random volume/pitch/speed/noise change (0 = "
                         "off; at most 1).",
                    into=lambda share: {"config.train_augment": share > 0,
                                        "config.train_augment_probability": share or 0.5})


def _check_characters(characters: list[Path] | None, meshes: list[str] | None, convention: str | None = None,
                      mapping: Path | None = None, formats: tuple[str, ...] = ()) -> None:
    """Each character the user named loads (and, with --mesh, holds those meshes; with --convention or --mapping,
    binds to the visemes that way): else one line naming the file and why, exit 2, before any flow starts (an empty
    glTF or a convention the character does not use would otherwise fail every package after the predictions)."""
    from visemeflow.rig import demo_rig_path

    demo = demo_rig_path().resolve()
    named = [path for path in characters or [] if Path(path).resolve() != demo]
    if meshes and not named:
        _fail("--mesh chooses meshes of a .glb/.gltf --character")
    # a character's own names are bound too: names no convention knows were a traceback after the predictions
    binding = convention is not None or mapping is not None
    checked = [Path(path) for path in characters or [demo]] if binding else named
    if not checked:
        return
    from visemeflow.animation.load import load_bound_character
    from visemeflow.rig.character import CharacterError

    for path in checked:
        own_meshes = meshes or None if path.resolve() != demo else None
        try:
            character, _ = load_bound_character(path, convention, mapping, own_meshes)
        except (CharacterError, OSError, ValueError) as exc:
            reason = str(exc)
            for named_as in (f"{path}: ", f"{path.resolve()}: "):   # the file is named once, as the user gave it
                reason = reason.removeprefix(named_as)
            _fail(f"character {path}: {reason}")
        if "glb" in formats and character.parts and not any(part.nodes for part in character.parts):
            # the GLB's clip plays on the nodes that show the meshes: this failed after the predictions
            _fail(f"character {path}: no node of its scene shows the meshes it would drive "
                  f"({', '.join(part.name for part in character.parts)}), and a GLB's animation plays on nodes; "
                  "export the avatar with its scene, choose meshes a node shows with --mesh, or leave glb out of "
                  "--format")


def _unwritable(folder: Path) -> tuple[Path, str | None]:
    """(the nearest existing folder of `folder`, why nothing can be written there or None): "a file" where a file
    stands in the way, else the reason a file cannot be made in it (tried: a root user passes every permission
    check, yet not a read-only mount or an immutable folder)."""
    probe = Path(folder)
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.exists():
        return probe, None
    if not probe.is_dir():
        return probe, "a file"
    if not os.access(probe, os.W_OK | os.X_OK):
        return probe, "no write permission"
    try:
        with tempfile.TemporaryFile(dir=probe, prefix=".visemeflow-probe-"):
            pass
    except OSError as exc:
        return probe, (exc.strerror or str(exc)).lower()
    return probe, None


def _check_out_folder(out: Path | None) -> None:
    """--out names a folder (made when missing) where files can be written: else one line, exit 2, before the
    work."""
    if out is None or is_url(str(out)):
        return
    probe, problem = _unwritable(Path(out))
    if problem == "a file":
        where = "" if probe == Path(out) else f" {probe}"
        _fail(f"--out {out}:{where} is a file; give a folder for the output files (made when missing)")
    if problem:
        _fail(f"--out {out}: cannot write there ({problem} on {probe})")


def _check_store_has(store: Path, what: str, hint: str) -> None:
    """A stage that reads the store's utterances needs some: else one line with what to run first, exit 2."""
    from visemeflow.storage import Store

    if Store(store).read_table("utterances").num_rows == 0:
        _fail(f"no {what} in the store {store}; {hint}")


INGEST_FIRST = "run `visemeflow ingest CORPUS` or `visemeflow pipeline CORPUS` first"


def _check_corpus_change(store: Path | str, corpus: Path | str, replace: bool) -> None:
    """An ingest of another corpus than the store's, which would drop the store's utterances, is one line and exit 2
    before any flow starts (it was a Prefect ERROR log, a summary and `failed:` with the same sentence)."""
    if replace:
        return
    from visemeflow.flows.ingest import corpus_change_refusal
    from visemeflow.location import as_text
    from visemeflow.storage import Store

    problem = corpus_change_refusal(Store(store), as_text(corpus))
    if problem:
        _fail(problem)


def _check_preset(preset: str, tune_layers: int = 0) -> None:
    from visemeflow.learning.presets import get_preset

    try:
        feature = get_preset(preset).feature
    except ValueError as exc:
        _fail(f"--preset: {exc}")
    if tune_layers and feature != "whisper":
        _fail(f"--tune-layers: preset {preset!r} has no Whisper encoder to tune (its feature is {feature})")


def _check_curves(store: Path, source: str, variant: str | None, several: bool = False) -> None:
    """The store has curves of `source` (of `variant`, or of one variant when none is named; of any when `several`:
    animate takes each utterance's own, several names may be given comma-separated): else one line saying which
    curves it has and what to do, exit 2."""
    from visemeflow.flows.train import resolve_variant
    from visemeflow.storage import Store

    s = Store(store)
    stored = s.curve_variants(source)
    if not stored:
        others = [c for c in ("tracked", "procedural", "captured", "ground_truth", "predicted")
                  if c != source and s.curve_variants(c)]
        then = ", then `visemeflow track` for tracked curves" if source == "tracked" else ""
        _fail(f"no {source} curves in the store {store}; "
              + (f"it has {', '.join(others)} curves: add --source {others[0]}" if others else INGEST_FIRST + then))
    named = [v.strip() for v in (variant or "").split(",") if v.strip()] if several else [variant] if variant else []
    missing = [v for v in named if v not in stored]
    if missing:
        _fail(f"no {source} curves of variant {', '.join(missing)} in the store {store}; it has {', '.join(stored)}")
    if several:
        return
    try:
        resolve_variant(s, source, variant)
    except LookupError as exc:
        _fail(str(exc))


def _check_training_rows(store: Path, source: str, variant: str | None) -> None:
    """Some utterance of the train split has the curves `train` or `sweep` learns from: else one line saying where
    they are (the val split) and which curves could be trained on, exit 2 (it was a Prefect traceback)."""
    from visemeflow.flows.train import no_training_reason, resolve_variant
    from visemeflow.storage import Store

    s = Store(store)
    reason = no_training_reason(s, source, resolve_variant(s, source, variant))
    if reason:
        _fail(reason)


def _check_utterance_curves(store: Path, utterance_ids: list[str], sources: list[str]) -> None:
    """Each of `utterance_ids` has curves of one of `sources` (any variant) in the store: else one line naming those
    that have none, with the stored ids nearest the first, and exit 2 (not a flow that fails or a reject)."""
    from difflib import get_close_matches

    from visemeflow.storage import Store

    s = Store(store)
    missing = [u for u in utterance_ids if not any(s.curve_variants(source, u) for source in sources)]
    if not missing:
        return
    known = sorted({uid for source in sources for variant in s.curve_variants(source)
                    for uid in s.curve_ids(source, variant)})
    near = get_close_matches(missing[0], known, n=3, cutoff=0.6)
    kinds = sources[0] if len(sources) == 1 else f"{', '.join(sources[:-1])} or {sources[-1]}"
    hint = (f"did you mean {' or '.join(near)}?" if near
            else f"it has such curves of {_plural(len(known), 'utterance')}"
            + (f" ({', '.join(known[:3])}{', ...' if len(known) > 3 else ''})" if known else ""))
    _fail(f"no {kinds} curves of {', '.join(missing)} in the store {store}; {hint} (`visemeflow rejects` says why "
          "an utterance was left out)")


# summary keys printed under a clearer label, and the unit their value is in
_SUMMARY_LABELS: dict[str, tuple[str, str]] = {
    "mean_mouth_error_px": ("mean_mouth_error", "px"), "val_l1_x100": ("validation L1 x 100", ""),
    "unguided_why": ("unguided because", ""),
}


def _plural(n: int, word: str) -> str:
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def _summary_value(key: str, value: object) -> str | None:
    """A summary value as a person reads it: floats rounded (to what the measure can tell), the unit named, None
    and NaN omitted (None is the absence of a figure, not a figure): then None."""
    import math

    if value is None or (isinstance(value, float) and math.isnan(value)) or isinstance(value, (list, tuple, dict)):
        return None   # lists (packages written, character choices) are printed by their command, not as a figure
    label, unit = _SUMMARY_LABELS.get(key, (key, ""))
    if isinstance(value, bool):
        return f"{label} {'yes' if value else 'no'}"
    if not unit:
        for suffix in ("_px", "_mm", "_s"):
            if key.endswith(suffix) and isinstance(value, (int, float)):
                label, unit = key[: -len(suffix)], suffix[1:]
    if isinstance(value, float):
        text = (f"{value:.0f}" if abs(value) >= 100 else f"{value:.2f}" if abs(value) >= 1
                else f"{value:.3f}" if abs(value) >= 0.001 or value == 0 else f"{value:.2g}")   # 0.00013, not 0.000
    else:
        text = str(value)
    return f"{label} {text}" + (f" {unit}" if unit else "")


def _print_summary(title: str, summary: dict) -> None:
    """`title: key value, ...`; a stage that ran in several modes (track: guided, unguided) names the ones used in
    its title, not the one asked for."""
    summary = dict(summary)
    used = summary.pop("variants", None)
    if used:
        summary.pop("variant", None)
        title = f"{title} ({used})"
    parts = (_summary_value(k, v) for k, v in summary.items())
    typer.echo(f"{title}: " + ", ".join(p for p in parts if p is not None))


@stage_command(app, IngestParams, [
    Opt("corpus", argument=True, callback=_corpus), STORE, SHARDS, Opt("config.inventory"),
    Opt("config.phone_tiers", "--phone-tier", repeat=True), Opt("config.alignment_tolerance_s", "--tolerance"),
    Opt("config.fps"), Opt("replace"), STRICT,
])
def ingest(params: IngestParams, strict: bool) -> None:
    """Read alignments and audio into the `utterances` and `phones` tables."""
    _check_corpus_change(params.store, params.corpus, params.replace)
    from visemeflow.flows.ingest import ingest_flow

    _print_summary("ingest", ingest_flow(params))
    _print_rejects_hint(params.store, "discover", "ingest", strict=strict)



@stage_command(app, ProceduralParams, [STORE, SHARDS, Opt("config.fps"), Opt("variant"), STRICT])
def procedural(params: ProceduralParams, strict: bool) -> None:
    """Generate JALI-like procedural viseme curves for every ingested utterance."""
    _check_store_has(params.store, "ingested utterances", INGEST_FIRST)
    from visemeflow.flows.procedural import procedural_flow

    _print_summary("procedural", procedural_flow(params))
    _print_rejects_hint(params.store, "procedural", strict=strict)



@stage_command(app, TrackParams, [
    STORE, SHARDS, Opt("config.solver"), Opt("config.guidance"), Opt("config.use_rgb", "--rgb"),
    Opt("config.use_flow", "--flow"), Opt("config.flow_preset"), Opt("config.flow_max_roi_px"),
    Opt("config.flow_region"), Opt("config.speaker_identity"), Opt("joint_frames"), Opt("device"),
    Opt("rig", callback=_path),
    *RUNNER, STRICT,
])
def track(params: TrackParams, strict: bool) -> None:
    """Fit viseme curves to every ingested utterance with a video (phoneme-guided tracking, paper 4.3)."""
    _device(params.device)
    _check_store_has(params.store, "ingested utterances", INGEST_FIRST)
    from visemeflow.flows.runners import run_on_runner
    from visemeflow.flows.track import track_flow

    _print_summary("track", run_on_runner(track_flow, params))
    _print_rejects_hint(params.store, "track", strict=strict)



@stage_command(app, LandmarksParams, [
    Opt(None, name="video", argument=True, type=Optional[Path], default=None, callback=_file,
        help="One video: detect its landmarks into --out. Without it: every utterance of the store with a video and "
             "no landmark file."),
    Opt(None, "--out", type=Optional[Path], default=None, help="CSV to write for VIDEO (the .mediapipe478.csv layout)."),
    STORE, SHARDS, Opt("config.refine_landmarks", "--refine"), Opt("config.max_faces"),
    Opt("config.min_detected_share", "--min-face-share"), *RUNNER, STRICT,
])
def landmarks(params: LandmarksParams, video: Path | None, out: Path | None, strict: bool) -> None:
    """Detect face landmarks (MediaPipe FaceMesh, 478 points per frame) on one video or on the store's videos."""
    if video is None:
        _check_store_has(params.store, "ingested utterances", INGEST_FIRST)
        from visemeflow.flows.landmarks import landmarks_flow
        from visemeflow.flows.runners import run_on_runner

        _print_summary("landmarks", run_on_runner(landmarks_flow, params))
        _print_rejects_hint(params.store, "landmarks", strict=strict)
        return
    if out is None:
        _fail("--out FILE.csv is needed with a VIDEO")
    from visemeflow.tracking.facemesh import FaceMeshError, detect_clip

    try:
        result = detect_clip(video, out, params.config)
    except FaceMeshError as exc:
        _fail(str(exc))
    found = int(result.detected.sum())
    typer.echo(f"wrote {out}: {result.n_frames} frames ({result.times[0]:.3f}-{result.times[-1]:.3f} s), a face on "
               f"{found} ({100 * result.detected_share:.1f}%)"
               + (f"; {result.faces} faces seen, the largest and most central followed" if result.multi_face else ""))



@stage_command(app, PipelineParams, [
    Opt("corpus", argument=True, callback=_corpus), STORE, SHARDS, Opt("replace"), Opt("ingest.inventory"),
    Opt("ingest.phone_tiers", "--phone-tier", repeat=True), Opt("ingest.alignment_tolerance_s", "--tolerance"),
    Opt("ingest.fps"), *RUNNER,
    Opt("tracking.solver"), Opt("tracking.use_flow", "--flow"), Opt("tracking.flow_preset"),
    Opt("tracking.flow_max_roi_px"), Opt("tracking.flow_region"), Opt("tracking.speaker_identity"),
    Opt("joint_frames"), Opt("device"),
    Opt("characters", "--character", repeat=True, callback=_character), Opt("animate.formats", "--format"),
    Opt("animate.meshes", "--mesh", repeat=True), STRICT,
])
def pipeline(params: PipelineParams, strict: bool) -> None:
    """Run every stage on a corpus: ingest, procedural curves, tracking of the videos (and animation with --character)."""
    from visemeflow.flows.pipeline import pipeline_flow

    _device(params.device)
    _check_characters(params.characters, list(params.animate.meshes), params.animate.convention,
                      formats=params.animate.formats)
    _check_corpus_change(params.store, params.corpus, params.replace)
    for stage, summary in pipeline_flow(params).items():
        if stage == "animate":
            _print_packages(dict(summary))
        else:
            _print_summary(stage, summary)
    _print_outputs(params.store, strict=strict)



def _output_location(ctx: typer.Context, value):
    """An output folder or URL (`synth --out`): a URL's bucket must answer (one request), as a store's must."""
    if value is None:
        return value
    try:
        value = parse_root(value)
    except ValueError as exc:
        _fail(str(exc))
    if is_url(value) and not ctx.resilient_parsing:
        problem = remote_problem(value)
        if problem:
            _fail(problem.replace("cannot use the store", "cannot write to", 1))
    return value


@stage_command(app, SynthParams, [
    Opt("corpus", argument=True, callback=_corpus), Opt("out", type=str, callback=_output_location), STORE,
    Opt("rig", callback=_path),
    Opt("config.width"), Opt("config.height"), Opt("config.fps"), Opt("config.truth.seed"),
], prints_rejects=False)
def synth(params: SynthParams) -> None:
    """Render talking-face videos with known true viseme curves from a corpus of audio + alignments."""
    from visemeflow.flows.synth import synth_flow

    _print_summary("synth", synth_flow(params))



@app.command("espeak-corpus")
def espeak_corpus(
    out: Annotated[Path, typer.Argument(help="Folder of the corpus to write (<speaker>/<name>.wav + .TextGrid).")],
    english: Annotated[int, typer.Option(help="GRID-grammar English sentences.")] = 600,
    mandarin: Annotated[int, typer.Option(help="Mandarin pinyin sentences.")] = 400,
    seed: Annotated[int, typer.Option(help="Seed of the sentence generators.")] = 0,
) -> None:
    """Synthesise a scale corpus with espeak-ng: many voices and rates, exact phone timings as TextGrids."""
    from visemeflow.synth.espeak import EspeakUnavailableError, espeak_available
    from visemeflow.synth.sentences import write_espeak_corpus

    if not espeak_available():
        typer.echo(f"error: {EspeakUnavailableError.__doc__ or ''} Install it with: apt-get install espeak-ng", err=True)
        raise typer.Exit(2)
    ids = write_espeak_corpus(out, english, mandarin, seed)
    speakers = sorted({i.split("/")[0] for i in ids})
    typer.echo(f"espeak corpus: {len(ids)} utterances, {len(speakers)} speakers in {out}")
    typer.echo(f"next: visemeflow synth {out} --out {out}-video   (renders videos with true curves)")


@app.command()
def serve(
    store: StoreOpt = DEFAULT_STORE,
    corpus: Annotated[Optional[str], typer.Option(
        help="Corpus of the scheduled pipeline (a folder, a manifest, or its URL on object storage); default: the "
             "one the store last ingested.")] = None,
    cron: Annotated[str, typer.Option(help="Schedule of the pipeline (cron); '' for none.")] = "0 3 * * *",
    timezone: Annotated[str, typer.Option(help="Time zone of the schedule (IANA name).")] = "UTC",
    port: Annotated[int, typer.Option(help="Port of the local Prefect server started when PREFECT_API_URL is unset.")] = 4200,
    root: Annotated[Optional[list[Path]], typer.Option(
        help="Another folder flow runs may name paths under (audio, characters, takes, outputs); repeatable. "
             "The store and the corpus always are.")] = None,
) -> None:
    """Serve every stage as a Prefect deployment (the pipeline on a schedule) with the UI; Ctrl-C stops."""
    from visemeflow.ops.serve import ServerStartError, serve_stages

    try:
        serve_stages(store, (corpus if is_url(corpus) else Path(corpus)) if corpus else None, cron or None, timezone,
                     port, echo=typer.echo, roots=root or [])
    except ServerStartError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None


@stage_command(app, TrainParams, [
    STORE, Opt("config.preset"), Opt("config.epochs"), Opt("source"), Opt("variant"), Opt("model_name", "--name"),
    Opt("config.d_model"), Opt("config.dropout"), Opt("config.seed"), Opt("config.wav2vec2_model", "--wav2vec2"),
    TRAIN_AUGMENT, Opt("config.batch_size"), Opt("device"), Opt("precision"), Opt("encoder_cache_dir", "--encoder-cache"),
    Opt("config.whisper_tune_layers", "--tune-layers"), Opt("config.whisper_tune_lr", "--tune-lr"),
], prints_rejects=False)
def train(params: TrainParams) -> None:
    """Train an audio-to-curves model on the store's curves; a killed run resumes from its last epoch."""
    _device(params.device, params.precision)
    _check_preset(params.config.preset, params.config.whisper_tune_layers)
    _check_curves(params.store, params.source, params.variant)
    _check_training_rows(params.store, params.source, params.variant)
    from visemeflow.flows.train import train_flow

    report = train_flow(params)
    # `train`/`val` count utterances; the model file goes last, on its own line, as what to use next
    names = {"train": "training_utterances", "val": "validation_utterances"}
    path = report.get("path")
    _print_summary("train", {names.get(k, k): v for k, v in report.items() if k != "path"})
    if path:
        typer.echo(f"model: {path} (use it with --model {report['model']})")
    if report.get("val") == 0:
        typer.echo("note: no validation utterance (ingest puts about 10% of the ids in the `val` split by a hash of "
                   "each id; a manifest's `split` column chooses): `evaluate` and `sweep` judge on that split", err=True)



@stage_command(app, SweepParams, [
    STORE, Opt("config.preset"), Opt("sizes"), Opt("steps"), Opt("source"), Opt("variant"), Opt("config.d_model"),
    *RUNNER, Opt("config.batch_size"), Opt("device"), Opt("precision"), Opt("encoder_cache_dir", "--encoder-cache"),
], prints_rejects=False)
def sweep(params: SweepParams) -> None:
    """Train one preset on nested subsets of the training set and plot validation L1 x 100 by size (paper Fig. 5)."""
    _device(params.device, params.precision)
    _check_preset(params.config.preset)
    _check_curves(params.store, params.source, params.variant)
    _check_training_rows(params.store, params.source, params.variant)
    from visemeflow.flows.runners import run_on_runner
    from visemeflow.flows.sweep import sweep_flow

    result = run_on_runner(sweep_flow, params)
    for size, value in result["points"]:
        typer.echo(f"{size:>6} training utterances: validation L1 x 100 = {value:.3f}")
    typer.echo(f"plot: {result['plot']}")



def _print_evaluation(result: dict) -> None:
    """The robustness table as a terminal reads it: one row per model with its kind, baselines labelled as such
    (a mean curve is a reference to beat, not a result, though its b/p/m top-viseme score can be 100%), L1 x 100
    rounded, and the b/p/m closure on the mesh where measured; the full table (real-speech and lip columns, 13
    and more) is the markdown file named last."""
    import math

    from visemeflow.learning.robustness_table import lip_metrics, table_columns

    table = result["table"]
    conditions = table_columns(table)[1:]
    lips = "lip_closed" in lip_metrics(table)

    def num(value: float | None, digits: int = 2) -> str:
        return "-" if value is None or math.isnan(value) else f"{value:.{digits}f}"

    rows = [["model", "kind", "validation", *conditions] + (["b/p/m lips closed"] if lips else [])]
    for r in table:
        kind = (r["preset"] or "-") + (", baseline" if r["group"].startswith("baselines") else "")
        cells = [r["model"], kind, num(r["validation"])]
        cells += [f"{num(r.get(c))} ({num(r.get(f'ratio_{c}'))}x)" for c in conditions]
        if lips:
            closed = r.get("lip_closed_validation")
            cells.append("-" if closed is None or math.isnan(closed) else f"{closed:.0f}%")
        rows.append(cells)
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    n = result["validation_utterances"]
    typer.echo(f"Validation L1 x 100 on {_plural(n, 'utterance')} ({result['source']}/"
               f"{result['variant']}), lower is better; in brackets: ratio to validation")
    for row in rows:
        typer.echo("  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip())
    if any(r["group"].startswith("baselines") for r in table):
        typer.echo("baseline: a reference a trained model should beat (e.g. the training set's mean curve), not a "
                   "result")
    if lips:
        typer.echo("b/p/m lips closed: of the validation set's b/p/m phones, the share at which the model's curves "
                   "close\n  the demo character's lips below 1.5 mm on its mesh. A model trained for a few epochs on a "
                   "few utterances\n  (the demo's) rarely does; `speak` without --model uses the shipped default")
    typer.echo(f"full table (every condition, real-speech and lip metrics): {result['markdown']} "
               f"(CSV: {result['csv']})")


@stage_command(app, EvaluateParams, [
    Opt("models"), STORE, Opt("conditions"), Opt("seed"), Opt("source"), Opt("variant"), Opt("device"),
])
def evaluate(params: EvaluateParams) -> None:
    """Judge models on the validation set and on copies augmented in volume, pitch, speed and noise (paper 5.2)."""
    _device(params.device)
    for model in params.models:
        _known_model(params.store, model)
    from visemeflow.flows.evaluate import evaluate_flow

    result = evaluate_flow(params)
    _print_evaluation(result)
    typer.echo(f"evaluate: {len(result['models'])} of {len(params.models)} models judged, "
               f"{result['rejected']} rejected")
    _print_stage_rejects(result["rejects"], params.store, "evaluate")



@stage_command(app, PredictParams, [
    Opt("audio", argument=True, repeat=True), Opt("model"), STORE, Opt("fps"), Opt("out"),
    Opt("device"),
])
def predict(params: PredictParams) -> None:
    """Predict viseme curves from audio with a trained model; curves go to the store (source predicted).

    Runs the `predict` flow: one cached task per file (keyed on the model's and the audio's content hashes, not
    on the device), a markdown artifact with the outputs and real-time factors.
    """
    _known_model(params.store, params.model)
    _check_paths(params.audio, "audio file", "file")
    _check_audio_readable(params.audio)
    _device(params.device)
    from visemeflow.flows.predict import predict_flow

    _unjoined_heartbeats()
    result = predict_flow(params)
    for r in result["predictions"]:
        speed = f"real-time factor {r['real_time_factor']:.2g}"
        typer.echo(f"{r['audio']}: {r['frames']} frames -> {r['utterance_id']} "
                   + (f"(cached; computed at {speed})" if r["cached"] else f"({speed})"))
        for path in r["exports"]:
            typer.echo(f"wrote {path}")
    files = result["files"]
    typer.echo(f"predict: {_plural(files, 'file')}, {result['predicted']} predicted, "
               f"{result['cached']} cached, {result['rejected']} rejected")
    done = [r for r in result["predictions"] if not r["exports"]]
    if done:   # no --out: say where the curves are and how to get them out
        typer.echo(f"the curves are in the store {params.store} (source predicted, variant {params.model}): "
                   f"`visemeflow curves export {done[0]['utterance_id']} --source predicted --variant {params.model} "
                   f"--store {params.store} --out FILE.csv`, or predict with --out DIR (CSV and JSON), or `visemeflow "
                   "speak` for a character")
    _print_stage_rejects(result["rejects"], params.store, "predict")



def _animations_line(title: str, result: dict) -> str:
    """The summary line of animate and speak in words: what was animated, what was written, reused, rejected.
    `speak: 2 audio files on 1 character (model default): 1 animation written, 1 reused from the store, 1 audio
    file rejected; 580 frames`."""
    done = [f"{_plural(result.get('written', 0), 'animation')} written"]
    if result.get("cached"):
        done.append(f"{result['cached']} reused from the store (cached)")
    if result.get("rejected"):
        done.append(f"{result['rejected']} rejected")
    if result.get("audio_rejected"):
        done.append(f"{_plural(result['audio_rejected'], 'audio file')} rejected")
    characters = result.get("characters")
    on = f" on {_plural(characters, 'character')}" if characters else ""
    if "audio_files" in result:
        what = f"{_plural(result['audio_files'], 'audio file')}{on} (model {result.get('variant')})"
    else:
        curves = f"{result.get('source')}/{result.get('variants') or result.get('variant')} curves"
        what = f"{_plural(result.get('packages', 0), 'animation')} of {curves}{on}"
    return f"{title}: {what}: " + ", ".join(done) + f"; {_plural(result.get('frames', 0), 'frame')}"


def _print_packages(result: dict, title: str = "animate") -> None:
    packages = result.pop("packages_written", [])
    audio_of = result.pop("audio_of", {})   # speak: the file each take came from
    for choice in result.pop("character_choices", []):
        typer.echo(choice)
    typer.echo(_animations_line(title, result))
    for report in packages:
        cached = " (cached)" if report.get("cached") else ""
        uid, audio = report["utterance_id"], audio_of.get(report["utterance_id"])
        # files of one name get ids with a hash (predict/take-1afb83b6): say which file each is
        source = f" ({audio})" if audio and uid != f"predict/{Path(audio).stem}" else ""
        typer.echo(f"{uid}{source} -> {report['character']} [{report['convention']}], "
                   f"{report['frames']} frames at {report['fps']:g} fps{cached}:")
        for path in report["files"].values():
            typer.echo(f"  {path}")
        lips = report.get("lips") or {}
        if lips.get("bilabials"):
            typer.echo(f"  lips on the mesh: {lips['closed']} of {lips['bilabials']} b/p/m closed below 1.5 mm "
                       f"(median gap {lips['median_gap_mm']:.1f} mm)")
        if lips.get("warning"):
            typer.echo(f"  warning: {lips['warning']}", err=True)
        for warning in report.get("warnings") or ():   # e.g. a preview without its unreadable source video
            typer.echo(f"  warning: {warning}", err=True)
    uncounted = [r for r in packages if (r.get("lips") or {}) and "bilabials" not in r["lips"]]
    if title == "speak" and uncounted:   # no phones known for these takes: how to get the count
        typer.echo(f"lips on the mesh: b/p/m closures not counted for {_plural(len(uncounted), 'package')} (no "
                   "phones known): put an alignment (NAME.TextGrid) or an English transcript (NAME.txt) beside "
                   "the audio to count them")


@stage_command(app, ImportCurvesParams, [
    Opt("takes", argument=True, callback=_path), STORE, SHARDS, Opt("channel_table", callback=_file),
    Opt("names", callback=_file), Opt("config.fps"), Opt("config.variant"),
    Opt("config.max_drift_frames_per_s", "--max-drift"), Opt("config.val_fraction"), STRICT,
], name="import-curves")
def import_curves(params: ImportCurvesParams, strict: bool) -> None:
    """Import captured animation (Live Link Face CSV, channel CSV/NPY) as `captured` viseme curves of real speech.

    ARKit weights become the 16 visemes by a per-frame non-negative least-squares fit through the ICT face; each take
    is an utterance (no alignment) with its audio, ready for `visemeflow train --source captured`.
    """
    from visemeflow.flows.import_curves import import_curves_flow
    from visemeflow.ingest.captured import check_takes

    try:
        check_takes(params.takes)
    except ValueError as exc:
        _fail(str(exc))
    result = dict(import_curves_flow(params))
    reports = result.pop("takes_report", [])
    _print_summary("import-curves", result)
    for r in reports[:20]:
        parts = (_summary_value(k, v) for k, v in r.items() if k != "utterance_id")
        typer.echo(f"  {r.get('utterance_id')}: " + ", ".join(p for p in parts if p is not None))
    _print_rejects_hint(params.store, "import_curves", strict=strict)



@app.command("transfer")
def transfer(
    template: Annotated[Path, typer.Option("--template", help="Viseme rig or character (folder, .glb, .npz) whose shapes are transferred.", callback=_path)],
    target: Annotated[Path, typer.Option("--target", help="The new character's neutral mesh (.obj, .ply, .glb).", callback=_path)],
    out: Annotated[Path, typer.Option("--out", help="The character GLB to write.")],
    markers: Annotated[Optional[Path], typer.Option("--markers", help="CSV template_vertex,target_vertex; default: TARGET.landmarks.json beside the target, else (another topology) found by MediaPipe FaceMesh on renders of both meshes.", callback=_file)] = None,
    no_parts: Annotated[bool, typer.Option("--no-parts", help="Leave out the template's mouth interior and eyes on a target of another topology.")] = False,
) -> None:
    """Deformation transfer (Sumner and Popovic 2004) of the template's visemes onto a new neutral mesh."""
    from visemeflow.authoring.transfer import TransferError, transfer_command

    try:
        report = transfer_command(template, target, markers, out, carry_parts=not no_parts)
    except TransferError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    typer.echo(str(report))
    typer.echo(f"wrote {out}")


@stage_command(app, AnimateParams, [
    Opt("utterances", argument=True, repeat=True), CHARACTERS, STORE, Opt("source"), Opt("variant"), *ANIMATE_OPTIONS,
    Opt("config.fps"), Opt("config.convention"), Opt("mapping", callback=_file), Opt("config.preview"), Opt("out"),
    STRICT,
])
def animate(params: AnimateParams, strict: bool) -> None:
    """Put stored curves on characters and export them: glTF (GLB), USD, Live Link Face CSV, web JSON, the audio.

    Runs the `animate` flow: one cached task per (utterance, character); bad input becomes rejects.
    """
    _check_characters(params.characters, list(params.config.meshes), params.config.convention, params.mapping,
                      formats=params.config.formats)
    _check_out_folder(params.out)
    _check_curves(params.store, params.source, params.variant, several=True)
    if params.utterances:
        _check_utterance_curves(params.store, list(params.utterances), [params.source])
    from visemeflow.flows.animate import animate_flow

    _print_packages(dict(animate_flow(params)))
    _print_rejects_hint(params.store, "animate", strict=strict)


@stage_command(app, SpeakParams, [
    Opt("audio", argument=True, repeat=True), Opt("model"), CHARACTERS, STORE, *ANIMATE_OPTIONS,
    Opt("fps"), Opt("config.convention"), Opt("mapping", callback=_file),
    Opt("config.preview", help="Also render <name>.mp4 (the character speaking, with the audio)."), Opt("out"),
])
def speak(params: SpeakParams) -> None:
    """From audio to talking characters in one command: predict the curves, then animate them (the `speak` flow)."""
    _known_model(params.store, params.model)
    _check_paths(params.audio, "audio file", "file")
    _check_characters(params.characters, list(params.config.meshes), params.config.convention, params.mapping,
                      formats=params.config.formats)
    _check_out_folder(params.out)
    _check_audio_readable(params.audio)
    from visemeflow.flows.animate import speak_flow

    _unjoined_heartbeats()

    result = dict(speak_flow(params))
    audio_rejects = result.pop("rejects")
    _print_packages(result, "speak")
    for r in audio_rejects:
        typer.echo(f"rejected {r['reason'].splitlines()[0]}", err=True)
    _print_rejects_hint(params.store, "animate")
    if audio_rejects or result["rejected"]:   # an audio file or a package left out: the command did not do it all
        raise typer.Exit(1)



@stage_command(app, PreviewParams, [
    Opt("utterance_id", argument=True), Opt("character", callback=_character), Opt("sources"), STORE,
    Opt("mapping", callback=_file), Opt("size"), Opt("out"), Opt("mode"), Opt("bones"), Opt("closure_rule"),
    Opt("meshes", "--mesh", repeat=True), Opt("force"),
], name="preview", prints_rejects=False)
def preview_command(params: PreviewParams) -> None:
    """Render an MP4 of the character's face driven by each source, side by side, with the audio and the phones."""
    from visemeflow.flows.animate import preview_flow

    _existing_store(params.store)
    _check_utterance_curves(params.store, [params.utterance_id],   # a source may name its variant: tracked:guided-fast
                            list(dict.fromkeys(spec.partition(":")[0] for spec in params.sources)))
    from visemeflow.flows.animate import preview_sources
    from visemeflow.storage import Store

    found, skipped = preview_sources(Store(params.store), params.utterance_id, params.sources)
    if not found:   # curves there, but none the preview can choose (several variants, none named)
        _fail(f"{params.utterance_id}: no source to preview: {'; '.join(skipped)}")
    _check_characters([params.character], params.meshes)
    result = preview_flow(params)
    typer.echo(result["character"])
    for skipped in result["skipped"]:
        typer.echo(f"left out {skipped}")
    if result.get("reused"):
        typer.echo(f"kept {result['path']} ({result['frames']} frames at {result['fps']:g} fps; "
                   f"{', '.join(result['sources'])}): made from the same curves, character and settings; --force "
                   "renders it again")
        return
    typer.echo(f"wrote {result['path']} ({result['frames']} frames at {result['fps']:g} fps; "
               f"{', '.join(result['sources'])}; rendered at {result['frames_per_second']:.1f} frames/s)")



@app.command("blender")
def blender_command(
    animation: Annotated[Path, typer.Argument(help="A GLB or USD that `animate` or `speak` wrote; the .wav of the same "
                                                   "name beside it is its sound.")],
    save: Annotated[Optional[Path], typer.Option("--save", help="Write the scene as this .blend, without Blender's "
                                                                "window.")] = None,
    wav: Annotated[Optional[Path], typer.Option("--wav", help="The sound, when not the .wav beside the file.")] = None,
    blender: Annotated[Optional[str], typer.Option("--blender", help="The Blender program, or a Python with the bpy "
                                                                     "module (default: $VISEMEFLOW_BLENDER, else "
                                                                     "`blender` on PATH).")] = None,
) -> None:
    """Open an animation in Blender ready to play: the file's frame rate and frame range, its sound in the sequencer."""
    from visemeflow.animation.blender import BlenderError, open_in_blender

    try:
        run = open_in_blender(animation, save=save, wav=wav, blender=blender)
    except BlenderError as exc:
        _fail(str(exc))
    r = run.report
    if r.get("saved"):
        typer.echo(f"wrote {r['saved']}: {', '.join(r['objects'])}; {r['fps']:g} fps, frames {r['frame_start']}-"
                   f"{r['frame_end']}; " + (f"sound {r['sound']}" if r["sound"] else "no sound (no .wav beside it)"))


@app.command("export-model")
def export_model(
    model: Annotated[str, typer.Argument(help="Model name in the store (`default`: the shipped model).")],
    out: Annotated[Path, typer.Option("--out", help="Output file (.onnx).")],
    store: StoreOpt = DEFAULT_STORE,
    format: Annotated[str, typer.Option("--format", help="onnx (what Unity Sentis and Unreal NNE load).")] = "onnx",
    opset: Annotated[int, typer.Option(help="ONNX opset (15 for Unity Sentis before 2.6).")] = 17,
    sample_rate: Annotated[int, typer.Option(help="Rate of the graph's audio input (mono float32).")] = 16000,
    fps: Annotated[Optional[float], typer.Option(help="Curve frame rate; default: the model's own.")] = None,
    check: Annotated[bool, typer.Option(help="Run the graph with onnxruntime and compare with torch (1e-4; 1e-3 for Whisper models); a graph that fails replaces no file.")] = True,
) -> None:
    """Export a trained model for engines: an ONNX graph, audio samples in, (1, frames, 16) curves out."""
    from visemeflow.learning.default_model import is_shipped, shipped_model_path
    from visemeflow.storage import Store

    if format != "onnx":
        typer.echo(f"error: unknown format {format!r}; use onnx", err=True)
        raise typer.Exit(2)
    s = Store(store)
    if s.has_model(model):
        path = Path(s.model_file(model))   # on object storage: a local copy named by the object's version
    elif is_shipped(model):
        path = shipped_model_path(model)
    else:
        typer.echo(f"error: no model {model!r} in {s.root} ({s.model_path(model)} missing)", err=True)
        raise typer.Exit(2)
    try:
        from visemeflow.learning.onnx_export import OnnxExportError, export_onnx
    except ImportError as exc:
        typer.echo(f"error: {exc}; install the onnx extra: pip install 'visemeflow[onnx]'", err=True)
        raise typer.Exit(2) from None
    try:
        report = export_onnx(path, out, opset=opset, sample_rate=sample_rate, fps=fps, check=check)
    except OnnxExportError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    checked = f", onnxruntime vs torch max |diff| {report.max_abs_diff:.1e}" if report.max_abs_diff is not None else ""
    typer.echo(f"wrote {report.path} ({report.size_bytes / 1e6:.2f} MB, opset {report.opset}, {report.preset}, "
               f"audio {report.sample_rate} Hz mono -> curves at {report.fps:g} fps{checked})")


@stage_command(app, RerunParams, [
    Opt("utterance_id", argument=True), Opt("stage"), STORE, Opt("force"),
])
def rerun(params: RerunParams) -> None:
    """Rerun one utterance through one stage, with the settings that stage last ran with."""
    _existing_store(params.store)   # every stage reruns what a run wrote into a store
    from visemeflow.flows.errors import RerunError
    from visemeflow.storage import Store

    uid, store = params.utterance_id, Store(params.store)
    predicted = (f"{uid} was made by `visemeflow predict` or `speak` from an audio file, not ingested from a corpus: "
                 "run that command on the audio again (its curves come back from the store's cache)"
                 if uid.startswith("predict/") and store.curve_variants("predicted", uid) else None)
    if params.stage == "ingest":   # an utterance ingest rejected can be ingested again, once its files are fixed
        from visemeflow.flows.common import last_settings
        from visemeflow.flows.ingest import rerun_entry

        try:
            rerun_entry(store, uid, last_settings(store, "ingest"))
        except RerunError as exc:
            _fail(predicted or str(exc))
    else:
        from visemeflow.flows.stages import stage_named
        from visemeflow.schemas import C

        row = store.read_table("utterances", utterance_ids=[uid])
        if row.num_rows == 0:
            _fail(predicted or f"no utterance {uid} in the store {params.store} (`visemeflow rejects` says why an "
                               f"utterance was left out; `rerun {uid} --stage ingest` reads it again)")
        if stage_named(params.stage).needs_video and not row.column(C.VIDEO_PATH)[0].as_py():
            _fail(f"{params.utterance_id} has no video (its corpus gave audio only): the {params.stage} stage works on "
                  "video; its curves come from the procedural stage (`--stage procedural`)")
        if params.stage == "animate":   # asked here: raised inside the flow, Prefect logs it with its traceback
            from visemeflow.flows.animate import rerun_variant
            from visemeflow.flows.common import last_settings

            try:
                rerun_variant(store, uid, last_settings(store, "animate"))
            except RerunError as exc:
                _fail(str(exc))
    from visemeflow.flows.rerun import rerun_flow

    _unjoined_heartbeats()

    report = dict(rerun_flow(params))
    warnings = report.pop("warnings", None) or ()   # animate's packages: what the viewer will miss
    _print_summary(f"rerun {params.stage} {params.utterance_id}", report)
    for warning in warnings:
        typer.echo(f"warning: {warning}", err=True)
    if not report.get("rejected"):
        _print_next_reruns(store, uid, params.stage)
    if report.get("rejected"):   # still bad input: its reason, and exit 1 (the utterance was not made)
        from visemeflow.schemas import C
        from visemeflow.storage import Store

        rows = [{"reason": r[C.MESSAGE]} for r in Store(params.store).read_table("rejects", params.stage).to_pylist()
                if r[C.UTTERANCE_ID] == params.utterance_id]
        _print_stage_rejects(rows or [{"reason": f"{params.utterance_id}: rejected again"}], params.store,
                             params.stage)



@app.command()
def rejects(store: StoreOpt = DEFAULT_STORE, stage: Annotated[Optional[str], typer.Option(
        help="Only this stage's rejects (discover, ingest, procedural, landmarks, track, animate, predict, "
             "evaluate, import_curves); default: every stage's.")] = None,
        full: Annotated[bool, typer.Option("--full", help="Each reason whole: an unexpected error's traceback "
                                                          "too (default: its first line).")] = False) -> None:
    """List rejected inputs with their reasons."""
    from visemeflow.storage import Store

    _existing_store(store)
    table = Store(store).read_table("rejects", stage)
    if table.num_rows == 0:
        typer.echo("no rejects")
        return
    held = 0
    for r in table.to_pylist():
        message = r["message"] or ""
        first, _, rest = message.partition("\n")
        typer.echo(f"[{r['stage']}] {r['error_type']}: {message if full else first}")
        held += bool(rest.strip()) and not full
    if held:
        verb = "goes" if held == 1 else "go"
        typer.echo(f"{held} reason{'s' if held != 1 else ''} {verb} on over more lines (a traceback): --full shows "
                   "them")


@app.command()
def clean(
    kinds: Annotated[Optional[list[str]], typer.Argument(
        help="What to remove: temporary, augmented, checkpoints, results (several allowed). None: only list.")] = None,
    store: StoreOpt = DEFAULT_STORE,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="List what would be removed; remove nothing.")] = False,
) -> None:
    """Reclaim disk: data the flows can make again (never curves, tables, models or metrics).

    temporary: files of killed writers (on object storage: their unfinished uploads); augmented: evaluate's augmented audio (written again when needed);
    checkpoints: of models whose training finished; results: Prefect's cached task results (the next run of
    every stage then recomputes its tasks once). Run it while no flow writes to the store.
    """
    from visemeflow.ops.clean import KINDS, clean as remove, human_bytes, reclaimable
    from visemeflow.storage import Store

    unknown = sorted(set(kinds or []) - set(KINDS))
    if unknown:
        _fail(f"unknown kind {', '.join(unknown)}; choose from {', '.join(KINDS)}")
    _existing_store(store)
    s = Store(store)
    chosen = [k for k in KINDS if k in (kinds or [])]
    listing = not chosen or dry_run
    items = reclaimable(s, chosen or KINDS) if listing else remove(s, chosen)
    verb = "reclaimable" if listing else "removed"
    for item in items:
        what = f"{item.count} {'item' if item.uploads else 'path'}{'' if item.count == 1 else 's'}"
        if item.uploads:
            what += f" (of which {len(item.uploads)} unfinished upload{'' if len(item.uploads) == 1 else 's'})"
        typer.echo(f"{item.kind:12s} {human_bytes(item.n_bytes):>10s} {verb} in {what}")
    if not chosen:
        typer.echo(f"nothing removed; name the kinds to remove, e.g. visemeflow clean augmented --store {store}")


_CURVE_SOURCES_HELP = ("Which curves: procedural, tracked, predicted, ground_truth or captured "
                       "(`visemeflow curves list` says which the store has).")


def _load_curves(utterance_id: str, store: Path, source: str, variant: str | None):
    from visemeflow.storage import Store

    try:
        return Store(store).read_curves(utterance_id, source, variant)
    except LookupError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None


def _print_next_reruns(store, uid: str, stage: str) -> None:
    """After a rerun, the later stages that still hold what the earlier output made (`rerun --stage ingest` alone
    left the utterance without curves, and nothing said so); those on video only when it has one."""
    from visemeflow.flows.stages import later_stages
    from visemeflow.schemas import C

    later = later_stages(stage)
    if not later:
        return
    rows = store.read_table("utterances", utterance_ids=[uid]).select([C.VIDEO_PATH]).to_pylist()
    video = bool(rows and rows[0][C.VIDEO_PATH])
    names = [s.name for s in later if video or not s.needs_video]
    if names:
        typer.echo("next, for its later stages: " + "; ".join(
            f"visemeflow rerun {uid} --stage {s} --store {store.root}" for s in names))


@curves_app.command("list")
def curves_list(store: StoreOpt = DEFAULT_STORE) -> None:
    """Which curves the store holds: each source and variant, with how many utterances have them."""
    from visemeflow.storage import Store

    _existing_store(store)
    s = Store(store)
    sets = s.curve_sets()
    if not sets:
        typer.echo(f"no curves in {store}")
    current = set(s.read_table("utterances").column("utterance_id").to_pylist()) if sets else set()
    for source, variant in sets:
        ids = s.curve_ids(source, variant)
        stale = [u for u in ids if current and u not in current and not u.startswith("predict/")]
        n = len(ids)
        typer.echo(f"{source:<13}{variant:<24}{n} utterance{'s' if n != 1 else ''}"
                   + (f" ({len(stale)} of them no longer in the store's utterances, e.g. {stale[0]}: rejected or "
                      "gone from the corpus since; `visemeflow rejects`)" if stale else ""))


def _stale_curves_warning(store: Path, utterance_id: str) -> None:
    """A warning on stderr when `utterance_id` has curves but is no longer in the store's utterances (a later ingest
    rejected it, or its files left the corpus): its curves are an earlier run's."""
    from visemeflow.schemas import C
    from visemeflow.storage import Store

    if utterance_id.startswith("predict/"):      # `predict` on an audio file: never in the corpus tables
        return
    s = Store(store)
    ids = s.read_table("utterances").column(C.UTTERANCE_ID).to_pylist()
    if not ids or utterance_id in ids:           # no corpus ingested (curves written or imported as they are)
        return
    reasons = [r[C.MESSAGE] for r in s.read_table("rejects").to_pylist() if r[C.UTTERANCE_ID] == utterance_id]
    why = f"rejected since: {reasons[0].splitlines()[0]}" if reasons else "gone from the corpus since"
    typer.echo(f"warning: {utterance_id} is no longer in the store's utterances ({why}); these curves are from an "
               "earlier run", err=True)


@curves_app.command("show")
def curves_show(
    utterance_id: str, store: StoreOpt = DEFAULT_STORE,
    source: Annotated[str, typer.Option(help=_CURVE_SOURCES_HELP)] = "procedural",
    variant: Annotated[Optional[str], typer.Option(
        help="Variant of those curves (a model's name for predicted); may be omitted when only one exists.")] = None,
) -> None:
    """Print a short summary of one utterance's curves."""
    import numpy as np

    from visemeflow.schemas import C, curves_array
    from visemeflow.visemes import VISEMES

    table = _load_curves(utterance_id, store, source, variant)
    _stale_curves_warning(store, utterance_id)
    curves = curves_array(table)
    times = table.column(C.TIME_S).to_numpy()
    variant_name = table.column(C.VARIANT)[0].as_py()
    duration = times[-1] if len(times) else 0.0
    typer.echo(f"{utterance_id}  source {source}  variant {variant_name}  {len(curves)} frames  {duration:.2f} s")
    top = np.argmax(curves, axis=1)
    active = curves.max(axis=1) > 0.05
    typer.echo(f"{'viseme':<7}{'max':>6}{'mean':>7}{'frames on top':>15}")
    for i, v in enumerate(VISEMES):
        typer.echo(f"{v:<7}{curves[:, i].max():6.2f}{curves[:, i].mean():7.3f}{int(((top == i) & active).sum()):15d}")


@curves_app.command("export")
def curves_export(
    utterance_id: str, store: StoreOpt = DEFAULT_STORE,
    source: Annotated[str, typer.Option(help=_CURVE_SOURCES_HELP)] = "procedural",
    variant: Annotated[Optional[str], typer.Option(
        help="Variant of those curves (a model's name for predicted); may be omitted when only one exists.")] = None,
    format: Annotated[str, typer.Option("--format", help="csv or json.")] = "csv",
    out: Annotated[Optional[Path], typer.Option(help="Output file; default: standard output.")] = None,
) -> None:
    """Write one utterance's curves as CSV (one row per frame) or JSON (one list per viseme)."""
    from visemeflow.animation.export import FORMATS, CurveTrack, export_text, write_export
    from visemeflow.schemas import C, curves_array

    if format not in FORMATS:
        typer.echo(f"error: unknown format {format!r}; use csv or json", err=True)
        raise typer.Exit(2)
    table = _load_curves(utterance_id, store, source, variant)
    _stale_curves_warning(store, utterance_id)
    track = CurveTrack(utterance_id, source, table.column(C.VARIANT)[0].as_py(), curves_array(table),
                       table.column(C.TIME_S).to_numpy(), table.column(C.FRAME).to_numpy())
    if out is None:
        sys.stdout.write(export_text(track, format))
    else:
        write_export(track, out, format)
        typer.echo(f"wrote {out}")


def _print_rejects_hint(store: Path, *stages: str, strict: bool = False) -> None:
    """The first rejects (of `stages`, the ones this command runs; of every stage when none is named), one line
    each (utterance, file, reason), what to do about the usual ones, and where the rest are: the reason is on the
    terminal without a second command, and an earlier stage's rejects are not repeated by a later one's command.
    `strict` (the commands' --strict): exit 1 after the list when there is any."""
    from visemeflow.ingest.hints import reject_advice, reject_lines
    from visemeflow.storage import Store

    s = Store(store)
    rows = [r for stage in stages for r in s.read_table("rejects", stage).to_pylist()] if stages \
        else s.read_table("rejects").to_pylist()
    if rows:
        typer.echo(f"{len(rows)} rejected:")
        for line in reject_lines(rows) + [f"hint: {a}" for a in reject_advice(rows)]:
            typer.echo(line)
        only = f" --stage {stages[0]}" if len(stages) == 1 else ""
        typer.echo(f"all of them: `visemeflow rejects --store {store}{only}`")
        if strict:
            typer.echo(f"--strict: {len(rows)} rejected, exit 1", err=True)
            raise typer.Exit(1)


def _print_outputs(store: Path, strict: bool = False) -> None:
    from visemeflow.storage import Store

    s = Store(store)
    utterances = s.read_table("utterances").num_rows
    typer.echo(f"store: {s.root}")
    typer.echo(f"  tables/utterances  {utterances} utterances")
    typer.echo(f"  tables/phones      {s.read_table('phones').num_rows} phone rows")
    for source, variant in s.curve_sets():
        typer.echo(f"  curves/{source}/{variant}  {len(s.curve_files(source, variant))} files")
    _print_rejects_hint(store, strict=strict)


@app.command()
def dashboard(
    store: StoreOpt = DEFAULT_STORE,
    out: Annotated[Path, typer.Option("--out", help="Folder of the report (index.html).")] = Path("visemeflow-out/dashboard"),
    utterance: Annotated[list[str] | None, typer.Option(
        "--utterance", help="Utterance to draw, '<speaker>/<name>' (repeatable); default: a selection.")] = None,
    max_utterances: Annotated[int, typer.Option(
        "--max-utterances", min=0, help="Utterances drawn when none is named.")] = 12,
) -> None:
    """Write a static HTML report of the store (curves, tracking error, training, sweeps, robustness, rejects)."""
    import time

    from visemeflow.dashboards.html import build_dashboard

    _existing_store(store)
    started = time.perf_counter()
    result = build_dashboard(store, out, utterance, max_utterances)
    for uid in result.missing:
        typer.echo(f"warning: {uid!r} has no row and no curves in the store", err=True)
    what = "nothing yet in the store, " if result.empty else ""
    typer.echo(f"dashboard: {result.path} ({what}{len(result.utterances)} utterances, {len(result.charts)} charts, "
               f"{time.perf_counter() - started:.1f} s); open it in any browser, it needs no network:")
    typer.echo(f"  {result.path.resolve().as_uri()}")


_STOPPED: list[str] = []   # the signal that stopped the command, if one did


def _stopped_by(signum: int, frame: object) -> None:
    import signal

    _STOPPED.append(signal.Signals(signum).name)
    raise KeyboardInterrupt


def main() -> None:
    """The `visemeflow` command: errors a user can act on print one line and exit 2, without a traceback.

    The error types are imported only when an error comes: importing them (pyarrow, the flows) would cost seconds
    before the arguments are even checked.

    A command that ends (its result printed, or an error of one line) ends its process at once: the exit handlers
    run (Prefect's send the run's last logs and events, ours stop an early temporary server), the output is
    flushed, and `os._exit` skips Python's teardown of every module a flow command imported (Prefect, pydantic,
    pyarrow, pandas), which took 0.4-0.5 s after the last line with nothing left to do: files are closed and store
    writes atomic before that point. Only where this function is the program (the `visemeflow` script, `python -m
    visemeflow.cli`): called in-process (tests) it raises SystemExit as before. An error that ends in a traceback,
    and a process where a thread that Python would wait for is still running, exit as Python does.
    """
    global _AS_COMMAND
    _AS_COMMAND = True
    import signal

    # Ctrl-C, and SIGTERM (`kill`, `timeout`, a scheduler's stop) as Ctrl-C: remembered, so that the command ends
    # below without waiting for tasks still running in worker threads (while a flow runs, Prefect's engine puts its
    # own SIGTERM handler in place; either way the run is marked Crashed first)
    program = sys.modules.get("__main__")
    the_program = (getattr(getattr(program, "__spec__", None), "name", None) == "visemeflow.cli.__main__"
                   or Path(getattr(program, "__file__", None) or "").stem == "visemeflow")
    if the_program:
        signal.signal(signal.SIGINT, _stopped_by)
        signal.signal(signal.SIGTERM, _stopped_by)
    code: object = 0
    try:
        try:
            app()
        except Exception as exc:
            from visemeflow.flows.errors import StageFailed
            from visemeflow.schemas import InvalidIdError
            from visemeflow.storage import StoreError

            if isinstance(exc, (StoreError, InvalidIdError, LookupError)):
                typer.echo(f"error: {exc.strerror if isinstance(exc, StoreError) else exc}", err=True)
                raise SystemExit(2) from None
            if isinstance(exc, StageFailed):  # the flow ran to its end; its run is Failed in the UI, same message
                own = str(exc).split(":", 1)[0].strip() or "summary"    # "import_curves: its one utterance failed"
                for stage, summary in exc.summary.items() if _is_per_stage(exc.summary) else [(own, exc.summary)]:
                    _print_summary(stage, summary)
                typer.echo(f"failed: {exc}", err=True)
                raise SystemExit(1) from None
            raise
    except SystemExit as done:
        if not the_program:
            raise
        code = done.code
    except BaseException as stop:
        # Prefect's TerminationSignal (SIGTERM while a flow runs; KeyboardInterrupt comes back from typer as exit 130)
        if not the_program or type(stop).__name__ != "TerminationSignal":
            raise
        _STOPPED.append("SIGTERM")
    if the_program and _STOPPED:
        # tasks still running in worker threads (a training run, a tracked clip) are abandoned, not waited for:
        # every store write is atomic and the next run resumes
        typer.echo("interrupted" if _STOPPED[0] == "SIGINT" else "terminated", err=True)
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError, ValueError):
                stream.flush()
        os._exit(130 if _STOPPED[0] == "SIGINT" else 143)
    if not the_program:
        return
    import atexit
    import threading

    if any(t.is_alive() and not t.daemon for t in threading.enumerate() if t is not threading.main_thread()):
        raise SystemExit(code)  # Python waits for such a thread before its exit handlers: let it
    if code is not None and not isinstance(code, int):  # a message: printed, status 1, as Python does
        print(code, file=sys.stderr)
        code = 1
    # as Python's own exit: first the threading module's exit callbacks (Prefect's log and event workers drain
    # there, `threading._register_atexit`), then the atexit handlers (which stop a temporary server); skipping the
    # first sent the run's last logs to a server already stopped ("Error logging to API")
    shutdown = getattr(threading, "_shutdown", None)
    if shutdown is not None:
        shutdown()
    atexit._run_exitfuncs()
    status = code or 0
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            status = 120  # Python's status when the output cannot be flushed at exit (e.g. a closed pipe)
    os._exit(status)


def _is_per_stage(summary: dict) -> bool:
    """Whether a flow's summary is the pipeline's, one summary per stage."""
    return bool(summary) and all(isinstance(v, dict) for v in summary.values())

