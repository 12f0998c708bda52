"""ONNX export of whisper models (issue 25 item 5): log-mel and the Whisper-base encoder inside the graph.

One whisper-base-blstm (small head, trained two epochs on two LJSpeech clips) is saved and exported once for the
module; the graph is compared with torch's predict_curves on real speech up to one 30-s window (within
WHISPER_TOLERANCE, 1e-3), the graph refuses longer input at run time, and onnx_curves runs longer audio in
crossfaded windows as the module docstring documents. The encoder weights are the package's (`visemeflow[whisper]`,
in `dev`); the model folder is assembled into a temporary cache (VISEMEFLOW_CACHE_DIR).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
import torch

import onnx  # noqa: F401  (the export's dependencies: installed by `.[dev]`)
import onnxruntime

from visemeflow.learning import onnx_export as ox
from visemeflow.learning.train import Example, TrainConfig, predict_curves, save_model, train_model

ROOT = Path(__file__).resolve().parents[1]
LJ = sorted((ROOT / "examples/corpus/LJ").glob("*.wav"))
FPS = 30.0
# needs the Whisper weights of the dev extra (make test installs them): fails, never skips, without them


def read(path: Path) -> np.ndarray:
    a, sr = sf.read(path, dtype="float32")
    assert sr == 16000
    return a


@pytest.fixture(scope="module")
def speech() -> np.ndarray:
    """The LJ clips end to end (about 160 s of one speaker)."""
    return np.concatenate([read(p) for p in LJ])


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """(report, torch model, model file) of a whisper-base-blstm trained two epochs on two LJ clips."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("VISEMEFLOW_CACHE_DIR", str(tmp_path_factory.mktemp("vf-cache")))
        torch.manual_seed(0)
        rng = np.random.default_rng(0)
        train = []
        for p in LJ[:2]:
            a = read(p)[: 16000 * 4]
            train.append(Example(p.stem, a, rng.random((round(len(a) / 16000 * FPS), 16)).astype(np.float32), FPS))
        # with the shipped default's inference-only MBP peaks, so the graph is held to them too
        config = TrainConfig(preset="whisper-base-blstm", d_model=32, epochs=2, batch_size=2,
                             mbp_peaks_half_window_s=0.1, mbp_peaks_power=32.0, mbp_lead_s=0.008,
                             mbp_others_power=3.0)
        model = train_model(train, [], config).model.eval()
        root = tmp_path_factory.mktemp("onnx-whisper")
        path = save_model(model, config, root / "whisper.pt", {"source": "test"})
        report = ox.export_onnx(path, root / "whisper.onnx")
        yield report, model, path


def test_graph_equals_torch_up_to_one_window(exported, speech):
    report, model, _ = exported
    assert report.feature == "whisper" and report.opset == 17 and report.preset == "whisper-base-blstm"
    assert report.max_abs_diff is not None and report.max_abs_diff <= ox.WHISPER_TOLERANCE
    assert report.max_samples == 480_159  # n // 160 <= 3000 mel frames: one window in whisper.py
    proto = onnx.load(report.path)
    assert [(o.domain, o.version) for o in proto.opset_import] == [("", 17)]
    ops = {n.op_type for n in proto.graph.node}
    assert "LSTM" in ops and "Conv" in ops and not ops & {"DFT", "STFT", "Loop", "If", "Scan"}
    assert all(i.data_type == onnx.TensorProto.FLOAT for i in proto.graph.initializer if len(i.dims) == 2)
    assert report.size_bytes > 70e6  # the encoder's 20.6 M weights in float32
    meta = {p.key: p.value for p in proto.metadata_props}
    assert meta["visemeflow.max_samples"] == "480159" and "crossfade" in meta["visemeflow.long_audio"]
    clips = {"LJ001-0001": read(LJ[0]), "0.5 s": speech[:8000], "min": speech[: report.min_samples],
             "one window": speech[: report.max_samples]}
    sess = ox._session(report.path)
    for name, x in clips.items():
        want = predict_curves(model, x, 16000, FPS)
        got = ox.onnx_curves(sess, x)
        assert got.shape == want.shape and want.shape[0] >= 1, name
        assert np.abs(got - want).max() <= ox.WHISPER_TOLERANCE, (name, float(np.abs(got - want).max()))
        if name != "min":
            assert want.std() > 1e-3, name


def test_longer_audio_fails_in_the_graph_and_goes_in_windows_through_onnx_curves(exported, speech):
    report, model, _ = exported
    sess = ox._session(report.path, threads=2)
    with pytest.raises(onnxruntime.capi.onnxruntime_pybind11_state.Fail, match="ConstantOfShape"):
        sess.run(None, {"audio": speech[None, : report.max_samples + 1]})
    x = speech[: 16000 * 40]  # two windows: [0, 30 s) and [10 s, 40 s), crossfaded over 10-30 s
    got = ox.onnx_curves(sess, x)
    assert got.shape == (1200, 16)
    first = sess.run(None, {"audio": x[None, : 16000 * 30]})[0][0]
    second = sess.run(None, {"audio": x[None, 16000 * 10 :]})[0][0]
    np.testing.assert_allclose(got[:300], first[:300], atol=1e-6)  # outside the overlap: the window's own
    np.testing.assert_allclose(got[900:], second[600:], atol=1e-6)
    mid = got[300:900]
    assert np.all(mid >= np.minimum(first[300:900], second[:600]) - 1e-6)  # a convex blend of the two
    assert np.all(mid <= np.maximum(first[300:900], second[:600]) + 1e-6)
    # not what torch computes past one window (it crossfades encoder features under one BLSTM pass): printed
    want = predict_curves(model, x, 16000, FPS)
    print(f"40-s clip, windowed ONNX vs torch: max |diff| {np.abs(got - want).max():.3f}, "
          f"mean {np.abs(got - want).mean():.4f}")


def test_cli_export_model_exports_a_whisper_model(exported, tmp_path):
    from typer.testing import CliRunner

    from visemeflow.cli import app
    from visemeflow.storage import Store

    _, _, path = exported
    store = Store(tmp_path / "store")
    store.model_path("wb").parent.mkdir(parents=True, exist_ok=True)
    store.model_path("wb").write_bytes(path.read_bytes())
    out = tmp_path / "wb.onnx"
    result = CliRunner().invoke(app, ["export-model", "wb", "--out", str(out), "--store", str(store.root)])
    assert result.exit_code == 0, result.output  # checked against torch within WHISPER_TOLERANCE
    assert "whisper-base-blstm" in result.output and "onnxruntime vs torch max |diff|" in result.output
    (curves,) = ox._session(out).run(None, {"audio": np.zeros((1, 16000), np.float32)})
    assert curves.shape == (1, 30, 16)
