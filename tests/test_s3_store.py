"""The store on object storage: a real S3 server (moto, in server mode on 127.0.0.1) holds the store; stages and
workers in other processes reach it only through the S3 endpoint and the Prefect API."""

import logging
import multiprocessing
import os
import secrets
import threading
import time
from pathlib import Path
from unittest.mock import ANY

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from visemeflow.schemas import C, TABLE_SCHEMAS, curves_array
from visemeflow.schemas.curves import Curves
from visemeflow.storage import Store, StoreError
from visemeflow.visemes import VISEMES


@pytest.fixture(scope="module")
def s3_endpoint():
    """A moto S3 server on a free port of 127.0.0.1, with the environment every AWS client (and so every worker
    process started here) reads: endpoint and test credentials."""
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    env = {"AWS_ENDPOINT_URL": f"http://{host}:{port}", "AWS_ACCESS_KEY_ID": "test",
           "AWS_SECRET_ACCESS_KEY": "test", "AWS_DEFAULT_REGION": "us-east-1"}
    before = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    yield env
    for key, value in before.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value
    server.stop()


@pytest.fixture
def bucket(s3_endpoint) -> str:
    """A new, empty bucket."""
    import s3fs

    name = f"vf-{secrets.token_hex(4)}"
    s3fs.S3FileSystem(use_listings_cache=False).mkdir(name)
    return name


def _curves(uid: str, n: int = 12, seed: int = 0, variant: str = "v1") -> Curves:
    values = np.random.default_rng(seed).random((n, len(VISEMES))).astype(np.float32)
    return Curves(values, 25.0, uid, "procedural", variant, f"made by seed {seed}")


def test_curves_tables_and_listings_round_trip_on_s3(bucket):
    store = Store(f"s3://{bucket}/store")
    assert store.remote and store.location == f"s3://{bucket}/store"
    path = store.save_curves(_curves("spk one/a", seed=1))
    store.save_curves(_curves("spk/b", seed=2))
    assert str(path) == f"s3://{bucket}/store/curves/procedural/v1/spk%20one/a.parquet"
    assert store.has_curves("procedural", "v1", "spk one/a") and not store.has_curves("procedural", "v1", "spk/c")
    assert store.curves_provenance("procedural", "v1", "spk/b") == "made by seed 2"
    assert store.curve_ids("procedural", "v1") == ["spk one/a", "spk/b"]
    assert store.curve_sets() == [("procedural", "v1")]
    loaded = store.load_curves("spk/b", "procedural")
    np.testing.assert_array_equal(loaded.values, _curves("spk/b", seed=2).values)
    assert loaded.fps == 25.0
    scanned = store.scan_curves(utterance_ids=["spk one/a"])
    assert scanned.num_rows == 12 and set(scanned.column(C.UTTERANCE_ID).to_pylist()) == {"spk one/a"}

    rows = pa.table({C.UTTERANCE_ID: ["u1"], C.STAGE: ["ingest"], C.ERROR_TYPE: ["E"], C.MESSAGE: ["m" * 9000],
                     C.PATH: [None], C.TIME: pa.array([0], pa.timestamp("us", tz="UTC"))})
    store.write_shard("rejects", 3, rows, stage="ingest", metadata={b"k": b"v"})
    assert store.shards("rejects", "ingest") == [3]
    assert store.shard_metadata("rejects", 3, "ingest")[b"k"] == b"v"
    message = store.read_table("rejects").column(C.MESSAGE)[0].as_py()
    assert len(message) == 4000 and message.endswith("characters cut]")   # capped as in a folder store
    assert store.disk_usage(store.root / "curves") > 0
    store.delete_path(store.root / "curves" / "procedural" / "v1" / "spk%20one")
    assert store.curve_ids("procedural", "v1") == ["spk/b"]
    with pytest.raises(ValueError, match="not inside the store"):
        store.delete_path(Store(f"s3://{bucket}/other").root / "x")
    with pytest.raises(ValueError, match="whole store"):
        store.delete_path(store.root)


def test_a_failing_writer_uploads_nothing_and_keeps_the_old_object(bucket):
    store = Store(f"s3://{bucket}/s")
    path = store.report_path("note.md")
    store.write_report_text("note.md", "first")

    def broken(tmp):
        tmp.write_text("half of it")
        raise RuntimeError("the writer died")

    with pytest.raises(RuntimeError, match="died"):
        store.write_file(path, broken)
    assert path.read_text() == "first"
    assert [p.name for p in store.report_files()] == ["note.md"]   # no temporary object was ever made
    assert store.stale_temporary_files() == [] and store.sweep_temporary_files() == 0


def test_the_lock_is_exclusive_across_threads_and_a_dead_holders_lock_expires(bucket, monkeypatch):
    store = Store(f"s3://{bucket}/locks")
    inside, overlaps = [], []

    def work(i: int) -> None:
        with store.locked("shard-0001"):
            inside.append(i)
            if len(inside) > 1:
                overlaps.append(tuple(inside))
            time.sleep(0.05)
            inside.remove(i)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert overlaps == []
    assert not store.root.fs.exists(f"{store.root.path}/.locks/shard-0001.lock")   # released

    # a holder killed inside the block leaves its lock object: younger than the lease it blocks, older it is broken
    store.root.fs.pipe_file(f"{store.root.path}/.locks/stuck.lock", b"a dead process")
    import visemeflow.storage.store as store_module

    monkeypatch.setattr(store_module, "LOCK_LEASE_S", 2.0)
    started = time.monotonic()
    with store.locked("stuck"):
        waited = time.monotonic() - started
    assert 0.9 <= waited < 30   # it waited for the lease (S3 dates objects to the second), then broke the lock


def test_a_locks_age_is_judged_on_the_servers_clock_not_the_machines(bucket, monkeypatch):
    """A machine whose clock runs an hour ahead does not break a live holder's lock, and one an hour behind does
    not wait an hour on a dead holder's: the lock's age is its object's date against the server's now (a probe
    object's date), both on the object store's clock."""
    import types

    import visemeflow.storage.store as store_module

    store = Store(f"s3://{bucket}/clocks")
    lock_key = f"{store.root.path}/.locks/shard-0002.lock"

    def skewed(seconds: float):
        monkeypatch.setattr(store_module, "time", types.SimpleNamespace(
            time=lambda: time.time() + seconds, sleep=time.sleep, monotonic=time.monotonic))

    # an hour ahead, the default lease: the live holder releases after 1.5 s, and only then is the lock ours
    skewed(3600.0)
    store.root.fs.pipe_file(lock_key, b"a live holder")
    releaser = threading.Timer(1.5, lambda: store.root.fs.rm_file(lock_key))
    releaser.start()
    started = time.monotonic()
    with store.locked("shard-0002"):
        waited = time.monotonic() - started
        assert store.root.fs.cat_file(lock_key) != b"a live holder"
    releaser.join()
    assert waited >= 1.4
    # an hour behind, a 2-s lease: a dead holder's lock is broken after about the lease, not after an hour
    skewed(-3600.0)
    monkeypatch.setattr(store_module, "LOCK_LEASE_S", 2.0)
    store.root.fs.pipe_file(lock_key, b"a dead process")
    started = time.monotonic()
    with store.locked("shard-0002"):
        waited = time.monotonic() - started
    assert 0.9 <= waited < 30
    keys = store.root.fs.find(f"{store.root.path}/.locks")
    assert keys == []   # the lock released, no clock probe left


def _replace_rows(url: str, worker: int, n: int) -> None:
    store = Store(url)
    for i in range(n):
        uid = f"w{worker}/u{i}"
        rows = pa.table({C.UTTERANCE_ID: [uid], C.STAGE: ["ingest"], C.ERROR_TYPE: ["E"], C.MESSAGE: [f"{worker}"],
                         C.PATH: [None], C.TIME: pa.array([0], pa.timestamp("us", tz="UTC"))})
        store.replace_utterance_rows("rejects", 0, uid, rows, stage="ingest")


def test_two_processes_rewriting_one_shard_lose_no_rows(bucket):
    """Two processes (sharing nothing but the endpoint) replace rows of one shard file 10 times each."""
    url = f"s3://{bucket}/rmw"
    context = multiprocessing.get_context("spawn")
    workers = [context.Process(target=_replace_rows, args=(url, w, 10)) for w in range(2)]
    for p in workers:
        p.start()
    for p in workers:
        p.join(120)
    assert [p.exitcode for p in workers] == [0, 0]
    ids = sorted(Store(url).read_shard("rejects", 0, "ingest").column(C.UTTERANCE_ID).to_pylist())
    assert ids == sorted(f"w{w}/u{i}" for w in range(2) for i in range(10))


def test_a_shard_changed_after_it_was_read_is_read_again(bucket, monkeypatch):
    """The conditional PUT (If-Match the ETag read) refuses a write over a version the writer never saw: a writer
    whose lock was broken as stale re-reads instead of dropping the other writer's rows."""
    url = f"s3://{bucket}/cas"
    store = Store(url)
    _replace_rows(url, 0, 1)
    original = Store._upload
    calls = []

    def racing_upload(self, path, writer, keep_suffix, put=None):
        if put is not None and not calls:   # first conditional write: another writer gets in first
            calls.append(1)
            _replace_rows(url, 1, 1)
        return original(self, path, writer, keep_suffix, put)

    monkeypatch.setattr(Store, "_upload", racing_upload)
    monkeypatch.setattr(Store, "locked", lambda self, name: _no_lock())   # as if the lock had been broken
    rows = pa.table({C.UTTERANCE_ID: ["w2/u0"], C.STAGE: ["ingest"], C.ERROR_TYPE: ["E"], C.MESSAGE: ["2"],
                     C.PATH: [None], C.TIME: pa.array([0], pa.timestamp("us", tz="UTC"))})
    store.replace_utterance_rows("rejects", 0, "w2/u0", rows, stage="ingest")
    ids = sorted(store.read_shard("rejects", 0, "ingest").column(C.UTTERANCE_ID).to_pylist())
    assert calls and ids == ["w0/u0", "w1/u0", "w2/u0"]


class _no_lock:
    def __enter__(self):
        return None

    def __exit__(self, *exc):
        return False


def test_every_command_with_a_store_takes_a_url_and_urls_are_checked():
    import typing

    import visemeflow.flows.params as params
    from visemeflow.flows.params import AnimateParams, PipelineParams, PreviewParams, SpeakParams, SynthParams, \
        TrainParams
    from visemeflow.location import parse_root

    with_store = [m for m in vars(params).values() if isinstance(m, type) and issubclass(m, params.BaseModel)
                  and "store" in m.model_fields]
    assert len(with_store) >= 15
    for model in with_store:   # a store field of every params model is a StoreLocation: a folder or a URL
        assert typing.get_args(model.model_fields["store"].annotation) == (Path, str), model
    assert PreviewParams(store="s3://bucket/store", utterance_id="spk/a").store == "s3://bucket/store"
    assert SynthParams(corpus=".", store="s3://bucket/store").store == "s3://bucket/store"
    assert AnimateParams(store="s3://bucket/store").store == "s3://bucket/store"
    assert SpeakParams(store="s3://bucket/store", audio=["a.wav"]).store == "s3://bucket/store"
    assert TrainParams(store="s3://bucket/store/").store == "s3://bucket/store"
    assert PipelineParams(corpus="c", store="s3://bucket/store", characters=["x.glb"]).characters == [Path("x.glb")]
    assert PipelineParams(corpus="c", store="s3://bucket/store/").store == "s3://bucket/store"
    assert str(PipelineParams(corpus="c", store="file:///tmp/store").store) == "/tmp/store"
    assert PipelineParams(corpus="s3://bucket/corpus/", store="s3://bucket/store").corpus == "s3://bucket/corpus"
    with pytest.raises(ValueError, match="needs a bucket"):
        parse_root("s3://")
    with pytest.raises(ValueError, match="'..'"):
        parse_root("s3://bucket/a/../b")


def test_result_records_on_s3_are_checked_before_prefect_reads_them(bucket):
    """A planted pickle among the cached results is refused and deleted, as in a folder store."""
    from visemeflow.tasks.common import discard_untrusted_record, results_of

    storage = results_of(f"s3://{bucket}/r").result_storage
    fs = storage.filesystem
    fs.pipe_file(f"{storage.basepath}/badkey", b"\x80\x04pickle")
    assert discard_untrusted_record(storage, "badkey", logging.getLogger("test")) is True
    assert not fs.exists(f"{storage.basepath}/badkey")
    assert discard_untrusted_record(storage, "absent", logging.getLogger("test")) is False


def test_shards_missing_on_s3_read_as_empty(bucket):
    store = Store(f"s3://{bucket}/empty")
    assert store.read_table("utterances").num_rows == 0
    assert store.read_shard("phones", 0).schema == TABLE_SCHEMAS["phones"]
    assert store.curve_ids("procedural", "v1") == [] and store.model_names() == []
    with pytest.raises(StoreError, match="cannot write s3://no-such-bucket-here/x/reports/a.md"):
        Store("s3://no-such-bucket-here/x").write_report_text("a.md", "x")
    from visemeflow.location import remote_problem

    assert "bucket 'no-such-bucket-here' at http://127.0.0.1" in remote_problem("s3://no-such-bucket-here/x")
    assert remote_problem(store.location) is None
    assert curves_array(store.scan_curves()).shape[0] == 0
    assert pq is not None


# ---- the pipeline on an S3 store: Dask workers, a killed run, two runs at once ---------------------------------
TWO = [("LJ", "LJ001-0002"), ("SSB1624", "SSB16240001")]


@pytest.fixture(scope="module")
def video_corpus(tmp_path_factory, prefect_harness):
    """Two demo utterances (English, Mandarin) rendered as talking-face videos."""
    from factories import render_videos

    return render_videos(tmp_path_factory.mktemp("s3videos"), TWO)


@pytest.fixture(scope="module")
def local_reference(tmp_path_factory, video_corpus):
    """The pipeline's store in a local folder, in this process (Prefect's thread pool): what every S3 run must equal."""
    from factories import run_pipeline, snapshot

    store = tmp_path_factory.mktemp("s3ref") / "store"
    result = run_pipeline(video_corpus, store, n_shards=2)
    assert result["track"]["tracked"] == len(TWO)
    return snapshot(store)


def _assert_same_store(got: dict, want: dict, corpus: tuple[str, object] | None = None) -> None:
    """Equal tables, curve files and diagnostics; tracked values up to float summation order (one torch thread per
    Dask worker against the thread pool's: seen 7e-7 apart). `corpus` (URL, folder): the store `got` read the
    corpus from that URL, `want` from that folder; their paths are compared as the folder's, and the utterances'
    content hashes (of the objects' ETags on S3, of the bytes in a folder) wherever they appear as the folder's."""
    if corpus is not None:
        url, folder = corpus
        assert all(row[C.VIDEO_PATH].startswith(f"{url}/") for row in got["utterances"])   # read from the URL
        paths = (C.AUDIO_PATH, C.ALIGNMENT_PATH, C.VIDEO_PATH, C.LANDMARK_PATH, C.PATH, C.MESSAGE)
        got = {**got, **{table: [{k: v.replace(url, str(folder.resolve())) if k in paths and v else v
                                  for k, v in row.items()} for row in got[table]]
                         for table in ("utterances", "rejects")}}
        theirs = {row[C.UTTERANCE_ID]: row[C.CONTENT_HASH] for row in want["utterances"]}
        hashes = {row[C.CONTENT_HASH]: theirs[row[C.UTTERANCE_ID]] for row in got["utterances"]}
        assert not set(hashes) & set(theirs.values())   # the corpus's identity on S3 is not its bytes'

        def as_folder(value):
            if isinstance(value, str):
                for mine, folder_hash in hashes.items():
                    value = value.replace(mine, folder_hash)
            return value

        got = {key: [{k: as_folder(v) for k, v in row.items()} if isinstance(row, dict) else as_folder(row)
                     for row in rows] for key, rows in got.items()}
    for key in ("utterances", "phones", "rejects", "curve_files"):
        assert got[key] == want[key], key
    for key in ("curves", "tracking_frames"):
        assert len(got[key]) == len(want[key]), key
        for a, b in zip(got[key], want[key]):
            assert {k: v for k, v in a.items() if not isinstance(v, float)} == \
                   {k: v for k, v in b.items() if not isinstance(v, float)}
            floats = [k for k, v in b.items() if isinstance(v, float)]
            np.testing.assert_allclose([a[k] for k in floats], [b[k] for k in floats], rtol=0, atol=1e-5,
                                       equal_nan=True)


@pytest.mark.flow
def test_the_pipeline_on_s3_with_two_dask_workers_equals_a_local_run(bucket, video_corpus, local_reference,
                                                                      prefect_harness):
    """Two Dask worker processes (started by the flow, each reaching the store only through the S3 endpoint in its
    environment and the flow run through the Prefect API) track the clips; the S3 store equals the folder store;
    a second run is all cache hits, read from the result records on S3."""
    from factories import snapshot

    from visemeflow.flows.params import PipelineParams, RunnerConfig
    from visemeflow.flows.pipeline import pipeline_flow

    url = f"s3://{bucket}/store"
    params = PipelineParams(corpus=video_corpus, store=url, n_shards=2,
                            runner=RunnerConfig(kind="dask", dask_workers=2))
    first = pipeline_flow(params)
    assert first["track"]["tracked"] == len(TWO) and first["track"]["rejected"] == 0
    _assert_same_store(snapshot(url), local_reference)
    again = pipeline_flow(params)
    assert again["ingest"]["cached_shards"] == first["ingest"]["shards"] >= 1
    assert again["procedural"]["cached_shards"] == first["procedural"]["shards"]
    assert again["track"]["cached"] == len(TWO) and again["track"]["tracked"] == 0
    import s3fs

    keys = s3fs.S3FileSystem(use_listings_cache=False).find(f"{bucket}/store")
    assert any("/.prefect-results/" in k for k in keys)
    assert not any(k.rsplit("/", 1)[-1].startswith(".") and k.endswith(".tmp") for k in keys)
    assert not any("/.locks/" in k for k in keys)   # every lock released


def _cli(args: list[str], api: str):
    import subprocess
    import sys

    env = {**os.environ, "PREFECT_API_URL": api, "PREFECT_LOGGING_LEVEL": "WARNING"}
    return subprocess.Popen([sys.executable, "-m", "visemeflow.cli", *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


@pytest.mark.flow
def test_a_pipeline_killed_on_s3_loses_nothing_and_two_runs_at_once_corrupt_nothing(
        bucket, video_corpus, local_reference, prefect_api_url):
    """kill -9 of a `visemeflow pipeline` process once the procedural stage has written curves; then that store
    rerun twice at once, by two processes: both finish, and the store equals the local run's."""
    import s3fs
    from factories import kill_cli_when, snapshot

    url = f"s3://{bucket}/killed"
    fs = s3fs.S3FileSystem(use_listings_cache=False)
    args = ["pipeline", str(video_corpus), "--store", url, "--shards", "2"]

    def procedural_written() -> bool:   # the stage before tracking (which writes a joint group's curves at once)
        try:
            return bool(fs.find(f"{bucket}/killed/curves/procedural"))
        except FileNotFoundError:
            return False

    kill_cli_when(args, prefect_api_url, procedural_written)
    assert len(fs.find(f"{bucket}/killed/curves/tracked")) < len(TWO)   # killed mid-run
    runs = [_cli(args, prefect_api_url) for _ in range(2)]
    outputs = [p.communicate(timeout=600)[0] for p in runs]
    assert [p.returncode for p in runs] == [0, 0], outputs
    _assert_same_store(snapshot(url), local_reference)
    assert not fs.exists(f"{bucket}/killed/.locks") or fs.find(f"{bucket}/killed/.locks") == []


@pytest.fixture
def own_prefect_api(local_reference) -> str:
    """A Prefect server of the test's own, with its own SQLite database (about 10 s to start on a copy of the
    template). In three
    clean-clone CI runs the workers of the work-pool test could not register with the session's shared server: its
    SQLite refused their heartbeats for minutes ("database is locked"); alone the test passed. It takes
    `local_reference` so that the reference run is made first, on the session's server, not on this one."""
    from prefect.settings import get_current_settings

    from visemeflow.ops.prefect_db import test_harness

    with test_harness(startup_timeout_s=180):
        yield str(get_current_settings().api.url)


@pytest.mark.flow
def test_a_process_work_pool_with_two_workers_runs_the_pipeline_on_s3(bucket, video_corpus, local_reference,
                                                                      own_prefect_api):
    """prefect.yaml's `pipeline/pool` entrypoint deployed to a process work pool; two `prefect worker` processes
    (sharing nothing with this one but the Prefect API and the S3 endpoint: each has its own temporary folder and
    Prefect home, and the corpus is on S3 too, read through each one's own local copies) each take one of two runs
    started at once on one S3 store; both complete and the store equals the local run's."""
    import shutil
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    from factories import REPO, snapshot
    from prefect import Flow
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.actions import WorkPoolCreate
    from prefect.deployments import run_deployment

    import s3fs

    pool = f"s3pool-{secrets.token_hex(3)}"
    url = f"s3://{bucket}/pool"
    corpus = f"s3://{bucket}/pool-corpus"
    s3fs.S3FileSystem(use_listings_cache=False).put(str(video_corpus), corpus.removeprefix("s3://"), recursive=True)
    with get_client(sync_client=True) as client:
        client.create_work_pool(WorkPoolCreate(name=pool, type="process"))
    pipeline = Flow.from_source(source=str(REPO), entrypoint="visemeflow/ops/pool.py:pipeline_flow")
    deployment = pipeline.deploy(name=pool, work_pool_name=pool, build=False, print_next_steps=False,
                                 parameters={"store": url, "corpus": corpus, "n_shards": 2})
    # workers poll every second (Prefect's default is 10 s): a run is now shorter than one default poll, and the
    # second worker would pick its run up after the first had finished
    # A worker registers by its heartbeat; one refused is sent again after this many seconds rather than Prefect's 30
    env = {**os.environ, "PREFECT_API_URL": own_prefect_api, "PREFECT_LOGGING_LEVEL": "WARNING",
           "PREFECT_WORKER_QUERY_SECONDS": "1", "PREFECT_WORKER_HEARTBEAT_SECONDS": "5"}
    env.pop("VISEMEFLOW_SERVE_ROOTS", None)
    prefect = str(Path(sys.executable).with_name("prefect"))
    # each worker (and the flow runs it starts) with a temporary folder and a Prefect home of its own, as on two
    # machines: nothing host-local is shared
    homes = [Path(tempfile.mkdtemp(prefix=f"s3pool-w{i}-")) for i in range(2)]
    for home in homes:
        (home / "tmp").mkdir()
    workers = [subprocess.Popen([prefect, "worker", "start", "--pool", pool, "--limit", "1", "--name", f"w{i}"],
                                env={**env, "TMPDIR": str(home / "tmp"), "PREFECT_HOME": str(home / "prefect")},
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO)
               for i, home in enumerate(homes)]
    try:
        # both workers polling before the runs exist: a worker still starting (seconds under load) would leave both
        # runs to the first, one after the other
        with get_client(sync_client=True) as client:
            deadline = time.monotonic() + 180
            while len(client.read_workers_for_work_pool(pool)) < 2 and time.monotonic() < deadline:
                time.sleep(0.5)
            assert len(client.read_workers_for_work_pool(pool)) == 2, "a worker never registered"
        runs = [run_deployment(deployment, timeout=0) for _ in range(2)]
        deadline = time.monotonic() + 600
        with get_client(sync_client=True) as client:
            while True:
                states = [client.read_flow_run(r.id).state for r in runs]
                if all(s.is_final() for s in states) or time.monotonic() > deadline:
                    break
                time.sleep(2)
            spans = sorted((run.start_time, run.end_time) for run in (client.read_flow_run(r.id) for r in runs))
    finally:
        for w in workers:
            w.terminate()
        for w in workers:
            # a worker whose channel to the server is reconnecting after a refused heartbeat (seen in a full run)
            # can take minutes to act on SIGTERM; how fast Prefect's worker stops is not what this test is about
            try:
                w.wait(60)
            except subprocess.TimeoutExpired:
                w.kill()
                w.wait(30)
        for home in homes:
            shutil.rmtree(home, ignore_errors=True)
    assert [s.type.value for s in states] == ["COMPLETED", "COMPLETED"], [s.message for s in states]
    assert spans[1][0] < spans[0][1]   # they overlapped: each worker takes one run at a time (--limit 1)
    _assert_same_store(snapshot(url), local_reference, corpus=(corpus, video_corpus))


def test_bulk_presence_provenance_and_records_on_s3(bucket):
    """What the flows ask of thousands of utterances at once, answered with one listing or one batch of GETs: an
    empty or garbled curve file counts as missing, as in a folder; a planted record is refused, not decoded."""
    from visemeflow.tasks.common import fetch_records, results_of

    store = Store(f"s3://{bucket}/bulk")
    for i, uid in enumerate(["s/a", "s/b", "s/c"]):
        store.save_curves(_curves(uid, seed=i))
    fs = store.root.fs
    fs.pipe_file(store.curve_path("procedural", "v1", "s/d").path, b"")             # cut short by a crash
    fs.pipe_file(store.curve_path("procedural", "v1", "s/e").path, b"not parquet")  # garbled
    ids = ["s/a", "s/b", "s/c", "s/d", "s/e", "s/missing"]
    assert store.curves_present("procedural", "v1", ids) == {"s/a", "s/b", "s/c", "s/e"}
    assert store.curves_present("procedural", "nothing", ids) == set()
    assert store.curves_provenances("procedural", "v1", ids) == {
        "s/a": "made by seed 0", "s/b": "made by seed 1", "s/c": "made by seed 2", "s/d": None, "s/e": None,
        "s/missing": None}

    results = results_of(store.location)
    base = results.result_storage.basepath
    fs.pipe_file(f"{base}/planted", b"\x80\x04pickle")
    assert fetch_records(results, ["planted", "absent"], logging.getLogger("test")) == {}
    assert not fs.exists(f"{base}/planted")   # refused and deleted, never decoded


def test_local_copies_of_objects_are_kept_per_version_in_a_private_folder(bucket, tmp_path, monkeypatch):
    import tempfile

    monkeypatch.setattr(tempfile, "gettempdir", lambda: str(tmp_path))
    store = Store(f"s3://{bucket}/copies")
    path = store.report_path("a.bin")
    store.write_file(path, lambda tmp: tmp.write_bytes(b"one"))
    first = store.local_file(path)
    assert open(first, "rb").read() == b"one" and store.local_file(path) == first   # the same version: no new copy
    store.write_file(path, lambda tmp: tmp.write_bytes(b"two"))
    second = store.local_file(path)
    assert second != first and open(second, "rb").read() == b"two"
    folder = tmp_path / f"visemeflow-objects-{os.getuid()}"
    assert folder.stat().st_mode & 0o777 == 0o700
    folder.chmod(0o777)   # a folder others may write: a copy planted there would be read as the store's
    with pytest.raises(StoreError, match="no one else may write"):
        store.local_file(path)


def test_inputs_on_s3_are_read_through_local_copies_and_a_mirror_that_follows_the_prefix(bucket, tmp_path,
                                                                                         monkeypatch):
    """`local_input` copies an object once per version; `mirror` is the prefix as it is now (a changed object
    fetched again, a deleted one gone, keys that would leave the folder skipped); a missing object names its URL."""
    import s3fs

    from visemeflow.location import input_exists, local_input, mirror

    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr("tempfile.tempdir", None)
    fs = s3fs.S3FileSystem(use_listings_cache=False)
    base = f"{bucket}/corpus"
    fs.pipe_file(f"{base}/spk/a.wav", b"one")
    fs.pipe_file(f"{base}/spk/b.TextGrid", b"text")
    fs.pipe_file(f"{base}/spk/../escape.wav", b"x")   # a key S3 takes as it is
    url = f"s3://{base}"
    first = local_input(f"{url}/spk/a.wav")
    assert first.startswith(str(tmp_path)) and open(first, "rb").read() == b"one"
    assert local_input(f"{url}/spk/a.wav") == first and local_input("rel/x.wav") == "rel/x.wav"
    assert local_input(None) is None and input_exists(f"{url}/spk/a.wav") and not input_exists(f"{url}/spk/z.wav")
    tree = mirror(url)
    assert sorted(str(p.relative_to(tree)) for p in tree.rglob("*") if p.is_file()) == ["spk/a.wav", "spk/b.TextGrid"]
    assert os.path.samefile(tree / "spk" / "a.wav", first)   # a hard link to the versioned copy, not a second one
    fs.pipe_file(f"{base}/spk/a.wav", b"two")
    fs.rm(f"{base}/spk/b.TextGrid")
    tree = mirror(url)
    assert (tree / "spk" / "a.wav").read_bytes() == b"two" and not (tree / "spk" / "b.TextGrid").exists()
    second = local_input(f"{url}/spk/a.wav")
    assert open(second, "rb").read() == b"two" and not os.path.exists(first)   # no copy of the old version kept
    with pytest.raises(FileNotFoundError, match=f"{url}/spk/z.wav: no such object"):
        local_input(f"{url}/spk/z.wav")
    with pytest.raises(FileNotFoundError, match="no objects under this prefix"):
        mirror(f"s3://{bucket}/nothing")
    # media only named: the file holds the object's ETag and size, never its bytes; it follows the object
    named = mirror(url, lambda name: name.endswith(".wav"))
    identity = (named / "spk" / "a.wav").read_text()
    assert identity.startswith("visemeflow object version ") and identity.endswith(" size 3\n")
    assert not os.path.samefile(named / "spk" / "a.wav", second) and open(second, "rb").read() == b"two"
    fs.pipe_file(f"{base}/spk/a.wav", b"three")
    assert (mirror(url, lambda name: name.endswith(".wav")) / "spk" / "a.wav").read_text() not in (identity, "")
    assert not any(p.read_bytes() == b"three" for p in tmp_path.rglob("a.wav"))   # never downloaded
    # a file readers look for beside another (a synthetic video's camera record) comes along, and goes with it
    fs.pipe_file(f"{base}/spk/v.mp4", b"video")
    fs.pipe_file(f"{base}/spk/v.camera.json", b"{}")
    video = local_input(f"{url}/spk/v.mp4", beside=(".camera.json",))
    assert os.path.basename(video) == "v.mp4" and open(os.path.join(os.path.dirname(video), "v.camera.json")).read() == "{}"
    fs.rm(f"{base}/spk/v.camera.json")
    assert local_input(f"{url}/spk/v.mp4", beside=(".camera.json",)) == video
    assert not os.path.exists(os.path.join(os.path.dirname(video), "v.camera.json"))


def test_a_mirror_fetches_many_objects_at_once_or_one_by_one_and_leaves_only_whole_copies(bucket, tmp_path,
                                                                                          monkeypatch):
    """S3 (asynchronous in fsspec) is fetched in batches, memory:// one by one: the same tree, no partial file; an
    object that vanishes between the listing and its download fails the mirror and leaves no partial copy."""
    import fsspec
    import s3fs

    from visemeflow.location import _fetch_copies, mirror

    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr("tempfile.tempdir", None)
    files = {f"spk{i % 3}/u{i:03d}.TextGrid": f"alignment {i}".encode() for i in range(40)}
    s3fs.S3FileSystem(use_listings_cache=False).pipe({f"{bucket}/many/{k}": v for k, v in files.items()})
    fsspec.filesystem("memory").pipe({f"/many/{k}": v for k, v in files.items()})
    for url in (f"s3://{bucket}/many", "memory://many"):
        tree = mirror(url, concurrency=8)
        assert {str(p.relative_to(tree)): p.read_bytes() for p in tree.rglob("*") if p.is_file()} == files
    objects = tmp_path / f"visemeflow-objects-{os.getuid()}"
    assert not [p for p in objects.rglob("*.part")]
    with pytest.raises(FileNotFoundError):
        _fetch_copies(s3fs.S3FileSystem(), [(f"{bucket}/many/spk0/u000.TextGrid", tmp_path / "x" / "a" / "ok"),
                                            (f"{bucket}/many/gone", tmp_path / "x" / "b" / "gone")], 2)
    assert not (tmp_path / "x" / "b" / "gone").exists() and not list((tmp_path / "x").rglob("*.part"))


def test_speaker_identity_grouping_reads_a_video_objects_header_only(bucket, tmp_path, monkeypatch):
    """`--speaker-identity` groups real videos by speaker and image size: of a video on S3 the flow reads the camera
    record's presence (a HEAD) and the header (ranged reads), never a local copy of the whole clip."""
    import s3fs
    from factories import SHARED_DATA

    from visemeflow.flows.track import frame_size, real_video
    from visemeflow.tracking.utterance import video_size

    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr("tempfile.tempdir", None)
    fs = s3fs.S3FileSystem(use_listings_cache=False)
    clips = {"heads/1.mp4": SHARED_DATA / "talking_heads" / "1.mp4",
             "grid/bbaf2n.mpg": SHARED_DATA / "grid_s1" / "video" / "bbaf2n.mpg"}
    for key, path in clips.items():
        assert path.is_file(), f"test data {path} is missing"
        fs.put_file(str(path), f"{bucket}/v.d/{key}")
    for key, path in clips.items():
        url = f"s3://{bucket}/v.d/{key}"
        assert frame_size(url) == video_size(str(path)) is not None and real_video(url)
    fs.pipe_file(f"{bucket}/v.d/heads/1.camera.json", b"{}")
    assert not real_video(f"s3://{bucket}/v.d/heads/1.mp4") and real_video(f"s3://{bucket}/v.d/grid/bbaf2n.mpg")
    fs.pipe_file(f"{bucket}/v.d/heads/broken.mp4", b"not a video at all")
    assert frame_size(f"s3://{bucket}/v.d/heads/broken.mp4") is None
    assert frame_size(f"s3://{bucket}/v.d/heads/gone.mp4") is None
    assert not list(tmp_path.rglob("*.mp4")) and not list(tmp_path.rglob("*.mpg"))   # no copy was made


@pytest.mark.flow
def test_a_corpus_on_s3_is_ingested_as_a_folder_is_its_media_named_not_downloaded_at_discovery(
        bucket, tmp_path, prefect_harness, monkeypatch):
    """`ingest s3://bucket/corpus`: the same rows as the same corpus in a folder but for the paths, which name the
    objects, and the content hashes, which cover the media objects' ETags (discovery downloads the alignments only;
    a changed object changes its utterance's hash alone); a broken TextGrid and an object deleted after discovery
    are rejects naming their URLs, the rest is ingested; the CLI checks the corpus URL before any flow starts."""
    import shutil
    import subprocess
    import sys

    import s3fs
    from factories import REPO, snapshot

    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.params import IngestParams
    from visemeflow.ingest.corpus import discover_corpus
    from visemeflow.tasks.ingest import ingest_entries

    local = tmp_path / "corpus"
    (local / "LJ").mkdir(parents=True)
    for name in ("LJ001-0001", "LJ001-0002", "LJ001-0003"):
        for ext in (".wav", ".TextGrid"):
            shutil.copyfile(REPO / "examples" / "corpus" / "LJ" / f"{name}{ext}", local / "LJ" / f"{name}{ext}")
    (local / "LJ" / "broken.wav").write_bytes((local / "LJ" / "LJ001-0001.wav").read_bytes())
    (local / "LJ" / "broken.TextGrid").write_text("File type = \"ooTextFile\"\nObject class = \"TextGrid\"\nxmin = 0\n")
    fs = s3fs.S3FileSystem(use_listings_cache=False)
    fs.put(str(local / "LJ"), f"{bucket}/corpus/LJ", recursive=True)
    url = f"s3://{bucket}/corpus"

    ingest_flow(IngestParams(corpus=local, store=tmp_path / "folder", n_shards=2))
    ingest_flow(IngestParams(corpus=url, store=tmp_path / "s3", n_shards=2))
    want, got = snapshot(tmp_path / "folder"), snapshot(tmp_path / "s3")
    assert len(got["utterances"]) == len(want["utterances"]) >= 3
    to_folder = {c: (lambda v: v and v.replace(url, str(local.resolve()))) for c in
                 (C.AUDIO_PATH, C.ALIGNMENT_PATH, C.VIDEO_PATH, C.LANDMARK_PATH, C.PATH, C.MESSAGE)}
    to_folder[C.CONTENT_HASH] = lambda v: None
    for table in ("utterances", "phones", "rejects"):
        assert [{k: to_folder.get(k, lambda v: v)(v) for k, v in row.items()} for row in got[table]] == \
            [{k: to_folder.get(k, lambda v: v)(v) if k == C.CONTENT_HASH else v for k, v in row.items()}
             for row in want[table]]
    assert all(row[C.AUDIO_PATH].startswith(f"{url}/LJ/") for row in got["utterances"])
    [reject] = got["rejects"]
    assert reject[C.UTTERANCE_ID] == "LJ/broken" and reject[C.PATH] == f"{url}/LJ/broken.TextGrid"

    # discovery on a machine with no copies yet: a listing and the TextGrids; no audio object is downloaded
    fresh = tmp_path / "fresh-machine"
    fresh.mkdir()
    monkeypatch.setenv("TMPDIR", str(fresh))
    monkeypatch.setattr("tempfile.tempdir", None)
    hashes = {e.utterance_id: e.content_hash for e in discover_corpus(url).entries}
    assert hashes == {row[C.UTTERANCE_ID]: row[C.CONTENT_HASH] for row in got["utterances"]} | {"LJ/broken": ANY}
    fetched = sorted(p.name for p in (fresh / f"visemeflow-objects-{os.getuid()}").rglob("*") if p.is_file())
    assert fetched == sorted(f"{n}.TextGrid" for n in ("LJ001-0001", "LJ001-0002", "LJ001-0003", "broken"))
    fs.pipe_file(f"{bucket}/corpus/LJ/LJ001-0002.wav", (local / "LJ" / "LJ001-0003.wav").read_bytes())
    changed = {e.utterance_id: e.content_hash for e in discover_corpus(url).entries}
    assert {u for u in hashes if hashes[u] != changed[u]} == {"LJ/LJ001-0002"}

    entries = [e for e in discover_corpus(url).entries if e.utterance_id == "LJ/LJ001-0001"]
    fs.rm(f"{bucket}/corpus/LJ/LJ001-0001.wav")   # gone between discovery and the task (a move, a lifecycle rule)
    rows, _, rejects, _ = ingest_entries(entries, IngestParams(corpus=url).config)
    assert rows == [] and rejects[0][C.ERROR_TYPE] == "UnreadableObject" and rejects[0][C.PATH] == f"{url}/LJ/LJ001-0001.wav"

    def cli(*args):
        return subprocess.run([sys.executable, "-m", "visemeflow.cli", *args], capture_output=True, text=True,
                              timeout=120, env={**os.environ, "VISEMEFLOW_NO_SERVER_LOOKUP": "1"})

    for corpus, expected in ((f"s3://{bucket}/nothing", "corpus s3://" + bucket + "/nothing does not exist"),
                             ("s3://no-such-bucket-here/c", "cannot read the corpus s3://no-such-bucket-here/c: bucket")):
        out = cli("ingest", corpus, "--store", str(tmp_path / "never"))
        assert out.returncode == 2 and expected in out.stderr and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert not (tmp_path / "never").exists()


@pytest.mark.flow
def test_animate_and_speak_on_s3_upload_the_packages_a_folder_store_gets(bucket, tmp_path, prefect_harness):
    """`animate` on an S3 store writes each package locally and uploads it: the same files as in a folder, read back
    by their readers; a second run is all cache hits, a deleted object is made again; `speak` puts its package in the
    S3 store; the dashboard of that store lists the packages."""
    import subprocess
    import sys

    import s3fs
    from factories import DEMO_AUDIO, make_curve_store, tiny_character, tiny_model

    from visemeflow.animation.gltf import write_glb
    from visemeflow.animation.package import AnimateConfig
    from visemeflow.animation.usd import read_usd_weights
    from visemeflow.dashboards.html import build_dashboard
    from visemeflow.flows.animate import AnimateParams, SpeakParams, animate_flow, speak_flow
    from visemeflow.shapes.conventions import ARKIT_52

    fs = s3fs.S3FileSystem(use_listings_cache=False)
    folder = make_curve_store(tmp_path / "folder", n=2)
    fs.put(str(folder.root), f"{bucket}/anim", recursive=True)   # the same store, byte for byte, on S3
    url = f"s3://{bucket}/anim"
    glb = tmp_path / "arkit.glb"
    write_glb(glb, tiny_character(list(ARKIT_52), name="arkit"), np.zeros((1, len(ARKIT_52)), np.float32), 30.0)
    config = AnimateConfig(formats=("glb", "usd", "json"))

    def animate(store):
        return animate_flow(AnimateParams(store=store, characters=[glb], source="ground_truth", config=config))

    want, got = animate(folder.root), animate(url)
    assert got["written"] == 2 and got["rejected"] == 0
    s3 = Store(url)
    for mine, theirs in zip(sorted(got["packages_written"], key=lambda r: r["utterance_id"]),
                            sorted(want["packages_written"], key=lambda r: r["utterance_id"])):
        assert mine["folder"].startswith(f"{url}/animations/arkit/") and set(mine["files"]) == set(theirs["files"])
        for kind, path in mine["files"].items():
            assert path.startswith(mine["folder"] + "/"), path
            local = s3.local_file_at(path)
            if kind == "usd":   # what a reader of the file sees
                np.testing.assert_array_equal(read_usd_weights(local)[1], read_usd_weights(theirs["files"][kind])[1])
            else:
                assert open(local, "rb").read() == open(theirs["files"][kind], "rb").read(), kind
    again = animate(url)
    assert again["cached"] == 2 and again["written"] == 0
    fs.rm(got["packages_written"][0]["files"]["glb"].removeprefix("s3://"))
    third = animate(url)
    assert third["written"] == 1 and third["cached"] == 1
    # another file named arkit.glb, animated later into the same S3 store: a folder of its own (the first's folder
    # says whose it is in `.character`), not the first avatar's packages replaced
    assert fs.cat_file(f"{bucket}/anim/animations/arkit/.character").decode().strip() == str(glb.resolve())
    (tmp_path / "other").mkdir()
    other = tmp_path / "other" / "arkit.glb"
    write_glb(other, tiny_character(list(ARKIT_52), name="arkit"), np.zeros((1, len(ARKIT_52)), np.float32), 30.0)
    fourth = animate_flow(AnimateParams(store=url, characters=[other], source="ground_truth", config=config))
    folders = {r["folder"].split("/animations/")[1].split("/")[0] for r in fourth["packages_written"]}
    assert len(folders) == 1 and folders != {"arkit"} and folders.pop().startswith("arkit-"), fourth
    assert animate(url)["cached"] == 2   # the first file still finds its own packages

    model = tmp_path / "tiny"
    tiny_model_store = Store(model)
    tiny_model(tiny_model_store)
    s3.install_model("tiny", tiny_model_store.model_path("tiny"))
    exported = subprocess.run([sys.executable, "-m", "visemeflow.cli", "export-model", "tiny", "--store", url, "--out",
                               str(tmp_path / "tiny.onnx")], capture_output=True, text=True, timeout=300)
    assert exported.returncode == 0 and "onnxruntime vs torch" in exported.stdout, exported.stderr
    assert (tmp_path / "tiny.onnx").stat().st_size > 1000
    spoken = speak_flow(SpeakParams(store=url, model="tiny", audio=[DEMO_AUDIO], characters=[glb],
                                    config=AnimateConfig(formats=("glb",), preview=True)))
    (report,) = spoken["packages_written"]
    assert report["files"]["glb"].startswith(f"{url}/animations/arkit/predict/SSB16240001/")
    assert fs.exists(report["files"]["glb"].removeprefix("s3://"))
    build_dashboard(s3, tmp_path / "board")
    page = (tmp_path / "board" / "index.html").read_text()
    assert "spk/u0" in page and "predict/SSB16240001" in page
    assert f'href="{report["files"]["glb"]}"' in page   # files on S3 are named by their URL
    copy = tmp_path / "board" / "media" / "arkit" / "predict" / "SSB16240001" / "SSB16240001.mp4"
    assert 'src="media/arkit/predict/SSB16240001/SSB16240001.mp4"' in page   # the preview plays from a local copy
    assert copy.read_bytes() == fs.cat_file(report["files"]["preview"].removeprefix("s3://"))

    # `preview` of an utterance of the S3 store: rendered locally, uploaded beside its package
    from visemeflow.flows.animate import PreviewParams, preview_flow
    from visemeflow.tracking.video import read_video_frames

    shown = {store: preview_flow(PreviewParams(store=store, utterance_id="spk/u0", character=glb,
                                               sources=["ground_truth"])) for store in (folder.root, url)}
    assert shown[url]["path"] == f"{url}/animations/arkit/spk/u0/u0.preview.mp4"
    mp4 = s3.local_file_at(shown[url]["path"])
    assert shown[url]["frames"] == shown[folder.root]["frames"] == len(read_video_frames(mp4)) > 0


@pytest.mark.flow
def test_import_curves_into_an_s3_store_writes_what_a_folder_gets(bucket, tmp_path, prefect_harness):
    """Captured takes (local files) imported into an S3 store: the rows and curves a folder store gets, a bad take a
    reject, and a second run all cache hits."""
    from factories import snapshot, write_wav

    from visemeflow.flows.import_curves import ImportCurvesParams, import_curves_flow
    from visemeflow.shapes.conventions import arkit_weights
    from visemeflow.shapes.livelink import write_livelink_csv

    takes = tmp_path / "takes"
    rng = np.random.default_rng(3)
    for name in ("a", "b"):
        write_wav(takes / "spk" / f"{name}.wav", 1.0)
        write_livelink_csv(takes / "spk" / f"{name}.livelink.csv",
                           arkit_weights(rng.uniform(0, 0.6, (30, len(VISEMES))).astype(np.float32)), 30)
    write_wav(takes / "spk" / "short.wav", 1.0)
    write_livelink_csv(takes / "spk" / "short.livelink.csv", arkit_weights(np.zeros((10, len(VISEMES)))), 30)
    url = f"s3://{bucket}/captured"
    runs = {store: import_curves_flow(ImportCurvesParams(takes=takes, store=store, n_shards=2))
            for store in (tmp_path / "folder", url)}
    assert runs[url]["imported"] == runs[tmp_path / "folder"]["imported"] == 2 and runs[url]["rejected"] == 1
    got, want = snapshot(url), snapshot(tmp_path / "folder")
    for key in ("utterances", "rejects", "curves", "curve_files"):
        assert got[key] == want[key], key
    assert import_curves_flow(ImportCurvesParams(takes=takes, store=url, n_shards=2))["cached"] == 2


@pytest.mark.server
def test_serve_serves_a_store_and_corpus_on_s3_and_keeps_runs_to_their_prefixes(bucket, tmp_path):
    """`visemeflow serve --store s3://... --corpus s3://...` on this machine: its Prefect home is a local folder
    named by the store's URL; the served `ingest` (no parameters: the served store and corpus) and `rerun` write the
    S3 store; a run naming another prefix of the bucket fails before its stage runs."""
    import socket

    import s3fs
    from factories import make_corpus, start_serve, stop_process
    from prefect.deployments import run_deployment
    from prefect.settings import PREFECT_API_AUTH_STRING, PREFECT_API_URL, temporary_settings

    from visemeflow.ops.serve import AUTH_FILE, serve_home
    from visemeflow.procedural import ProceduralConfig
    from visemeflow.tasks.procedural import default_variant

    corpus = make_corpus(tmp_path / "corpus", {"spk/a": [("", 0.0, 0.2), ("AA1", 0.2, 0.5), ("M", 0.5, 0.7)]})
    s3fs.S3FileSystem(use_listings_cache=False).put(str(corpus), f"{bucket}/corpus", recursive=True)
    store, corpus_url = f"s3://{bucket}/served", f"s3://{bucket}/corpus"
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "PREFECT_API_AUTH_STRING")}
    env.update(PREFECT_HOME=str(tmp_path / "prefect-home"), PREFECT_SERVER_ANALYTICS_ENABLED="false",
               PREFECT_RUNNER_POLL_FREQUENCY="2", XDG_STATE_HOME=str(tmp_path / "state"))
    said = tmp_path / "serve.log"
    serve = start_serve(["--store", store, "--corpus", corpus_url, "--port", str(port), "--cron", ""], env, tmp_path,
                        said)
    try:
        assert f"flow runs may name paths under: s3://{bucket}/corpus, {store}" in said.read_text()
        home = tmp_path / "state" / "visemeflow" / "serve"
        (auth_file,) = home.glob(f"*/{AUTH_FILE}")
        assert auth_file.parent.name == serve_home(store).name and auth_file.parent.stat().st_mode & 0o777 == 0o700
        with temporary_settings(updates={PREFECT_API_URL: f"http://127.0.0.1:{port}/api",
                                         PREFECT_API_AUTH_STRING: auth_file.read_text()}):
            states = [run_deployment(name, parameters=parameters, timeout=240).state for name, parameters in (
                ("ingest/served", {}),
                ("rerun/served", {"utterance_id": "spk/a", "stage": "procedural"}),
                ("rerun/served", {"utterance_id": "spk/a", "store": f"s3://{bucket}/other"}))]
    finally:
        stop_process(serve)
    assert states[0].is_completed() and states[1].is_completed(), (states, said.read_text())
    assert states[2].is_failed() and "outside the prefixes" in str(states[2].message) + said.read_text()
    served = Store(store)
    assert served.read_table("utterances").column(C.UTTERANCE_ID).to_pylist() == ["spk/a"]
    assert served.has_curves("procedural", default_variant(ProceduralConfig()), "spk/a")
    assert served.read_table("utterances").column(C.AUDIO_PATH)[0].as_py() == f"{corpus_url}/spk/a.wav"
    assert not s3fs.S3FileSystem(use_listings_cache=False).exists(f"{bucket}/other")


@pytest.mark.flow
def test_synth_writes_the_true_curves_into_an_s3_store_as_into_a_folder(bucket, tmp_path, prefect_harness,
                                                                        monkeypatch):
    from factories import make_corpus, snapshot

    from visemeflow.flows.params import SynthParams
    from visemeflow.flows.synth import synth_flow
    from visemeflow.tracking.video import read_video_frames

    corpus = make_corpus(tmp_path / "source", {"spk/a": [("", 0.0, 0.2), ("AA1", 0.2, 0.5), ("M", 0.5, 0.7)]})
    url = f"s3://{bucket}/truth"
    for store, out in ((tmp_path / "truth", tmp_path / "videos-folder"), (url, tmp_path / "videos-s3")):
        synth_flow(SynthParams(corpus=corpus, out=out, store=store))
    got, want = snapshot(url), snapshot(tmp_path / "truth")
    assert got["curves"] == want["curves"] and got["curve_files"] == want["curve_files"] and len(got["curves"]) > 0
    np.testing.assert_array_equal(read_video_frames(tmp_path / "videos-s3" / "spk" / "a.mp4"),
                                  read_video_frames(tmp_path / "videos-folder" / "spk" / "a.mp4"))

    # the rendered corpus itself into the bucket: the same files, each object whole, and a corpus the pipeline reads
    import tempfile

    import s3fs

    fs = s3fs.S3FileSystem(use_listings_cache=False)
    work = tmp_path / "tmp"
    work.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(work))
    videos = f"s3://{bucket}/videos"
    first = synth_flow(SynthParams(corpus=corpus, out=videos, store=f"s3://{bucket}/truth2"))
    assert first["rendered"] == 1 and first["failed"] == 0 and first["out"] == videos
    folder = tmp_path / "videos-folder" / "spk"
    names = sorted(p.name for p in folder.iterdir())
    assert sorted(Path(k).name for k in fs.ls(f"{bucket}/videos/spk")) == names
    for name in names:
        if name.endswith((".mp4", ".parquet")):
            continue   # an encoder's and Parquet's metadata may differ byte for byte; compared below by content
        assert fs.cat_file(f"{bucket}/videos/spk/{name}") == (folder / name).read_bytes(), name
    fs.get_file(f"{bucket}/videos/spk/a.mp4", str(tmp_path / "fetched.mp4"))
    np.testing.assert_array_equal(read_video_frames(tmp_path / "fetched.mp4"), read_video_frames(folder / "a.mp4"))
    assert not list(work.glob("visemeflow-synth-*")), "the local work folder stays behind"
    again = synth_flow(SynthParams(corpus=corpus, out=videos, store=f"s3://{bucket}/truth2"))
    assert again["rendered"] == 0 and again["cached"] == 1
    fs.rm_file(f"{bucket}/videos/spk/a.mp4")     # a lost video is rendered again
    assert synth_flow(SynthParams(corpus=corpus, out=videos, store=f"s3://{bucket}/truth2"))["rendered"] == 1
    assert fs.exists(f"{bucket}/videos/spk/a.mp4")
    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.params import IngestParams

    ingested = ingest_flow(IngestParams(corpus=videos, store=f"s3://{bucket}/from-videos"))
    assert ingested["ingested"] == 1 and ingested.get("rejected", 0) == 0, ingested


def test_commands_on_an_s3_store(bucket, tmp_path):
    """`curves show`, `rejects` and `dashboard` read an S3 store; a missing bucket is one line."""
    import subprocess
    import sys

    url = f"s3://{bucket}/cli"
    Store(url).save_curves(_curves("spk/a", n=30, seed=4))

    def cli(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "visemeflow.cli", *args], capture_output=True, text=True,
                              timeout=120, env={**os.environ, "VISEMEFLOW_NO_SERVER_LOOKUP": "1"})

    shown = cli("curves", "show", "spk/a", "--store", url)
    assert shown.returncode == 0 and "spk/a  source procedural  variant v1  30 frames" in shown.stdout, shown.stderr
    assert cli("rejects", "--store", url).stdout.strip() == "no rejects"
    board = cli("dashboard", "--store", url, "--out", str(tmp_path / "board"))
    assert board.returncode == 0 and "dashboard:" in board.stdout, board.stderr
    assert "spk/a" in (tmp_path / "board" / "index.html").read_text()
    missing = cli("rejects", "--store", "s3://no-such-bucket-here/x")
    assert missing.returncode == 2 and "bucket 'no-such-bucket-here'" in missing.stderr
    assert len(missing.stderr.strip().splitlines()) == 1
    corpus = tmp_path / "corpus" / "spk"
    corpus.mkdir(parents=True)
    (corpus / "a.wav").write_bytes(b"")
    (corpus / "a.TextGrid").write_text("")
    nowhere = cli("synth", str(corpus.parent), "--out", "s3://no-such-bucket-here/videos", "--store", url)
    assert nowhere.returncode == 2 and nowhere.stderr.strip() == (
        "error: cannot write to s3://no-such-bucket-here/videos: bucket 'no-such-bucket-here' at "
        f"{os.environ['AWS_ENDPOINT_URL']} does not exist or this machine's credentials may not see it"), nowhere.stderr


def test_clean_aborts_the_unfinished_uploads_a_killed_writer_left(bucket, monkeypatch):
    """A writer killed while uploading a large file leaves a multipart upload whose parts the bucket keeps and bills.
    `visemeflow clean temporary` on an S3 store finds those begun over an hour ago on the server's clock, with
    their size, and aborts them; a younger one (maybe a live writer's), one of another store in the bucket and
    finished objects are left alone; listing them writes nothing. A store at a bucket's root finds its own. (moto
    dates every upload 2010-11-10, so the server's "now", the date of its answer, is set here.)"""
    import subprocess
    import sys

    import s3fs

    import visemeflow.storage.store as store_module
    from visemeflow.ops.clean import reclaimable

    fs = s3fs.S3FileSystem(use_listings_cache=False)
    url = f"s3://{bucket}/farm"
    store = Store(url)
    store.save_curves(_curves("spk/a", seed=5))

    def start(key: str, parts: int) -> str:
        upload = fs.call_s3("create_multipart_upload", Bucket=bucket, Key=key)["UploadId"]
        for n in range(1, parts + 1):
            fs.call_s3("upload_part", Bucket=bucket, Key=key, UploadId=upload, PartNumber=n, Body=b"x" * 5 * 2**20)
        return upload

    def uploads() -> list[tuple[str, str]]:
        return sorted((u["Key"], u["UploadId"]) for u in fs.call_s3("list_multipart_uploads", Bucket=bucket)
                      .get("Uploads", []))

    killed = start("farm/landmarks/spk/a.mediapipe478.parquet", 2)
    other = start("another-store/curves/x.parquet", 1)
    began = fs.call_s3("list_multipart_uploads", Bucket=bucket)["Uploads"][0]["Initiated"].timestamp()
    listing = fs.call_s3("list_multipart_uploads", Bucket=bucket)
    assert abs(store_module._server_time(listing) - time.time()) < 60   # the answer's Date: the server's now
    monkeypatch.setattr(store_module, "_server_time", lambda response: began + 60)
    assert store.stale_uploads() == []          # begun a minute ago: may be a live writer's
    assert reclaimable(store, ["temporary"])[0].count == 0
    monkeypatch.setattr(store_module, "_server_time", lambda response: began + 3660)
    objects = fs.find(bucket)
    found = store.stale_uploads()
    assert fs.find(bucket) == objects           # no probe object: read-only credentials may list
    assert [(str(u.path), u.upload_id, u.n_bytes) for u in found] == [
        (f"{url}/landmarks/spk/a.mediapipe478.parquet", killed, 10 * 2**20)]
    item, = reclaimable(store, ["temporary"])
    assert item.count == 1 and item.n_bytes == 10 * 2**20 and item.paths == []

    def cli(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "visemeflow.cli", "clean", *args, "--store", url],
                              capture_output=True, text=True, timeout=120,
                              env={**os.environ, "VISEMEFLOW_NO_SERVER_LOOKUP": "1"})

    listed = cli()                              # the command on the real clock: moto's 2010 uploads are stale
    assert listed.returncode == 0, listed.stderr
    assert "temporary      10.0 MiB reclaimable in 1 item (of which 1 unfinished upload)" in listed.stdout
    assert len(uploads()) == 2
    removed = cli("temporary")
    assert removed.returncode == 0, removed.stderr
    assert "temporary      10.0 MiB removed in 1 item" in removed.stdout
    assert uploads() == [("another-store/curves/x.parquet", other)]
    assert store.has_curves("procedural", "v1", "spk/a") and store.stale_uploads() == []

    root = f"vf-{secrets.token_hex(4)}"         # a store at a bucket's root
    fs.mkdir(root)
    at_root = fs.call_s3("create_multipart_upload", Bucket=root, Key="landmarks/b.parquet")["UploadId"]
    upload, = Store(f"s3://{root}").stale_uploads()
    assert (str(upload.path), upload.key, upload.upload_id) == (f"s3://{root}/landmarks/b.parquet",
                                                                  "landmarks/b.parquet", at_root)
    Store(f"s3://{root}").abort_upload(upload)
    assert fs.call_s3("list_multipart_uploads", Bucket=root).get("Uploads", []) == []


@pytest.mark.flow
def test_train_on_s3_resumes_on_any_machine_from_the_stored_checkpoint_and_predict_evaluate_sweep_run_there(
        bucket, tmp_path, prefect_harness, monkeypatch):
    """A training on an S3 store uploads its checkpoint after every epoch: killed after the first, and started again
    where no local file of it is left (another machine), it resumes from the stored one and ends with the weights
    of an uninterrupted training in a folder; `predict` then reads the model from S3 and writes the same curves,
    `evaluate` judges it on augmented copies written to S3 as in the folder, a sweep trains its sizes and uploads
    its plot, and the dashboard of the S3 store shows them."""
    import shutil

    import torch
    from factories import DEMO_CORPUS, make_lj_corpus

    import visemeflow.tasks.train as train_tasks
    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.params import IngestParams, PredictParams, ProceduralParams, TrainParams
    from visemeflow.flows.predict import predict_flow
    from visemeflow.flows.procedural import procedural_flow
    from visemeflow.flows.train import train_flow
    from visemeflow.ingest import IngestConfig
    from visemeflow.learning.train import TrainConfig, load_model

    corpus = make_lj_corpus(tmp_path / "corpus", speakers=1, names=["LJ001-0002", "LJ001-0005", "LJ001-0012"])
    url, folder = f"s3://{bucket}/learn", tmp_path / "store"
    for store in (url, folder):
        ingest_flow(IngestParams(corpus=corpus, store=store, n_shards=2, config=IngestConfig(val_fraction=0.25)))
        procedural_flow(ProceduralParams(store=store))
    config = TrainConfig(preset="fbank-tcn", epochs=2, d_model=16)
    local = train_flow(TrainParams(store=folder, config=config, source="procedural", model_name="tiny"))

    real, uploads = train_tasks.upload_checkpoint, []

    def killed_after_the_first_epoch(store, name, work):
        real(store, name, work)
        raise RuntimeError("killed after epoch 1")

    monkeypatch.setattr(train_tasks, "upload_checkpoint", killed_after_the_first_epoch)
    params = TrainParams(store=url, config=config, source="procedural", model_name="tiny")
    with pytest.raises(RuntimeError, match="killed after epoch 1"):
        train_flow(params)
    s3 = Store(url)
    assert s3.has_model("tiny") is False and (s3.checkpoint_dir("tiny") / "last.pt").is_file()
    shutil.rmtree(s3.local_work_dir(s3.checkpoint_dir("tiny")))          # another machine: no local copy
    monkeypatch.setattr(train_tasks, "upload_checkpoint",
                        lambda store, name, work: (uploads.append(name), real(store, name, work)))
    report = train_flow(params)
    assert uploads == ["tiny"]                                            # epoch 2 only: epoch 1 came from S3
    assert report["epochs"] == local["epochs"] == 2 and s3.model_names() == ["tiny"]
    assert report["path"].startswith(f"s3://{bucket}/learn/models/tiny/")
    ours, theirs = load_model(s3.model_file("tiny"))[0], load_model(Store(folder).model_path("tiny"))[0]
    for (name, a), (_, b) in zip(ours.state_dict().items(), theirs.state_dict().items(), strict=True):
        assert torch.equal(a, b), name
    assert s3.read_metrics("tiny").num_rows == Store(folder).read_metrics("tiny").num_rows > 0

    audio = DEMO_CORPUS / "SSB1624" / "SSB16240001.wav"
    for store in (url, folder):
        predict_flow(PredictParams(store=store, model="tiny", audio=[audio], fps=25, device="cpu"))
    got = s3.read_curves("predict/SSB16240001", "predicted", "tiny")
    want = Store(folder).read_curves("predict/SSB16240001", "predicted", "tiny")
    assert got.num_rows == want.num_rows > 0
    assert got.select(VISEMES).equals(want.select(VISEMES))

    from visemeflow.flows.evaluate import evaluate_flow
    from visemeflow.flows.params import EvaluateParams, SweepParams
    from visemeflow.flows.sweep import sweep_flow

    for store in (url, folder):
        evaluate_flow(EvaluateParams(store=store, models=["tiny"], conditions=["volume", "speed"], device="cpu"))
    import pyarrow.compute as pc

    judged = [Store(x).read_metrics("tiny").filter(pc.equal(pc.field(C.RUN), "evaluate"))
              .sort_by([(C.CONDITION, "ascending"), (C.UTTERANCE_ID, "ascending")]) for x in (url, folder)]
    assert judged[0].num_rows == judged[1].num_rows > 0
    assert judged[0].select([C.CONDITION, C.UTTERANCE_ID, C.L1_X100]).equals(
        judged[1].select([C.CONDITION, C.UTTERANCE_ID, C.L1_X100]))
    assert (s3.root / "reports" / "robustness.md").read_text() == (folder / "reports" / "robustness.md").read_text()

    swept = sweep_flow(SweepParams(store=url, config=TrainConfig(preset="fbank-tcn", d_model=8), sizes=[1, 2],
                                   steps=4, source="procedural"))
    assert [p[0] for p in swept["points"]] == [1, 2] and swept["plot"].startswith(f"s3://{bucket}/learn/reports/")
    assert (s3.root / "reports" / "sweep-fbank-tcn.png").read_bytes()[:4] == b"\x89PNG"

    from visemeflow.dashboards.html import build_dashboard

    result = build_dashboard(s3, tmp_path / "dashboard")
    page = (tmp_path / "dashboard" / "index.html").read_text()
    assert f"<code>s3://{bucket}/learn</code>" in page and 'id="chart-sweep-0"' in page
    assert not result.empty and len(result.utterances) == 5 and len(result.charts) > 5   # 4 ingested + 1 predicted
    assert "tiny" in page.split('id="robustness"', 1)[1]


def test_a_lease_is_held_across_machines_renewed_while_held_and_taken_from_a_dead_holder(bucket, monkeypatch):
    """`Store.held`: a second holder is refused with the holder named while the first holds it, however long (the
    lease object is rewritten); released at the end; one not renewed for LOCK_LEASE_S is taken."""
    import errno
    import socket

    import s3fs

    import visemeflow.storage.store as store_module

    monkeypatch.setattr(store_module, "LOCK_LEASE_S", 2.0)
    url = f"s3://{bucket}/leased"
    fs = s3fs.S3FileSystem(use_listings_cache=False)
    key = f"{bucket}/leased/.locks/serve.lease"
    with Store(url).held("serve", "the test store"):
        first = fs.info(key)["LastModified"]
        time.sleep(3.5)    # beyond the lease: renewed, so still held
        with pytest.raises(StoreError) as refused:
            with Store(url).held("serve", "the test store"):
                pass
        assert refused.value.errno == errno.EBUSY
        assert f"the test store is held by {socket.gethostname()} pid {os.getpid()} (renewed" in str(refused.value)
        assert fs.info(key, refresh=True)["LastModified"] > first
    assert not fs.exists(key)
    fs.pipe_file(key, b"gone-host pid 1 0123456789abcdef")   # a holder killed with -9 never removes its lease
    with pytest.raises(StoreError, match="held by gone-host pid 1"):
        with Store(url).held("serve", "the test store"):
            pass
    time.sleep(3.2)
    with Store(url).held("serve", "the test store"):
        assert fs.cat_file(key).startswith(f"{socket.gethostname()} pid {os.getpid()} ".encode())


def test_a_lease_in_a_folder_store_refuses_a_second_holder(tmp_path):
    with Store(tmp_path / "store").held("serve", "the folder store"):
        with pytest.raises(StoreError, match=f"the folder store is held by .* pid {os.getpid()}"):
            with Store(tmp_path / "store").held("serve", "the folder store"):
                pass
    with Store(tmp_path / "store").held("serve", "the folder store"):
        pass


def test_a_second_serve_of_a_bucket_store_is_refused_before_it_starts_a_server(bucket, monkeypatch):
    """Two `visemeflow serve` of one bucket store (on two machines: here a held lease) would each schedule the
    pipeline; the second stops with one line naming the first, before starting any server."""
    import signal

    from visemeflow.ops import serve as serve_module

    started = []
    monkeypatch.setattr(serve_module, "ensure_server", lambda *a, **k: started.append(a))
    monkeypatch.setattr(signal, "signal", lambda *a: None)
    url = f"s3://{bucket}/served-twice"
    with Store(url).held("serve", "held by the first serve"):
        with pytest.raises(serve_module.ServerStartError,
                           match=rf"another `visemeflow serve` runs on this store: the store {url} is held by .* pid "
                                 r".*; stop it first, or serve another store"):
            serve_module.serve_stages(url, None, port=0)
    assert started == []
