"""Robustness evaluation: augmented validation copies, the paper-style table, and the `evaluate` flow."""

import hashlib
import math
import re

import numpy as np
import pytest
import torch
from factories import make_curve_store
from torch import nn

from visemeflow.learning.augment import CONDITIONS, draw_value, source_id
from visemeflow.learning.robustness import augment_examples, robustness_table, table_csv, table_markdown
from visemeflow.learning.train import Example, evaluate, resample_curves
from visemeflow.visemes import VISEMES

FPS = 25.0


def _examples(n=3, seconds=1.2):
    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        audio = (0.1 * rng.standard_normal(int(16000 * seconds))).astype(np.float32)
        out.append(Example(f"spk/u{i}", audio, rng.random((round(seconds * FPS), 16)).astype(np.float32), FPS))
    return out


class Oracle(nn.Module):
    """Returns, for audio it was told about, the curves the test expects: a model that is exactly right."""

    def __init__(self, answers: dict[str, np.ndarray]):
        super().__init__()
        self.answers = answers

    def forward(self, audio, lengths, n_frames, fps=None):
        key = hashlib.sha256(audio[0, : int(lengths[0])].numpy().tobytes()).hexdigest()
        curves = torch.from_numpy(self.answers[key])[None]
        assert curves.shape[1] == int(n_frames[0]), "evaluation asked for a different number of frames"
        return curves, torch.ones(curves.shape[:2], dtype=torch.bool)


def test_augmented_copies_trace_to_their_source_and_speed_resamples_targets():
    examples = _examples()
    for condition in CONDITIONS:
        copies = augment_examples(examples, condition, seed=3)
        assert [source_id(c.utterance_id) for c in copies] == [e.utterance_id for e in examples]
        assert all(condition in c.utterance_id for c in copies)
        again = augment_examples(examples, condition, seed=3)
        assert all(np.array_equal(a.audio, b.audio) for a, b in zip(copies, again))
        for ex, c in zip(examples, copies):
            factor = draw_value(condition, ex.utterance_id, 3) if condition == "speed" else 1.0
            assert len(c.curves) == round(len(ex.curves) / factor)
            assert len(c.audio) == round(len(ex.audio) / factor)


def test_a_model_that_outputs_the_targets_scores_zero_on_every_condition():
    examples = _examples()
    answers = {}
    sets = {"validation": examples}
    for condition in CONDITIONS:
        sets[condition] = augment_examples(examples, condition, seed=0)
    for condition, copies in sets.items():
        for ex, c in zip(examples, copies):
            # the expected targets computed here, independently of augment_examples' own curves
            factor = draw_value(condition, ex.utterance_id, 0) if condition == "speed" else 1.0
            answers[hashlib.sha256(c.audio.tobytes()).hexdigest()] = resample_curves(ex.curves, factor)
    oracle = Oracle(answers)
    for condition, copies in sets.items():
        overall, per_utt, per_viseme = evaluate(oracle, copies)
        assert overall == 0.0 and set(per_utt.values()) == {0.0} and not per_viseme.any(), condition
    # and a model that is off by 0.1 everywhere scores 10
    shifted = Oracle({k: np.clip(v + 0.1, 0, 2).astype(np.float32) for k, v in answers.items()})
    assert evaluate(shifted, sets["speed"])[0] == pytest.approx(10.0, abs=1e-4)


# six 0.2 s phones over 1.2 s (frames of 0.04 s): a copy whose phones were not scaled with its speed would be judged
# on frames up to 0.36 s away at its end
PHONES = [(0.0, 0.2, None), (0.2, 0.4, "MBP"), (0.4, 0.6, "AAA"), (0.6, 0.8, "FFF"), (0.8, 1.0, "MBP"),
          (1.0, 1.2, "OHH")]


def _ideal(n_frames, fps, time_factor, phones=PHONES):
    """Curves that show each phone's viseme (1.0) exactly while it is spoken, in audio sped up by time_factor:
    frame k is the original time k * time_factor / fps (computed here, not with realspeech's helpers)."""
    c = np.zeros((n_frames, 16), np.float32)
    for k in range(n_frames):
        t = k * time_factor / fps
        for start, end, viseme in phones:
            if viseme and start <= t < end:
                c[k, VISEMES.index(viseme)] = 1.0
    return c


def test_realspeech_metrics_follow_each_augmented_copy_and_speed_scales_the_phones():
    from visemeflow.learning.realspeech import Phone, scale_phones
    from visemeflow.learning.robustness import realspeech_evaluation

    examples = _examples(n=2)
    phones = [Phone(a, b, v) for a, b, v in PHONES]
    factor = draw_value("speed", "spk/u0", 0)
    assert abs(factor - 1.0) > 0.1, "the test needs a clearly faster or slower copy"
    answers, sets = {}, {"validation": (examples, 1.0)}
    for condition in CONDITIONS:
        sets[condition] = (augment_examples(examples, condition, seed=0), None)
    for condition, (copies, _) in sets.items():
        for ex, c in zip(examples, copies):
            f = draw_value(condition, ex.utterance_id, 0) if condition == "speed" else 1.0
            answers[hashlib.sha256(c.audio.tobytes()).hexdigest()] = _ideal(len(c.curves), FPS, f)
    oracle = Oracle(answers)
    for condition, (copies, _) in sets.items():
        factors = {c.utterance_id: (draw_value(condition, ex.utterance_id, 0) if condition == "speed" else 1.0)
                   for ex, c in zip(examples, copies)}
        # phones of the first utterance only: the second is not scored
        aligned = {copies[0].utterance_id: scale_phones(phones, factors[copies[0].utterance_id])}
        pooled, per = realspeech_evaluation(oracle, copies, aligned)
        assert list(per) == [copies[0].utterance_id], condition
        assert pooled.closure["MBP"].hits == pooled.closure["MBP"].total == 2, condition
        assert pooled.closure["FFF"].hits == pooled.closure["FFF"].total == 1, condition
        assert pooled.agreement.overall.hits == pooled.agreement.overall.total == 5, condition
        if condition == "speed":
            # the same copy judged on the unscaled phones is wrong at its end: the metric sees the time axis
            unscaled, _ = realspeech_evaluation(oracle, copies, {copies[0].utterance_id: phones})
            assert unscaled.agreement.overall.hits < 5


def _row(model, condition, value, uid=None):
    return {"run": "evaluate", "model": model, "condition": condition, "utterance_id": uid, "l1_x100": value}


def test_robustness_table_gains_realspeech_columns_only_when_there_are_realspeech_rows():
    rows = [_row("a", "validation", 4.0), _row("a", "pitch", 5.0), _row("m", "validation", 8.0)]
    plain = robustness_table(rows, presets={"a": "fbank-blstm", "m": "mean-curve"})
    assert "closure" not in table_markdown(plain) and "closure" not in table_csv(plain)

    def real(metric, model, condition, pct, uid=None):
        return {"run": f"evaluate.{metric}", "model": model, "condition": condition, "utterance_id": uid,
                "l1_x100": pct}

    rows += [real("mbp_closure", "a", "validation", 75.0), real("mbp_closure", "a", "pitch", 50.0),
             real("mbp_closure", "a", "validation", 0.0, uid="spk/u0"),     # per utterance: not a cell
             real("agreement", "a", "validation", 60.0), real("agreement", "a", "pitch", 55.5),
             real("agreement", "m", "validation", 20.0),
             real("agreement", "m", "validation", 25.0)]                    # the latest evaluation wins
    table = robustness_table(rows, presets={"a": "fbank-blstm", "m": "mean-curve"})
    a, m = table
    assert a["mbp_closure_validation"] == 75.0 and a["mbp_closure_pitch"] == 50.0 and a["agreement_pitch"] == 55.5
    assert math.isnan(m["mbp_closure_validation"]) and m["agreement_validation"] == 25.0
    assert "fff_closure_validation" not in a                                # no FFF rows: no FFF column
    assert [c for c in a if c in CONDITIONS or c == "validation"] == ["validation", *CONDITIONS]  # no new condition
    md = table_markdown(table, note="On 2 utterances.")
    assert "| model | preset | train aug. | validation | volume | pitch | speed | noise | MBP closure % | agreement % |" in md
    assert "| a | fbank-blstm | no | 4.00 | - (-) | 5.00 (1.25) | - (-) | - (-) | 75.0 (- / 50.0 / - / -) | " \
           "60.0 (- / 55.5 / - / -) |" in md
    assert "| m | mean-curve | no | 8.00 | - (-) | - (-) | - (-) | - (-) | - (- / - / - / -) | 25.0 (- / - / - / -) |" in md
    assert "in brackets under volume / pitch / speed / noise" in md and md.rstrip().endswith("On 2 utterances.")
    csv = table_csv(table).splitlines()
    header = csv[0].split(",")
    assert header[:4] == ["group", "model", "preset", "train_augment"] and header.index("ratio_noise") == 12
    assert header[13:] == [f"{m}_{c}" for m in ("mbp_closure", "agreement") for c in ("validation", *CONDITIONS)]
    import csv as csv_module

    first = next(csv_module.DictReader(csv))
    assert (first["model"], first["mbp_closure_validation"], first["mbp_closure_volume"]) == ("a", "75.0000", "nan")
    assert first["agreement_pitch"] == "55.5000"


def test_robustness_table_pivots_groups_and_ratios():
    rows = [_row("a", "validation", 4.0), _row("a", "pitch", 5.0), _row("a", "speed", 4.4), _row("a", "volume", 4.0),
            _row("a", "noise", 6.0), _row("a", "pitch", 99.0, uid="spk/u0__pitch_p1.00"),
            _row("m", "validation", 8.0), _row("m", "pitch", 8.0), _row("t", "validation", 5.0)]
    table = robustness_table(rows, presets={"a": "fbank-blstm", "m": "mean-curve", "t": "fbank-tcn"},
                             augmented={"a": True})
    assert [r["model"] for r in table] == ["a", "t", "m"]  # Table 1 rows, then decoders, then baselines
    a = table[0]
    assert a["pitch"] == 5.0 and a["ratio_pitch"] == pytest.approx(1.25) and a["ratio_speed"] == pytest.approx(1.1)
    assert a["train_augment"] is True and table[2]["ratio_pitch"] == 1.0
    assert math.isnan(table[1]["pitch"]) and math.isnan(table[1]["ratio_pitch"])
    md = table_markdown(table)
    assert "| a | fbank-blstm | yes | 4.00 | 4.00 (1.00) | 5.00 (1.25) | 4.40 (1.10) | 6.00 (1.50) |" in md
    assert "**baselines and floors (Table 3)**" in md and "| t | fbank-tcn | no | 5.00 | - (-) |" in md
    csv = table_csv(table).splitlines()
    assert csv[0].startswith("group,model,preset,train_augment,validation,volume,pitch,speed,noise,ratio_volume")
    assert len(csv) == 4
    # a feature under the BLSTM decoder is a Table 1 row whatever its name's parts (whisper-base-blstm)
    table = robustness_table([_row("w", "validation", 4.0), _row("t", "validation", 5.0)],
                             presets={"w": "whisper-base-blstm", "t": "whisper-base-tcn"}, augmented={})
    assert [(r["model"], r["group"]) for r in table] == [("w", "features, BLSTM decoder (Table 1)"),
                                                         ("t", "decoders (Table 2)")]


def _dashboard_view(table):
    """What the dashboard shows: models in order and their non-missing cells."""
    return table.models, {k: round(v, 9) for k, v in table.values.items()}


def _report_view(table):
    cells = {(r["model"], c): round(r[c], 9) for r in table for c in r
             if c in ("validation", *CONDITIONS, "reverb") and not math.isnan(r[c])}
    return [r["model"] for r in table], cells


def test_report_and_dashboard_build_one_table_from_the_same_rows():
    """Duplicate aggregate cells (two evaluations of a model gathered together), per-utterance rows, training rows
    and an unknown condition: the evaluate report and the dashboard used to differ (the dashboard averaged the
    duplicates, sorted models by name and kept training rows out by run only); now both are the same table."""
    import pyarrow as pa

    from visemeflow.dashboards.html import robustness_table as dashboard_table
    from visemeflow.schemas import METRICS

    def row(run, model, condition, value, uid=None, epoch=None):
        return {"run": run, "model": model, "condition": condition, "utterance_id": uid, "epoch": epoch,
                "l1": value / 100, "l1_x100": value}

    rows = [row("evaluate", "zeta", "validation", 4.0), row("evaluate", "zeta", "noise", 9.0),
            row("evaluate", "zeta", "noise", 6.0),               # a later evaluation of the same cell: it wins
            row("evaluate", "zeta", "pitch", 50.0, uid="spk/u0"),  # per utterance: not a cell
            row("evaluate", "alpha", "validation", 8.0), row("evaluate", "alpha", "pitch", 8.8),
            row("evaluate", "alpha", "reverb", 16.0),
            row("train", "alpha", "validation", 3.0, epoch=2),     # training's validation: not the evaluation
            row("final", "zeta", "validation", 1.0)]
    presets = {"zeta": "fbank-blstm", "alpha": "mean-curve"}
    report = robustness_table(rows, presets=presets)
    dashboard = dashboard_table(pa.Table.from_pylist(rows, schema=METRICS), presets=presets)
    assert _dashboard_view(dashboard) == _report_view(report)
    assert dashboard.models == ["zeta", "alpha"]  # Table 1 before the baselines, as the report
    assert dashboard.values[("zeta", "noise")] == 6.0 and dashboard.ratio("zeta", "noise") == pytest.approx(1.5)
    assert report[0]["ratio_noise"] == pytest.approx(1.5)
    assert dashboard.values[("alpha", "validation")] == 8.0 and ("zeta", "pitch") not in dashboard.values
    assert dashboard.conditions == ["validation", "pitch", "noise", "reverb"]
    assert report[1]["ratio_reverb"] == pytest.approx(2.0) and "reverb" in table_markdown(report)
    # without labels both put every model under "other", by name
    assert dashboard_table(pa.Table.from_pylist(rows, schema=METRICS)).models == ["alpha", "zeta"]
    assert [r["model"] for r in robustness_table(rows)] == ["alpha", "zeta"]


def _html_robustness(page: str) -> tuple[list[str], list[list[str]]]:
    body = re.search(r'<table id="robustness-table">.*?<tbody>(.*?)</tbody>', page, re.S).group(1)
    rows = [re.findall(r"<td[^>]*>(.*?)</td>", tr) for tr in re.findall(r"<tr>(.*?)</tr>", body)]
    return [r[0] for r in rows], rows


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_evaluate_flow_writes_metrics_reuses_augmented_audio_and_recomputes_nothing(tmp_path):
    from visemeflow.flows.evaluate import evaluate_flow
    from visemeflow.flows.params import EvaluateParams, TrainParams
    from visemeflow.flows.train import train_flow
    from visemeflow.learning.train import TrainConfig
    from visemeflow.schemas import C

    store = make_curve_store(tmp_path / "store")
    for name, config in (("tcn", TrainConfig(preset="fbank-tcn", epochs=1, d_model=8)),
                         ("mean", TrainConfig(preset="mean-curve", epochs=1))):
        train_flow(TrainParams(store=store.root, config=config, source="ground_truth", model_name=name))

    first = evaluate_flow(EvaluateParams(store=store.root, models=["tcn"]))
    assert first["source"] == "ground_truth" and first["variant"] == "cm" and first["validation_utterances"] == 2
    augmented = sorted((store.root / "augmented").rglob("*.wav"))
    assert len(augmented) == 2 * len(CONDITIONS)
    stamps = {p: p.stat().st_mtime_ns for p in augmented}
    rows = [r for r in store.read_metrics("tcn").to_pylist() if r[C.RUN] == "evaluate"]
    aggregates = {r[C.CONDITION]: r[C.L1_X100] for r in rows if r[C.UTTERANCE_ID] is None}
    assert set(aggregates) == {"validation", *CONDITIONS} and all(np.isfinite(list(aggregates.values())))
    per_utt = [r for r in rows if r[C.UTTERANCE_ID] is not None]
    assert len(per_utt) == 2 * (1 + len(CONDITIONS))
    assert {source_id(r[C.UTTERANCE_ID]) for r in per_utt} == {"spk/u0", "spk/u1"}
    assert all(r[C.L1_PREFIX + "MBP"] is not None for r in rows if r[C.UTTERANCE_ID] is None)

    metrics_file = store.metrics_path("tcn", "evaluate")
    tcn_stamp = metrics_file.stat().st_mtime_ns
    second = evaluate_flow(EvaluateParams(store=store.root, models=["tcn", "mean"], device="cpu"))
    # the second model reused the augmented audio; the first model was not evaluated again (on another device word:
    # where a model runs is not part of the key)
    assert {p: p.stat().st_mtime_ns for p in augmented} == stamps
    assert metrics_file.stat().st_mtime_ns == tcn_stamp
    assert [r["model"] for r in second["table"]] == ["tcn", "mean"]
    assert second["table"][0]["validation"] == pytest.approx(aggregates["validation"])
    text = (store.root / "reports" / "robustness.md").read_text()
    assert "| mean | mean-curve | no |" in text and (store.root / "reports" / "robustness.csv").exists()

    # the dashboard shows the report's table: same models in the same order (by preset group, not by name), same numbers
    from visemeflow.dashboards.html import build_dashboard

    page = build_dashboard(store.root, tmp_path / "dashboard", max_utterances=0).path.read_text(encoding="utf-8")
    models, cells = _html_robustness(page)
    assert models == [r["model"] for r in second["table"]] == ["tcn", "mean"]
    for r, shown in zip(second["table"], cells):
        assert [float(x) for x in shown[1:6]] == pytest.approx([r[c] for c in ("validation", *CONDITIONS)], abs=5e-4)

    # a deleted augmented file is made again; unknown models are a clear error
    augmented[0].unlink()
    evaluate_flow(EvaluateParams(store=store.root, models=["mean"]))
    assert augmented[0].exists()
    with pytest.raises(LookupError, match="no trained model named nope.*known models: mean, tcn"):
        evaluate_flow(EvaluateParams(store=store.root, models=["nope"]))


def _html_headers(page: str) -> list[list[str]]:
    head = re.search(r'<table id="robustness-table"><thead>(.*?)</thead>', page, re.S).group(1)
    return [re.findall(r"<th[^>]*>(.*?)</th>", tr) for tr in re.findall(r"<tr>(.*?)</tr>", head)]


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_evaluate_flow_adds_realspeech_metrics_where_validation_utterances_have_phones(tmp_path):
    """Two mean-curve models whose constant output is known: `mbp` shows MBP most and FFF second, `fff` FFF most and
    AAA second. On the validation phones (MBP, AAA, FFF | FFF, EH, MBP, and silence) their closure recall and
    agreement are known on every condition (their output ignores the audio)."""
    from visemeflow.dashboards.html import build_dashboard
    from visemeflow.flows.evaluate import evaluate_flow
    from visemeflow.flows.params import EvaluateParams, TrainParams
    from visemeflow.flows.train import train_flow
    from visemeflow.learning.train import TrainConfig
    from visemeflow.schemas import PHONES as PHONES_SCHEMA
    from visemeflow.schemas import C, curves_table, table_from_rows

    store = make_curve_store(tmp_path / "store")
    rng = np.random.default_rng(5)
    for variant, first, second in (("mbp", "MBP", "FFF"), ("fff", "FFF", "AAA")):
        for i in range(6):    # u0, u1 (validation, not in the mean) too: training without validation fails
            c = 0.3 * rng.random((25, 16))
            c[:, VISEMES.index(first)], c[:, VISEMES.index(second)] = 0.9, 0.7
            store.write_curves(curves_table(f"spk/u{i}", "ground_truth", variant, c.astype(np.float32), 25.0))
    layout = {"spk/u0": [("sil", 0.0, 0.2, None), ("B", 0.2, 0.4, "MBP"), ("AA1", 0.4, 0.6, "AAA"),
                         ("F", 0.6, 0.8, "FFF"), ("", 0.8, 1.0, None)],
              # u1's speed copy is 1.097x faster: 23 frames (0.92 s); its last phone starts at 0.93 s, i.e. at
              # 0.848 s in the copy: inside it only when the phones are scaled with the audio
              "spk/u1": [("V", 0.0, 0.3, "FFF"), ("EH1", 0.3, 0.6, "EH"), ("sp", 0.6, 0.93, None),
                         ("M", 0.93, 1.0, "MBP")],
              "spk/u3": [("P", 0.0, 1.0, "MBP")]}                    # a training utterance: never scored
    rows = [{C.UTTERANCE_ID: uid, C.INDEX: i, C.PART: 0, C.LABEL: label, C.START_S: a, C.END_S: b, C.VISEME: v}
            for uid, phones in layout.items() for i, (label, a, b, v) in enumerate(phones)]
    store.write_shard("phones", 0, table_from_rows(rows, PHONES_SCHEMA))
    for name in ("mbp", "fff"):
        train_flow(TrainParams(store=store.root, config=TrainConfig(preset="mean-curve", epochs=1),
                               source="ground_truth", variant=name, model_name=name))

    result = evaluate_flow(EvaluateParams(store=store.root, models=["mbp", "fff"], variant="cm"))
    # false closures: of the 4 phones that are not b/p/m (AAA, FFF, FFF, EH), `mbp` shows MBP on top in all 4;
    # of the 4 that are not f/v (MBP, AAA, EH, MBP), `fff` shows FFF on top in all 4
    expected = {"mbp": {"mbp_closure": 100.0, "fff_closure": 0.0, "mbp_false_closure": 100.0,
                        "fff_false_closure": 0.0, "agreement": 400 / 6},
                "fff": {"mbp_closure": 0.0, "fff_closure": 100.0, "mbp_false_closure": 0.0,
                        "fff_false_closure": 100.0, "agreement": 300 / 6}}
    by_model = {r["model"]: r for r in result["table"]}
    for model, values in expected.items():
        for metric, value in values.items():
            for condition in ("validation", *CONDITIONS):
                assert by_model[model][f"{metric}_{condition}"] == pytest.approx(value), (model, metric, condition)
        assert by_model[model]["validation"] > 0                              # the L1 columns are still there

    # what the mesh shows: `mbp`'s constant MBP 0.9 tops every b/p/m phone, yet with every other viseme at 0.1 (the
    # closure rule's cap) the demo character's lips stand open at every b/p/m; neither model reaches the teeth at f/v
    for model in ("mbp", "fff"):
        for condition in ("validation", *CONDITIONS):
            row = by_model[model]
            assert row[f"lip_closed_{condition}"] == 0.0 and row[f"lip_closed_raw_{condition}"] == 0.0, model
            assert row[f"fv_contact_{condition}"] == 0.0 and row[f"lip_false_closed_{condition}"] == 0.0, model
            assert row[f"lip_gap_mm_{condition}"] > 10.0, model
    metrics = store.read_metrics("mbp").to_pylist()
    runs = {r[C.RUN] for r in metrics}
    assert runs == {"train", "final", "evaluate", "evaluate.mbp_closure", "evaluate.fff_closure",
                    "evaluate.mbp_false_closure", "evaluate.fff_false_closure", "evaluate.agreement",
                    "evaluate.lip_closed", "evaluate.lip_gap_mm", "evaluate.fv_contact", "evaluate.vowel_opening",
                    "evaluate.lip_false_closed", "evaluate.lip_closed_raw"}
    agreement = [r for r in metrics if r[C.RUN] == "evaluate.agreement" and r[C.CONDITION] == "validation"]
    aggregate = next(r for r in agreement if r[C.UTTERANCE_ID] is None)
    assert aggregate[C.L1] == pytest.approx(4 / 6) and aggregate[C.L1_X100] == pytest.approx(400 / 6)
    per_viseme = {v: aggregate[C.L1_PREFIX + v] for v in VISEMES if aggregate[C.L1_PREFIX + v] is not None}
    assert per_viseme == {"AAA": 0.0, "EH": 0.0, "FFF": 1.0, "MBP": 1.0}
    assert {r[C.UTTERANCE_ID]: r[C.L1] for r in agreement if r[C.UTTERANCE_ID]} == pytest.approx(
        {"spk/u0": 2 / 3, "spk/u1": 2 / 3})
    assert draw_value("speed", "spk/u1", 0) == pytest.approx(1.0971, abs=1e-4)
    speed_ids = {r[C.UTTERANCE_ID] for r in metrics if r[C.RUN] == "evaluate.mbp_closure" and r[C.CONDITION] == "speed"}
    assert {source_id(u) for u in speed_ids if u} == {"spk/u0", "spk/u1"} and None in speed_ids

    text = (store.root / "reports" / "robustness.md").read_text()
    assert "| MBP closure % | FFF closure % | false MBP closure % | false FFF closure % | agreement % |" in text
    full, none = "100.0 (100.0 / 100.0 / 100.0 / 100.0)", "0.0 (0.0 / 0.0 / 0.0 / 0.0)"
    assert f"| {full} | {none} | {full} | {none} | 66.7 (66.7 / 66.7 / 66.7 / 66.7) |" \
        in text.split("| mbp |")[1].splitlines()[0]
    assert "On 2 validation utterances with phones: 2 b/p/m, 2 f/v and 6 non-silent phones." in text
    csv_head = (store.root / "reports" / "robustness.csv").read_text().splitlines()[0]
    assert ",agreement_validation,agreement_volume,agreement_pitch,agreement_speed,agreement_noise,lip_closed_validation" \
        in csv_head and csv_head.endswith(",lip_closed_raw_speed,lip_closed_raw_noise")

    page = build_dashboard(store.root, tmp_path / "dashboard", max_utterances=0).path.read_text(encoding="utf-8")
    groups, headers = _html_headers(page)
    labels = ("MBP closure", "FFF closure", "false MBP closure", "false FFF closure", "agreement")
    assert groups[-11:-6] == [f"{m} % (real-speech metric)" for m in labels]   # then the 6 lip metrics
    assert groups[-6] == "lips closed at b/p/m % (on the mesh)"
    assert headers[-55:] == [*(("validation", *CONDITIONS) * 11)]
    models, cells = _html_robustness(page)
    assert models == ["fff", "mbp"]
    for model, shown in zip(models, cells):
        want = [expected[model][m] for m in ("mbp_closure", "fff_closure", "mbp_false_closure", "fff_false_closure",
                                             "agreement") for _ in range(5)]
        assert [float(x) for x in shown[-55:-30]] == pytest.approx(want, abs=5e-4)


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_evaluate_flow_scores_recognised_phones_as_the_baseline_that_needs_no_training(tmp_path):
    import shutil

    from factories import DEMO_CORPUS

    from visemeflow.flows.evaluate import evaluate_flow
    from visemeflow.flows.params import EvaluateParams, TrainParams
    from visemeflow.flows.train import train_flow, training_rows
    from visemeflow.learning.train import TrainConfig
    from visemeflow.procedural.recognised import recognised_curves
    from visemeflow.schemas import C
    from visemeflow.tasks.train import load_examples
    from visemeflow.visemes import VISEME_INDEX

    store = make_curve_store(tmp_path / "store")
    # the first validation utterance speaks (LJ001-0002: "in being comparatively modern", a b at 0.15 s)
    shutil.copyfile(DEMO_CORPUS / "LJ" / "LJ001-0002.wav", tmp_path / "store-audio" / "u0.wav")
    with pytest.raises(LookupError, match="`phones` alone has no training curves to name the targets; pass --variant"):
        evaluate_flow(EvaluateParams(store=store.root, models=["phones"]))
    train_flow(TrainParams(store=store.root, config=TrainConfig(preset="mean-curve", epochs=1),
                           source="ground_truth", model_name="mean"))
    result = evaluate_flow(EvaluateParams(store=store.root, models=["mean", "phones"]))
    assert sorted(r["model"] for r in result["table"]) == ["mean", "phones"]

    _, val, _ = training_rows(store, "ground_truth", "cm")
    speech = next(ex for ex in load_examples(store, val, "ground_truth", "cm") if ex.utterance_id == "spk/u0")
    curves = recognised_curves(np.asarray(speech.audio, np.float32), 16000, speech.fps, len(speech.curves))
    assert curves[:, VISEME_INDEX["MBP"]].max() == pytest.approx(1.0)
    rows = [r for r in store.read_metrics("phones").to_pylist() if r[C.RUN] == "evaluate"]
    scored = next(r for r in rows if r[C.UTTERANCE_ID] == "spk/u0" and r[C.CONDITION] == "validation")
    assert scored[C.L1_X100] == pytest.approx(100 * np.abs(curves - speech.curves).mean(), rel=1e-5)
    assert {r[C.CONDITION] for r in rows} == {"validation", *CONDITIONS}
    text = (store.root / "reports" / "robustness.md").read_text()
    assert "| phones | phones (pocketsphinx, no training) | no |" in text


@pytest.mark.usefixtures("prefect_harness")
def test_evaluate_flow_installs_the_shipped_models_it_is_asked_for(tmp_path):
    """`evaluate --models default-fbank` (a shipped model) works on any store, as `predict` does: the model is installed
    from the package; the targets are named by --variant since a shipped model's lineage names none of this store."""
    from visemeflow.flows.evaluate import evaluate_flow
    from visemeflow.flows.params import EvaluateParams
    from visemeflow.learning.default_model import shipped_model_path

    store = make_curve_store(tmp_path / "store")
    assert not store.has_model("default-fbank")
    result = evaluate_flow(EvaluateParams(store=store.root, models=["default-fbank"], source="ground_truth",
                                          variant="cm", conditions=["volume"]))
    assert store.model_path("default-fbank").read_bytes() == shipped_model_path("default-fbank").read_bytes()
    (row,) = result["table"]
    assert row["model"] == "default-fbank" and row["group"] == "features, BLSTM decoder (Table 1)"
    assert np.isfinite(row["validation"])


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_a_bad_model_is_a_reject_and_the_others_are_judged(tmp_path):
    from typer.testing import CliRunner

    from visemeflow.cli import app
    from visemeflow.flows.evaluate import evaluate_flow
    from visemeflow.flows.params import EvaluateParams, TrainParams
    from visemeflow.flows.train import train_flow
    from visemeflow.learning.train import TrainConfig
    from visemeflow.schemas import C

    store = make_curve_store(tmp_path / "store")
    train_flow(TrainParams(store=store.root, config=TrainConfig(preset="mean-curve", epochs=1), source="ground_truth",
                           model_name="mean"))
    broken = store.model_path("broken")
    broken.parent.mkdir(parents=True)
    broken.write_text("not a model")
    # the first model named is the broken one: the targets come from the first model that loads
    result = evaluate_flow(EvaluateParams(store=store.root, models=["broken", "mean", "nope"], conditions=["volume"]))
    assert [r["model"] for r in result["table"]] == ["mean"] and result["variant"] == "cm"
    assert result["rejected"] == 2 and result["models"] == ["mean"]
    rejects = {r[C.MESSAGE].split()[1].rstrip(":"): r for r in store.read_table("rejects", "evaluate").to_pylist()}
    assert set(rejects) == {"broken", "nope"}
    assert rejects["broken"][C.PATH] == str(broken)
    assert rejects["broken"][C.MESSAGE].startswith(f"model broken ({broken}): ")
    assert rejects["nope"][C.MESSAGE].startswith("model nope: no trained model named nope")
    assert "| mean |" in (store.root / "reports" / "robustness.md").read_text()

    done = CliRunner().invoke(app, ["evaluate", "--models", "mean,broken", "--store", str(store.root),
                                    "--conditions", "volume"])
    assert done.exit_code == 1, done.output
    assert "evaluate: 1 of 2 models judged, 1 rejected" in done.output and f"rejected model broken ({broken})" in done.output
    with pytest.raises(LookupError, match="no model to evaluate: model broken .*; model nope: no trained model"):
        evaluate_flow(EvaluateParams(store=store.root, models=["broken", "nope"], conditions=["volume"]))


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_evaluate_without_validation_utterances_ends_failed_with_one_line_and_no_traceback(tmp_path, capsys):
    """A new user's small corpus put no id in the `val` split: the run ends Failed saying what evaluate judges, as a
    message, not an exception whose traceback Prefect prints."""
    from visemeflow.flows.errors import StageFailed
    from visemeflow.flows.evaluate import evaluate_flow
    from visemeflow.flows.params import EvaluateParams, TrainParams
    from visemeflow.flows.train import train_flow
    from visemeflow.learning.train import TrainConfig

    store = make_curve_store(tmp_path / "store")
    train_flow(TrainParams(store=store.root, config=TrainConfig(preset="mean-curve", epochs=1),
                           source="ground_truth", variant="cm", model_name="m"))
    capsys.readouterr()
    with pytest.raises(StageFailed, match=r"^evaluate: no validation utterance in .* has ground_truth curves of "
                                          r"variant 'absent'; evaluate judges the `val` split") as info:
        evaluate_flow(EvaluateParams(store=store.root, models=["m"], source="ground_truth", variant="absent"))
    assert info.value.summary == {"models": 1, "validation_utterances": 0}
    out = capsys.readouterr()
    assert "Traceback" not in out.out + out.err
