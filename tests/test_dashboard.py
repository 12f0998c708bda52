"""The static HTML report (`visemeflow dashboard`): content, escaping, the robustness pivot, and a real browser.

The browser test drives Debian's chromium headless over the DevTools protocol (tests/browser.py: a websocket to
the page target, through the `websockets` package Prefect already depends on): it loads the page from file://,
collects every console message, uncaught exception, browser log entry and network request, checks that each chart
<img> decoded, and takes a screenshot. Without chromium it fails (never skips) with the install command: `make test`
and .ci/run install it first through scripts/system-deps.sh.
"""

import html
import re
from datetime import UTC, datetime
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest
from browser import Browser, chromium_or_fail
from factories import write_wav
from typer.testing import CliRunner

from visemeflow.cli import app
from visemeflow.dashboards.html import (
    build_dashboard,
    curve_index,
    robustness_html,
    robustness_table,
    select_utterances,
    tracking_sample,
)
from visemeflow.schemas import (
    METRICS,
    PHONES,
    REJECTS,
    TRACKING_FRAMES,
    UTTERANCES,
    C,
    curves_table,
    table_from_rows,
)
from visemeflow.storage import Store
from visemeflow.visemes import VISEMES

runner = CliRunner()
HOSTILE_ID = "spk/<img src=x onerror=alert(1)>&\"'"
HOSTILE_MESSAGE = "expected \"</td></tr></table><script>alert('x')</script>\" & <b>bold</b>"
HOSTILE_CONDITION = "<script>alert(\"c\")</script>&"
CONDITIONS = {"validation": 10.0, "volume": 10.5, "pitch": 13.0, "speed": 12.0, "noise": 16.0}


# ---- store builders ---------------------------------------------------------------------------------
def _utterance_row(uid: str, audio: Path, video: Path | None, seconds: float, fps: float, split: str) -> dict:
    return {C.UTTERANCE_ID: uid, C.SPEAKER: uid.split("/")[0], C.LANGUAGE: "en", C.AUDIO_PATH: str(audio),
            C.VIDEO_PATH: str(video) if video else None, C.ALIGNMENT_PATH: "x.TextGrid", C.ALIGNMENT_FORMAT: "textgrid",
            C.SAMPLE_RATE: 16000, C.DURATION_S: seconds, C.FPS: fps, C.N_FRAMES: round(seconds * fps),
            C.CONTENT_HASH: uid, C.SPLIT: split}


def _phone_rows(uid: str, seconds: float) -> list[dict]:
    labels = [("sil", None), ("HH", "GK"), ("AH0", "SCHWA"), ("L", "LNTD"), ("OW1", "OHH"), ("<&\">", None),
              ("M", "MBP"), ("sil", None)]
    edges = np.linspace(0.0, seconds, len(labels) + 1)
    return [{C.UTTERANCE_ID: uid, C.INDEX: k, C.PART: 0, C.LABEL: label, C.PHONEME: label, C.VISEME: viseme,
             C.START_S: float(edges[k]), C.END_S: float(edges[k + 1])} for k, (label, viseme) in enumerate(labels)]


def _tracking_frames(uid: str, variant: str, n: int, rng) -> pa.Table:
    cols = {C.UTTERANCE_ID: [uid] * n, C.VARIANT: [variant] * n, C.FRAME: list(range(n)),
            C.MOUTH_ERROR_PX: [None if k == 3 else float(x) for k, x in enumerate(rng.gamma(4.0, 0.5, n))],
            C.LANDMARKS_VALID: [k != 3 for k in range(n)], C.FLOW_VALID_FRACTION: rng.random(n).tolist()}
    cols.update({c: [0.0] * n for c in C.POSE_COLUMNS})
    return table_from_rows([{k: v[i] for k, v in cols.items()} for i in range(n)], TRACKING_FRAMES)


def _metric(run: str, model: str, condition: str, value: float, uid: str | None = None, epoch: int | None = None):
    row = {C.RUN: run, C.MODEL: model, C.CONDITION: condition, C.UTTERANCE_ID: uid, C.EPOCH: epoch,
           C.L1: value / 100, C.L1_X100: value}
    row.update({C.L1_PREFIX + v: value / 100 * (1 + k / 16) for k, v in enumerate(VISEMES)})  # plain L1, as `l1`
    return row


def _reject(uid: str | None, stage: str, message: str) -> dict:
    return {C.UTTERANCE_ID: uid, C.STAGE: stage, C.ERROR_TYPE: "BadInput<x>", C.MESSAGE: message,
            C.PATH: "/corpus/a&b.TextGrid", C.TIME: datetime(2026, 11, 1, tzinfo=UTC)}


def realistic_store(root: Path) -> Store:
    """Three utterances (one whose audio is inside an .mp4), curves of every source, phones, two tracked variants,
    training, final and evaluate metrics, a sweep plot, and rejects with hostile text. Written with the Store API."""
    from visemeflow.tracking.video import write_video

    s = Store(root)
    rng = np.random.default_rng(0)
    media = root.parent / f"{root.name}-media"
    seconds, fps = 1.2, 25.0
    n = round(seconds * fps)
    wav0 = write_wav(media / "u0.wav", seconds)
    t = np.arange(int(seconds * 16000)) / 16000
    mp4 = write_video(media / "u1.mp4", np.full((n, 48, 64, 3), 120, np.uint8), fps=fps,
                      audio=(0.3 * np.sin(2 * np.pi * 300 * t)).astype(np.float32), audio_rate=16000)
    wav2 = write_wav(media / "u2.wav", seconds)
    rows = [_utterance_row("spk/u0", wav0, None, seconds, fps, "val"),
            _utterance_row("spk/u1", mp4, mp4, seconds, fps, "train"),
            _utterance_row("spk/u2", wav2, None, seconds, fps, "train")]
    s.write_shard("utterances", 0, table_from_rows(rows, UTTERANCES))
    s.write_shard("phones", 0, table_from_rows([p for r in rows for p in _phone_rows(r[C.UTTERANCE_ID], seconds)],
                                                PHONES))
    sources = {"spk/u0": [("procedural", "jali"), ("tracked", "guided-fast"), ("tracked", "unguided-fast"),
                          ("ground_truth", "cm-seed0"), ("predicted", "m1")],
               "spk/u1": [("procedural", "jali"), ("ground_truth", "cm-seed0")],
               "spk/u2": [("procedural", "jali")]}
    for uid, items in sources.items():
        for source, variant in items:
            s.write_curves(curves_table(uid, source, variant, rng.random((n, 16)).astype(np.float32), fps), fps=fps)
    for uid in ("spk/u0", "spk/u1"):
        for variant in ("guided-fast", "unguided-fast"):
            s.write_tracking_frames(_tracking_frames(uid, variant, n, rng))
    train = [_metric("train", "m1", "validation", 20.0 - 3 * e, epoch=e) for e in (1, 2, 3)]
    final = [_metric("final", "m1", "validation", 11.0), _metric("final", "m1", "validation", 11.0, uid="spk/u0")]
    s.write_metrics("m1", "train", table_from_rows(train + final, METRICS))
    evaluate = [_metric("evaluate", m, c, v * (1.1 if m == "m2" else 1.0)) for m in ("m1", "m2")
                for c, v in CONDITIONS.items()]
    evaluate.append(_metric("evaluate", "m1", "noise", 30.0, uid="spk/u0"))   # per utterance: not in the table
    evaluate.append(_metric("evaluate", "m1", HOSTILE_CONDITION, 12.5))
    s.write_metrics("m1", "evaluate", table_from_rows(evaluate, METRICS))
    import cv2

    (root / "reports").mkdir(parents=True)
    sweep = np.full((120, 200, 3), 255, np.uint8)
    cv2.line(sweep, (10, 100), (190, 20), (180, 80, 20), 2)
    cv2.imwrite(str(root / "reports" / "sweep-fbank-blstm.png"), sweep)
    s.write_shard("rejects", 0, table_from_rows([_reject(HOSTILE_ID, "ingest", HOSTILE_MESSAGE)], REJECTS),
                  stage="ingest")
    s.write_shard("rejects", 0, table_from_rows([_reject(None, "track", "no landmarks & no <video>")], REJECTS),
                  stage="track")
    return s


class _Tags(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict]] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))


def _tags(page: str) -> list[tuple[str, dict]]:
    parser = _Tags()
    parser.feed(page)
    return parser.tags


@pytest.fixture(scope="module")
def dashboard(tmp_path_factory):
    """(store, out folder, page text, CLI output) of the dashboard of `realistic_store`, built through the CLI."""
    root = tmp_path_factory.mktemp("dash") / "store"
    store = realistic_store(root)
    out = root.parent / "report"
    result = runner.invoke(app, ["dashboard", "--store", str(root), "--out", str(out)])
    assert result.exit_code == 0, result.output
    return store, out, (out / "index.html").read_text(encoding="utf-8"), result.output


# ---- content ------------------------------------------------------------------------------------------
def test_dashboard_holds_every_section_and_chart(dashboard):
    _, out, page, output = dashboard
    assert "3 utterances, 6 charts" in output
    assert f"  {(out / 'index.html').resolve().as_uri()}\n" in output          # where to open it
    assert [p.name for p in out.iterdir()] == ["index.html"]        # one self-contained file
    tags = _tags(page)
    images = {a["id"]: a for t, a in tags if t == "img"}
    assert set(images) == {"chart-curves-0", "chart-curves-1", "chart-curves-2", "chart-mouth-error",
                           "chart-training", "chart-sweep-0"}
    assert all(a["alt"] and a["src"].startswith("data:image/png;base64,") for a in images.values())
    assert "spk/u0" in images["chart-curves-0"]["alt"]
    for section in ("store", "utterances", "tracking", "training", "sweeps", "robustness", "rejects"):
        assert ("section", {"id": section}) in tags
    # nothing is fetched: no script, no stylesheet or other link, a CSP that forbids any load but data: images
    assert not [t for t, _ in tags if t in {"script", "link", "iframe", "object", "embed"}]
    assert "default-src &#x27;none&#x27;; img-src data:" in page
    assert "audio unreadable" not in page                        # the .wav and the .mp4 audio track were read
    assert "L1 x 100 vs ground truth: procedural/jali" in page
    assert 'id="training-table"' in page and 'id="tracking-table"' in page and 'id="robustness-table"' in page
    assert "guided-fast" in page and "unguided-fast" in page
    assert "WWW 21.3, UUU 20.6, TTH 19.9" in page                   # worst visemes of the final row of m1


def test_hostile_ids_messages_and_conditions_are_escaped(dashboard, tmp_path):
    store, _, page, _ = dashboard
    for raw in (HOSTILE_ID, HOSTILE_MESSAGE, HOSTILE_CONDITION, "BadInput<x>", "no landmarks & no <video>"):
        assert raw not in page
        assert html.escape(raw, quote=True) in page
    assert not [t for t, _ in _tags(page) if t in {"script", "b", "video"}]
    # a requested id is echoed back escaped too
    requested = '"><script>alert(1)</script>'
    result = runner.invoke(app, ["dashboard", "--store", str(store.root), "--out", str(tmp_path),
                                 "--utterance", "spk/u2", "--utterance", requested])
    assert result.exit_code == 0, result.output
    assert "warning" in result.output and "1 utterances" in result.output
    again = (tmp_path / "index.html").read_text(encoding="utf-8")
    assert requested not in again and html.escape(requested) in again
    assert ["chart-curves-0"] == [a["id"] for t, a in _tags(again) if t == "img" and a["id"].startswith("chart-curves")]
    assert "spk/u2" in again and "spk/u0</strong>" not in again


def test_robustness_table_pivots_aggregate_evaluate_rows_with_ratios():
    rows = [_metric("evaluate", "b", c, v) for c, v in CONDITIONS.items()]
    rows += [_metric("evaluate", "a", "validation", 8.0), _metric("evaluate", "a", "noise", 10.0),
             _metric("evaluate", "a", "noise", 14.0),                         # two aggregates: the latest wins
             _metric("evaluate", "a", "speed", 99.0, uid="spk/u0"),          # per utterance: ignored
             _metric("final", "a", "validation", 1.0), _metric("train", "a", "pitch", 1.0, epoch=1),
             _metric("evaluate", "c", "volume", 5.0),                          # no validation: no ratio
             _metric("evaluate", "b", "reverb", 30.0)]                         # any other condition, after the known
    table = robustness_table(table_from_rows(rows, METRICS))
    assert table.models == ["a", "b", "c"]
    assert table.conditions == ["validation", "volume", "pitch", "speed", "noise", "reverb"]
    assert table.values[("a", "noise")] == pytest.approx(14.0)
    assert ("a", "speed") not in table.values and ("a", "pitch") not in table.values
    assert table.ratio("a", "noise") == pytest.approx(1.75)
    assert table.ratio("b", "pitch") == pytest.approx(1.3)
    assert table.ratio("b", "reverb") == pytest.approx(3.0)
    assert table.ratio("a", "volume") is None and table.ratio("c", "volume") is None
    rendered = robustness_html(table)
    headers = [a for t, a in _tags(rendered) if t == "th"]
    assert len(headers) == 3 + 1 + 6 + 5             # groups; model, 6 conditions, 5 ratios
    assert [h.get("colspan") for h in headers[:3]] == ["1", "6", "5"]
    assert "ratio to validation" in rendered and "<td class=\"num\">1.750</td>" in rendered
    assert "<td class=\"num\">3.000</td>" in rendered


def test_robustness_table_shows_realspeech_metrics_as_their_own_column_groups():
    rows = [_metric("evaluate", "a", c, v) for c, v in CONDITIONS.items()]
    rows += [_metric("evaluate.mbp_closure", "a", "validation", 80.0), _metric("evaluate.mbp_closure", "a", "pitch", 40.0),
             _metric("evaluate.mbp_closure", "a", "pitch", 10.0, uid="spk/u0"),     # per utterance: not a cell
             _metric("evaluate.agreement", "a", "validation", 62.5), _metric("evaluate.agreement", "a", "noise", 50.0),
             _metric("evaluate.agreement", "b", "validation", 12.5)]                 # a model without L1 rows
    table = robustness_table(table_from_rows(rows, METRICS))
    assert table.models == ["a", "b"] and table.realspeech_metrics == ["mbp_closure", "agreement"]
    assert table.conditions == ["validation", "volume", "pitch", "speed", "noise"]
    assert table.realspeech == {("a", "mbp_closure", "validation"): 80.0, ("a", "mbp_closure", "pitch"): 40.0,
                                ("a", "agreement", "validation"): 62.5, ("a", "agreement", "noise"): 50.0,
                                ("b", "agreement", "validation"): 12.5}
    assert table.realspeech_conditions("mbp_closure") == ["validation", "pitch"]
    rendered = robustness_html(table)
    headers = [a for t, a in _tags(rendered) if t == "th"]
    assert len(headers) == 5 + 1 + 5 + 4 + 2 + 2     # groups; model, 5 conditions, 4 ratios, MBP 2, agreement 2
    assert [h.get("colspan") for h in headers[:5]] == ["1", "5", "4", "2", "2"]
    assert "MBP closure % (real-speech metric)" in rendered and "agreement % (real-speech metric)" in rendered
    cells = re.findall(r"<td[^>]*>(.*?)</td>", rendered)
    assert cells[10:14] == ["80.000", "40.000", "62.500", "50.000"]
    assert cells[14:] == ["b"] + ["–"] * 9 + ["–", "–", "12.500", "–"]
    # without real-speech rows the table is the one it always was
    plain = robustness_table(table_from_rows([r for r in rows if r[C.RUN] == "evaluate"], METRICS))
    assert plain.realspeech_metrics == [] and "real-speech" not in robustness_html(plain)


def test_robustness_table_is_empty_without_evaluate_rows():
    table = robustness_table(table_from_rows([_metric("final", "a", "validation", 1.0)], METRICS))
    assert table.models == [] and table.conditions == []


def test_selection_shows_every_source_and_respects_the_limit():
    index = {f"s/u{i}": {"procedural": ["jali"]} for i in range(30)}
    index["s/u17"]["ground_truth"] = ["cm"]
    index["predict/x"] = {"predicted": ["m"]}
    known = [f"s/u{i}" for i in range(30)]
    selected, missing = select_utterances(known, index, None, 3)
    assert len(selected) == 3 and not missing
    assert "s/u17" in selected and "predict/x" in selected          # each source at least once
    assert selected[0] == "s/u17"                                     # richest first, curve-only last
    assert selected[-1] == "predict/x"
    assert select_utterances(known, index, ["s/u5", "nope/x", "s/u5"], 3) == (["s/u5"], ["nope/x"])
    assert select_utterances(known, index, None, 0) == ([], [])


def test_tracking_diagnostics_are_a_bounded_stable_sample(dashboard):
    store = dashboard[0]
    frames, counts = tracking_sample(store, limit=1)
    assert counts == {"guided-fast": (1, 2), "unguided-fast": (1, 2)}
    per_variant = {v: set(frames.filter(pc.equal(frames.column(C.VARIANT), v)).column(C.UTTERANCE_ID).to_pylist())
                   for v in counts}
    assert all(len(ids) == 1 for ids in per_variant.values())
    assert tracking_sample(store, limit=1)[0].equals(frames)           # the same sample every run
    assert tracking_sample(store)[0].num_rows == 4 * 30


def test_empty_store_says_there_is_nothing_yet(tmp_path):
    (tmp_path / "store").mkdir()
    result = runner.invoke(app, ["dashboard", "--store", str(tmp_path / "store"), "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    assert "nothing yet" in result.output
    page = (tmp_path / "out" / "index.html").read_text()
    assert 'id="nothing-yet"' in page and 'id="no-training"' in page and 'id="no-robustness"' in page
    assert "No utterances yet" in page and "No sweep yet" in page and "No tracking diagnostics yet" in page
    assert not [t for t, _ in _tags(page) if t == "img"]
    missing = runner.invoke(app, ["dashboard", "--store", str(tmp_path / "absent"), "--out", str(tmp_path / "o2")])
    assert missing.exit_code == 2 and "no store at" in missing.output
    assert not (tmp_path / "o2").exists()


def test_unreadable_audio_is_noted_not_fatal(tmp_path):
    s = Store(tmp_path / "store")
    s.write_shard("utterances", 0, table_from_rows(
        [_utterance_row("spk/a", tmp_path / "gone.wav", None, 1.0, 25.0, "train")], UTTERANCES))
    s.write_curves(curves_table("spk/a", "procedural", "jali", np.zeros((25, 16), np.float32), 25.0))
    result = build_dashboard(s, tmp_path / "out")
    page = result.path.read_text()
    assert result.utterances == ["spk/a"] and result.charts == ["chart-curves-0"]
    assert "audio unreadable" in page and "gone.wav" in page and 'id="no-rejects"' in page


def test_a_rejected_utterance_whose_old_curves_stay_is_called_rejected_not_curve_only(tmp_path):
    """An utterance an ingest rejected (its row gone) keeps the curves of an earlier run: the report called it a
    curve-only utterance of predict or speak, "from a file the store does not record"."""
    s = Store(tmp_path / "store")
    s.write_shard("utterances", 0, table_from_rows(
        [_utterance_row("spk/a", write_wav(tmp_path / "a.wav", 1.0), None, 1.0, 25.0, "train")], UTTERANCES))
    for uid in ("spk/a", "spk/b", "predict/c"):
        s.write_curves(curves_table(uid, "procedural", "jali", np.zeros((25, 16), np.float32), 25.0))
    s.write_shard("rejects", 0, table_from_rows([_reject("spk/b", "ingest", "bad wav")], REJECTS), stage="ingest")
    page = build_dashboard(s, tmp_path / "out").path.read_text()
    text = html.unescape(re.sub(r"<[^>]+>", " ", page))
    assert re.search(r"rejected utterances whose curves of an earlier run stay \(see Rejects\)\s+1", text), text[:3000]
    assert re.search(r"curve-only utterances \(predict, speak: no row in the utterances table\)\s+1", text)
    assert "rejected at its last run" in text and "these curves are of an earlier run" in text


# ---- a real browser -------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    exe = chromium_or_fail()
    b = Browser(exe, tmp_path_factory.mktemp("chromium") / "profile")
    yield b
    b.close()


def test_the_page_renders_in_chromium_without_errors_or_network(dashboard, browser, tmp_path):
    _, out, page, _ = dashboard
    state = browser.load(out / "index.html")
    assert state["errors"] == []
    assert [u for u in state["requests"] if not u.startswith(("file:", "data:"))] == []
    ids = [a["id"] for t, a in _tags(page) if t == "img"]
    assert [i["id"] for i in state["images"]] == ids and len(ids) == 6
    broken = [i for i in state["images"] if not (i["complete"] and i["width"] > 0 and i["height"] > 0)]
    assert broken == []
    from PIL import Image

    shot = browser.screenshot(tmp_path / "dashboard.png")
    with Image.open(shot) as image:
        assert image.format == "PNG" and image.size == (1280, 2000)
        pixels = np.asarray(image.convert("L"), dtype=np.float32)
    assert shot.stat().st_size > 20_000 and pixels.std() > 20       # not a blank page


def test_the_browser_check_sees_errors_broken_images_and_blocked_fetches(browser, tmp_path):
    """The checks above can fail: a console error, an undecodable image and a fetch the CSP blocks are all seen."""
    bad = tmp_path / "bad.html"
    bad.write_text('<!DOCTYPE html><html><body><img id="broken" alt="x" src="data:image/png;base64,AAAA">'
                   '<script>console.error("boom")</script></body></html>')
    state = browser.load(bad)
    assert any("boom" in e for e in state["errors"])
    assert state["images"][0]["width"] == 0
    blocked = tmp_path / "blocked.html"
    blocked.write_text('<!DOCTYPE html><html><head><meta http-equiv="Content-Security-Policy" '
                       "content=\"default-src 'none'; img-src data:\"></head><body>"
                       '<img id="remote" alt="x" src="http://127.0.0.1:9/x.png"></body></html>')
    state = browser.load(blocked)
    assert state["images"][0]["width"] == 0
    assert any("Content Security Policy" in e for e in state["errors"])
    assert "http://127.0.0.1:9/x.png" in state["requests"]      # the attempt is seen even though CSP blocks it


def test_utterances_with_ids_in_any_script_are_listed_by_their_ids_not_their_file_names(tmp_path):
    from visemeflow.dashboards.html import curve_index

    s = Store(tmp_path / "store")
    for uid in ("张三/句子 1", "Sprecher_ü/Satz%1", "spk/plain"):
        s.write_curves(curves_table(uid, "procedural", "jali", np.zeros((5, 16), np.float32), 25.0))
    assert curve_index(s) == {uid: {"procedural": ["jali"]} for uid in ("张三/句子 1", "Sprecher_ü/Satz%1", "spk/plain")}
    result = build_dashboard(s, tmp_path / "out")
    page = result.path.read_text(encoding="utf-8")
    assert "张三/句子 1" in page and "Sprecher_ü/Satz%1" in page and "%E5%BC%A0" not in page


def test_animation_packages_are_listed_with_links_and_previews_as_video_elements(tmp_path):
    from urllib.parse import unquote

    s = Store(tmp_path / "store")
    s.write_curves(curves_table("spk/a", "procedural", "jali", np.zeros((25, 16), np.float32), 25.0))
    folder = s.animation_dir("ict_visemes", "张三/第一句")
    folder.mkdir(parents=True)
    for suffix in (".glb", ".livelink.csv", ".mp4"):
        (folder / f"{folder.name}{suffix}").write_bytes(b"x")
    out = tmp_path / "report"
    page = build_dashboard(s, out).path.read_text()
    tags = _tags(page)
    videos = [a for t, a in tags if t == "video"]
    assert len(videos) == 1 and videos[0]["preload"] == "none" and "controls" in videos[0]
    links = [a["href"] for t, a in tags if t == "a" and not a.get("href", "").startswith("#")]
    assert len(links) == 3
    for href in links + [videos[0]["src"]]:
        assert (out / unquote(href)).resolve().is_file(), href  # relative to the page, percent-encoded
    assert "<code>张三/第一句</code> on ict_visemes" in page
    empty = build_dashboard(Store(tmp_path / "other"), tmp_path / "r2").path.read_text()
    assert 'id="no-animations"' in empty


# ---- long utterances ------------------------------------------------------------------------------------
def _long_utterance_store(root: Path, n_phones: int, fps: float = 30.0, rate: int = 1000) -> Store:
    """One utterance of `n_phones` phones of 0.08 s, procedural curves and audio over the whole of it."""
    s = Store(root / "store")
    seconds = n_phones * 0.08
    wav = write_wav(root / "long.wav", seconds, rate=rate)
    s.write_shard("utterances", 0, table_from_rows([_utterance_row("spk/long", wav, None, seconds, fps, "train")],
                                                   UTTERANCES))
    labels = [("sil", None), ("HH", "GK"), ("AH0", "SCHWA"), ("M", "MBP")]
    s.write_shard("phones", 0, table_from_rows([
        {C.UTTERANCE_ID: "spk/long", C.INDEX: k, C.PART: 0, C.LABEL: labels[k % 4][0], C.PHONEME: labels[k % 4][0],
         C.VISEME: labels[k % 4][1], C.START_S: k * 0.08, C.END_S: (k + 1) * 0.08} for k in range(n_phones)], PHONES))
    frames = round(seconds * fps)
    s.write_curves(curves_table("spk/long", "procedural", "jali",
                                np.random.default_rng(0).random((frames, 16)).astype(np.float32), fps), fps=fps)
    return s


def test_a_long_utterance_draws_its_first_phones_and_says_how_much_was_left_out(tmp_path, monkeypatch):
    """20,000 phones (27 minutes): the chart draws a bounded window from the start (phones, curve frames and audio
    within it) and the page says how much was left out. Drawing all of 100k phones took 201 s and 4.2 GB."""
    from visemeflow.dashboards import html as dash
    from visemeflow.dashboards import plots

    s = _long_utterance_store(tmp_path, 20_000)
    drawn = []
    real_figure = plots.utterance_figure
    monkeypatch.setattr(plots, "utterance_figure", lambda *args: drawn.append(args) or b"\x89PNG\r\n\x1a\n")
    page = build_dashboard(s, tmp_path / "out").path.read_text(encoding="utf-8")
    [(title, duration, waveform, _, phones, panels)] = drawn
    assert title == "spk/long" and 0 < len(phones) < 20_000
    assert len(phones) <= dash.MAX_DRAWN_PHONES
    assert [p.start_s for p in phones] == pytest.approx([k * 0.08 for k in range(len(phones))])
    assert duration == pytest.approx(phones[-1].end_s) and duration < 20_000 * 0.08
    [panel] = panels
    assert len(panel.time_s) <= dash.MAX_DRAWN_FRAMES and panel.time_s[-1] <= duration
    samples, rate = waveform
    assert rate == 1000 and len(samples) == pytest.approx(duration * rate, abs=1)
    note = re.search(r'<span class="note" id="drawn-window-0">([^<]*)</span>', page)
    assert note is not None, "no note saying what was left out"
    assert f"{len(phones)} of 20000 phones" in note[1] and f"first {duration:.1f} s of 1600.0 s" in note[1]
    assert "20000 phones" in page

    monkeypatch.setattr(plots, "utterance_figure", real_figure)
    result = build_dashboard(s, tmp_path / "real")
    assert result.charts == ["chart-curves-0"]


def test_a_short_utterance_is_drawn_whole_without_a_note(tmp_path, monkeypatch):
    from visemeflow.dashboards import plots

    s = _long_utterance_store(tmp_path, 50)
    drawn = []
    monkeypatch.setattr(plots, "utterance_figure", lambda *args: drawn.append(args) or b"\x89PNG\r\n\x1a\n")
    page = build_dashboard(s, tmp_path / "out").path.read_text(encoding="utf-8")
    [(_, duration, (samples, _), _, phones, [panel])] = drawn
    assert len(phones) == 50 and duration == pytest.approx(4.0) and len(panel.time_s) == 120
    assert len(samples) == 4000 and 'id="drawn-window-0"' not in page


# ---- a store shaped like the demo's: curve-only predictions, a Mandarin utterance, --out packages ----------------
def demo_like_store(root: Path) -> tuple[Store, Path]:
    """`realistic_store` plus what `make demo` adds: a Mandarin utterance with one source only (fewer than the
    English ones), a package of spk/u2 in the store (a preview), curve-only predictions (`predict/u0` from the very
    file of spk/u0, `predict/spoken` through `speak --out`, recorded, and `predict/lost` from a file nothing
    records), and real-speech and lip metrics that make the robustness table wider than the page. Returns the store
    and the --out folder of the recorded package."""
    from visemeflow.dashboards.records import record_packages
    from visemeflow.hashing import file_hash
    from visemeflow.learning.robustness_table import TABLE_RUNS

    s = realistic_store(root)
    media = root.parent / f"{root.name}-media"
    rng = np.random.default_rng(1)
    wav = write_wav(media / "SSB16240001.wav", 1.2)
    row = {**_utterance_row("SSB1624/SSB16240001", wav, None, 1.2, 25.0, "train"), C.LANGUAGE: "zh"}
    s.write_shard("utterances", 1, table_from_rows([row], UTTERANCES))
    s.write_shard("phones", 1, table_from_rows(_phone_rows("SSB1624/SSB16240001", 1.2), PHONES))
    s.write_curves(curves_table("SSB1624/SSB16240001", "procedural", "jali", rng.random((30, 16), np.float32), 25.0),
                   fps=25.0)
    folder = s.animation_dir("ict_visemes", "spk/u2")
    folder.mkdir(parents=True)
    (folder / "u2.preview.mp4").write_bytes(b"x")
    u0_wav = Path(s.read_table("utterances", utterance_ids=["spk/u0"]).to_pylist()[0][C.AUDIO_PATH])
    s.write_curves(curves_table("predict/u0", "predicted", "m1", rng.random((36, 16), np.float32), 30.0), fps=30.0,
                   provenance=f"predicted:m1:{'0' * 32}:{file_hash(u0_wav)}:30.0:code")
    s.write_curves(curves_table("predict/lost", "predicted", "m1", rng.random((36, 16), np.float32), 30.0),
                   fps=30.0, provenance=f"predicted:m1:{'0' * 32}:{'1' * 32}:30.0:code")
    spoken = write_wav(media / "spoken.wav", 1.1)
    s.write_curves(curves_table("predict/spoken", "predicted", "m1", rng.random((36, 16), np.float32), 30.0),
                   fps=30.0, provenance=f"predicted:m1:{'0' * 32}:{file_hash(spoken)}:30.0:code")
    out = root.parent / "speak out"
    package = out / "ict_visemes" / "predict" / "spoken"
    package.mkdir(parents=True)
    for suffix in (".glb", ".usda", ".mp4"):
        (package / f"spoken{suffix}").write_bytes(b"x")
    record_packages(s, [{"utterance_id": "predict/spoken", "character": "ict_visemes", "folder": str(package)}],
                    {"predict/spoken": str(spoken)})
    # a plain `predict new.wav` (no --out): the predict flow records the file it read
    from visemeflow.dashboards.records import record_predicted_audio

    new = write_wav(media / "new.wav", 1.0)
    s.write_curves(curves_table("predict/new", "predicted", "m1", rng.random((33, 16), np.float32), 30.0),
                   fps=30.0, provenance=f"predicted:m1:{'0' * 32}:{file_hash(new)}:30.0:code")
    changed = write_wav(media / "changed.wav", 1.0)
    s.write_curves(curves_table("predict/changed", "predicted", "m1", rng.random((33, 16), np.float32), 30.0),
                   fps=30.0, provenance=f"predicted:m1:{'0' * 32}:{'2' * 32}:30.0:code")   # the file changed since
    record_predicted_audio(s, {"predict/new": str(new), "predict/changed": str(changed)})
    wide = [_metric(run, "m1", c, 40.0 + k) for run in TABLE_RUNS for k, c in enumerate(CONDITIONS)]
    s.write_metrics("m1", "evaluate-extra", table_from_rows(wide, METRICS))
    return s, out


@pytest.fixture(scope="module")
def demo_like(tmp_path_factory):
    """(store, --out folder, report folder, page text) of the dashboard of `demo_like_store`, through the CLI."""
    root = tmp_path_factory.mktemp("demo-like") / "store"
    store, speak_out = demo_like_store(root)
    report = root.parent / "report"
    result = runner.invoke(app, ["dashboard", "--store", str(root), "--out", str(report)])
    assert result.exit_code == 0, result.output
    return store, speak_out, report, (report / "index.html").read_text(encoding="utf-8")


def _utterance_captions(page: str) -> dict[str, str]:
    """utterance id -> the caption of its chart."""
    captions = re.findall(r'<figcaption><strong class="utterance-id">(.*?)</strong>(.*?)</figcaption>', page, re.S)
    return {html.unescape(uid): caption for uid, caption in captions}


def test_the_utterance_count_agrees_with_the_store_table(demo_like):
    _, _, _, page = demo_like
    store_table = dict(re.findall(r"<tr><td>([^<]*)</td><td class=\"num\">(\d+)</td></tr>", page))
    in_table = int(store_table["utterances"])
    curve_only = int(store_table["curve-only utterances (predict, speak: no row in the utterances table)"])
    assert (in_table, curve_only) == (4, 5)
    note = re.search(r'<p class="note" id="utterance-count">(\d+) of (\d+) utterances \((\d+) in the utterances '
                     r"table, (\d+) curve-only\)", page)
    assert note is not None
    drawn, total, table_part, only_part = map(int, note.groups())
    assert total == in_table + curve_only == table_part + only_part and table_part == in_table
    assert drawn == len(_utterance_captions(page)) == 9


def test_predicted_clips_are_drawn_over_their_audio_when_the_store_knows_it(demo_like, tmp_path, monkeypatch):
    store, _, _, page = demo_like
    captions = _utterance_captions(page)
    # from the very file of spk/u0 (same bytes): its audio and phones, its ground truth as the reference
    assert "the same audio file as <code>spk/u0</code>" in captions["predict/u0"]
    assert "L1 x 100 vs the ground truth of <code>spk/u0</code>: predicted/m1" in captions["predict/u0"]
    # through speak --out: the audio the record names
    assert "audio recorded by speak/animate" in captions["predict/spoken"]
    assert "audio unknown" not in captions["predict/u0"] + captions["predict/spoken"]
    # a plain predict: the file the predict flow recorded, unless it changed since
    assert "audio recorded by predict" in captions["predict/new"]
    assert "audio unknown" in captions["predict/changed"]
    # a file nothing records: said so, not drawn
    assert "audio unknown" in captions["predict/lost"]
    from visemeflow.dashboards import plots

    drawn = {}
    monkeypatch.setattr(plots, "utterance_figure",
                        lambda title, *args: drawn.setdefault(title, args) and b"\x89PNG\r\n\x1a\n")
    build_dashboard(store, tmp_path / "out")
    (_, waveform, _, phones, _) = drawn["predict/u0"]
    assert waveform is not None and waveform[1] == 16000 and len(phones) == 8     # spk/u0's audio and phones
    assert drawn["predict/spoken"][1] is not None and drawn["predict/spoken"][3] == []
    assert drawn["predict/lost"][1] is None


def test_packages_written_outside_the_store_are_listed_with_working_links(demo_like):
    from urllib.parse import unquote

    _, speak_out, report, page = demo_like
    assert "2 of 2 packages (character, utterance), 1 of them written outside the store" in page
    blocks = re.findall(r'<div class="animation" id="animation-\d+">(.*?)</div>', page, re.S)
    [outside] = [b for b in blocks if "predict/spoken" in b]
    assert html.escape(str((speak_out / "ict_visemes" / "predict" / "spoken").resolve())) in outside
    hrefs = re.findall(r'(?:href|src)="([^"]+)"', outside)
    assert {Path(unquote(h)).name for h in hrefs} == {"spoken.glb", "spoken.usda", "spoken.mp4"}
    for href in hrefs:
        assert (report / unquote(href)).resolve().is_file(), href


def test_a_package_record_keeps_one_entry_per_folder_and_forgets_deleted_folders(tmp_path):
    from visemeflow.dashboards.records import MAX_RECORDED, RECORD_NAME, record_packages, recorded_packages

    s = Store(tmp_path / "store")
    folders = [tmp_path / "out" / f"p{k}" for k in range(3)]
    for f in folders:
        f.mkdir(parents=True)
    reports = [{"utterance_id": f"predict/p{k}", "character": "c", "folder": str(f)} for k, f in enumerate(folders)]
    assert record_packages(s, reports[:2], {"predict/p0": "a.wav"}) == 2
    assert record_packages(s, reports[1:], {}) == 3                    # p1 again: replaced, not added
    got = recorded_packages(s)
    assert [e["utterance_id"] for e in got] == ["predict/p2", "predict/p1", "predict/p0"]
    assert got[2]["audio"] == str(Path("a.wav").resolve()) and got[1]["audio"] is None
    folders[0].rmdir()
    assert [e["utterance_id"] for e in recorded_packages(s)] == ["predict/p2", "predict/p1"]
    s.report_path(RECORD_NAME).write_text("{not json")
    assert recorded_packages(s) == [] and record_packages(s, reports[:1]) == 1
    many = [{"utterance_id": f"predict/m{k}", "character": "c", "folder": str(tmp_path / f"m{k}")}
            for k in range(MAX_RECORDED + 5)]
    assert record_packages(s, many) == MAX_RECORDED


def test_every_language_and_the_packaged_utterances_are_drawn_within_the_limit(demo_like, tmp_path):
    store = demo_like[0]
    two = build_dashboard(store, tmp_path / "two", max_utterances=2)
    assert two.utterances == ["spk/u0", "SSB1624/SSB16240001"]       # the one Mandarin utterance, one source only
    three = build_dashboard(store, tmp_path / "three", max_utterances=3)
    assert three.utterances == ["spk/u2", "spk/u0", "SSB1624/SSB16240001"]  # spk/u2 has a preview: first
    page = three.path.read_text(encoding="utf-8")
    assert "SSB1624/SSB16240001</strong> · speaker SSB1624 · language zh" in page
    # without the languages, or the packages, the richest utterances win
    index = curve_index(store)
    known = store.read_table("utterances").column(C.UTTERANCE_ID).to_pylist()
    assert select_utterances(known, index, None, 2)[0] == ["spk/u0", "spk/u1"]
    assert select_utterances(known, index, None, 3, {u: "en" for u in known}, {"spk/u2"})[0] == \
        ["spk/u2", "spk/u0", "spk/u1"]


def test_the_wide_robustness_table_scrolls_in_its_box_and_the_page_does_not(demo_like, browser, tmp_path):
    _, _, report, page = demo_like
    measure = """(() => {
        const box = document.getElementById('robustness-scroll'), table = document.getElementById('robustness-table');
        const root = document.documentElement;
        return {page: [root.scrollWidth, root.clientWidth], table: table.getBoundingClientRect().width,
                box: box ? [box.scrollWidth, box.clientWidth] : null};
    })()"""
    state = browser.load(report / "index.html")
    assert state["errors"] == []
    sizes = browser.send("Runtime.evaluate", {"expression": measure, "returnByValue": True})["result"]["value"]
    assert sizes["table"] > sizes["page"][1]                        # the table is wider than the window...
    assert sizes["box"][0] > sizes["box"][1]                        # ...and scrolls inside its box...
    assert sizes["page"][0] <= sizes["page"][1]                     # ...so the page does not scroll sideways
    shot = browser.screenshot(tmp_path / "demo-like.png")
    assert shot.stat().st_size > 20_000
    # the measurement sees the overflow: the same page without the scroll box is wider than the window
    unwrapped = tmp_path / "unwrapped.html"
    unwrapped.write_text(page.replace('<div class="wide" id="robustness-scroll">', "<div>"), encoding="utf-8")
    browser.load(unwrapped)
    sizes = browser.send("Runtime.evaluate", {"expression": measure, "returnByValue": True})["result"]["value"]
    assert sizes["box"] is None and sizes["page"][0] > sizes["page"][1]


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_speak_with_out_records_its_packages_and_the_dashboard_lists_them(tmp_path):
    """The real `speak` flow with `--out`: the store records the package (and its audio), and the dashboard lists
    it and draws the predicted clip over that audio."""
    from factories import DEMO_AUDIO, tiny_model

    from visemeflow.animation.package import AnimateConfig
    from visemeflow.flows.animate import SpeakParams, speak_flow
    from visemeflow.rig.character import make_character, save_character_npz
    from visemeflow.shapes.conventions import OCULUS_15

    grid = np.stack(np.meshgrid(np.arange(4.0), np.arange(4.0)), -1).reshape(-1, 2)
    shapes = np.random.default_rng(0).normal(0, 0.1, size=(len(OCULUS_15), 16, 3))
    character = save_character_npz(make_character("tiny", np.c_[grid, np.zeros(16)],
                                                  [[i, i + 1, i + 4] for i in range(11) if i % 4 != 3],
                                                  list(OCULUS_15), shapes), tmp_path / "tiny.npz")
    store = Store(tmp_path / "store")
    tiny_model(store)
    out = tmp_path / "speak"
    result = speak_flow(SpeakParams(store=store.root, model="tiny", audio=[DEMO_AUDIO], characters=[character],
                                    out=out, config=AnimateConfig(formats=("glb",))))
    [package] = result["packages_written"]
    report = tmp_path / "report"
    cli = runner.invoke(app, ["dashboard", "--store", str(store.root), "--out", str(report)])
    assert cli.exit_code == 0, cli.output
    page = (report / "index.html").read_text(encoding="utf-8")
    assert "1 of 1 packages (character, utterance), 1 of them written outside the store" in page
    assert html.escape(str(Path(package["folder"]).resolve())) in page
    assert re.search(r'href="[^"]*SSB16240001\.glb"', page)
    caption = _utterance_captions(page)["predict/SSB16240001"]
    assert "audio unknown" not in caption and html.escape(str(DEMO_AUDIO.resolve())) in caption


def test_a_chinese_utterance_id_is_drawn_in_a_cjk_font_not_as_boxes():
    """The charts' titles are utterance ids; a Mandarin corpus names its files in characters. matplotlib's own font
    has none of them, so they drew as empty boxes (with a warning per glyph); make installs a CJK font."""
    import warnings

    from visemeflow.dashboards import plots

    assert len(plots.font_families()) > 1, "no CJK font found (scripts/system-deps.sh installs fonts-droid-fallback)"
    t = np.arange(30) / 30.0
    panel = plots.CurvePanel("procedural\ndefault", t, np.zeros((30, 16), np.float32))
    phones = [plots.Phone(0.0, 0.5, "zh", False), plots.Phone(0.5, 1.0, "ong1", False)]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        png = plots.utterance_figure("普通话/说话人0001", 1.0, None, "", phones, [panel])
        plots.sweep_figure([(10, 0.5), (20, 0.4)], "扫描 of 普通话")
    missing = [str(w.message) for w in caught if "missing from font" in str(w.message)]
    assert not missing, missing
    assert png.startswith(b"\x89PNG")
