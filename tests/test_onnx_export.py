"""ONNX export of saved curve models (visemeflow.learning.onnx_export): onnxruntime on CPU against
torch's predict_curves for every exportable preset, on three clip lengths (the time axis is dynamic),
in-graph resampling, opsets, the frame-count rule, and clear errors for what cannot be exported."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
import torch
from factories import DEMO_CORPUS

# installed by `.[dev]` (make test): a missing one fails the tests, never skips them
import onnx  # noqa: E402
import onnxruntime  # noqa: E402, F401
import onnxscript  # noqa: E402, F401

from visemeflow.learning import onnx_export as ox  # noqa: E402
from visemeflow.learning.features import (  # noqa: E402
    FeatureConfig,
    build_feature_extractor,
    make_tiny_wav2vec2,
    resample_audio,
)
from visemeflow.learning.presets import PRESETS  # noqa: E402
from visemeflow.learning.train import TrainConfig, build_training_model, predict_curves, save_model  # noqa: E402
from visemeflow.visemes import VISEMES  # noqa: E402

SPEECH = DEMO_CORPUS / "LJ" / "LJ001-0001.wav"  # 9.7 s of 16 kHz speech
FPS = 30.0
TOL = 1e-4
LENGTHS_S = (0.5, 2.3, 7.0)


@pytest.fixture(scope="module")
def speech() -> np.ndarray:
    audio, rate = sf.read(SPEECH, dtype="float32")
    assert rate == 16000 and audio.ndim == 1 and len(audio) >= 7 * rate
    return audio


@pytest.fixture(scope="module")
def w2v_dir(tmp_path_factory):
    return make_tiny_wav2vec2(tmp_path_factory.mktemp("w2v") / "tiny")


def save_tiny(path, preset: str, w2v_dir=None, seed: int = 0, fps: float = FPS):
    """An untrained small model of ``preset`` (fixed seed) saved like a trained one; returns (path, model)."""
    torch.manual_seed(seed)
    config = TrainConfig(preset=preset, d_model=16, seed=seed,
                         wav2vec2_model=str(w2v_dir) if PRESETS[preset].feature == "wav2vec2" else None)
    model = build_training_model(config, curve_fps=fps)
    if preset == "mean-curve":  # fit it, so that its curve is not all zeros
        model.head.fit([np.random.default_rng(seed).uniform(0, 1, (50, 16))])
    model.eval()
    save_model(model, config, path, {"source": "test"})
    return path, model


@pytest.fixture(scope="module")
def exported(tmp_path_factory, w2v_dir):
    """preset -> (report, torch model), exported once per module on first use."""
    root = tmp_path_factory.mktemp("onnx")
    cache: dict = {}

    def get(preset: str):
        if preset not in cache:
            path, model = save_tiny(root / f"{preset}.pt", preset, w2v_dir)
            cache[preset] = (ox.export_onnx(path, root / f"{preset}.onnx"), model)
        return cache[preset]

    return get


def test_the_preset_lists_split_every_preset():
    assert set(ox.EXPORTABLE_PRESETS) | set(ox.NOT_EXPORTABLE) == set(PRESETS)
    assert set(ox.NOT_EXPORTABLE) == {"faceformer-fbank", "faceformer-wav2vec2"}
    assert not set(ox.EXPORTABLE_PRESETS) & set(ox.NOT_EXPORTABLE)


# whisper presets need the package weights (or the hub): tests/test_onnx_whisper.py
@pytest.mark.parametrize("preset", [p for p in ox.EXPORTABLE_PRESETS if PRESETS[p].feature != "whisper"])
def test_onnx_curves_equal_torch_on_three_lengths(preset, exported, speech):
    report, model = exported(preset)
    assert report.preset == preset and report.opset == ox.DEFAULT_OPSET
    assert report.sample_rate == 16000 and report.fps == FPS
    assert report.max_abs_diff is not None and report.max_abs_diff <= TOL  # the export's own check ran
    assert report.uses_float64 == (PRESETS[preset].feature == "lpc" and preset != "mean-curve")
    frames = set()
    for seconds in LENGTHS_S:
        x = speech[: round(seconds * 16000)]
        want = predict_curves(model, x, 16000, FPS)
        got = ox.onnx_curves(report.path, x)
        assert got.shape == want.shape == (round(seconds * FPS), 16)
        assert np.abs(got - want).max() <= TOL, (preset, seconds, float(np.abs(got - want).max()))
        if preset != "mean-curve":  # a comparison of two all-zero (clipped) outputs would prove nothing
            assert want.std() > 1e-3
        frames.add(got.shape[0])
    assert len(frames) == 3
    # the shortest input the report promises works too
    x = speech[: report.min_samples]
    want = predict_curves(model, x, 16000, FPS)
    got = ox.onnx_curves(report.path, x)
    assert got.shape == want.shape and want.shape[0] >= 1 and np.abs(got - want).max() <= TOL


def test_graph_signature_opset_and_metadata(exported):
    report, _ = exported("fbank-blstm")
    proto = onnx.load(report.path)
    onnx.checker.check_model(proto, full_check=True)
    assert [(o.domain, o.version) for o in proto.opset_import] == [("", 17)]
    (inp,), (out,) = proto.graph.input, proto.graph.output
    assert inp.name == "audio" and inp.type.tensor_type.elem_type == onnx.TensorProto.FLOAT
    assert [d.dim_value or d.dim_param for d in inp.type.tensor_type.shape.dim] == [1, "n_samples"]
    assert out.name == "curves" and out.type.tensor_type.elem_type == onnx.TensorProto.FLOAT
    assert [d.dim_value or d.dim_param for d in out.type.tensor_type.shape.dim] == [1, "n_frames", 16]
    meta = {p.key: p.value for p in proto.metadata_props}
    assert meta["viseme_names"].split(",") == list(VISEMES)
    assert meta["visemeflow.preset"] == "fbank-blstm" and float(meta["visemeflow.fps"]) == FPS
    assert int(meta["visemeflow.min_samples"]) == report.min_samples == 400  # one 25 ms window
    ops = {n.op_type for n in proto.graph.node}
    assert ops == set(report.ops) and "LSTM" in ops
    assert not ops & {"DFT", "STFT", "Loop", "If", "Scan"}  # features as Conv/MatMul, no control flow
    assert all(n.domain in ("", "ai.onnx") for n in proto.graph.node)
    assert not report.uses_float64
    assert report.size_bytes == report.path.stat().st_size


def test_frame_count_is_exact_with_ties_to_even():
    for rate, fps in ((16000, 25.0), (16000, 30.0), (44100, 29.97), (48000, 60.0)):
        for n in range(1, 60000, 7):
            exact = n * fps / rate
            if abs(exact - round(exact) - 0.5) > 1e-6 and abs(exact - round(exact) + 0.5) > 1e-6:
                assert ox.n_frames_for(n, rate, fps) == round(n / rate * fps)
    # exact half-frame ties go to the even neighbour (predict_curves's float expression may not)
    assert ox.n_frames_for(34880, 16000, 25.0) == 54  # 54.5
    assert ox.n_frames_for(16320, 16000, 25.0) == 26  # 25.5
    assert ox.n_frames_for(320, 16000, 25.0) == 0  # 0.5


def test_fps_override_and_a_tie_length(tmp_path, speech):
    path, model = save_tiny(tmp_path / "m.pt", "fbank-tcn", fps=30.0)
    report = ox.export_onnx(path, tmp_path / "m25.onnx", fps=25.0)
    assert report.fps == 25.0
    for n in (34880, 34880 + 640 * 3 + 1):  # a tie (54.5 frames) and an ordinary length
        x = speech[:n]
        t = ox.n_frames_for(n, 16000, 25.0)
        got = ox.onnx_curves(report.path, x)
        want = predict_curves(model, x, 16000, 25.0, n_frames=t)
        assert got.shape == (t, 16) and np.abs(got - want).max() <= TOL


@pytest.mark.parametrize("rate", [44100, 8000])
def test_resampling_inside_the_graph(rate, tmp_path, speech):
    path, model = save_tiny(tmp_path / "m.pt", "fbank-blstm")
    report = ox.export_onnx(path, tmp_path / f"m{rate}.onnx", sample_rate=rate)
    assert report.sample_rate == rate and any("resamples" in n for n in report.notes)
    audio = resample_audio(speech[: 16000 * 4], 16000, rate)
    for seconds in (0.7, 3.3):
        x = audio[: round(seconds * rate)]
        want = predict_curves(model, x, rate, FPS)  # resamples to 16 kHz in float64 first
        got = ox.onnx_curves(report.path, x)
        assert got.shape == want.shape and np.abs(got - want).max() <= TOL


def test_a_rate_the_graph_cannot_resample_is_refused(tmp_path):
    path, _ = save_tiny(tmp_path / "m.pt", "mean-curve")
    with pytest.raises(ox.OnnxExportError, match="44101 cannot be resampled inside the graph"):
        ox.export_onnx(path, tmp_path / "m.onnx", sample_rate=44101)
    assert not (tmp_path / "m.onnx").exists()


def test_opset_15_for_engines_that_read_no_newer(tmp_path, speech):
    path, model = save_tiny(tmp_path / "m.pt", "fbank-blstm")
    report = ox.export_onnx(path, tmp_path / "m15.onnx", opset=15)
    proto = onnx.load(report.path)
    assert [(o.domain, o.version) for o in proto.opset_import] == [("", 15)]
    onnx.checker.check_model(proto, full_check=True)
    x = speech[:16000 * 2]
    assert np.abs(ox.onnx_curves(report.path, x) - predict_curves(model, x, 16000, FPS)).max() <= TOL
    tpath, _ = save_tiny(tmp_path / "t.pt", "fbank-transformer")
    with pytest.raises(ox.OnnxExportError, match="opset 15.*LayerNormalization"):
        ox.export_onnx(tpath, tmp_path / "t15.onnx", opset=15)
    with pytest.raises(ox.OnnxExportError, match="opset must be in"):
        ox.export_onnx(path, tmp_path / "m9.onnx", opset=9)


@pytest.mark.parametrize("preset", sorted(n for n, p in PRESETS.items() if p.architecture == "faceformer"))
def test_faceformer_presets_are_refused_with_the_reason(preset, tmp_path, w2v_dir):
    path, _ = save_tiny(tmp_path / "f.pt", preset, w2v_dir)
    with pytest.raises(ox.OnnxExportError, match=f"preset '{preset}' cannot be exported.*autoregressive"):
        ox.export_onnx(path, tmp_path / "f.onnx")
    assert not (tmp_path / "f.onnx").exists()


def test_files_that_are_not_this_versions_models_are_refused(tmp_path):
    out = tmp_path / "x.onnx"
    with pytest.raises(ox.OnnxExportError, match="no such model file"):
        ox.export_onnx(tmp_path / "missing.pt", out)
    text = tmp_path / "notes.pt"
    text.write_text("not a model")
    with pytest.raises(ox.OnnxExportError, match="is not a visemeflow model file"):
        ox.export_onnx(text, out)
    lst = tmp_path / "list.pt"
    torch.save([1, 2, 3], lst)
    with pytest.raises(ox.OnnxExportError, match="holds no visemeflow model"):
        ox.export_onnx(lst, out)

    good, _ = save_tiny(tmp_path / "good.pt", "fbank-tcn")
    blob = torch.load(good, weights_only=True)
    newer = tmp_path / "newer.pt"
    torch.save({**blob, "format": "visemeflow-curve-model/2"}, newer)
    with pytest.raises(ox.OnnxExportError, match="written by another visemeflow version.*curve-model/2"):
        ox.export_onnx(newer, out)
    extra = tmp_path / "extra.pt"  # a TrainConfig field this version does not know
    torch.save({**blob, "config": json.dumps({**json.loads(blob["config"]), "device": "cuda"})}, extra)
    with pytest.raises(ox.OnnxExportError, match="config does not validate.*another visemeflow version"):
        ox.export_onnx(extra, out)
    weights = tmp_path / "weights.pt"  # weights of another architecture
    torch.save({**blob, "state_dict": {k: v for k, v in blob["state_dict"].items() if "convs" not in k}}, weights)
    with pytest.raises(ox.OnnxExportError, match="missing weights head.decoder.convs.0.weight"):
        ox.export_onnx(weights, out)
    assert not out.exists()


def test_the_check_fails_when_the_graph_disagrees(tmp_path, monkeypatch):
    path, _ = save_tiny(tmp_path / "m.pt", "mean-curve")
    real = ox.onnx_curves
    monkeypatch.setattr(ox, "onnx_curves", lambda p, a, **kw: real(p, a, **kw) + 2e-4)
    with pytest.raises(ox.OnnxExportError, match="differ from torch by 0.0002"):
        ox.export_onnx(path, tmp_path / "m.onnx")
    report = ox.export_onnx(path, tmp_path / "m.onnx", check=False)
    assert report.max_abs_diff is None


def test_a_failed_check_keeps_the_previous_export(tmp_path, monkeypatch):
    """The graph is written beside the target and checked there; only a graph that passes replaces the file."""
    path, _ = save_tiny(tmp_path / "m.pt", "mean-curve")
    out = tmp_path / "m.onnx"
    ox.export_onnx(path, out)
    before = out.read_bytes()
    checked = []
    real = ox.onnx_curves

    def off(p, a, **kw):
        checked.append(Path(p))
        return real(p, a, **kw) + 2e-4

    monkeypatch.setattr(ox, "onnx_curves", off)
    other, _ = save_tiny(tmp_path / "other.pt", "mean-curve", seed=1)
    with pytest.raises(ox.OnnxExportError, match=f"{out}: ONNX curves differ from torch by 0.0002"):
        ox.export_onnx(other, out)
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.onnx", "m.pt", "other.pt"]
    assert checked[0].parent == out.parent and checked[0] != out


def test_lpc_white_noise_correction_survives_the_optimisers(speech):
    """r0 * (1 + 1e-9) + 1e-12: onnxscript's and onnxruntime's optimisers both dropped a plain Mul/Add by
    these constants, which moved ill-conditioned frames' coefficients by 7e-3 (now about 5e-7)."""
    ext = build_feature_extractor(FeatureConfig(kind="lpc", normalize=False))
    proto = ox._to_onnx(ox._LpcGraph(ext).eval(), torch.from_numpy(speech[:16000])[None], 17, out_dim=12)
    sess = ox._session(proto.SerializeToString())
    x = speech[: 16000 * 7]
    got = sess.run(None, {"audio": x[None]})[0][0]
    with torch.no_grad():
        want = ext(torch.from_numpy(x)[None])[0][0].numpy()
    assert got.shape == want.shape
    assert np.abs(got - want).max() <= 1e-5


def test_the_lstm_op_matches_torch_in_both_directions_and_layers():
    torch.manual_seed(0)
    lstm = torch.nn.LSTM(6, 5, num_layers=2, batch_first=True, bidirectional=True).eval()
    x = torch.randn(1, 17, 6)
    with torch.no_grad():
        assert torch.allclose(ox._LstmStack(lstm)(x), lstm(x)[0], atol=1e-6)


def test_the_shipped_default_model_exports(tmp_path, speech):
    """A trained model (the package's previous default, fbank-blstm, d 128), not only untrained ones; the whisper
    default's encoder does not export yet (issue 25 item 5)."""
    from visemeflow.learning.default_model import shipped_model_path
    from visemeflow.learning.train import load_model

    path = shipped_model_path("default-fbank")
    assert path.is_file(), f"{path} missing: the package ships a default model (examples/train_default_model.py)"
    model, config, _ = load_model(path)
    report = ox.export_onnx(path, tmp_path / "default.onnx")
    assert report.preset == config.preset and report.fps == model.head.curve_fps
    for seconds in LENGTHS_S:
        x = speech[: round(seconds * 16000)]
        want = predict_curves(model, x, 16000, report.fps)
        got = ox.onnx_curves(report.path, x)
        assert got.shape == want.shape and want.std() > 1e-3 and np.abs(got - want).max() <= TOL
