"""Rebuild examples/corpus from ../shared/data (maintainers only; needs `pip install soxr`).

Copies the 24 LJSpeech utterances with their MFA TextGrids and the Mandarin charsiu utterance
SSB16240001, with the audio resampled to 16 kHz mono 16-bit to keep the repository small. TextGrids
are copied byte for byte. Licenses and sources are copied next to the data.
"""

import shutil
import sys
from pathlib import Path

import numpy as np
import soundfile as sf
import soxr

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
OUT = REPO / "examples" / "corpus"
RATE = 16000


def copy_audio(src: Path, dst: Path) -> None:
    audio, rate = sf.read(src, dtype="float32", always_2d=True)
    mono = audio.mean(axis=1)
    if rate != RATE:
        mono = soxr.resample(mono, rate, RATE, quality="HQ")
    sf.write(dst, np.clip(mono, -1, 1), RATE, subtype="PCM_16")


def main() -> int:
    lj, zh = OUT / "LJ", OUT / "SSB1624"
    for folder in (lj, zh):
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
    src = SHARED / "ljspeech_mfa"
    for grid in sorted((src / "TextGrid").glob("*.TextGrid")):
        shutil.copyfile(grid, lj / grid.name)
        copy_audio(src / "wav" / f"{grid.stem}.wav", lj / f"{grid.stem}.wav")
    for name in ("SOURCE.txt", "LICENSE_alignments_repo_MIT.txt", "LICENSE_coqui_TTS_repo_MPL2.txt", "metadata.csv"):
        shutil.copyfile(src / name, lj / name)
    src = SHARED / "charsiu_mandarin"
    shutil.copyfile(src / "SSB16240001.TextGrid", zh / "SSB16240001.TextGrid")
    copy_audio(src / "SSB16240001_16k.wav", zh / "SSB16240001.wav")
    for name in ("SOURCE.txt", "LICENSE"):
        shutil.copyfile(src / name, zh / name)
    print(f"demo corpus written to {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
