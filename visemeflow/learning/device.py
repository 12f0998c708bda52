"""Where models run: ``--device auto|cpu|cuda`` and mixed precision (pure torch, no Prefect).

:func:`resolve_device` turns the command-line word into a ``torch.device``:

* ``auto``: ``cuda`` when ``torch.cuda.is_available()``, else ``cpu``;
* ``cpu``;
* ``cuda`` or ``cuda:N``: the GPU, or :class:`DeviceError` (one line) when this torch has no CUDA or no GPU
  is visible, or when there is no device N. Nothing falls back to the CPU silently when a GPU was asked for.

:func:`autocast_context` is the mixed-precision context for a forward pass: ``torch.autocast`` on CUDA with
bfloat16 (``"bf16"``) or float16 (``"fp16"``), and a no-op on the CPU or with ``dtype=None``, so CPU runs stay
bit-identical to runs without it. Training in fp16 also needs loss scaling (:func:`grad_scaler`); bf16 does
not. The CPU is the reference: the exact-resume guarantee of ``train_model`` (bit-identical weights) holds
there; CUDA kernels (cuDNN LSTMs, atomics in reductions) are not bit-reproducible by default.

:func:`resolve_precision` turns ``--precision auto|fp32|bf16|fp16`` into the autocast dtype for a device:
``auto`` is bf16 on a CUDA GPU that supports it and float32 (None) everywhere else; the CPU always runs in
float32, whatever was asked (autocast is only used on CUDA). :func:`check_device_word` checks the spelling of a
device word without asking whether the device exists (flow parameters are validated where they are made, the
device is resolved where the work runs).
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import AfterValidator

if TYPE_CHECKING:   # torch is imported where a device is resolved: `--device cpu` on a cached run never loads it
    import torch

__all__ = [
    "DEVICE_CHOICES",
    "PRECISION_CHOICES",
    "AutocastDtype",
    "DeviceError",
    "DeviceWord",
    "autocast_context",
    "check_device_here",
    "check_device_word",
    "grad_scaler",
    "model_device",
    "resolve_device",
    "resolve_precision",
]

DEVICE_CHOICES = ("auto", "cpu", "cuda")  # what --device offers (cuda:N is accepted too)
PRECISION_CHOICES = ("auto", "fp32", "bf16", "fp16")  # what --precision offers
AutocastDtype = Literal["bf16", "fp16"]
Precision = Literal["auto", "fp32", "bf16", "fp16"]
_AUTOCAST_DTYPES: dict[str, str] = {"bf16": "bfloat16", "fp16": "float16"}   # names of torch dtypes
_CUDA_N = re.compile(r"^cuda(?::(\d+))?$")

NO_CUDA = (
    "cuda requested but torch.cuda.is_available() is False (CPU-only torch build or no GPU); "
    "use --device cpu or auto"
)


class DeviceError(RuntimeError):
    """The requested device cannot be used here; the message is one line, fit for a command's error output."""


def check_device_word(request: str) -> str:
    """The device word normalised (``" CUDA:1 "`` -> ``"cuda:1"``), or :class:`DeviceError` for an unknown one.

    Only the spelling is checked: whether this machine has the device is :func:`resolve_device`'s question.
    """
    word = str(request).strip().lower()
    if word not in ("auto", "cpu") and _CUDA_N.match(word) is None:
        raise DeviceError(f"unknown device {request!r}; expected one of {', '.join(DEVICE_CHOICES)} (or cuda:N)")
    return word


def _valid_word(request: str) -> str:
    try:
        return check_device_word(request)
    except DeviceError as exc:
        raise ValueError(str(exc)) from None


# A flow parameter naming a device: spelling checked (and normalised) when the parameters are made; whether the
# machine has it is asked where the work runs (resolve_device).
DeviceWord = Annotated[str, AfterValidator(_valid_word)]


def resolve_device(request: str | torch.device) -> torch.device:
    """``auto`` / ``cpu`` / ``cuda`` / ``cuda:N`` (case and surrounding spaces ignored) -> ``torch.device``.

    A ``torch.device`` is checked the same way (a CUDA device without CUDA is refused)."""
    import torch

    if isinstance(request, torch.device):
        request = str(request)
    word = check_device_word(request)
    if word == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if word == "cpu":
        return torch.device("cpu")
    m = _CUDA_N.match(word)
    assert m is not None  # check_device_word
    if not torch.cuda.is_available():
        raise DeviceError(NO_CUDA)
    if m.group(1) is None:
        return torch.device("cuda")
    index, count = int(m.group(1)), torch.cuda.device_count()
    if index >= count:
        raise DeviceError(f"{word} requested but torch sees {count} CUDA device(s) (cuda:0..cuda:{count - 1})")
    return torch.device("cuda", index)


def _precision_word(precision: str | None) -> str:
    """The --precision word normalised (None is fp32), or :class:`DeviceError` for an unknown one."""
    word = "fp32" if precision is None else str(precision).strip().lower()
    if word not in PRECISION_CHOICES:
        raise DeviceError(f"unknown precision {precision!r}; expected one of {', '.join(PRECISION_CHOICES)}")
    return word


def check_device_here(request: str, precision: str | None = None) -> str:
    """The device word normalised, refused with :class:`DeviceError` (one line) where this machine cannot give it.

    What can fail is asked of torch: ``cuda``/``cuda:N``, or ``auto`` with a precision other than auto/fp32. ``cpu``
    and a plain ``auto`` never fail, so they are checked without importing torch: a command whose work is cached
    then never loads it (the device is resolved again where the work runs)."""
    word = check_device_word(request)
    wanted = _precision_word(precision)
    if word == "cpu" or (word == "auto" and wanted in ("auto", "fp32")):
        return word
    resolve_precision(resolve_device(word), precision)
    return word


def resolve_precision(device: torch.device | str, precision: str | None) -> AutocastDtype | None:
    """The autocast dtype for ``precision`` (``auto``, ``fp32``, ``bf16``, ``fp16``; None is fp32) on ``device``.

    The CPU: always None (float32, bit-identical to a run without autocast). CUDA: ``auto`` is bf16 where the GPU
    supports it, else None (fp16 is never chosen for the user: it needs loss scaling and can overflow); ``bf16``
    on a GPU without bfloat16 is :class:`DeviceError`.
    """
    word = _precision_word(precision)
    if word == "fp32":
        return None
    import torch

    device = torch.device(device)
    if device.type != "cuda":
        return None
    if word == "auto":
        return "bf16" if torch.cuda.is_bf16_supported() else None
    if word == "bf16" and not torch.cuda.is_bf16_supported():
        raise DeviceError("bf16 precision requested but this GPU has no bfloat16 support; use fp16 or fp32")
    return word  # type: ignore[return-value]


def model_device(model: torch.nn.Module) -> torch.device:
    """Where a module's parameters (else buffers) are; the CPU for a module that has neither."""
    import torch

    for tensor in (*model.parameters(), *model.buffers()):
        return tensor.device
    return torch.device("cpu")


def _check_dtype(dtype: str | None) -> torch.dtype | None:
    if dtype is None:
        return None
    if dtype not in _AUTOCAST_DTYPES:
        raise DeviceError(f"unknown autocast dtype {dtype!r}; expected bf16, fp16 or None")
    import torch

    return getattr(torch, _AUTOCAST_DTYPES[dtype])


@contextlib.contextmanager
def autocast_context(device: torch.device | str, dtype: AutocastDtype | None = "bf16") -> Iterator[None]:
    """Mixed precision for the forward passes inside; a no-op on the CPU and with ``dtype=None``.

    On CUDA, ``"bf16"`` needs a GPU that supports it (``torch.cuda.is_bf16_supported()``, Ampere and newer):
    otherwise :class:`DeviceError` rather than torch's silent fallback. Ops autocast keeps in float32
    (reductions, losses, softmax) stay float32; outputs of matmuls / convolutions / LSTMs are ``dtype``.
    """
    import torch

    device = torch.device(device)
    torch_dtype = _check_dtype(dtype)
    if torch_dtype is None or device.type == "cpu":
        yield
        return
    if device.type != "cuda":
        raise DeviceError(f"no autocast for device type {device.type!r} (cpu or cuda)")
    if not torch.cuda.is_available():
        raise DeviceError(NO_CUDA)
    if torch_dtype is torch.bfloat16 and not torch.cuda.is_bf16_supported():
        raise DeviceError("bf16 autocast requested but this GPU has no bfloat16 support; use fp16 or None")
    with torch.autocast(device_type="cuda", dtype=torch_dtype):
        yield


def grad_scaler(device: torch.device | str, dtype: AutocastDtype | None) -> torch.amp.GradScaler:
    """Loss scaling for training under :func:`autocast_context`: enabled for fp16 on CUDA only (a pass-through
    otherwise: ``scale(loss)`` returns the loss, ``step(opt)`` calls ``opt.step()``)."""
    import torch

    device = torch.device(device)
    enabled = _check_dtype(dtype) is torch.float16 and device.type == "cuda"
    return torch.amp.GradScaler("cuda" if enabled else "cpu", enabled=enabled)
