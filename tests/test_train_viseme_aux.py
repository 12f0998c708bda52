"""The auxiliary viseme-classification loss (TrainConfig.viseme_loss_weight): off by default and then bit-identical
to the plain recipe, recorded in the model's config, trains the decoder towards separating the labelled visemes,
resumes exactly, and per-frame labels come from aligned phones (realspeech.frame_visemes)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from factories import assert_same_params as _assert_same
from factories import envelope_examples as make_examples
from factories import params_of as _params

from visemeflow.learning.realspeech import Phone, frame_visemes
from visemeflow.learning.train import Example, TrainConfig, load_model, save_model, train_model
from visemeflow.visemes import VISEME_INDEX


def labelled(examples: list[Example]) -> list[Example]:
    """Each frame labelled by its loudest target viseme (learnable from the audio envelope), the first 3 unlabelled."""
    out = []
    for ex in examples:
        labels = (np.asarray(ex.curves).mean(axis=1) > np.median(np.asarray(ex.curves).mean(axis=1))).astype(np.int64)
        labels[:3] = -1
        out.append(Example(ex.utterance_id, ex.audio, ex.curves, ex.fps, labels))
    return out


def test_frame_visemes_labels_each_frame_by_its_phone():
    phones = [Phone(0.0, 0.1, "MBP"), Phone(0.1, 0.2, None), Phone(0.2, 0.3, "AHH")]
    labels = frame_visemes(phones, 10, 30.0)
    mbp, ahh = VISEME_INDEX["MBP"], VISEME_INDEX["AHH"]
    assert labels.tolist() == [mbp, mbp, mbp, -1, -1, -1, ahh, ahh, ahh, -1]


def test_off_by_default_and_unchanged_by_labels():
    train = make_examples(2, seed=11)
    cfg = TrainConfig(preset="fbank-blstm", epochs=1, d_model=16, lr=1e-3)
    assert cfg.viseme_loss_weight == 0 and "viseme_loss_weight" not in cfg.model_dump()
    plain = _params(train_model(train, [], cfg).model)
    # labels alone change nothing while the loss is off
    _assert_same(plain, _params(train_model(labelled(train), [], cfg).model))


def test_the_aux_loss_trains_and_is_recorded(tmp_path):
    train = labelled(make_examples(3, seed=12))
    cfg = TrainConfig(preset="fbank-blstm", epochs=2, d_model=16, lr=1e-3, viseme_loss_weight=0.5)
    plain = TrainConfig(preset="fbank-blstm", epochs=2, d_model=16, lr=1e-3)
    with_aux = train_model(train, [], cfg)
    without = train_model(train, [], plain)
    a, b = _params(with_aux.model), _params(without.model)
    assert any(not torch.equal(a[k], b[k]) for k in a)  # the extra gradient reached the decoder
    assert set(a) == set(b)  # the classifier is not part of the model
    assert with_aux.history[-1].train_l1_x100 > without.history[-1].train_l1_x100  # the loss includes the CE
    path = save_model(with_aux.model, cfg, tmp_path / "m.pt", {})
    assert load_model(path)[1].viseme_loss_weight == 0.5
    # unlabelled examples train on the curve loss alone
    unl = [Example(e.utterance_id, e.audio, e.curves, e.fps) for e in train]
    _assert_same(_params(train_model(unl, [], cfg).model), _params(train_model(unl, [], plain).model))


def test_exact_resume_with_the_aux_loss(tmp_path):
    train = labelled(make_examples(2, seed=13))
    cfg = TrainConfig(preset="fbank-blstm", epochs=2, d_model=16, lr=1e-3, viseme_loss_weight=0.5)
    full = _params(train_model(train, [], cfg, checkpoint_dir=tmp_path / "full").model)
    train_model(train, [], cfg.model_copy(update={"epochs": 1}), checkpoint_dir=tmp_path / "part")
    _assert_same(full, _params(train_model(train, [], cfg, checkpoint_dir=tmp_path / "part").model))


def test_refused_for_heads_without_a_decoder():
    with pytest.raises(ValueError, match="curve-model preset"):
        train_model(labelled(make_examples(1, seed=14)), [],
                    TrainConfig(preset="karras-lpc", epochs=1, d_model=16, viseme_loss_weight=0.5))
