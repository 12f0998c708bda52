"""The `animate`, `speak` and `preview` flows, `rerun --stage animate` and the pipeline's animate stage: stored curves
reach characters in every format, cached per (utterance, character), bad input as rejects while the rest goes on."""

import json
from pathlib import Path

import av
import numpy as np
import pytest
import soundfile as sf
from factories import make_corpus, make_curve_store, validate
from factories import DEMO_AUDIO as AUDIO
from factories import tiny_character, tiny_model

from visemeflow.articulation import close_lips
from visemeflow.rig.character import make_character, save_character_npz
from visemeflow.animation.load import load_character
from visemeflow.shapes.conventions import ARKIT_52, OCULUS_15, arkit_weights, bind
from visemeflow.animation.gltf import write_glb
from visemeflow.shapes.livelink import arkit_from_livelink, read_livelink_csv
from visemeflow.animation.apply import resample_visemes
from visemeflow.animation.usd import read_usd_weights
from visemeflow.animation.webjson import read_web_json
from visemeflow.flows.animate import AnimateParams, PreviewParams, SpeakParams, animate_flow, preview_flow, \
    speak_flow
from visemeflow.animation.package import AnimateConfig
from visemeflow.flows.errors import StageFailed
from visemeflow.schemas import C, curves_array, curves_table
from visemeflow.storage import Store

pytestmark = [pytest.mark.flow, pytest.mark.usefixtures("prefect_harness")]
ALL = ("glb", "usd", "livelink", "json", "curves-csv", "curves-json")


@pytest.fixture
def characters(tmp_path):
    arkit = tiny_character(list(ARKIT_52), name="Wolf3D_Head")   # a mesh named otherwise than its file
    oculus = tiny_character(list(OCULUS_15), seed=1, name="oculus")
    glb = tmp_path / "chars" / "arkit.glb"
    write_glb(glb, arkit, np.zeros((1, len(ARKIT_52)), np.float32), 30.0)
    return glb, save_character_npz(oculus, tmp_path / "chars" / "oculus.npz")


def test_every_format_of_every_package_holds_the_curves_at_the_asked_rate(tmp_path, characters):
    store = make_curve_store(tmp_path / "store", n=3)
    glb, npz = characters
    config = AnimateConfig(formats=ALL, fps=30.0)
    result = animate_flow(AnimateParams(store=store.root, characters=[glb, npz], source="ground_truth",
                                        config=config))
    assert result["packages"] == 6 and result["written"] == 6 and result["rejected"] == 0
    for report in result["packages_written"]:
        uid = report["utterance_id"]
        curves = close_lips(resample_visemes(curves_array(store.read_curves(uid, "ground_truth", "cm")), 25.0, 30.0))   # what the exports play: the lip rules on
        assert report["frames"] == len(curves) == 29 and report["fps"] == 30.0 and report["resampled_from"] == 25.0
        character = load_character(glb if report["character"] == "arkit" else npz)
        weights = bind(character).weights(curves)
        names, usd_weights, usd_fps = read_usd_weights(report["files"]["usd"])
        assert names == character.shape_names and usd_fps == 30.0
        np.testing.assert_allclose(usd_weights, weights, atol=1e-6)
        _, values, timecodes = read_livelink_csv(report["files"]["livelink"])
        np.testing.assert_allclose(arkit_from_livelink(values), arkit_weights(curves), atol=1e-6)
        assert len(timecodes) == len(curves)
        web_names, web_weights, web_fps = read_web_json(report["files"]["json"])
        assert web_names == character.shape_names and web_fps == 30.0
        np.testing.assert_allclose(web_weights, weights, atol=1e-4)
        back = load_character(report["files"]["glb"])
        assert back.shape_names == character.shape_names
        curves_json = json.loads(open(report["files"]["curves-json"]).read())
        assert curves_json["fps"] == pytest.approx(30.0) and len(curves_json["time_s"]) == len(curves)
        audio, rate = sf.read(report["files"]["audio"])
        assert len(audio) / rate == pytest.approx(1.0, abs=1e-3)
    assert {r["convention"] for r in result["packages_written"]} == {"arkit52", "oculus15"}
    # each package names its character as people do, by its file (arkit.glb), not by the mesh inside
    assert {r["character"] for r in result["packages_written"]} == {"arkit", "oculus"}


def test_a_second_run_is_all_cache_hits_and_a_deleted_file_is_made_again(tmp_path, characters):
    store = make_curve_store(tmp_path / "store", n=2)
    params = AnimateParams(store=store.root, characters=[characters[1]], source="ground_truth")
    first = animate_flow(params)
    assert first["written"] == 2
    again = animate_flow(params)
    assert again["cached"] == 2 and again["written"] == 0
    victim = first["packages_written"][0]["files"]["glb"]
    Store(store.root).root.joinpath(victim).unlink()
    third = animate_flow(params)
    assert third["written"] == 1 and third["cached"] == 1
    assert (store.root / victim).is_file()


def test_bad_characters_and_curves_are_rejects_naming_the_file_and_the_rest_goes_on(tmp_path, characters):
    store = make_curve_store(tmp_path / "store", n=3)
    loud = np.full((25, 16), 0.2, np.float32)
    loud[7, 3] = 1.5  # outside [0, 1]
    store.write_curves(curves_table("spk/u1", "ground_truth", "cm", loud, 25.0))
    broken = tmp_path / "broken.glb"
    broken.write_bytes(b"glTF\x02\x00\x00\x00garbage")
    mapping = tmp_path / "map.csv"
    mapping.write_text("viseme,shape,weight\nMBP,NoSuchShape,1\n")
    result = animate_flow(AnimateParams(store=store.root, characters=[broken, characters[1]], source="ground_truth"))
    assert result["written"] == 2 and result["rejected"] == 2
    rejects = store.read_table("rejects", "animate").to_pylist()
    by_type = {r[C.ERROR_TYPE]: r for r in rejects}
    assert str(broken) in by_type["CharacterError"][C.MESSAGE] and by_type["CharacterError"][C.UTTERANCE_ID] is None
    curve_reject = by_type["CurvesError"]
    assert curve_reject[C.UTTERANCE_ID] == "spk/u1" and "FFF is 1.5000 at frame 7" in curve_reject[C.MESSAGE]
    assert curve_reject[C.PATH].endswith("u1.parquet")
    with pytest.raises(StageFailed, match="its one utterance failed"):  # nothing could be done: the run is Failed
        animate_flow(AnimateParams(store=store.root, characters=[characters[1]], source="ground_truth",
                                   utterances=["spk/u0"], mapping=mapping))
    rows = store.read_table("rejects", "animate").to_pylist()
    (message,) = [r[C.MESSAGE] for r in rows if r[C.ERROR_TYPE] == "CharacterError"]
    assert "map.csv" in message and "NoSuchShape" in message and "viseme_PP" in message
    # a run of some utterances keeps the other utterances' rejects (speak wiped them: a new user's report) ...
    assert [r[C.UTTERANCE_ID] for r in rows if r[C.ERROR_TYPE] == "CurvesError"] == ["spk/u1"]
    # ... until those utterances are animated again
    store.write_curves(curves_table("spk/u1", "ground_truth", "cm", np.clip(loud, 0, 1), 25.0))
    animate_flow(AnimateParams(store=store.root, characters=[characters[1]], source="ground_truth",
                               utterances=["spk/u1"]))
    assert store.read_table("rejects", "animate").num_rows == 0


def test_speak_counts_the_lips_closed_at_the_bilabials_of_an_alignment_beside_the_audio(tmp_path):
    """`speak take.wav` with `take.TextGrid` beside it (a corpus's layout) reports how many of its b/p/m the mesh
    closed, as `animate` does for ingested utterances; without one, or with one that cannot be read, the package is
    made all the same, without that count."""
    import shutil

    from visemeflow.animation.lips import is_bilabial
    from visemeflow.flows.animate import phones_beside

    phones = phones_beside(AUDIO)
    bilabials = sum(is_bilabial(label) for _, _, label in phones)
    assert bilabials >= 1 and ("zh", 0.28, 0.36) == (phones[1][2], phones[1][0], phones[1][1])
    store = Store(tmp_path / "store")
    tiny_model(store)
    config = AnimateConfig(formats=("json",))
    (report,) = speak_flow(SpeakParams(store=store.root, model="tiny", audio=[AUDIO],   # the demo head: its lips
                                       out=tmp_path / "out", config=config))["packages_written"]
    assert report["lips"].get("bilabials") == bilabials and 0 <= report["lips"]["closed"] <= bilabials, report["lips"]
    alone = tmp_path / "alone" / "take.wav"
    alone.parent.mkdir()
    shutil.copy(AUDIO, alone)
    assert phones_beside(alone) is None
    (alone.parent / "take.TextGrid").write_text("not a TextGrid")
    assert phones_beside(alone) is None
    (report,) = speak_flow(SpeakParams(store=store.root, model="tiny", audio=[alone], out=tmp_path / "out",
                                       config=config))["packages_written"]
    assert "bilabials" not in report["lips"] and "mbp_shape_gap_mm" in report["lips"]
    # a transcript beside the audio (take.txt) is forced-aligned in English for the count, as `ingest` aligns one
    spoken = tmp_path / "spoken" / "take.wav"
    spoken.parent.mkdir()
    shutil.copy(AUDIO.parents[1] / "LJ" / "LJ001-0002.wav", spoken)
    (spoken.parent / "take.txt").write_text("in being comparatively modern.\n")
    phones = phones_beside(spoken)
    assert [label for _, _, label in phones if is_bilabial(label)] == ["B", "M", "P", "M"], phones
    assert all(0.0 <= a < b <= 1.9 for a, b, _ in phones)
    (spoken.parent / "take.txt").write_text("dans une maison très moderne\n")   # not English: no count
    assert phones_beside(spoken) is None


def test_speak_turns_audio_into_a_talking_character_in_one_flow(tmp_path, characters):
    store = Store(tmp_path / "store")
    tiny_model(store)
    out = tmp_path / "out"
    result = speak_flow(SpeakParams(store=store.root, model="tiny", audio=[AUDIO], characters=[characters[0]],
                                    out=out, config=AnimateConfig(formats=("glb", "livelink"))))
    (report,) = result["packages_written"]
    predicted = curves_array(store.read_curves("predict/SSB16240001", "predicted", "tiny"))
    assert report["frames"] == len(predicted) and report["fps"] == 30.0
    assert set(report["files"]) == {"glb", "livelink", "audio"}
    assert str(out) in report["files"]["glb"]
    samples, rate = sf.read(report["files"]["audio"])
    source, source_rate = sf.read(AUDIO)
    assert rate == source_rate and len(samples) == len(source)
    again = speak_flow(SpeakParams(store=store.root, model="tiny", audio=[AUDIO], characters=[characters[0]],
                                   out=out, config=AnimateConfig(formats=("glb", "livelink"))))
    assert again["cached"] == 1
    # the same audio again with one format fewer: the folder then holds this package only (the old Live Link CSV
    # would pass for this one's); a file of the user's own there is left alone
    folder = Path(report["files"]["glb"]).parent
    (folder / "notes.txt").write_text("mine")
    fewer = speak_flow(SpeakParams(store=store.root, model="tiny", audio=[AUDIO], characters=[characters[0]],
                                   out=out, config=AnimateConfig(formats=("glb",))))
    (report,) = fewer["packages_written"]
    assert sorted(p.name for p in folder.iterdir() if not p.name.startswith(".")) == sorted(
        [Path(report["files"]["glb"]).name, Path(report["files"]["audio"]).name, "notes.txt"])


def test_rerun_animate_makes_one_utterance_again_with_the_last_settings(tmp_path, characters):
    from visemeflow.flows.params import RerunParams
    from visemeflow.flows.rerun import rerun_flow

    store = make_curve_store(tmp_path / "store", n=2)
    first = animate_flow(AnimateParams(store=store.root, characters=[characters[1]], source="ground_truth",
                                       config=AnimateConfig(formats=("json",))))
    target = next(r for r in first["packages_written"] if r["utterance_id"] == "spk/u1")["files"]["json"]
    (store.root / target).unlink()
    report = rerun_flow(RerunParams(utterance_id="spk/u1", stage="animate", store=store.root))
    assert report == {"packages": 1, "files": 2, "warnings": []}
    assert (store.root / target).is_file()


def test_a_store_of_guided_and_unguided_tracked_curves_is_animated_whole_each_utterance_from_its_own(
        tmp_path, characters):
    """Tracked curves in two variants (aligned videos guided, the others unguided): animate with no variant names
    every utterance once, from its own variant (the guided one where both exist), one rejects table for the stage;
    `rerun` of an unguided utterance finds its curves; a named variant order is kept."""
    from visemeflow.flows.params import RerunParams
    from visemeflow.flows.rerun import rerun_flow

    store = make_curve_store(tmp_path / "store", n=4)
    rng = np.random.default_rng(3)
    for i, variant in enumerate(["guided-fast", "guided-fast", "unguided-fast", "unguided-fast"]):
        store.write_curves(curves_table(f"spk/u{i}", "tracked", variant, rng.random((25, 16)).astype(np.float32), 25.0))
    # u0 also has older unguided curves: the guided ones win (the track stage's last run wrote guided-fast)
    store.write_curves(curves_table("spk/u0", "tracked", "unguided-fast", np.zeros((25, 16), np.float32), 25.0))
    store.write_run_config("track", {"variant": "guided-fast"})
    result = animate_flow(AnimateParams(store=store.root, characters=[characters[1]], source="tracked",
                                        config=AnimateConfig(formats=("curves-csv",))))
    assert result["packages"] == 4 and result["rejected"] == 0
    assert result["variants"] == "guided-fast: 2, unguided-fast: 2"
    frames = {r["utterance_id"]: np.loadtxt(store.root / r["files"]["curves-csv"], delimiter=",", skiprows=1)
              for r in result["packages_written"]}
    assert set(frames) == {f"spk/u{i}" for i in range(4)}
    assert frames["spk/u0"][:, 2:].max() > 0   # guided (random), not the all-zero unguided take
    # a named order: unguided first, so u0 now comes from its zero curves
    named = animate_flow(AnimateParams(store=store.root, characters=[characters[1]], source="tracked",
                                       variant="unguided-fast,guided-fast", utterances=["spk/u0", "spk/u1"],
                                       config=AnimateConfig(formats=("curves-csv",))))
    assert named["variants"] == "unguided-fast: 1, guided-fast: 1"
    u0 = next(r for r in named["packages_written"] if r["utterance_id"] == "spk/u0")
    assert np.loadtxt(store.root / u0["files"]["curves-csv"], delimiter=",", skiprows=1)[:, 2:].max() == 0
    report = rerun_flow(RerunParams(utterance_id="spk/u3", stage="animate", store=store.root))
    assert report == {"packages": 1, "files": 2, "warnings": []}


def test_the_pipeline_animates_its_curves_when_characters_are_given(tmp_path, characters):
    from visemeflow.flows.params import PipelineParams
    from visemeflow.flows.pipeline import pipeline_flow

    corpus = make_corpus(tmp_path / "corpus", {"spk/a": [("", 0.0, 0.2), ("AA1", 0.2, 0.5), ("M", 0.5, 0.7)],
                                               "spk/b": [("B", 0.0, 0.3), ("IY1", 0.3, 0.6)]})
    result = pipeline_flow(PipelineParams(corpus=corpus, store=tmp_path / "store", characters=[characters[1]],
                                          animate=AnimateConfig(formats=("glb",))))
    assert result["animate"]["source"] == "procedural" and result["animate"]["written"] == 2
    assert all(r["files"]["glb"].endswith(".glb") for r in result["animate"]["packages_written"])


def test_preview_puts_the_sources_side_by_side_with_the_audio(tmp_path, characters):
    store = make_curve_store(tmp_path / "store", n=1)
    curves = curves_array(store.read_curves("spk/u0", "ground_truth", "cm"))
    store.write_curves(curves_table("spk/u0", "tracked", "v1", np.clip(curves[::-1] * 0.5, 0, 1), 25.0))
    result = preview_flow(PreviewParams(store=store.root, utterance_id="spk/u0", character=characters[1],
                                        sources=["tracked", "predicted", "ground_truth"], size=96,
                                        out=tmp_path / "p.mp4"))
    assert result["sources"] == ["tracked (v1)", "ground truth (cm)"]
    assert any("predicted" in s for s in result["skipped"])
    with av.open(str(tmp_path / "p.mp4")) as container:
        video = container.streams.video[0]
        assert video.codec_context.name == "h264" and container.streams.audio[0].codec_context.name == "aac"
        assert video.codec_context.width >= 2 * 96
        assert sum(1 for _ in container.decode(video=0)) == result["frames"] == 25


def viseme_grid_counting_solves(tmp_path, monkeypatch, seed: int):
    """An 8 x 8 grid character with 16 random viseme shapes (saved as .npz), and a list that grows by one per SSDR
    solve of the animate package (its per-process rig cache emptied)."""
    from visemeflow.animation import package
    from visemeflow.visemes import VISEMES

    rng = np.random.default_rng(seed)
    grid = np.stack(np.meshgrid(np.arange(8.0), np.arange(8.0)), -1).reshape(-1, 2)
    neutral = np.c_[grid, np.zeros(len(grid))]
    faces = [[i, i + 1, i + 8] for i in range(55) if i % 8 != 7] + [[i + 1, i + 9, i + 8] for i in range(55) if i % 8 != 7]
    character = make_character("grid", neutral, faces, list(VISEMES), rng.normal(0, 0.05, (16, len(neutral), 3)))
    path = save_character_npz(character, tmp_path / "chars" / "grid.npz")
    solves = []
    real_solve = package.solve_bones
    monkeypatch.setattr(package, "solve_bones", lambda *a, **k: solves.append(1) or real_solve(*a, **k))
    monkeypatch.setattr(package, "_RIGS", {})
    return path, solves


def test_bone_mode_writes_skinned_glb_and_pose_tables_solving_each_character_once(tmp_path, monkeypatch):
    """`--mode bones`: glb becomes `<stem>.bones.glb` (a skinned glTF the Khronos validator accepts), pose tables are
    written, the blendshape-independent formats are unchanged, and the SSDR solve runs once per character for all
    utterances of the run; pose tables without bone mode are refused."""
    import csv

    from visemeflow.visemes import VISEMES

    path, solves = viseme_grid_counting_solves(tmp_path, monkeypatch, seed=3)

    store = make_curve_store(tmp_path / "store", n=3)
    config = AnimateConfig(formats=("glb", "pose-csv", "livelink"), mode="bones", bones=4)
    result = animate_flow(AnimateParams(store=store.root, characters=[path], source="ground_truth", config=config))
    assert result["packages"] == 3 and result["rejected"] == 0 and len(solves) == 1
    for report in result["packages_written"]:
        files = report["files"]
        assert files["glb"].endswith(".bones.glb") and files["pose-csv"].endswith(".poses.csv")
        issues = validate(Path(files["glb"]))["issues"]
        assert issues["numErrors"] == 0 and issues["numWarnings"] == 0
        with open(files["pose-csv"], newline="") as f:
            rows = list(csv.DictReader(f))
        assert {r["pose"] for r in rows} == set(VISEMES) and len({r["bone"] for r in rows}) >= 2
        _, values, _ = read_livelink_csv(files["livelink"])
        assert len(values) == report["frames"]
    with pytest.raises(ValueError, match="bone-mode formats"):
        AnimateConfig(formats=("pose-json",))


def test_preview_and_bone_mode_packages_show_bones_beside_blendshapes(tmp_path, monkeypatch):
    """`preview --mode both`: each source's blendshape panel and its bone panel side by side (`--mode bones`: the
    bone panels alone); `animate --mode bones --preview` shows the blendshapes beside the bones the exports play.
    One SSDR solve serves them all."""
    path, solves = viseme_grid_counting_solves(tmp_path, monkeypatch, seed=4)
    store = make_curve_store(tmp_path / "store", n=1)

    def width_and_frames(video_path):
        with av.open(str(video_path)) as container:
            return container.streams.video[0].codec_context.width, sum(1 for _ in container.decode(video=0))

    both = preview_flow(PreviewParams(store=store.root, utterance_id="spk/u0", character=path, mode="both", bones=4,
                                      sources=["ground_truth"], size=96, out=tmp_path / "both.mp4"))
    assert both["sources"] == ["ground truth (cm)", "ground truth, 4 bones"]
    assert width_and_frames(tmp_path / "both.mp4") == (2 * 96, both["frames"])
    bones = preview_flow(PreviewParams(store=store.root, utterance_id="spk/u0", character=path, mode="bones", bones=4,
                                       sources=["ground_truth"], size=96, out=tmp_path / "bones.mp4"))
    assert bones["sources"] == ["ground truth, 4 bones"] and width_and_frames(tmp_path / "bones.mp4")[0] == 96
    config = AnimateConfig(formats=("glb",), mode="bones", bones=4, preview=True)
    result = animate_flow(AnimateParams(store=store.root, characters=[path], source="ground_truth", config=config))
    report = result["packages_written"][0]
    assert width_and_frames(report["files"]["preview"]) == (2 * 360, report["frames"])
    assert len(solves) == 1
    with pytest.raises(ValueError, match="mode"):
        PreviewParams(store=store.root, utterance_id="spk/u0", mode="skeleton")


def test_the_lips_report_counts_the_closures_without_a_preview(tmp_path):
    """The b/p/m closed on the mesh are counted wherever the utterance has phones, as the docs say; the phones were
    read only for a preview, so `animate` without --preview never printed the count."""
    from visemeflow.schemas import PHONES, table_from_rows

    store = make_curve_store(tmp_path / "store", n=1)
    rows = [{C.UTTERANCE_ID: "spk/u0", "index": i, "part": 0, "label": label, C.PHONEME: label, "viseme": viseme,
             C.START_S: start, C.END_S: end} for i, (label, viseme, start, end) in
            enumerate([("AA1", "AHH", 0.1, 0.4), ("B", "MBP", 0.4, 0.5), ("AA1", "AHH", 0.5, 0.9)])]
    store.write_shard("phones", 0, table_from_rows(rows, PHONES))
    (report,) = animate_flow(AnimateParams(store=store.root, source="ground_truth",
                                           config=AnimateConfig(formats=("glb",))))["packages_written"]
    assert report["lips"]["bilabials"] == 1 and 0 <= report["lips"]["closed"] <= 1, report["lips"]
    # `rerun --stage animate` makes the package from the same phones: the next `animate` finds it as its own
    # (before, the rerun left the phones out: a package without the count, which `animate` then made again)
    from visemeflow.flows.params import RerunParams
    from visemeflow.flows.rerun import rerun_flow

    rerun_flow(RerunParams(utterance_id="spk/u0", stage="animate", store=store.root))
    inputs = json.loads((Path(report["folder"]) / ".inputs.json").read_text())
    assert inputs["phones"] is not None
    again = animate_flow(AnimateParams(store=store.root, source="ground_truth", config=AnimateConfig(formats=("glb",))))
    assert again["cached"] == 1 and again["written"] == 0, again


@pytest.fixture
def two_named_good(tmp_path):
    """c1/good.glb (ARKit shapes) and c2/good.glb (Oculus shapes): one file name, two characters."""
    paths = []
    for folder, names, seed in (("c1", list(ARKIT_52), 0), ("c2", list(OCULUS_15), 1)):
        path = tmp_path / folder / "good.glb"
        write_glb(path, tiny_character(names, seed=seed, name=folder), np.zeros((1, len(names)), np.float32), 30.0)
        paths.append(path)
    return paths


def _glb_shapes(report) -> list[str]:
    return list(load_character(report["files"]["glb"]).shape_names)


def test_characters_of_one_file_name_in_different_folders_each_get_their_own_packages(tmp_path, two_named_good):
    store = make_curve_store(tmp_path / "store", n=1)
    result = animate_flow(AnimateParams(store=store.root, characters=two_named_good, source="ground_truth",
                                        config=AnimateConfig(formats=("glb",))))
    assert result["written"] == 2 and result["rejected"] == 0
    folders = {r["folder"] for r in result["packages_written"]}
    assert len(folders) == 2 and all(Path(f).parts[-3].startswith("good-") for f in folders)
    assert sorted(len(_glb_shapes(r)) for r in result["packages_written"]) == [len(OCULUS_15), len(ARKIT_52)]
    # the same batch again: all hits, the same folders
    again = animate_flow(AnimateParams(store=store.root, characters=two_named_good, source="ground_truth",
                                       config=AnimateConfig(formats=("glb",))))
    assert again["cached"] == 2 and {r["folder"] for r in again["packages_written"]} == folders


def test_a_cache_hit_never_serves_a_package_another_character_wrote(tmp_path, two_named_good):
    store = make_curve_store(tmp_path / "store", n=1)
    arkit, oculus = two_named_good

    def run(character, out=None):
        (report,) = animate_flow(AnimateParams(store=store.root, characters=[character], source="ground_truth",
                                               config=AnimateConfig(formats=("glb",)), out=out))["packages_written"]
        return report

    first = run(arkit)
    assert _glb_shapes(first) == list(ARKIT_52) and Path(first["folder"]).parts[-3] == "good"
    # another file of that name, in a run of its own: a folder of its own (animations/good holds c1/good.glb's
    # packages, as its .character says), so c1's package stays and is a cache hit again
    other = run(oculus)
    assert _glb_shapes(other) == list(OCULUS_15) and Path(other["folder"]).parts[-3].startswith("good-")
    again = run(arkit)
    assert again["cached"] and again["folder"] == first["folder"] and _glb_shapes(again) == list(ARKIT_52)
    assert run(oculus)["folder"] == other["folder"]
    # the same under --out: each file's packages in a folder of its own, one run after the other
    out = tmp_path / "out"
    assert Path(run(oculus, out)["folder"]).parts[-3] == "good" and \
        Path(run(arkit, out)["folder"]).parts[-3].startswith("good-")
    assert (out / "good" / "spk" / "u0" / "u0.glb").is_file() and _glb_shapes(run(oculus, out)) == list(OCULUS_15)


def test_speak_rejects_a_bad_audio_file_and_animates_the_others(tmp_path, characters, capfd):
    store = Store(tmp_path / "store")
    tiny_model(store)
    text = tmp_path / "notes.wav"
    text.write_text("not audio")
    result = speak_flow(SpeakParams(store=store.root, model="tiny", audio=[text, AUDIO], characters=[characters[0]],
                                    out=tmp_path / "out", config=AnimateConfig(formats=("glb",))))
    (report,) = result["packages_written"]
    assert report["utterance_id"] == "predict/SSB16240001" and Path(report["files"]["glb"]).is_file()
    assert result["audio_rejected"] == 1 and result["rejected"] == 0
    assert [r["audio"] for r in result["rejects"]] == [str(text)]
    (row,) = store.read_table("rejects", "predict").to_pylist()
    assert row[C.PATH] == str(text) and row[C.ERROR_TYPE] == "UnreadableAudio"
    # the file named once, and each decoder's reason without its own copies of the path
    assert row[C.MESSAGE].count(str(text)) == 1 and "neither soundfile nor FFmpeg" in row[C.MESSAGE], row[C.MESSAGE]

    from typer.testing import CliRunner

    from visemeflow.cli import app

    done = CliRunner().invoke(app, ["speak", str(text), str(AUDIO), "--model", "tiny", "--store", str(store.root),
                                    "--character", str(characters[0]), "--format", "glb", "--out",
                                    str(tmp_path / "out")])
    assert done.exit_code == 1, done.output
    assert ("speak: 2 audio files on 1 character (model tiny): 0 animations written, 1 reused from the store "
            "(cached), 1 audio file rejected; " in done.output), done.output
    assert f"rejected {text}: " in done.output

    # a click too short for one frame of curves alone: a reject in one line, the run failed, no traceback
    click = tmp_path / "click.wav"
    sf.write(click, np.full(96, 0.01, np.float32), 16000)   # 6 ms: no frame at 30 fps
    capfd.readouterr()
    state = speak_flow(SpeakParams(store=store.root, model="tiny", audio=[click], characters=[characters[0]],
                                   out=tmp_path / "out"), return_state=True)
    assert state.is_failed()
    assert state.message.startswith(f"predict: every audio file was rejected: {click}: 6 ms of audio makes no "
                                    "frame of curves at 30 fps"), state.message
    assert "Traceback" not in "".join(capfd.readouterr())
    rows = {r[C.PATH]: r for r in store.read_table("rejects", "predict").to_pylist()}
    assert sorted(rows) == sorted([str(text), str(click)])   # the earlier batch's reject stays listed
    assert rows[str(click)][C.ERROR_TYPE] == "AudioTooShort"
