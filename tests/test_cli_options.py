"""The stage commands are made from the flows' params models (visemeflow.cli.options): each option's help and default
are its field's, the values become the params model the flow takes, a refused value is one line naming the option,
and a new stage's command is one decorated function."""

import typing
from pathlib import Path

import numpy as np
import pytest
import typer
from pydantic import BaseModel, Field
from factories import make_curve_store, write_wav
from typer.testing import CliRunner

import visemeflow.cli as cli
import visemeflow.flows.runners as runners
from visemeflow.cli import app
from visemeflow.cli.options import FROM_FIELD, Opt, field_at, stage_command
from visemeflow.flows import landmarks, pipeline, sweep, track
from visemeflow.flows.params import DEFAULT_STORE, TrackParams, TrainParams
from visemeflow.schemas import curves_table

runner = CliRunner()
BINDERS = (landmarks, pipeline, sweep, track)
"""Flow modules that bind `run_on_runner` by name when first imported. They are imported here, before any test patches
`visemeflow.flows.runners.run_on_runner`: one imported first under a patch would keep the fake for the rest of the
worker process (seen: later pipeline tests in the same pytest-xdist worker got the fake's `{"utterances": 0}` as the
landmarks and track stages' summaries)."""


@pytest.fixture(autouse=True)
def _no_fake_run_on_runner_outlives_its_test():
    yield
    real = runners.run_on_runner
    assert real.__module__ == runners.__name__, "run_on_runner is still patched after the test"
    for module in BINDERS:
        assert module.run_on_runner is real, f"{module.__name__} kept a patched run_on_runner"


def stage_commands() -> list:
    return [c.callback for c in app.registered_commands if hasattr(c.callback, "params_model")]


def test_every_flow_command_but_the_few_with_their_own_modes_is_made_from_its_params_model():
    made = {c.name or c.callback.__name__ for c in app.registered_commands if hasattr(c.callback, "params_model")}
    assert made >= {"ingest", "procedural", "track", "landmarks", "pipeline", "synth", "train", "sweep", "evaluate",
                    "predict", "import-curves", "animate", "speak", "preview", "rerun"}


@pytest.mark.parametrize("command", stage_commands(), ids=lambda c: c.__name__)
def test_an_option_of_a_field_has_the_fields_help_and_default(command):
    """The help a user reads on the terminal is the description the Prefect UI shows beside the field: one text."""
    signature = command.__signature__
    for opt in command.options:
        if opt.path is None or opt.into is not None:
            continue
        info = field_at(command.params_model, opt.path)
        param = signature.parameters[opt.param_name]
        option = typing.get_args(param.annotation)[1]
        if opt.help is None:
            assert info.description and option.help.startswith(info.description), (opt.path, option.help)
        if opt.default is FROM_FIELD and info.default_factory is None and not opt.repeat:
            shown = param.default if param.default is not param.empty else ...
            expected = info.default if info.default is not None or shown is None else None
            if isinstance(expected, (list, tuple)):
                expected = ",".join(map(str, expected))
            assert shown == expected or (shown is ... and info.is_required()), (opt.path, shown, info.default)


def test_the_store_default_is_written_once():
    assert cli.DEFAULT_STORE is DEFAULT_STORE


def test_option_values_become_the_nested_params_model(monkeypatch, tmp_path):
    seen = {}

    def fake_run(flow, params):
        seen["params"] = params
        return {"utterances": 0}

    monkeypatch.setattr("visemeflow.flows.runners.run_on_runner", fake_run)
    store = make_curve_store(tmp_path / "s", n=1)   # the command checks the store has utterances first
    result = runner.invoke(app, ["track", "--store", str(store.root), "--shards", "3", "--solver", "faithful",
                                 "--no-guidance", "--rgb", "--no-flow", "--flow-preset", "fast", "--flow-max-roi-px", "192",
                                 "--flow-region", "face",
                                 "--dask-address", "tcp://127.0.0.1:1", "--threads", "2"])
    assert result.exit_code == 0, result.output
    params = seen["params"]
    assert isinstance(params, TrackParams)
    assert params == TrackParams(
        store=store.root, n_shards=3,
        config={"solver": "faithful", "guidance": False, "use_rgb": True, "use_flow": False, "flow_preset": "fast",
                "flow_max_roi_px": 192, "flow_region": "face"},
        runner={"kind": "dask", "dask_address": "tcp://127.0.0.1:1", "threads": 2})  # an address means dask


def test_a_number_that_may_be_none_takes_the_word_none_and_the_pipeline_takes_the_tracking_options(
        monkeypatch, tmp_path):
    seen = []
    monkeypatch.setattr("visemeflow.flows.runners.run_on_runner",
                        lambda flow, params: seen.append(params) or {"utterances": 0})
    store = make_curve_store(tmp_path / "s", n=1)
    for word, expected in (("none", None), ("NONE", None), ("320", 320)):
        result = runner.invoke(app, ["track", "--store", str(store.root), "--flow-max-roi-px", word])
        assert result.exit_code == 0, result.output
        assert seen.pop().config.flow_max_roi_px == expected
    result = runner.invoke(app, ["track", "--store", str(store.root)])
    assert result.exit_code == 0 and seen.pop().config.flow_max_roi_px == 256   # the field's default
    bad = runner.invoke(app, ["track", "--store", str(store.root), "--flow-max-roi-px", "big"])
    assert bad.exit_code == 2 and bad.output.startswith("error: --flow-max-roi-px: ") and bad.output.count("\n") == 1
    bad = runner.invoke(app, ["track", "--store", str(store.root), "--flow-max-roi-px", "8"])
    assert bad.exit_code == 2 and "greater than or equal to 16" in bad.output

    monkeypatch.setattr("visemeflow.flows.pipeline.pipeline_flow", lambda params: seen.append(params) or {})
    corpus = tmp_path / "corpus" / "alice"
    corpus.mkdir(parents=True)
    (corpus / "take01.wav").write_bytes(b"")
    result = runner.invoke(app, ["pipeline", str(tmp_path / "corpus"), "--store", str(tmp_path / "p"),
                                 "--flow-region", "face", "--flow-preset", "fast", "--flow-max-roi-px", "none",
                                 "--speaker-identity"])
    assert result.exit_code == 0, result.output
    tracking = seen.pop().tracking
    assert (tracking.flow_region, tracking.flow_preset, tracking.flow_max_roi_px, tracking.speaker_identity,
            tracking.use_flow) == ("face", "fast", None, True, True)
    # the ingest and track settings a corpus may need (a new user's report: `ingest --tolerance 0.5` then
    # `pipeline` could not keep it, and rejected what the ingest had accepted)
    result = runner.invoke(app, ["pipeline", str(tmp_path / "corpus"), "--store", str(tmp_path / "p"),
                                 "--tolerance", "0.5", "--fps", "25", "--solver", "faithful", "--joint-frames", "0",
                                 "--device", "cpu"])
    assert result.exit_code == 0, result.output
    params = seen.pop()
    assert (params.ingest.alignment_tolerance_s, params.ingest.fps, params.tracking.solver, params.joint_frames,
            params.device) == (0.5, 25, "faithful", 0, "cpu")


def test_an_ingest_with_other_settings_than_the_last_says_which():
    from visemeflow.flows.ingest import settings_changed
    from visemeflow.ingest import IngestConfig

    assert settings_changed(None, IngestConfig()) == ""
    assert settings_changed(IngestConfig(), IngestConfig()) == ""
    assert settings_changed(IngestConfig(alignment_tolerance_s=0.5), IngestConfig()) == \
        "alignment_tolerance_s 0.5 -> 0.1"


def test_an_option_filling_two_fields_and_a_list_option(monkeypatch, tmp_path):
    seen = {}
    monkeypatch.setattr("visemeflow.flows.train.train_flow", lambda params: seen.setdefault("params", params) and {})
    monkeypatch.setattr("visemeflow.flows.runners.run_on_runner",
                        lambda flow, params: seen.setdefault("params", params) and {"points": [], "plot": "p"})
    store = make_curve_store(tmp_path / "s", n=3)   # the commands check the store has curves to learn first
    result = runner.invoke(app, ["train", "--store", str(store.root), "--train-augment", "0.25", "--name", "m1",
                                 "--preset", "mean-curve", "--device", "cpu", "--source", "ground_truth"])
    assert result.exit_code == 0, result.output
    params = seen.pop("params")
    assert isinstance(params, TrainParams) and params.model_name == "m1"
    assert params.config.train_augment and params.config.train_augment_probability == 0.25
    result = runner.invoke(app, ["sweep", "--store", str(store.root), "--sizes", "10, 30", "--device", "cpu",
                                 "--source", "ground_truth"])
    assert result.exit_code == 0, result.output
    assert seen["params"].sizes == [10, 30]


def test_a_refused_value_is_one_line_naming_its_option(tmp_path):
    bad = runner.invoke(app, ["track", "--store", str(tmp_path / "s"), "--solver", "quick"])
    assert bad.exit_code == 2
    assert bad.output.strip() == "error: --solver must be one of fast, faithful, not 'quick'"
    bad = runner.invoke(app, ["track", "--store", str(tmp_path / "s"), "--flow-preset", "slow"])
    assert bad.exit_code == 2
    assert bad.output.strip() == "error: --flow-preset must be one of ultrafast, fast, balanced, medium, not 'slow'"
    bad = runner.invoke(app, ["sweep", "--store", str(tmp_path / "s"), "--sizes", "10,x"])
    assert bad.exit_code == 2 and bad.output.startswith("error: --sizes: ") and "\n" == bad.output[-1]
    bad = runner.invoke(app, ["landmarks", "--store", str(tmp_path / "s"), "--max-faces", "1"])
    assert bad.exit_code == 2 and bad.output.startswith("error: --max-faces: Input should be greater than or equal to 2")
    bad = runner.invoke(app, ["speak", str(tmp_path), "--store", str(tmp_path / "s"), "--format", "pose-csv"])
    assert bad.exit_code == 2


class ToyConfig(BaseModel):
    level: int = Field(3, ge=0, description="How loud.")


class ToyParams(BaseModel):
    store: Path = Field(Path("out"), description="Where.")
    names: list[str] = Field(["a", "b"], description="Which.")
    config: ToyConfig = Field(default_factory=ToyConfig)


def test_a_new_stage_command_is_one_decorated_function():
    """What a new stage writes in the CLI: its options by field path; help, defaults and checks come from its model."""
    toy = typer.Typer()
    got = []

    @stage_command(toy, ToyParams, [Opt("store"), Opt("names"), Opt("config.level", "--loudness"),
                                    Opt(None, "--dry", type=bool, default=False, help="Only say it.")])
    def toy_stage(params: ToyParams, dry: bool) -> None:
        """A toy stage."""
        got.append((params, dry))

    @toy.callback()
    def main() -> None:   # a group, so the command is named as a subcommand
        pass

    done = runner.invoke(toy, ["toy-stage", "--names", "x,y", "--loudness", "5", "--dry"])
    assert done.exit_code == 0, done.output
    assert got == [(ToyParams(names=["x", "y"], config=ToyConfig(level=5)), True)]
    helped = runner.invoke(toy, ["toy-stage", "--help"], env={"COLUMNS": "200"}).output
    assert "How loud." in helped and "Which." in helped and "a,b" in helped
    refused = runner.invoke(toy, ["toy-stage", "--loudness", "-1"])
    assert refused.exit_code == 2 and refused.output.startswith("error: --loudness: ")


def test_a_stage_with_nothing_to_read_says_what_to_run_first_before_any_flow(tmp_path):
    empty = tmp_path / "empty"
    done = runner.invoke(app, ["track", "--store", str(empty)])
    assert done.exit_code == 2 and "no ingested utterances" in done.output and "visemeflow ingest" in done.output
    store = make_curve_store(tmp_path / "s", n=1)   # ground-truth curves only
    done = runner.invoke(app, ["train", "--store", str(store.root)])
    assert done.exit_code == 2 and "no tracked curves" in done.output and "--source ground_truth" in done.output
    done = runner.invoke(app, ["train", "--store", str(store.root), "--source", "ground_truth", "--preset", "bogus"])
    assert done.exit_code == 2 and done.output.startswith("error: --preset: unknown preset 'bogus'")
    done = runner.invoke(app, ["train", "--store", str(store.root), "--source", "ground_truth", "--tune-layers", "2"])
    assert done.exit_code == 2 and done.output.startswith("error: --tune-layers: preset 'fbank-blstm' has no Whisper")
    done = runner.invoke(app, ["train", "--store", str(store.root), "--source", "ground_truth"])
    assert done.exit_code == 2 and done.output.count("\n") == 1, done.output    # was a Prefect traceback first
    assert done.output.startswith(f"error: no utterance in {store.root} has ground_truth curves of variant 'cm' in "
                                  "the train split: the 1 utterance that has them is in the `val` split")
    done = runner.invoke(app, ["sweep", "--store", str(store.root), "--source", "ground_truth"])
    assert done.exit_code == 2 and done.output.count("\n") == 1, done.output
    assert "in the train split: the 1 utterance that has them is in the `val` split" in done.output
    done = runner.invoke(app, ["rerun", "spk/nope", "--store", str(store.root)])
    assert done.exit_code == 2 and "no utterance spk/nope" in done.output
    for stage in ("track", "landmarks"):   # an audio-only utterance: one line, no flow (and no Prefect traceback)
        done = runner.invoke(app, ["rerun", "spk/u0", "--stage", stage, "--store", str(store.root)])
        assert done.exit_code == 2 and done.output.count("\n") == 1, done.output
        assert done.output.startswith("error: spk/u0 has no video") and f"the {stage} stage works on video" in done.output
    # no animate run to repeat: one line (was 20 lines of Prefect traceback before it)
    done = runner.invoke(app, ["rerun", "spk/u0", "--stage", "animate", "--store", str(store.root)])
    assert done.exit_code == 2 and done.output == (f"error: {store.root} has no animate run to repeat; run "
                                                   "`visemeflow animate` first\n"), done.output
    done = runner.invoke(app, ["rerun", "spk/u0", "--store", str(tmp_path / "mistyped")])
    assert done.exit_code == 2 and done.output.startswith(f"error: no store at {tmp_path / 'mistyped'}")
    # a mistyped utterance: one line before any flow, with the stored ids nearest it (was a Prefect traceback, or
    # an animate reject naming the id twice)
    done = runner.invoke(app, ["preview", "spk/u", "--store", str(store.root)])
    assert done.exit_code == 2 and done.output.count("\n") == 1, done.output
    assert done.output.startswith("error: no procedural, tracked, predicted or ground_truth curves of spk/u in the "
                                  f"store {store.root}; did you mean spk/u0?")
    done = runner.invoke(app, ["preview", "spk/u", "--sources", "ground_truth:cm", "--store", str(store.root)])
    assert done.exit_code == 2 and done.output.startswith("error: no ground_truth curves of spk/u in the store ")
    store.write_curves(curves_table("spk/u0", "ground_truth", "other", np.zeros((5, 16), np.float32), 30.0), fps=30.0)
    done = runner.invoke(app, ["preview", "spk/u0", "--sources", "ground_truth", "--store", str(store.root)])
    assert done.exit_code == 2 and done.output == (      # was "none of the sources has curves", after a traceback
        "error: spk/u0: no source to preview: ground_truth: 2 variants (cm, other); name one as ground_truth:VARIANT\n")
    done = runner.invoke(app, ["animate", "spk/u0", "nope/x", "--source", "ground_truth", "--store", str(store.root)])
    assert done.exit_code == 2 and done.output.count("\n") == 1, done.output
    assert done.output.startswith("error: no ground_truth curves of nope/x in the store") and \
        "it has such curves of 1 utterance (spk/u0)" in done.output
    store.write_curves(curves_table("predict/take", "predicted", "tiny", np.zeros((5, 16), np.float32), 30.0),
                       fps=30.0)
    for stage in ("animate", "ingest"):     # speak's output is no corpus utterance: say how it is made again
        done = runner.invoke(app, ["rerun", "predict/take", "--stage", stage, "--store", str(store.root)])
        assert done.exit_code == 2 and done.output.startswith("error: predict/take was made by `visemeflow predict` "
                                                              "or `speak` from an audio file"), done.output
    done = runner.invoke(app, ["rerun", "spk/u0", "--stage", "ingest", "--store", str(store.root)])
    assert done.exit_code == 2 and done.output == f"error: {store.root} has no ingest run to repeat; run " \
                                                  "`visemeflow ingest CORPUS` first\n"
    done = runner.invoke(app, ["evaluate", "--models", "nope", "--store", str(store.root)])
    assert done.exit_code == 2 and "no model 'nope'" in done.output
    done = runner.invoke(app, ["speak", str(tmp_path / "x.wav")])
    assert done.exit_code == 2   # a file that is not there: before anything else
    done = runner.invoke(app, ["sweep", "--store", str(store.root), "--source", "ground_truth", "--sizes", "0,5"])
    assert done.exit_code == 2 and done.output.startswith("error: --sizes: ")


def test_a_character_that_does_not_load_is_one_line_before_any_flow(tmp_path):
    empty = tmp_path / "empty.gltf"
    empty.write_text('{"asset": {"version": "2.0"}}')
    audio = tmp_path / "a.wav"
    audio.write_bytes(b"RIFF")   # never read: the character is checked first
    done = runner.invoke(app, ["speak", str(audio), "--character", str(empty), "--store", str(tmp_path / "s")])
    assert done.exit_code == 2 and done.output.startswith(f"error: character {empty}: "), done.output
    assert done.output.count(str(empty)) == 1 and done.output.count("\n") == 1, done.output   # named once
    assert not (tmp_path / "s").exists()


def test_a_convention_the_character_lacks_and_an_out_that_is_a_file_are_one_line_before_any_flow(tmp_path):
    """`speak --convention arkit52` on the demo character (its shapes are the 16 visemes) used to fail each package
    after the predictions, with Prefect's traceback; an --out that is a file failed the same way."""
    audio = tmp_path / "a.wav"
    write_wav(audio, 0.5)
    store = tmp_path / "s"
    done = runner.invoke(app, ["speak", str(audio), "--convention", "arkit52", "--store", str(store)])
    assert done.exit_code == 2 and done.output.count("\n") == 1, done.output
    assert done.output.startswith("error: character ") and "none of its shapes has a name of the arkit52 convention" in done.output
    (tmp_path / "taken.wav").write_bytes(b"")
    done = runner.invoke(app, ["speak", str(audio), "--out", str(tmp_path / "taken.wav"), "--store", str(store)])
    assert done.exit_code == 2 and done.output.startswith(f"error: --out {tmp_path / 'taken.wav'}: is a file")
    assert not store.exists()


def test_an_out_folder_nothing_can_be_written_in_is_one_line_before_any_flow(tmp_path, monkeypatch):
    """An --out on a read-only mount, or an immutable folder, failed each package after the predictions with 60
    lines of Prefect's traceback ("its one utterance failed"); a root user passes every permission check, so the
    folder is tried with a file. Here the file system's refusal is what `tempfile` raises."""
    import errno
    import os
    import tempfile

    audio = tmp_path / "a.wav"
    write_wav(audio, 0.5)
    store, locked = tmp_path / "s", tmp_path / "locked"
    locked.mkdir()
    real = tempfile.TemporaryFile

    def refused(*args, dir=None, **kwargs):
        if dir is not None and Path(dir) == locked:
            raise OSError(errno.EROFS, "Read-only file system")
        return real(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "TemporaryFile", refused)
    for out in (locked, locked / "new" / "folder"):     # the folder, or one to be made inside it
        done = runner.invoke(app, ["speak", str(audio), "--out", str(out), "--store", str(store)])
        assert done.exit_code == 2 and done.output == \
            f"error: --out {out}: cannot write there (read-only file system on {locked})\n", done.output
    assert not store.exists() and list(locked.iterdir()) == []
    access = os.access
    monkeypatch.setattr(os, "access", lambda path, mode: not (Path(path) == locked and mode & os.W_OK)
                        and access(path, mode))
    done = runner.invoke(app, ["animate", "--out", str(locked), "--store", str(store)])
    assert done.exit_code == 2 and f"--out {locked}: cannot write there (no write permission on {locked})" in \
        done.output, done.output


def test_audio_files_that_are_not_audio_are_one_line_before_the_model_loads(tmp_path):
    """`speak notaudio.wav` used to load the model, then print the reason four times (about a minute under load)."""
    text = tmp_path / "notes.wav"
    text.write_text("not a sound\n")
    done = runner.invoke(app, ["speak", str(text), "--store", str(tmp_path / "s")])
    assert done.exit_code == 2 and done.output.count("\n") == 1, done.output
    assert done.output.startswith(f"error: audio file {text}: neither soundfile nor FFmpeg reads it as audio")
    done = runner.invoke(app, ["predict", str(text), str(text), "--store", str(tmp_path / "s")])
    assert done.exit_code == 2 and "(the other file too)" in done.output
    empty = tmp_path / "empty.wav"
    empty.write_bytes(b"")
    done = runner.invoke(app, ["speak", str(empty), "--store", str(tmp_path / "s")])
    assert done.exit_code == 2 and done.output == f"error: audio file {empty}: the file is empty (0 bytes)\n"
    assert not (tmp_path / "s").exists()


def test_a_character_whose_names_follow_no_convention_is_one_line_before_any_flow_and_a_vrm_is_a_glb(tmp_path):
    """A GLB whose morph targets have names no convention knows ran the predictions, then failed with Prefect's
    traceback (a new user's report); now one line naming the file and what to give, before any flow. A VRoid avatar
    (.vrm, Fcl_MTH_* names) loads as the glTF scene it is, and its GLB is its whole asset with our clip."""
    from visemeflow.animation.gltf import write_glb
    from visemeflow.animation.gltf_asset import write_character_glb
    from visemeflow.animation.load import load_bound_character
    from visemeflow.rig.character import make_character

    grid = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32) * 0.1
    faces = np.array([[0, 1, 2], [1, 3, 2]])

    def glb(path: Path, names: list[str]) -> Path:
        deltas = np.random.default_rng(0).normal(0, 0.01, (len(names), 4, 3)).astype(np.float32)
        character = make_character("face", grid, faces, names, deltas)
        return write_glb(path, character, np.zeros((1, len(names)), np.float32), 30.0, name="rest")

    odd = glb(tmp_path / "odd.glb", ["smile", "frown", "blink"])
    audio = tmp_path / "a.wav"
    write_wav(audio, 0.5)
    done = runner.invoke(app, ["speak", str(audio), "--character", str(odd), "--store", str(tmp_path / "s")])
    assert done.exit_code == 2 and done.output.count("\n") == 1, done.output
    assert done.output.startswith(f"error: character {odd}: ") and "follow no known convention" in done.output
    assert "--mapping" in done.output and "--convention" in done.output and not (tmp_path / "s").exists()

    vrm = glb(tmp_path / "avatar.glb", ["Fcl_MTH_A", "Fcl_MTH_I", "Fcl_MTH_U", "Fcl_MTH_E", "Fcl_MTH_O"])
    vrm = vrm.rename(tmp_path / "avatar.vrm")
    character, binding = load_bound_character(vrm)
    assert binding.convention == "vrm5" and character.parts
    out = write_character_glb(tmp_path / "spoken.glb", character, np.ones((3, 5), np.float32) * 0.5, 30.0,
                              name="speech")
    assert out.read_bytes()[:4] == b"glTF" and b'"speech"' in out.read_bytes() and b'"rest"' in out.read_bytes()


def test_an_avatar_whose_driven_meshes_no_node_shows_is_one_line_before_any_flow(tmp_path):
    """A GLB whose face meshes are in the file but on no node (a user's export that left the head out of its scene,
    found by a probe): the GLB's clip has no node to play on; that failed after the predictions with a 150-line log.
    Now one line before any flow, saying what to do."""
    import pygltflib as gl

    from visemeflow.animation.gltf import write_glb
    from visemeflow.rig.character import make_character

    grid = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32) * 0.1
    names = ["jawOpen", "mouthClose", "mouthFunnel", "mouthPucker", "mouthSmileLeft", "mouthSmileRight",
             "mouthPressLeft", "mouthPressRight", "mouthLowerDownLeft", "mouthLowerDownRight"]
    deltas = np.random.default_rng(0).normal(0, 0.01, (len(names), 4, 3)).astype(np.float32)
    face = make_character("face", grid, np.array([[0, 1, 2], [1, 3, 2]]), names, deltas)
    path = write_glb(tmp_path / "face.glb", face, np.zeros((1, len(names)), np.float32), 30.0, name="rest")
    g = gl.GLTF2().load(str(path))
    g.nodes.append(gl.Node(name="Body"))                    # the scene shows a node without the face mesh
    g.scenes[0].nodes = [len(g.nodes) - 1]
    for node in g.nodes[:-1]:
        node.mesh = None
    g.animations = []
    g.save_binary(str(tmp_path / "headless.glb"))
    audio = tmp_path / "a.wav"
    write_wav(audio, 0.5)
    done = runner.invoke(app, ["speak", str(audio), "--character", str(tmp_path / "headless.glb"),
                               "--store", str(tmp_path / "s")])
    assert done.exit_code == 2 and done.output.count("\n") == 1, done.output
    assert "no node of its scene shows the meshes it would drive (face)" in done.output and "--format" in done.output
    assert not (tmp_path / "s").exists()
