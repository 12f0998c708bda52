"""Attack cases: what an untrusted store, character, alignment or caller can and cannot make visemeflow do.

Each section below covers one defect of the security probe (issue "Nobody gets in, nothing is lost"); every test
here failed before its fix. Sections are independent: each builds its own inputs under ``tmp_path``.
"""

from __future__ import annotations


# ---- ingest (corpus discovery, alignments, rejects, dashboard) ----
import subprocess  # noqa: E402
import sys  # noqa: E402

import pytest  # noqa: E402

_INGEST_CRAFTED_MLF_CHECK = """
import sys
from visemeflow.ingest import discover_corpus
found = discover_corpus(sys.argv[1])
print(sorted(e.utterance_id for e in found.entries), sorted(r.error_type for r in found.rejects))
"""


def test_ingest_crafted_mlf_pattern_is_matched_without_backtracking(tmp_path):
    """`"*/*a*a...*a*b.lab"` against a 60-character name backtracked for minutes with a regex; the matcher takes
    at most (pattern x name) steps. Run in a child process: a stuck regex holds the GIL, so only a kill stops it."""
    from factories import write_wav

    corpus = tmp_path / "corpus"
    name = "a" * 60
    write_wav(corpus / "s" / f"{name}.wav", 1.0)
    crafted = "*/" + "*a" * 25 + "*b.lab"
    (corpus / "s" / "labels.mlf").write_text(
        f'#!MLF!#\n"{crafted}"\n0 10000000 sil\n.\n"*/{name}.lab"\n0 10000000 sil\n.\n', encoding="utf-8")
    try:
        done = subprocess.run([sys.executable, "-c", _INGEST_CRAFTED_MLF_CHECK, str(corpus)], capture_output=True,
                              text=True, timeout=30)  # the fixed matcher takes milliseconds; the regex, hours
    except subprocess.TimeoutExpired:
        pytest.fail(f"discovery of {crafted!r} against a {len(name)}-character name ran past 30 s")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"['s/{name}'] []"


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_ingest_entity_expanding_xra_gives_a_bounded_reject_listing_and_page(tmp_path):
    """A 51 KB .xra whose entity expands to 7.5 MB inside the value its error quotes: the stored reject message,
    `visemeflow rejects` and the dashboard stay small, and still name the file and line."""
    from typer.testing import CliRunner

    from factories import textgrid_long, write_wav
    from visemeflow.cli import app
    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.params import IngestParams
    from visemeflow.schemas import C
    from visemeflow.storage import Store

    corpus, store = tmp_path / "corpus", tmp_path / "store"
    write_wav(corpus / "s" / "u.wav", 1.0)
    write_wav(corpus / "s" / "ok.wav", 1.0)  # a stage whose every utterance fails fails the flow
    (corpus / "s" / "ok.TextGrid").write_text(textgrid_long([(0.0, 0.5, "sil"), (0.5, 1.0, "AA1")], 1.0))
    bomb = (f'<?xml version="1.0"?>\n<!DOCTYPE Document [<!ENTITY e "{"x" * 50_000}">]>\n<Document format="1.4">\n'
            '<Tier id="t1" tiername="PhonAlign"><Annotation><Location><Interval>'
            f'<Begin midpoint="{"&e;" * 150}"/><End midpoint="1.0"/></Interval></Location>'
            "<Label><Tag>sil</Tag></Label></Annotation></Tier>\n</Document>\n")
    (corpus / "s" / "u.xra").write_text(bomb, encoding="utf-8")
    assert len(bomb) < 52_000
    ingest_flow(IngestParams(corpus=corpus, store=store, n_shards=1))
    [reject] = Store(store).read_table("rejects", "ingest").to_pylist()
    message = reject[C.MESSAGE]
    assert len(message) <= 4000 and message.endswith(" characters cut]"), len(message)
    assert f"{corpus / 's' / 'u.xra'}: line 4: Begin has no numeric midpoint" in message
    listing = CliRunner().invoke(app, ["rejects", "--store", str(store)])
    assert listing.exit_code == 0 and len(listing.output) < 5000, len(listing.output)
    done = CliRunner().invoke(app, ["dashboard", "--store", str(store), "--out", str(tmp_path / "page")])
    assert done.exit_code == 0, done.output
    assert (tmp_path / "page" / "index.html").stat().st_size < 200_000


# ---- store (Prefect's cached task results inside a store) ----
import base64  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import pickle  # noqa: E402
from pathlib import Path  # noqa: E402


class _StoreTouchOnLoad:
    """Runs a shell command when unpickled: the payload a planted result record carries."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch '{self.marker}'",)


def _store_pickle_record(marker: Path, storage_key: str = "planted") -> dict:
    """A well-formed Prefect result record whose metadata names the pickle serializer, as Prefect itself writes."""
    return {
        "metadata": {"storage_key": storage_key, "expiration": None, "storage_block_id": None,
                     "serializer": {"type": "pickle", "picklelib": "pickle"}},
        "result": base64.encodebytes(pickle.dumps(_StoreTouchOnLoad(marker))).decode(),
    }


def _store_plant_pickle_records(results: Path, marker: Path) -> list[Path]:
    """Replace every cached result record under `results` with a pickle record keeping its storage key."""
    planted = sorted(p for p in results.iterdir() if p.is_file())
    for path in planted:
        key = json.loads(path.read_bytes())["metadata"]["storage_key"]
        path.write_text(json.dumps(_store_pickle_record(marker, key)))
    return planted


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_store_planted_pickle_result_is_never_loaded(tmp_path):
    """A store copied from someone else whose cached results are pickles: the rerun loads none of them, recomputes
    those tasks instead and leaves the store as an honest run does, with JSON records that later runs hit."""
    from factories import make_lj_corpus, run_pipeline, snapshot

    from visemeflow.storage import Store

    corpus = make_lj_corpus(tmp_path / "corpus", speakers=1)
    store = tmp_path / "store"
    run_pipeline(corpus, store)
    honest = snapshot(store)
    marker = tmp_path / "code-ran"
    planted = _store_plant_pickle_records(Store(store).results_dir(), marker)
    assert planted

    try:
        again = run_pipeline(corpus, store)
    finally:
        assert not marker.exists(), "a pickle in the store's results folder was loaded"
    for stage in ("ingest", "procedural"):
        assert again[stage]["cached_shards"] == 0, f"{stage} served a planted record as a cache hit"
    assert snapshot(store) == honest
    for path in planted:
        assert json.loads(path.read_bytes())["metadata"]["serializer"] == {"type": "visemeflow-json"}, path

    third = run_pipeline(corpus, store)
    for stage in ("ingest", "procedural"):
        assert third[stage]["cached_shards"] == third[stage]["shards"], stage


def _store_planted_files(marker: Path) -> dict[str, bytes]:
    """What a results folder may hold besides our records; each would run or import code if Prefect decoded it."""
    evil = pickle.dumps(_StoreTouchOnLoad(marker))
    prefect_json = {  # Prefect's own JSON serializer imports any module a `__class__` names, with any decoder
        "metadata": {"storage_key": "k", "serializer": {"type": "json", "object_decoder": "os.system"}},
        "result": json.dumps({"__class__": "antigravity.geohash", "data": 1}),
    }
    ours_with_options = {"metadata": {"storage_key": "k", "serializer": {"type": "visemeflow-json", "x": 1}},
                         "result": "{}"}
    return {
        "pickle record": json.dumps(_store_pickle_record(marker)).encode(),
        "old-format pickle record": json.dumps({"serializer": {"type": "pickle"}, "data": "gAN9cQAu"}).encode(),
        "raw pickle": evil,
        "prefect json record": json.dumps(prefect_json).encode(),
        "unknown serializer": json.dumps({"metadata": {"serializer": {"type": "compressed/pickle"}},
                                          "result": ""}).encode(),
        "no serializer (Prefect's default is pickle)": json.dumps({"metadata": {}, "result": "gAN9cQAu"}).encode(),
        "our type with options": json.dumps(ours_with_options).encode(),
        "deep nesting": b"[" * 100_000,
    }


@pytest.mark.parametrize("kind", list(_store_planted_files(Path("m"))))
def test_store_results_folder_refuses_what_visemeflow_did_not_write(tmp_path, kind):
    """Each planted file is refused by name before Prefect reads it, and removed so the task writes a JSON one."""
    import logging

    from prefect.filesystems import LocalFileSystem
    from prefect.results import ResultStore

    from visemeflow.tasks.results import UntrustedResultError, check_result_record
    from visemeflow.tasks.common import RESULT_SERIALIZER, discard_untrusted_record

    marker = tmp_path / "code-ran"
    results = tmp_path / "store" / ".prefect-results"
    results.mkdir(parents=True)
    path = results / "0123abcd"
    path.write_bytes(_store_planted_files(marker)[kind])

    with pytest.raises(UntrustedResultError, match=str(path)):
        check_result_record(path)
    storage = LocalFileSystem(basepath=str(results))
    assert discard_untrusted_record(storage, path.name, logging.getLogger("test")) is True
    assert not path.exists()
    assert not ResultStore(result_storage=storage, serializer=RESULT_SERIALIZER).exists(path.name)
    assert not marker.exists()


def test_store_results_folder_refuses_links_and_special_files(tmp_path):
    """A link (it could point at a pickle anywhere) or a FIFO (reading it would hang) in place of a record."""
    import logging

    from prefect.filesystems import LocalFileSystem

    from visemeflow.tasks.results import UntrustedResultError, check_result_record
    from visemeflow.tasks.common import discard_untrusted_record

    results = tmp_path / ".prefect-results"
    results.mkdir()
    honest = results / "honest"
    honest.write_text(json.dumps({"metadata": {"serializer": {"type": "visemeflow-json"}}, "result": "{}"}))
    check_result_record(honest)
    (results / "link").symlink_to(honest)
    os.mkfifo(results / "fifo")
    storage = LocalFileSystem(basepath=str(results))
    for name in ("link", "fifo"):
        with pytest.raises(UntrustedResultError, match=f"{results / name}: .*regular file"):
            check_result_record(results / name)
        assert discard_untrusted_record(storage, name, logging.getLogger("test")) is True
        assert not os.path.lexists(results / name)
    assert honest.exists()


# ---- serve (API lockdown, flow-run roots, server log, server lifetime) ----
import signal  # noqa: E402
import socket  # noqa: E402
import stat  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402

_SERVE_EVIL_ORIGIN = "https://evil.example"


@dataclass
class _Served:
    process: subprocess.Popen
    api_url: str
    ui_origin: str
    store: Path
    corpus: Path
    output: Path
    victim: Path
    victim_text: str

    def auth_string(self) -> str:
        from visemeflow.ops.serve import AUTH_FILE, SERVE_DIR

        return (self.store / SERVE_DIR / AUTH_FILE).read_text()


def _serve_free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _serve_kill_leftover_servers(port: int) -> None:
    import psutil

    for process in psutil.process_iter(["cmdline"]):  # a server left behind by a failure here
        if "--port" in (cmd := process.info["cmdline"] or []) and str(port) in cmd and "server" in cmd:
            process.kill()


@pytest.fixture(scope="module")
def _served(tmp_path_factory):
    """One real `visemeflow serve` for this section (its start costs tens of seconds); the last test kills it."""
    root = tmp_path_factory.mktemp("serve")
    store, corpus, tmp = root / "store", root / "corpus", root / "tmp"
    corpus.mkdir()
    tmp.mkdir()
    port = _serve_free_port()
    victim = root / "victim.txt"
    victim.write_text("a file of the user's that a planted link points at\n")
    # serve's old log path, predictable in the temp folder: another local user plants a link there first
    (tmp / f"visemeflow-prefect-server-{port}.log").symlink_to(victim)
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "PREFECT_API_AUTH_STRING")}
    env.update(TMPDIR=str(tmp), PREFECT_HOME=str(root / "prefect-home"), PREFECT_SERVER_ANALYTICS_ENABLED="false",
               PREFECT_RUNNER_POLL_FREQUENCY="2")
    output = root / "serve.out"
    with output.open("w") as out:
        process = subprocess.Popen(
            [sys.executable, "-m", "visemeflow.cli", "serve", "--store", str(store), "--corpus", str(corpus),
             "--port", str(port), "--cron", ""], env=env, stdout=out, stderr=subprocess.STDOUT)
    served = _Served(process, f"http://127.0.0.1:{port}/api", f"http://127.0.0.1:{port}", store, corpus, output,
                     victim, victim.read_text())
    try:
        deadline = time.monotonic() + 240
        while "deployments are being served" not in output.read_text():  # Prefect's line once all are applied
            assert process.poll() is None and time.monotonic() < deadline, output.read_text()
            time.sleep(0.5)
        yield served
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        _serve_kill_leftover_servers(port)


@pytest.fixture
def _serve_client(_served):
    """A Prefect client holding the auth string `serve` gave its own processes."""
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_AUTH_STRING, PREFECT_API_URL, temporary_settings

    with temporary_settings(updates={PREFECT_API_URL: _served.api_url,
                                     PREFECT_API_AUTH_STRING: _served.auth_string()}):
        with get_client(sync_client=True) as client:
            yield client


@pytest.mark.server
def test_serve_refuses_a_cross_origin_post_without_the_auth_string(_served, _serve_client):
    """A page on another site, open in the user's browser, POSTs create_flow_run: refused, and no run exists."""
    import httpx

    deployment = _serve_client.read_deployment_by_name("ingest/served")
    attacker_store = _served.store.parent / "attacker-store"
    body = json.dumps({"parameters": {"params": {"store": str(attacker_store), "corpus": str(_served.corpus)}}})
    url = f"{_served.api_url}/deployments/{deployment.id}/create_flow_run"
    preflight = {"Access-Control-Request-Method": "POST",
                 "Access-Control-Request-Headers": "authorization,content-type,prefect-csrf-token,prefect-csrf-client"}
    evil = httpx.options(url, headers={"Origin": _SERVE_EVIL_ORIGIN, **preflight})
    assert evil.headers.get("access-control-allow-origin") not in (_SERVE_EVIL_ORIGIN, "*"), evil.headers
    ui = httpx.options(url, headers={"Origin": _served.ui_origin, **preflight})
    assert ui.headers.get("access-control-allow-origin") == _served.ui_origin, (ui.status_code, ui.text)
    # the page's fetch() as the browser sends it once a preflight passes, and as a "simple" text/plain request,
    # which a browser sends cross-origin without asking first
    for content_type in ("application/json", "text/plain"):
        attack = httpx.post(url, content=body, headers={"Origin": _SERVE_EVIL_ORIGIN, "Content-Type": content_type})
        assert attack.status_code in (401, 403), (content_type, attack.status_code, attack.text)
        assert attack.headers.get("access-control-allow-origin") not in (_SERVE_EVIL_ORIGIN, "*"), attack.headers
    token = httpx.get(f"{_served.api_url}/csrf-token", params={"client": "evil"},
                      headers={"Origin": _SERVE_EVIL_ORIGIN})
    assert token.status_code == 401, token.text  # no CSRF token without the auth string
    basic = base64.b64encode(_served.auth_string().encode()).decode()
    no_csrf = httpx.post(url, content=body, headers={"Authorization": f"Basic {basic}",
                                                     "Content-Type": "application/json"})
    assert no_csrf.status_code == 403, no_csrf.text  # CSRF protection is on
    assert _serve_client.read_flow_runs() == []
    assert not attacker_store.exists()


@pytest.mark.server
def test_the_readmes_curl_lines_reach_the_served_api_as_written(_served):
    """README: raw HTTP with the auth string alone got `Missing CSRF token`; its lines fetch a token and POST."""
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    start = readme.index('AUTH="$(cat my_store/')
    snippet = readme[start:readme.index("```", start)]
    snippet = snippet.replace("my_store/", f"{_served.store}/").replace("http://127.0.0.1:4200/api", _served.api_url)
    done = subprocess.run(["bash", "-ec", snippet], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    names = [d["name"] for d in json.loads(done.stdout)]
    assert len(names) >= 14 and set(names) == {"served"}, done.stdout[:500]    # one deployment per stage


@pytest.mark.server
def test_serve_refuses_a_flow_run_whose_store_is_outside_its_roots(_served, _serve_client):
    """Even with the auth string, a run names only paths under the folders serve was started with."""
    from prefect.states import StateType

    deployment = _serve_client.read_deployment_by_name("procedural/served")
    outside = _served.store.parent / "elsewhere" / "store"
    run = _serve_client.create_flow_run_from_deployment(deployment.id, parameters={"store": str(outside)})
    deadline = time.monotonic() + 240
    while not (run := _serve_client.read_flow_run(run.id)).state.is_final():
        assert time.monotonic() < deadline, f"flow run still {run.state.name}; serve said:\n{_served.output.read_text()}"
        time.sleep(1)
    assert run.state.type == StateType.FAILED, (run.state, _served.output.read_text())
    assert str(outside) in run.state.message and "outside" in run.state.message, run.state.message
    assert not outside.exists() and not outside.parent.exists()


@pytest.mark.server
def test_serve_writes_its_server_log_to_a_private_file_not_through_a_planted_link(_served):
    assert _served.victim.read_text() == _served.victim_text, "serve wrote its log through a planted symlink"
    said = _served.output.read_text()
    (line,) = [line for line in said.splitlines() if line.startswith("server log: ")]
    log = Path(line.removeprefix("server log: "))
    assert log.is_relative_to(_served.store), log
    mode = os.lstat(log).st_mode
    assert stat.S_ISREG(mode) and stat.S_IMODE(mode) == 0o600, oct(mode)
    assert stat.S_IMODE(os.stat(log.parent).st_mode) == 0o700
    assert log.stat().st_size > 0


@pytest.mark.server
def test_serve_server_dies_with_its_parent_on_kill_9(_served):
    """kill -9 of `visemeflow serve` (OOM killer, a crashed session): its Prefect server must not keep listening."""
    import psutil

    from visemeflow.ops.serve import api_healthy

    children = psutil.Process(_served.process.pid).children(recursive=True)
    assert children and api_healthy(_served.api_url)
    _served.process.send_signal(signal.SIGKILL)
    _served.process.wait()
    deadline = time.monotonic() + 30
    while api_healthy(_served.api_url) or any(c.is_running() and c.status() != psutil.STATUS_ZOMBIE for c in children):
        assert time.monotonic() < deadline, f"still running 30 s after kill -9 of serve: {children}"
        time.sleep(0.5)


# ---- model files (a crafted model.pt: sizes checked before anything is built) ----
_MODEL_LOAD_UNDER_A_MEMORY_LIMIT = """
import resource, sys
from transformers import Wav2Vec2Config, Wav2Vec2Model  # imported before the limit: load_model imports them
from visemeflow.learning.train import ModelFileError, load_model
size_kb = int(next(l for l in open("/proc/self/status") if l.startswith("VmSize:")).split()[1])
resource.setrlimit(resource.RLIMIT_AS, ((size_kb << 10) + (1 << 30), resource.getrlimit(resource.RLIMIT_AS)[1]))
for path in sys.argv[1:]:
    try:
        load_model(path)
    except ModelFileError as exc:
        print("refused:", exc)
    else:
        print("loaded:", path)
"""


def _model_crafted_files(tmp_path: Path) -> dict[str, Path]:
    import torch

    from visemeflow.learning.features import make_tiny_wav2vec2
    from visemeflow.learning.train import TrainConfig, _assemble, build_training_model, save_model

    def save(name: str, blob: dict) -> Path:
        torch.save(blob, tmp_path / name)
        return tmp_path / name

    cfg = TrainConfig(preset="fbank-tcn", d_model=16)
    good = save_model(build_training_model(cfg, 25.0), cfg, tmp_path / "good.pt", {})
    blob = torch.load(good, weights_only=True)
    wide = TrainConfig(preset="fbank-tcn", d_model=10**6)
    features = build_training_model(cfg, 25.0).features
    with torch.device("meta"):  # the shapes a config of d_model 10**6 asks for, as broadcast views of one value
        shapes = {k: v.shape for k, v in _assemble(wide, features, 25.0).state_dict().items()}
    w2v_cfg = TrainConfig(preset="wav2vec2-blstm", d_model=16, wav2vec2_model=str(make_tiny_wav2vec2(tmp_path / "w")))
    w2v = torch.load(save_model(build_training_model(w2v_cfg, 25.0), w2v_cfg, tmp_path / "w2v.pt", {}),
                     weights_only=True)
    return {
        "d_model": save("d_model.pt", {**blob, "config": wide.model_dump_json()}),
        "layers": save("layers.pt", {**w2v, "wav2vec2_config": json.dumps(
            {**json.loads(w2v["wav2vec2_config"]), "num_hidden_layers": 10**6})}),
        "hidden": save("hidden.pt", {**w2v, "wav2vec2_config": json.dumps(
            {**json.loads(w2v["wav2vec2_config"]), "hidden_size": 10**6})}),
        "broadcast": save("broadcast.pt", {**blob, "config": wide.model_dump_json(),
                                           "state_dict": {k: torch.zeros(()).expand(s) for k, s in shapes.items()}}),
        "mel": save("mel.pt", {**blob, "feature_config": json.dumps(
            {**json.loads(blob["feature_config"]), "n_mels": 10**7})}),
    }


def test_model_file_sizes_are_checked_before_anything_is_allocated(tmp_path):
    """A model.pt whose config asks for d_model 10**6, a million wav2vec2 layers or a 10**7-band mel filterbank, or
    whose weights are broadcast views claiming 10**12 values in a few bytes, is refused before the model is built:
    loading runs in a child process allowed 1 GiB more address space than it had after its imports."""
    files = _model_crafted_files(tmp_path)
    for name in files.values():
        assert name.stat().st_size < 2_000_000, name  # each a small file
    done = subprocess.run([sys.executable, "-c", _MODEL_LOAD_UNDER_A_MEMORY_LIMIT, *map(str, files.values())],
                          capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr[-3000:]
    said = dict(zip(files, done.stdout.splitlines()))
    prefix = "refused: {} is not a visemeflow model file (expected a file written by visemeflow train / save_model): "
    for key, path in files.items():
        assert said[key].startswith(prefix.format(path)), said[key]
    assert "head.f_proj.weight" in said["d_model"] and "(1000000, 80)" in said["d_model"], said["d_model"]
    assert "(16, 80)" in said["d_model"], said["d_model"]
    assert "num_hidden_layers" in said["layers"] and "1000000" in said["layers"], said["layers"]
    assert "hidden_size" in said["hidden"] or "features.model." in said["hidden"], said["hidden"]
    assert "broadcast" in said["broadcast"] and "head.f_proj.weight" in said["broadcast"], said["broadcast"]
    assert "n_mels" in said["mel"] and "feature tables" in said["mel"], said["mel"]


# ---- files (glTF characters and .xlsx channel tables: URIs stay in the folder, declared sizes are checked) ----
import struct  # noqa: E402
import zipfile  # noqa: E402
import zlib  # noqa: E402

import numpy as np  # noqa: E402

_FILES_SECRET = b"SECRET-KEY-do-not-export"


def _files_gltf(path: Path, buffer_uri: str | None = None, change=None) -> tuple[Path, bytes]:
    """A one-triangle .gltf at `path` with one morph target, jawOpen: its 72-byte buffer in a data: URI, or named
    `buffer_uri` (the caller puts the bytes there); `change(document)` edits the JSON first. (path, the bytes)."""
    blob = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, .1], [0, 0, .2], [0, 0, .3]], "<f4").tobytes()
    uri = buffer_uri or "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
    document = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "meshes": [{"name": "face", "extras": {"targetNames": ["jawOpen"]},
                    "primitives": [{"attributes": {"POSITION": 0}, "targets": [{"POSITION": 1}]}]}],
        "accessors": [{"bufferView": k, "componentType": 5126, "count": 3, "type": "VEC3"} for k in (0, 1)],
        "bufferViews": [{"buffer": 0, "byteOffset": 36 * k, "byteLength": 36} for k in (0, 1)],
        "buffers": [{"uri": uri, "byteLength": 72}],
    }
    if change is not None:
        change(document)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(document))
    return path, blob


@pytest.mark.parametrize("how", ["dotdot", "percent-encoded", "absolute", "symlink", "image"])
def test_files_gltf_uri_cannot_read_outside_the_character_folder(tmp_path, how):
    """A buffer or image URI of a .gltf that leads out of the character's folder (`..`, `%2E%2E`, an absolute
    path, a link inside the folder to a file outside) is refused at load, naming the file and the URI; the secret
    beside the folder (valid buffer bytes, so that reading it would load) is never read."""
    from visemeflow.rig.character import CharacterError
    from visemeflow.animation.load import load_character

    folder = tmp_path / "characters" / "face"
    secret = tmp_path / "secret.bin"
    uri = {"dotdot": "../../secret.bin", "percent-encoded": "%2E%2E/%2e%2e/secret.bin", "absolute": str(secret),
           "symlink": "link.bin", "image": "textures/../../../secret.bin"}[how]
    if how == "image":
        path, blob = _files_gltf(folder / "face.gltf", change=lambda d: d.update(images=[{"uri": uri}]))
    else:
        path, blob = _files_gltf(folder / "face.gltf", uri)
    secret.write_bytes(blob + _FILES_SECRET)
    if how == "symlink":
        (folder / "link.bin").symlink_to(secret)
    with pytest.raises(CharacterError) as caught:
        load_character(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: "), message
    assert repr(uri) in message and "outside the character's folder" in message, message


def test_files_gltf_asset_export_rereads_no_uri_outside_the_folder(tmp_path):
    """The GLB export reads the character's .gltf again (to keep the whole asset): an image URI changed to lead
    out of the folder after the character was loaded is refused there too, and nothing is written."""
    from visemeflow.rig.character import CharacterError
    from visemeflow.animation.gltf_asset import write_character_glb
    from visemeflow.animation.load import load_character

    path, blob = _files_gltf(tmp_path / "face" / "face.gltf", "face.bin")
    (path.parent / "face.bin").write_bytes(blob)
    (tmp_path / "secret.png").write_bytes(_FILES_SECRET)
    character = load_character(path)
    document = json.loads(path.read_text())
    document["images"] = [{"uri": "..%2Fsecret.png"}]
    path.write_text(json.dumps(document))
    out = tmp_path / "out" / "face.glb"
    with pytest.raises(CharacterError, match=r"image 0: '\.\.%2Fsecret\.png' leads outside the character's folder"):
        write_character_glb(out, character, np.zeros((2, character.n_shapes), np.float32), 30.0)
    assert not out.exists()


def test_files_gltf_declared_sizes_larger_than_the_data_are_refused(tmp_path):
    """A buffer whose byteLength claims more bytes than its data holds is a lie, refused naming the file."""
    from visemeflow.rig.character import CharacterError
    from visemeflow.animation.load import load_character

    path, _ = _files_gltf(tmp_path / "long.gltf", change=lambda d: d["buffers"][0].update(byteLength=2**40))
    with pytest.raises(CharacterError, match=r"long\.gltf: buffer 0 declares 1099511627776 bytes .* holds 72"):
        load_character(path)


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_files_animate_rejects_characters_that_escape_or_lie_and_goes_on(tmp_path):
    """`animate` given a character whose buffer URI escapes its folder and a 500-byte one declaring 2**40
    vertices, beside a good one: both become rejects naming their file and why, the good one is exported, and no
    output holds the secret."""
    from factories import make_curve_store

    from visemeflow.animation.package import AnimateConfig
    from visemeflow.flows.animate import AnimateParams, animate_flow
    from visemeflow.schemas import C

    secret = tmp_path / "secret.bin"
    escaping, blob = _files_gltf(tmp_path / "characters" / "escaping" / "escaping.gltf", "../../secret.bin")
    secret.write_bytes(blob + _FILES_SECRET)

    def unbacked(d):
        d["accessors"][0] = {"componentType": 5126, "count": 2**40, "type": "VEC3"}

    lying, _ = _files_gltf(tmp_path / "characters" / "lying.gltf", change=unbacked)
    good, _ = _files_gltf(tmp_path / "characters" / "good.gltf")
    store = make_curve_store(tmp_path / "store", n=1)
    out = tmp_path / "out"
    result = animate_flow(AnimateParams(store=store.root, characters=[escaping, lying, good], source="ground_truth",
                                        out=out, config=AnimateConfig(convention="arkit52", formats=("glb", "usd"))))
    assert [Path(r["files"]["glb"]).stem for r in result["packages_written"]] == ["u0"]
    rejects = {r[C.PATH]: r for r in store.read_table("rejects", "animate").to_pylist()}
    assert set(rejects) == {str(escaping), str(lying)}
    assert "'../../secret.bin' leads outside the character's folder" in rejects[str(escaping)][C.MESSAGE]
    assert "1099511627776" in rejects[str(lying)][C.MESSAGE]
    assert all(r[C.ERROR_TYPE] == "CharacterError" for r in rejects.values())
    assert not [p for p in out.rglob("*") if p.is_file() and _FILES_SECRET in p.read_bytes()]


_FILES_READ_UNDER_A_MEMORY_LIMIT = """
import resource, sys
from visemeflow.rig.character import CharacterError
from visemeflow.animation.load import load_character
from visemeflow.ingest.captured import CaptureReadError, read_xlsx_rows
size_kb = int(next(l for l in open("/proc/self/status") if l.startswith("VmSize:")).split()[1])
resource.setrlimit(resource.RLIMIT_AS, ((size_kb << 10) + (1 << 30), resource.getrlimit(resource.RLIMIT_AS)[1]))
for path in sys.argv[1:]:
    try:
        (read_xlsx_rows if path.endswith(".xlsx") else load_character)(path)
    except (CharacterError, CaptureReadError) as exc:
        print("refused:", str(exc).replace(chr(10), " "))
    except (MemoryError, Exception) as exc:  # what the test reports as the defect
        print(f"{type(exc).__name__}:", path, str(exc).replace(chr(10), " ")[:300])
    else:
        print("loaded:", path)
"""


def _files_read_under_a_memory_limit(paths: list[Path]) -> list[str]:
    """What loading each path said, in a child process allowed 1 GiB more address space than after its imports."""
    done = subprocess.run([sys.executable, "-c", _FILES_READ_UNDER_A_MEMORY_LIMIT, *map(str, paths)],
                          capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout.splitlines()


def test_files_tiny_gltf_declaring_huge_arrays_is_refused_before_allocating(tmp_path):
    """glTF files of a few hundred bytes whose accessors declare 2**40 or 2**27 vertices without data behind them,
    or 20,000 morph targets on a million declared vertices, are refused naming the file and what is too large;
    the same file with its real sizes loads under the same limit."""
    def unbacked(count: int):
        def change(d):
            d["accessors"][0] = {"componentType": 5126, "count": count, "type": "VEC3"}
            d["accessors"][1] = {"componentType": 5126, "count": count, "type": "VEC3"}
        return change

    def many_targets(d):
        unbacked(2**20)(d)
        d["meshes"][0]["primitives"][0]["targets"] = [{"POSITION": 1}] * 20_000
        d["meshes"][0]["extras"]["targetNames"] = [f"t{k}" for k in range(20_000)]

    files = {"count": _files_gltf(tmp_path / "count.gltf", change=unbacked(2**40))[0],
             "lazy": _files_gltf(tmp_path / "lazy.gltf", change=unbacked(2**27))[0],
             "targets": _files_gltf(tmp_path / "targets.gltf", change=many_targets)[0],
             "good": _files_gltf(tmp_path / "good.gltf")[0]}
    assert files["count"].stat().st_size < 710 and files["lazy"].stat().st_size < 710
    said = dict(zip(files, _files_read_under_a_memory_limit(list(files.values()))))
    assert said.pop("good") == f"loaded: {files['good']}"
    for key, path in list(files.items())[:-1]:
        assert said[key].startswith(f"refused: {path}: "), said[key]
    assert "accessor 0" in said["count"] and "1099511627776" in said["count"], said["count"]
    assert "134217728" in said["lazy"], said["lazy"]
    assert "20000 morph targets" in said["targets"], said["targets"]


_FILES_WORKBOOK = (b'<workbook xmlns:r="http://schemas.openxmlformats.org/officeDocument/2006/relationships"><sheets>'
                   b'<sheet name="S" sheetId="1" r:id="rId1"/></sheets></workbook>')
_FILES_RELS = (b'<Relationships><Relationship Id="rId1" Target="worksheets/sheet1.xml" Type="worksheet"/>'
               b'</Relationships>')
_FILES_SHEET = "xl/worksheets/sheet1.xml"


def _files_xlsx(path: Path, sheet: bytes, compression: int = zipfile.ZIP_DEFLATED) -> Path:
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("xl/workbook.xml", _FILES_WORKBOOK, zipfile.ZIP_DEFLATED)
        archive.writestr("xl/_rels/workbook.xml.rels", _FILES_RELS, zipfile.ZIP_DEFLATED)
        archive.writestr(_FILES_SHEET, sheet, compression)
    return path


def _files_xlsx_lying(path: Path, unpacked: int, declared: int) -> Path:
    """An .xlsx whose sheet unpacks to `unpacked` bytes of spaces while the zip declares `declared`.

    The deflate stream is one compressed MiB repeated (a full flush ends each copy on a byte boundary with an empty
    history, so copies join into one valid stream), stored as is, then the headers patched: method deflate, the
    declared size."""
    compressor = zlib.compressobj(9, zlib.DEFLATED, -15)
    piece = compressor.compress(b" " * (1 << 20)) + compressor.flush(zlib.Z_FULL_FLUSH)
    _files_xlsx(path, piece * (unpacked >> 20) + zlib.compressobj(9, zlib.DEFLATED, -15).flush(), zipfile.ZIP_STORED)
    with zipfile.ZipFile(path) as archive:
        local = archive.getinfo(_FILES_SHEET).header_offset
    data = bytearray(path.read_bytes())
    struct.pack_into("<H", data, local + 8, zipfile.ZIP_DEFLATED)
    struct.pack_into("<I", data, local + 22, declared)
    central = data.find(b"PK\x01\x02")
    while central != -1:
        name_length = struct.unpack_from("<H", data, central + 28)[0]
        if data[central + 46:central + 46 + name_length] == _FILES_SHEET.encode():
            struct.pack_into("<H", data, central + 10, zipfile.ZIP_DEFLATED)
            struct.pack_into("<I", data, central + 24, declared)
        central = data.find(b"PK\x01\x02", central + 46)
    path.write_bytes(bytes(data))
    return path


def test_files_xlsx_whose_sizes_lie_or_explode_is_refused_without_unpacking_it(tmp_path):
    """A channel table .xlsx whose zip directory declares 1 KB for a sheet of 1 GiB, declares 3 GB, packs 2 MiB
    of cells into 2 KB (a ratio no spreadsheet has), or uses a compression Excel never writes, is refused naming
    the file and the part, reading no more than it allows."""
    files = {"small": _files_xlsx_lying(tmp_path / "small.xlsx", 1 << 30, 1000),
             "huge": _files_xlsx_lying(tmp_path / "huge.xlsx", 1 << 20, 3_000_000_000),
             "ratio": _files_xlsx(tmp_path / "ratio.xlsx",
                                  b"<worksheet><sheetData><row>" + b"<c/>" * (512 << 10) + b"</row></sheetData>"
                                  b"</worksheet>"),
             "lzma": _files_xlsx(tmp_path / "lzma.xlsx", b"<worksheet/>", zipfile.ZIP_LZMA)}
    assert all(p.stat().st_size < 2_000_000 for p in files.values())
    said = dict(zip(files, _files_read_under_a_memory_limit(list(files.values()))))
    for key, path in files.items():
        assert said[key].startswith(f"refused: {path}: "), said[key]
        assert _FILES_SHEET in said[key], said[key]
    assert "3000000000" in said["huge"], said["huge"]
    assert "ratio" in said["ratio"], said["ratio"]
    assert "LZMA" in said["lzma"] or "compression" in said["lzma"], said["lzma"]


@pytest.mark.parametrize("kind", ["character", "rig"])
def test_files_npz_declared_sizes_are_checked_before_numpy_allocates_them(tmp_path, kind):
    """A 1 kB .npz whose header declares a 3 TB array made `np.load` ask for it and the animate flow die with a
    MemoryError, taking the other characters down with it; now it is that file's error."""
    import zipfile

    import numpy as np

    from visemeflow.animation.load import load_character
    from visemeflow.rig import RigError, load_demo_rig, load_rig_npz, save_rig_npz
    from visemeflow.rig.character import CharacterError, character_from_rig, save_character_npz
    from visemeflow.rig.io import check_npz_sizes

    good = (save_character_npz(character_from_rig(load_demo_rig()), tmp_path / "good.npz") if kind == "character"
            else save_rig_npz(load_demo_rig(), tmp_path / "good.npz"))
    lying = tmp_path / "lying.npz"
    with zipfile.ZipFile(good) as src, zipfile.ZipFile(lying, "w", zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            if info.filename == "deltas.npy":
                with dst.open("deltas.npy", "w") as member:
                    header = {"descr": "<f4", "fortran_order": False, "shape": (100_000, 100_000, 80)}
                    np.lib.format.write_array_header_1_0(member, header)
                    member.write(bytes(64))
            else:
                dst.writestr(info, src.read(info))
    assert lying.stat().st_size < 1_000_000      # the demo head's other arrays; the claim is 3 TB
    message = r"array deltas\.npy declares 3200000000000 bytes \(\(100000, 100000, 80\), float32\) but holds 192"
    if kind == "character":
        with pytest.raises(CharacterError, match=rf"^{lying}: not a readable \.npz character file \({message}\)"):
            load_character(lying)
        assert len(load_character(good).neutral) > 0
    else:
        with pytest.raises(RigError, match=rf"^{lying}: cannot read rig npz: {message}"):
            load_rig_npz(lying)
        assert len(load_rig_npz(good).neutral) > 0
    check_npz_sizes(good)
    with pytest.raises(ValueError, match=r"its arrays declare more than 0 MiB"):
        check_npz_sizes(good, limit=1000)      # a real archive over the limit: refused on its headers alone
