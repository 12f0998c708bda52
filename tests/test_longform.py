"""Long audio in chunks (visemeflow.learning.longform): frames line up with the whole file's, a real model's curves
match the whole-file run at and away from the seams, and blocks read from the file equal the whole read."""

from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from visemeflow.ingest.audio import AudioFile, NonFiniteAudioError, read_audio
from visemeflow.learning.default_model import shipped_model_path
from visemeflow.learning.longform import predict_long
from visemeflow.learning.train import load_model, predict_curves

LJ = Path(__file__).resolve().parents[1] / "examples" / "corpus" / "LJ"


def local_energy(samples: np.ndarray, rate: int, n: int, fps: float) -> np.ndarray:
    """A stand-in model whose frame k depends only on the audio at k / fps from the piece's start."""
    out = np.zeros((n, 16), np.float32)
    for k in range(n):
        i = round(k * rate / fps)
        out[k, 0] = np.abs(samples[i:i + 64]).mean() if i < len(samples) else 0.0
        out[k, 1] = k / max(n, 1)  # position inside the piece: differs per chunk, only frame alignment matters
    return out


@pytest.mark.parametrize("fps", [25.0, 30.0])
def test_chunks_line_up_with_the_whole_file(fps):
    rate = 16000
    rng = np.random.default_rng(0)
    audio = (rng.standard_normal(rate * 37) * np.linspace(0.01, 1, rate * 37)).astype(np.float32)
    whole = local_energy(audio, rate, round(len(audio) / rate * fps), fps)
    seen = []
    chunked = predict_long(lambda a, r, n: local_energy(a, r, n, fps), audio, fps, sample_rate=rate,
                           chunk_s=4.0, context_s=1.0, on_chunk=lambda d, t: seen.append((d, t)))
    assert chunked.shape == whole.shape
    assert seen[-1] == (10, 10) and len(seen) == 10
    # Frame times agree to a sample: energies of the same 64 samples (fps 25: 640 samples a frame, exact).
    tol = 0 if fps == 25.0 else 0.05
    assert np.abs(chunked[:, 0] - whole[:, 0]).max() <= tol
    assert not np.allclose(chunked[:, 1], whole[:, 1])  # the pieces really were predicted apart


def test_short_audio_is_one_piece_identical_to_the_whole_file():
    audio = np.random.default_rng(1).standard_normal(16000 * 3).astype(np.float32)
    calls = []

    def predict(a, r, n):
        calls.append(len(a))
        return np.full((n, 16), 0.5, np.float32)

    out = predict_long(predict, audio, 30.0, sample_rate=16000)
    assert calls == [len(audio)] and out.shape == (90, 16)


def test_file_blocks_equal_the_whole_read(tmp_path):
    rate = 22050
    stereo = np.random.default_rng(2).uniform(-0.5, 0.5, (rate * 5, 2)).astype(np.float32)
    path = tmp_path / "stereo.wav"
    sf.write(path, stereo, rate, subtype="FLOAT")
    source = AudioFile(path)
    whole, r = read_audio(path)
    assert (source.rate, source.n_samples) == (r, len(whole))
    np.testing.assert_array_equal(np.concatenate([source.read(0, 40000), source.read(40000, len(whole))]), whole)


def test_non_finite_block_names_the_file(tmp_path):
    rate = 16000
    audio = np.zeros(rate * 2, np.float32)
    audio[rate + 5] = np.nan
    path = tmp_path / "nan.wav"
    sf.write(path, audio, rate, subtype="FLOAT")
    source = AudioFile(path)
    source.read(0, rate)
    with pytest.raises(NonFiniteAudioError, match=r"nan\.wav.*samples 16005\.\.16005 \(1\.000"):
        source.read(rate, 2 * rate)  # the sample's place in the file, not in the block


def test_real_model_on_three_minutes_matches_the_whole_file():
    """The previous default (fbank BLSTM) on 3 minutes of LJ speech: chunked curves stay within 0.06 of the
    whole-file run (its features are normalised over each input, so chunks see slightly other statistics), 0.01 on
    average."""
    model = load_model(shipped_model_path("default-fbank"))[0]
    pieces = []
    for wav in sorted(LJ.glob("*.wav")):
        a, r = read_audio(wav)
        pieces.append(a)
    audio = np.concatenate(pieces)
    audio = np.tile(audio, int(np.ceil(180 * r / len(audio))))[: 180 * r]
    fps = 30.0
    whole = predict_curves(model, audio, r, fps)
    chunked = predict_long(lambda a, rr, n: predict_curves(model, a, rr, fps, n_frames=n), audio, fps,
                           sample_rate=r)
    assert chunked.shape == whole.shape == (5400, 16)
    diff = np.abs(chunked - whole).max(axis=1)
    assert diff.max() < 0.06 and diff.mean() < 0.01
