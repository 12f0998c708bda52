"""ARKit weights -> our 16 viseme curves (`visemeflow.shapes.capture`): the shipped Gram table, the per-frame NNLS
fit, its optimality, the round trip through the shipped ARKit table, silent frames and bad input.

The table is measured from `../shared/data/ict_facekit`; the test that measures it again fails (not skips) when
the shared data is missing."""

import subprocess
import sys

import numpy as np
import pytest
from scipy.optimize import lsq_linear

from factories import DEMO_CORPUS, REPO, SHARED_DATA
from visemeflow.shapes.capture import (
    ArkitToVisemes,
    CaptureError,
    arkit_to_visemes,
    curve_shares,
    fit_visemes,
    gram_table_text,
    load_arkit_to_visemes,
    parse_gram_table,
)
from visemeflow.shapes.conventions import ARKIT_52, arkit_weights
from visemeflow.visemes import N_VISEMES, VISEMES, viseme_index

ICT = SHARED_DATA / "ict_facekit"
AMBIGUOUS = {"AHH", "EH"}
"""Visemes the demo rig lets come back as an equivalent mix (see the table's comment lines)."""


def arkit(**weights: float) -> np.ndarray:
    row = np.zeros(len(ARKIT_52), np.float32)
    for name, value in weights.items():
        row[ARKIT_52.index(name)] = value
    return row


def procedural_curves(n_utterances: int = 8) -> np.ndarray:
    """Procedural curves of demo-corpus utterances: realistic mixes of neighbouring visemes."""
    from visemeflow.ingest import IngestConfig, discover_corpus, ingest_utterance
    from visemeflow.phonetics.types import VisemeSegment
    from visemeflow.procedural import ProceduralConfig, generate_procedural_curves

    out = []
    for entry in discover_corpus(DEMO_CORPUS).entries[:n_utterances]:
        ingested = ingest_utterance(entry, IngestConfig())
        phones = sorted(ingested.phones, key=lambda p: p["start_s"])
        segments = [VisemeSegment(p["viseme"], p["start_s"], p["end_s"], p["word_index"], p["phoneme"] or "")
                    for p in phones if p["viseme"]]
        out.append(generate_procedural_curves(segments, ingested.utterance["n_frames"], ingested.utterance["fps"],
                                              ProceduralConfig()))
    return np.concatenate(out).astype(np.float32)


def test_the_shipped_table_matches_a_new_measure_from_the_ict_face():
    assert ICT.is_dir(), f"{ICT} missing: the shared data must be present"
    run = subprocess.run([sys.executable, "examples/build_arkit_to_visemes.py", "--check"], cwd=REPO,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "matches a new measure" in run.stdout


def test_the_shipped_table_is_small_and_complete():
    table = load_arkit_to_visemes()
    assert table.names[:N_VISEMES] == VISEMES and len(table.arkit_names) == 32  # ICT's ARKit-style shapes
    assert not {"eyeBlinkLeft", "browInnerUp", "tongueOut"} & set(table.arkit_names)
    assert table.gram.shape == (16, 16) and table.cross.shape == (16, 52) and table.arkit_gram.shape == (52, 52)
    assert table.n_vertices > 20000
    path = REPO / "visemeflow" / "shapes" / "data" / "arkit_to_visemes.csv"
    assert path.stat().st_size < 64_000
    again = parse_gram_table(gram_table_text(table), "round trip")
    assert np.array_equal(again.matrix, table.matrix) and again.digest == table.digest  # exact float64 text


def test_round_trip_through_the_shipped_arkit_table_recovers_the_face_and_most_curves():
    """Its speed is bench/animation.py's (section 6)."""
    curves = procedural_curves()
    fit = fit_visemes(arkit_weights(curves))
    table = load_arkit_to_visemes()
    diff = (fit.curves - curves).astype(np.float64)
    face_error = np.sqrt(np.einsum("ti,ij,tj->t", diff, table.gram, diff))
    face = np.sqrt(np.einsum("ti,ij,tj->t", curves, table.gram, curves.astype(np.float64)))
    active = curves.max(axis=1) > 0.3
    l1 = 100 * float(np.abs(diff).mean())
    top = float((fit.curves.argmax(axis=1) == curves.argmax(axis=1))[active].mean())
    print(f"\nround trip of {len(curves)} procedural frames: curves L1 x 100 = {l1:.2f}, top viseme agrees on "
          f"{100 * top:.1f}% of active frames, face error {np.mean(face_error[active] / face[active]):.2e} "
          f"(relative), residual median {np.median(fit.residual[fit.moving]):.2e}, {fit.bounded} frames bounded")
    assert fit.curves.dtype == np.float32 and fit.curves.shape == curves.shape
    assert fit.curves.min() >= 0 and fit.curves.max() <= 1
    # the deformation is recovered: what the mesh shows matches within 2% (mean 0.4% when measured)
    assert float(np.mean(face_error[active] / face[active])) < 0.02
    assert float(np.median(fit.residual[fit.moving])) < 1e-3
    # the split among jaw-driven visemes is not unique on the demo rig (7 near-null directions of G): the curves
    # come back close, not exact (L1 x 100 = 3.6, top viseme 78% when measured)
    assert l1 < 6.0 and top > 0.7


def test_single_visemes_come_back_alone_except_the_rigs_equivalent_mixes():
    curves = np.eye(N_VISEMES, dtype=np.float32) * 0.8
    fit = fit_visemes(arkit_weights(curves))
    assert (fit.residual < 1e-3).all()  # every face is reproduced
    for i, viseme in enumerate(VISEMES):
        if viseme in AMBIGUOUS:
            continue
        np.testing.assert_allclose(fit.curves[i], curves[i], atol=0.02, err_msg=viseme)
    ahh = fit.curves[viseme_index("AHH")]
    assert ahh[viseme_index("AHH")] > 0.6 and ahh[viseme_index("SCHWA")] > 0.1  # AHH 0.74 + SCHWA 0.19


def test_the_fit_meets_the_optimality_conditions_and_agrees_with_a_bounded_solver():
    rng = np.random.default_rng(3)
    table = load_arkit_to_visemes()
    weights = np.zeros((200, len(ARKIT_52)), np.float32)
    mouth = [ARKIT_52.index(n) for n in table.arkit_names]
    weights[:, mouth] = rng.uniform(0, 1, (200, len(mouth))) * (rng.uniform(size=(200, len(mouth))) < 0.2)
    fit = fit_visemes(weights, table)
    x = fit.curves.astype(np.float64)
    grad = x @ table.gram - weights.astype(np.float64) @ table.cross.T  # half the gradient of the objective
    scale = np.abs(weights.astype(np.float64) @ table.cross.T).max()
    tol = 1e-5 * scale
    inner = (x > 1e-6) & (x < 1 - 1e-6)
    assert np.abs(grad[inner]).max() < tol
    assert grad[x <= 1e-6].min() > -tol  # at 0 the objective may only rise
    assert grad[x >= 1 - 1e-6].max(initial=-1) < tol  # at 1 it may only fall
    # the same optimum as scipy's bounded solver on the whitened system, in objective value
    lt = table.cholesky.T
    for k in range(0, 200, 20):
        target = np.linalg.solve(table.cholesky, table.cross @ weights[k])
        ref = lsq_linear(lt, target, bounds=(0, 1), method="bvls", tol=1e-12).x
        ours = np.linalg.norm(lt @ x[k] - target)
        assert ours <= np.linalg.norm(lt @ ref - target) * (1 + 1e-5) + 1e-9 * np.linalg.norm(target)


def test_frames_of_eyes_only_give_no_visemes_and_eyes_do_not_change_the_mouth():
    blink = arkit(eyeBlinkLeft=1.0, eyeBlinkRight=1.0, browInnerUp=0.7, eyeLookUpLeft=0.4)
    jaw = arkit(jawOpen=0.6, mouthFunnel=0.2)
    curves, residual = arkit_to_visemes(np.stack([blink, jaw, blink + jaw, np.zeros_like(jaw)]))
    assert curves.shape == (4, N_VISEMES) and residual.shape == (4,)
    assert (curves[0] == 0).all() and residual[0] == 0 and (curves[3] == 0).all()
    np.testing.assert_array_equal(curves[2], curves[1])
    assert curves[1].max() > 0.3
    fit = fit_visemes(np.stack([blink, jaw]))
    assert fit.silent == 1 and fit.moving.tolist() == [False, True]


def test_weights_past_one_are_fitted_within_bounds_and_counted():
    loud = arkit(jawOpen=3.0, mouthLowerDownLeft=1.2, mouthLowerDownRight=1.2)
    fit = fit_visemes(np.stack([loud, arkit(jawOpen=0.3)]))
    assert fit.bounded == 1
    assert fit.curves.max() == pytest.approx(1.0) and fit.curves.min() >= 0
    assert fit.residual[0] > 0.01  # a face moved three times ARKit's range cannot be matched exactly


def test_bad_weights_and_tables_are_errors_naming_the_source():
    with pytest.raises(CaptureError, match=r"take\.csv: ARKit weights must be \(frames, 52\)"):
        fit_visemes(np.zeros((3, 51)), where="take.csv")
    bad = np.zeros((3, 52))
    bad[2, ARKIT_52.index("jawOpen")] = np.nan
    with pytest.raises(CaptureError, match=r"take\.csv: jawOpen is nan at frame 2"):
        fit_visemes(bad, where="take.csv")
    assert fit_visemes(np.zeros((0, 52))).curves.shape == (0, N_VISEMES)
    table = load_arkit_to_visemes()
    broken = table.matrix.copy()
    broken[0, 1] += 1.0
    with pytest.raises(CaptureError, match="not symmetric"):
        ArkitToVisemes(table.names, broken, source="t.csv")
    with pytest.raises(CaptureError, match="t.csv: expected a header"):
        parse_gram_table("a,b\n1,2\n", "t.csv")
    with pytest.raises(CaptureError, match="not ARKit"):
        ArkitToVisemes(table.names[:-1] + ("jawWobble",), table.matrix, source="t.csv")


def test_curve_shares_describe_top_visemes_and_open_jaw():
    curves = np.zeros((10, N_VISEMES), np.float32)
    curves[:4, viseme_index("AHH")] = 0.5
    curves[4:6, viseme_index("MBP")] = 0.9
    shares = curve_shares(curves)
    assert shares["active_share"] == pytest.approx(0.6)
    assert shares["top_share"]["AHH"] == pytest.approx(4 / 6) and shares["top_share"]["MBP"] == pytest.approx(2 / 6)
    assert shares["jaw_open_share"] == pytest.approx(0.4)
