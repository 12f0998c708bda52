"""--device auto|cpu|cuda and mixed precision (visemeflow.learning.device). CUDA is simulated by patching
torch.cuda's queries; the one test that needs a real GPU is skipped without one."""

from __future__ import annotations

import pytest
import torch

from visemeflow.learning.device import (
    DEVICE_CHOICES,
    DeviceError,
    autocast_context,
    grad_scaler,
    resolve_device,
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


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_on_a_real_gpu():
    device = resolve_device("auto")
    assert device.type == "cuda"
    a = torch.randn(16, 16, device=device)
    with autocast_context(device, "bf16" if torch.cuda.is_bf16_supported() else "fp16"):
        assert (a @ a).dtype in (torch.bfloat16, torch.float16)
    assert (a @ a).dtype == torch.float32
