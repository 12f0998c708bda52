"""--device auto|cpu|cuda and mixed precision (visemeflow.learning.device), and the device through training,
evaluation, prediction, the flows and the commands. CUDA is simulated by patching torch.cuda's queries; the one test
that needs a real GPU is skipped without one. The command tests (`visemeflow train|sweep|evaluate|predict --device`)
need the --device options of visemeflow/cli.py."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from factories import DEMO_AUDIO

from visemeflow.learning.device import (
    DEVICE_CHOICES,
    NO_CUDA,
    PRECISION_CHOICES,
    DeviceError,
    autocast_context,
    check_device_word,
    grad_scaler,
    model_device,
    resolve_device,
    resolve_precision,
)


@pytest.fixture
def no_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)


@pytest.fixture
def two_gpus(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)


def test_auto_is_the_cpu_without_cuda(no_cuda):
    assert resolve_device("auto") == torch.device("cpu")


def test_auto_is_the_gpu_with_cuda(two_gpus):
    assert resolve_device("auto") == torch.device("cuda")


@pytest.mark.parametrize("word", ["cpu", " CPU ", "Cpu"])
def test_cpu_whatever_the_machine(word, two_gpus):
    assert resolve_device(word) == torch.device("cpu")


def test_cuda_without_cuda_is_a_one_line_error(no_cuda):
    for word in ("cuda", "cuda:0", "CUDA"):
        with pytest.raises(DeviceError) as err:
            resolve_device(word)
        assert str(err.value) == (
            "cuda requested but torch.cuda.is_available() is False (CPU-only torch build or no GPU); "
            "use --device cpu or auto"
        )
        assert "\n" not in str(err.value)


def test_cuda_and_an_index(two_gpus):
    assert resolve_device("cuda") == torch.device("cuda")
    assert resolve_device("cuda:1") == torch.device("cuda", 1)
    with pytest.raises(DeviceError, match=r"cuda:2 requested but torch sees 2 CUDA device\(s\) \(cuda:0..cuda:1\)"):
        resolve_device("cuda:2")


@pytest.mark.parametrize("word", ["gpu", "", "cuda:x", "mps", "cuda:-1"])
def test_unknown_words_name_the_choices(word):
    with pytest.raises(DeviceError, match="unknown device .*expected one of auto, cpu, cuda"):
        resolve_device(word)
    assert DEVICE_CHOICES == ("auto", "cpu", "cuda")


@pytest.mark.parametrize("dtype", ["bf16", "fp16", None])
def test_autocast_is_a_no_op_on_the_cpu(dtype):
    torch.manual_seed(0)
    a, b = torch.randn(8, 8), torch.randn(8, 8)
    lstm = torch.nn.LSTM(8, 4, batch_first=True)
    with torch.no_grad():
        ref_mm, ref_lstm = a @ b, lstm(a[None])[0]
        with autocast_context(torch.device("cpu"), dtype):
            assert not torch.is_autocast_enabled("cpu") and not torch.is_autocast_enabled("cuda")
            mm, out = a @ b, lstm(a[None])[0]
    assert mm.dtype == torch.float32 and torch.equal(mm, ref_mm) and torch.equal(out, ref_lstm)


def test_autocast_refuses_what_it_cannot_do(no_cuda, monkeypatch):
    with pytest.raises(DeviceError, match="unknown autocast dtype 'fp8'"):
        with autocast_context("cpu", "fp8"):  # type: ignore[arg-type]
            pass
    # torch itself would only warn and run in float32; a requested GPU must not silently become the CPU
    with pytest.raises(DeviceError, match="cuda requested but torch.cuda.is_available"):
        with autocast_context("cuda", "bf16"):
            pass
    with autocast_context("cuda", None):  # no precision change asked for: nothing to refuse
        assert not torch.is_autocast_enabled("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *a, **k: False)
    with pytest.raises(DeviceError, match="no bfloat16 support; use fp16"):
        with autocast_context("cuda", "bf16"):
            pass


def test_grad_scaler_only_for_fp16_on_cuda(two_gpus):
    assert not grad_scaler("cpu", "fp16").is_enabled()
    assert not grad_scaler("cuda", "bf16").is_enabled()
    assert not grad_scaler("cuda", None).is_enabled()
    assert grad_scaler("cuda", "fp16").is_enabled()
    loss = torch.tensor(2.0)
    assert grad_scaler("cpu", None).scale(loss) is loss  # disabled: a pass-through


def test_precision_words(two_gpus, monkeypatch):
    assert PRECISION_CHOICES == ("auto", "fp32", "bf16", "fp16")
    for word in (*PRECISION_CHOICES, None):  # the CPU always computes in float32
        assert resolve_precision("cpu", word) is None
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *a, **k: True)
    assert [resolve_precision("cuda", w) for w in ("auto", "fp32", "bf16", "fp16", None)] == [
        "bf16", None, "bf16", "fp16", None]
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *a, **k: False)
    assert resolve_precision("cuda", "auto") is None  # never fp16 behind the user's back
    with pytest.raises(DeviceError, match="no bfloat16 support"):
        resolve_precision("cuda", "bf16")
    with pytest.raises(DeviceError, match="unknown precision 'half'; expected one of auto, fp32, bf16, fp16"):
        resolve_precision("cpu", "half")


def test_device_words_are_checked_for_spelling_only(no_cuda):
    assert check_device_word(" CUDA:1 ") == "cuda:1" and check_device_word("Auto") == "auto"
    with pytest.raises(DeviceError, match="unknown device 'gpu'"):
        check_device_word("gpu")
    from pydantic import ValidationError

    from visemeflow.flows.params import EvaluateParams, SweepParams, TrainParams
    from visemeflow.flows.predict import PredictParams

    assert TrainParams(device="CUDA").device == "cuda"  # made on a machine without CUDA: it may run elsewhere
    assert TrainParams().device == "auto" and TrainParams().precision == "auto"
    makers = (lambda: TrainParams(device="gpu"), lambda: SweepParams(device="gpu"),
              lambda: EvaluateParams(models=["m"], device="gpu"), lambda: PredictParams(audio=["a.wav"], device="gpu"))
    for make in makers:
        with pytest.raises(ValidationError, match="unknown device 'gpu'; expected one of auto, cpu, cuda"):
            make()
    with pytest.raises(ValidationError):
        TrainParams(precision="half")


def test_model_device():
    assert model_device(torch.nn.Linear(2, 2)) == torch.device("cpu")
    assert model_device(torch.nn.Identity()) == torch.device("cpu")
    assert model_device(torch.nn.Linear(2, 2).to("meta")) == torch.device("meta")


# --------------------------------------------------------------------------------------------------
# training, evaluation and prediction on a device


def _examples(n: int, seed: int):
    sys.path.insert(0, str(Path(__file__).parent))
    from factories import envelope_examples as make_examples

    return make_examples(n, seed=seed)


def _same(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_train_evaluate_and_predict_accept_cpu_and_auto(no_cuda, tmp_path):
    from visemeflow.learning.train import TrainConfig, evaluate, load_model, predict_curves, save_model, train_model

    train, val = _examples(2, 1), _examples(1, 2)
    cfg = TrainConfig(preset="fbank-blstm", epochs=2, d_model=8, lr=1e-3)
    ref = train_model(train, val, cfg)  # the default: the CPU
    # the CPU trains in float32 whatever precision is asked
    for device, precision in (("cpu", "auto"), ("auto", "bf16"), ("auto", "fp16"), (torch.device("cpu"), "fp32")):
        res = train_model(train, val, cfg, device=device, precision=precision)
        assert _same(ref.model, res.model) and model_device(res.model) == torch.device("cpu")
        assert [h.val_l1_x100 for h in res.history] == [h.val_l1_x100 for h in ref.history]
    path = save_model(ref.model, cfg, tmp_path / "m.pt", {})
    for device in ("cpu", "auto", None):
        model = load_model(path, device=device)[0]
        assert model_device(model) == torch.device("cpu") and _same(ref.model, model)
        got, want = evaluate(model, val, precision="auto"), evaluate(ref.model, val)
        assert got[:2] == want[:2] and np.array_equal(got[2], want[2])
        np.testing.assert_array_equal(predict_curves(model, val[0].audio, 16000, 25.0, precision="bf16"),
                                      predict_curves(ref.model, val[0].audio, 16000, 25.0))


def test_cuda_without_cuda_fails_in_one_line_before_any_work(no_cuda, tmp_path):
    from visemeflow.learning.train import TrainConfig, build_training_model, load_model, save_model, train_model

    epochs = []
    for device in ("cuda", "cuda:0"):
        with pytest.raises(DeviceError) as err:
            train_model(_examples(1, 1), [], TrainConfig(preset="fbank-tcn", epochs=1, d_model=8),
                        checkpoint_dir=tmp_path / "ck", on_epoch=epochs.append, device=device)
        assert str(err.value) == NO_CUDA
    assert epochs == [] and not (tmp_path / "ck").exists()
    cfg = TrainConfig(preset="fbank-tcn", d_model=8)
    path = save_model(build_training_model(cfg, 25.0), cfg, tmp_path / "m.pt", {})
    with pytest.raises(DeviceError, match="^cuda requested but torch.cuda.is_available"):
        load_model(path, device="cuda")


def _as_if_saved_on_a_gpu(monkeypatch):
    """Every storage torch.save writes from now on is tagged as a CUDA storage (what a GPU run writes)."""
    import torch.serialization

    monkeypatch.setattr(torch.serialization, "location_tag", lambda storage: "cuda:0")


def test_files_written_on_a_gpu_load_and_resume_on_the_cpu(no_cuda, tmp_path, monkeypatch):
    from visemeflow.learning.train import TrainConfig, load_model, save_model, train_model

    train = _examples(2, 3)
    cfg = TrainConfig(preset="fbank-blstm", epochs=2, d_model=8, lr=1e-3, seed=4)
    full = train_model(train, [], cfg)
    with monkeypatch.context() as m:
        _as_if_saved_on_a_gpu(m)
        train_model(train, [], cfg.model_copy(update={"epochs": 1}), checkpoint_dir=tmp_path / "ck")
        save_model(full.model, cfg, tmp_path / "m.pt", {"where": "gpu"})
    for written in (tmp_path / "ck" / "last.pt", tmp_path / "m.pt"):  # really CUDA-tagged: a plain load fails here
        with pytest.raises(RuntimeError, match="CUDA"):
            torch.load(written, weights_only=True)
    resumed = train_model(train, [], cfg, checkpoint_dir=tmp_path / "ck")  # epoch 2 on the CPU
    assert _same(full.model, resumed.model)
    loaded, _, lineage = load_model(tmp_path / "m.pt")
    assert lineage == {"where": "gpu"} and _same(full.model, loaded)


# --------------------------------------------------------------------------------------------------
# flows and commands: a CUDA request on a machine without CUDA is one line


def _flows(tmp_path):
    from visemeflow.flows.evaluate import evaluate_flow
    from visemeflow.flows.params import EvaluateParams, SweepParams, TrainParams
    from visemeflow.flows.predict import PredictParams, predict_flow
    from visemeflow.flows.sweep import sweep_flow
    from visemeflow.flows.train import train_flow

    store = tmp_path / "store"
    return {
        "train": lambda d: train_flow(TrainParams(store=store, device=d)),
        "sweep": lambda d: sweep_flow(SweepParams(store=store, device=d)),
        "evaluate": lambda d: evaluate_flow(EvaluateParams(store=store, models=["m"], device=d)),
        "predict": lambda d: predict_flow(PredictParams(store=store, model="m", audio=[tmp_path / "a.wav"], device=d)),
    }


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_every_flow_refuses_cuda_without_cuda_first(no_cuda, tmp_path):
    for name, run in _flows(tmp_path).items():
        with pytest.raises(DeviceError) as err:
            run("cuda")
        assert str(err.value) == NO_CUDA, name
        assert not (tmp_path / "store").exists(), f"{name} touched the store before refusing the device"
    with pytest.raises(LookupError):  # on the CPU the same flow gets as far as the (empty) store
        _flows(tmp_path)["evaluate"]("cpu")


COMMANDS = {
    "train": ["train", "--source", "ground_truth"],
    "sweep": ["sweep", "--source", "ground_truth"],
    "evaluate": ["evaluate", "--models", "m"],
    # an audio file and model that exist: a missing model or file is refused first, before torch loads for --device
    "predict": ["predict", str(DEMO_AUDIO), "--model", "default"],
}


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_commands_refuse_cuda_without_cuda_in_one_line(command, no_cuda, tmp_path):
    """Needs the --device options of visemeflow/cli.py."""
    from typer.testing import CliRunner

    from visemeflow.cli import app

    store = tmp_path / "store"
    result = CliRunner().invoke(app, [*COMMANDS[command], "--store", str(store), "--device", "cuda"])
    assert result.exit_code == 2, result.output
    assert result.output.splitlines() == [f"error: {NO_CUDA}"]
    assert not store.exists()
    typo = CliRunner().invoke(app, [*COMMANDS[command], "--store", str(store), "--device", "gpu"])
    assert typo.exit_code == 2 and typo.output.splitlines() == [
        "error: --device: unknown device 'gpu'; expected one of auto, cpu, cuda (or cuda:N)"]
    if command in ("train", "sweep"):
        bad = CliRunner().invoke(app, [*COMMANDS[command], "--store", str(store), "--precision", "half"])
        assert bad.exit_code == 2 and bad.output.splitlines() == [
            "error: --precision must be one of auto, fp32, bf16, fp16, not 'half'"]


def test_the_installed_command_prints_one_line_and_no_traceback(tmp_path):
    """`visemeflow train --device cuda` in a process that sees no GPU (needs the --device options of cli.py)."""
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}
    visemeflow = str(Path(sys.executable).parent / "visemeflow")
    done = subprocess.run([visemeflow, "train", "--store", str(tmp_path / "store"), "--device", "cuda"],
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines() == [f"error: {NO_CUDA}"] and done.stdout == ""


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_on_a_real_gpu(tmp_path):
    device = resolve_device("auto")
    assert device.type == "cuda"
    a = torch.randn(16, 16, device=device)
    with autocast_context(device, "bf16" if torch.cuda.is_bf16_supported() else "fp16"):
        assert (a @ a).dtype in (torch.bfloat16, torch.float16)
    assert (a @ a).dtype == torch.float32
    # train in each precision on the GPU (batched), save, and load the file on the CPU
    from visemeflow.learning.train import TrainConfig, load_model, predict_curves, save_model, train_model

    train = _examples(4, 1)
    cfg = TrainConfig(preset="fbank-blstm", epochs=3, d_model=16, lr=3e-3, batch_size=2)
    for precision in ("fp32", "fp16", "auto"):
        res = train_model(train, train[:1], cfg, device="cuda", precision=precision,
                          checkpoint_dir=tmp_path / precision)
        assert model_device(res.model).type == "cuda" and np.isfinite(res.history[-1].train_l1_x100)
        path = save_model(res.model, cfg, tmp_path / f"{precision}.pt", {})
        cpu = load_model(path, device="cpu")[0]
        assert model_device(cpu) == torch.device("cpu")
        on_cpu = predict_curves(cpu, train[0].audio, 16000, 25.0)
        # float32 on CUDA: cuDNN's convolutions and LSTMs use TF32 tensor cores (PyTorch's default), 10-bit mantissas
        np.testing.assert_allclose(on_cpu, predict_curves(res.model, train[0].audio, 16000, 25.0), atol=2e-3)
        with torch.backends.cudnn.flags(enabled=True, allow_tf32=False):
            np.testing.assert_allclose(on_cpu, predict_curves(res.model, train[0].audio, 16000, 25.0), atol=1e-5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_wav2vec2_batches_and_the_encoder_cache_on_a_real_gpu(tmp_path):
    """Padded batches and the frozen CNN's outputs on the GPU: a disk cache filled by one run answers every step of
    the next, and its keys hold the precision (a float32 run computes its own)."""
    from visemeflow.learning.features import EncoderOutputCache, make_tiny_wav2vec2
    from visemeflow.learning.train import TrainConfig, predict_curves, train_model

    w2v = make_tiny_wav2vec2(tmp_path / "w2v", seed=0)
    train = _examples(4, 2)
    cfg = TrainConfig(preset="wav2vec2-blstm", epochs=3, d_model=16, wav2vec2_model=str(w2v), batch_size=2)
    first = EncoderOutputCache(tmp_path / "enc")
    trained = train_model(train, [], cfg, device="cuda", encoder_cache=first)
    assert (first.misses, first.hits) == (4, 8) and len(list((tmp_path / "enc").glob("*.pt"))) == 4
    again = EncoderOutputCache(tmp_path / "enc")
    retrained = train_model(train, [], cfg, device="cuda", encoder_cache=again)
    assert (again.misses, again.hits) == (0, 12)
    fp32 = EncoderOutputCache(tmp_path / "enc")
    train_model(train, [], cfg, device="cuda", precision="fp32", encoder_cache=fp32)
    assert fp32.misses == 4 and len(list((tmp_path / "enc").glob("*.pt"))) == 8
    for result in (trained, retrained):
        assert model_device(result.model).type == "cuda" and np.isfinite(result.history[-1].train_l1_x100)
        curves = predict_curves(result.model, train[0].audio, 16000, 25.0)
        assert curves.shape[1] == 16 and np.isfinite(curves).all()
