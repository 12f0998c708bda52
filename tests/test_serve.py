"""`visemeflow serve` and `prefect.yaml`: deployments, schedules, parameter forms, and the local server helper."""

import importlib
import os
import re
import socket
import stat
import sys

import httpx
import pytest
import yaml
from factories import REPO, make_corpus, start_serve, stop_process
from prefect.settings import PREFECT_API_AUTH_STRING, PREFECT_API_URL, temporary_settings

from visemeflow.ops import serve as serve_module
from visemeflow.ops.serve import (
    AUTH_FILE,
    ROOTS_ENV,
    URL_ROOTS_ENV,
    SERVE_DIR,
    PathOutsideRootsError,
    ServerStartError,
    api_healthy,
    build_deployments,
    check_paths_within,
    ensure_server,
    home_lock,
    server_environment,
)

STAGES = ("pipeline", "ingest", "procedural", "landmarks", "track", "train", "sweep", "evaluate", "predict", "import_curves",
          "animate", "speak", "preview", "rerun")
STORE_ONLY = ("procedural", "landmarks", "track", "train", "sweep", "evaluate", "predict", "import_curves", "animate", "speak",
              "preview", "rerun")


def flow_of(entrypoint: str):
    module, name = (entrypoint.split(":") if ":" in entrypoint else entrypoint.rsplit(".", 1))
    if module.endswith(".py"):
        module = module.removesuffix(".py").replace("/", ".")
    return getattr(importlib.import_module(module), name)


def test_deployments_of_every_stage_with_the_pipeline_on_the_cron_schedule(tmp_path):
    corpus, store = tmp_path / "corpus", tmp_path / "store"
    corpus.mkdir()
    deployments = {d.full_name: d for d in build_deployments(store, corpus, "0 3 * * *")}
    assert set(deployments) == {f"{stage}/served" for stage in STAGES}
    (schedule,) = deployments["pipeline/served"].schedules
    assert schedule.schedule.cron == "0 3 * * *" and schedule.schedule.timezone == "UTC" and schedule.active
    assert all(not d.schedules for name, d in deployments.items() if name != "pipeline/served")
    for stage in ("pipeline", "ingest"):
        assert deployments[f"{stage}/served"].parameters == {"store": str(store), "corpus": str(corpus)}
    for stage in STORE_ONLY:
        assert deployments[f"{stage}/served"].parameters == {"store": str(store)}
    for name, d in deployments.items():
        assert flow_of(d.entrypoint).name == d.flow_name == name.split("/")[0]


def test_a_store_and_corpus_on_object_storage_are_served_by_their_urls_and_confined_to_their_prefixes(
        tmp_path, monkeypatch):
    """`serve --store s3://... --corpus s3://...`: the deployments default to the URLs, served runs may name those
    prefixes (a manifest's: the prefix it lies under) and the folders given, the Prefect home is a local folder named
    by the store's URL."""
    from visemeflow.ops.serve import serve_home, serve_roots

    store, corpus = "s3://bucket/store/", "s3://bucket/corpora/c1"
    deployments = {d.full_name: d for d in build_deployments(store, corpus, "0 3 * * *")}
    assert deployments["pipeline/served"].parameters == {"store": "s3://bucket/store", "corpus": corpus}
    assert deployments["rerun/served"].parameters == {"store": "s3://bucket/store"}
    assert deployments["pipeline/served"].schedules
    roots = serve_roots(store, "s3://bucket/corpora/c2/manifest.csv", [tmp_path])
    assert roots == [tmp_path.resolve(), "s3://bucket/corpora/c2", "s3://bucket/store"]
    check_paths_within({"store": "s3://bucket/store", "corpus": "s3://bucket/corpora/c2/a.wav",
                        "out": tmp_path / "out"}, roots)
    for outside in ("s3://bucket/corpora/c1", "s3://bucket/corpora/c2/../c1/a.wav", "s3://bucket/corpora/c2/./a.wav"):
        with pytest.raises(PathOutsideRootsError, match=f"corpus = {re.escape(outside)} is outside"):
            check_paths_within({"store": "s3://bucket/store", "corpus": outside}, roots)
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    home = serve_home("s3://bucket/store")
    assert home.parent == tmp_path / "state" / "visemeflow" / "serve" and home != serve_home("s3://bucket/other")
    assert serve_home(tmp_path / "store") == tmp_path / "store" / SERVE_DIR


def test_the_pipeline_defaults_to_the_corpus_last_ingested_else_has_no_schedule(tmp_path):
    from visemeflow.storage import Store

    store = tmp_path / "store"
    (pipeline, *_) = build_deployments(store, None)
    assert not pipeline.schedules and pipeline.parameters == {"store": str(store)}
    Store(store).write_run_config("ingest", {"corpus": str(tmp_path / "corpus"), "n_shards": 8, "config": {}})
    (pipeline, *_) = build_deployments(store, None, "*/5 * * * *", timezone="Europe/Paris")
    assert pipeline.parameters["corpus"] == str(tmp_path / "corpus")
    assert pipeline.schedules[0].schedule.cron == "*/5 * * * *"
    assert pipeline.schedules[0].schedule.timezone == "Europe/Paris"
    (unscheduled, *_) = build_deployments(store, None, None)
    assert not unscheduled.schedules


def test_the_schedule_runs_with_the_settings_the_stages_last_ran_with(tmp_path):
    """`pipeline --fps 25 --tolerance 0.5` then `serve`: the nightly run used the code's defaults (30 fps, 0.1 s),
    read every utterance again and changed the store's frame rate. The pipeline's and the stages' deployments now
    default to the configs recorded in the store (never a path), and those defaults validate as the forms' values."""
    from visemeflow.flows.params import IngestSettings, ProceduralSettings
    from visemeflow.ingest import IngestConfig
    from visemeflow.procedural import ProceduralConfig
    from visemeflow.storage import Store

    store = tmp_path / "store"
    make_corpus(tmp_path / "corpus", {"spk/a": [("AA1", 0.0, 0.5)]})
    Store(store).write_run_config("ingest", IngestSettings(
        corpus=str(tmp_path / "corpus"), n_shards=4,
        config=IngestConfig(fps=25.0, alignment_tolerance_s=0.5)).model_dump(mode="json"))
    Store(store).write_run_config("procedural", ProceduralSettings(
        variant="mine", n_shards=4, config=ProceduralConfig(decay_s=0.08)).model_dump(mode="json"))
    deployments = build_deployments(store, None)
    pipeline, ingest, procedural = (next(d for d in deployments if d.flow_name == name)
                                    for name in ("pipeline", "ingest", "procedural"))
    assert pipeline.parameters["ingest"]["fps"] == 25.0 and pipeline.parameters["ingest"]["alignment_tolerance_s"] == 0.5
    assert pipeline.parameters["procedural"]["decay_s"] == 0.08 and pipeline.parameters["n_shards"] == 4
    assert ingest.parameters["config"]["fps"] == 25.0 and procedural.parameters["variant"] == "mine"
    for deployment in (pipeline, ingest, procedural):   # what a run of the form gets: the stage's model, valid
        served = flow_of(deployment.entrypoint)
        model = serve_module.params_model(serve_module.stage_flow(deployment.entrypoint.rsplit(".", 1)[1]).fn)
        params = model.model_validate(served.validate_parameters(deployment.parameters))
        assert str(params.store) == str(store)
    assert pipeline.parameters.keys() >= {"store", "corpus", "ingest", "procedural", "n_shards"}
    assert "rig" not in pipeline.parameters and "characters" not in pipeline.parameters   # paths are never recorded defaults


def test_a_scheduled_run_takes_the_settings_the_store_records_when_it_starts_not_when_serve_started(tmp_path,
                                                                                                    monkeypatch):
    """`serve` at 30 fps, then `pipeline --fps 25` by hand: the nightly run used the defaults serve was started with
    (30 fps) and mixed the store's frame rates again. A scheduled run whose recorded-default fields are all as serve
    gave them now takes what the store records at the run's start, as one set; a run started by hand, a schedule
    whose defaults were edited, and settings that do not validate keep the fields as given. The defaults reach the
    runs' processes in GIVEN_ENV."""
    import json

    from prefect import flow

    from visemeflow.flows.params import IngestSettings, PipelineParams
    from visemeflow.ingest import IngestConfig
    from visemeflow.storage import Store

    store = tmp_path / "store"
    make_corpus(tmp_path / "corpus", {"spk/a": [("AA1", 0.0, 0.5)]})

    def record(fps: float) -> None:
        Store(store).write_run_config("ingest", IngestSettings(
            corpus=str(tmp_path / "corpus"), n_shards=4, config=IngestConfig(fps=fps)).model_dump(mode="json"))

    record(30.0)
    monkeypatch.setattr(serve_module, "_SERVE_START", {})
    monkeypatch.delenv(serve_module.GIVEN_ENV, raising=False)
    pipeline = next(d for d in build_deployments(store, None) if d.flow_name == "pipeline")
    assert pipeline.parameters["ingest"]["fps"] == 30.0
    seen = []

    @flow(name="pipeline")
    def recording(params: PipelineParams) -> dict:
        seen.append(params)
        return {}

    served = serve_module.flat_flow(recording, __name__, lambda: None)

    def run(fields: dict, scheduled: bool = True) -> PipelineParams:
        monkeypatch.setattr(serve_module, "_auto_scheduled", lambda: scheduled)
        served.fn(**served.validate_parameters(fields))
        return seen[-1]

    with serve_module.using_given_defaults():
        given = os.environ[serve_module.GIVEN_ENV]
    monkeypatch.setattr(serve_module, "_SERVE_START", {})   # a run's own process: only the environment knows them
    monkeypatch.setenv(serve_module.GIVEN_ENV, given)
    record(25.0)   # `visemeflow pipeline --fps 25`, by hand, after serve started
    assert run(pipeline.parameters).ingest.fps == 25.0 and seen[-1].n_shards == 4
    assert run(pipeline.parameters, scheduled=False).ingest.fps == 30.0   # by hand: what the form says
    edited = {**pipeline.parameters, "n_shards": 8}   # the schedule's defaults edited in the UI: all kept
    assert (run(edited).ingest.fps, seen[-1].n_shards) == (30.0, 8)
    assert run({**pipeline.parameters, "store": str(tmp_path / "other")}).ingest.fps == 30.0   # another store
    config = store / "configs" / "ingest.json"
    for bad in ([1], {"config": {"fps": "fast"}}, {"config": {"fps": 25.0}, "n_shards": 10 ** 9}):
        config.write_text(json.dumps(bad))   # edited by hand: the run as serve started it
        assert run(pipeline.parameters).ingest.fps == 30.0 and seen[-1].n_shards == 4
    monkeypatch.setenv(serve_module.GIVEN_ENV, "not json")   # not ours: the run's fields as they are
    record(25.0)
    assert run(pipeline.parameters).ingest.fps == 30.0


def test_the_rerun_form_asks_for_utterance_stage_and_force():
    from prefect.utilities.callables import parameter_schema

    from visemeflow.flows.rerun import rerun_flow

    schema = parameter_schema(rerun_flow).model_dump()
    form = schema["definitions"]["RerunParams"]
    assert {"utterance_id", "stage", "force", "store"} <= set(form["properties"])
    assert form["required"] == ["utterance_id"]
    assert form["properties"]["force"]["default"] is True
    assert set(form["properties"]["stage"]["enum"]) == {"ingest", "procedural", "landmarks", "track", "animate"}


def test_prefect_yaml_is_what_the_stage_table_renders():
    """prefect.yaml is made from visemeflow/flows/stages.py: a stage added to the table and not to the file (or the
    other way round) fails here. Regenerate with
    `.venv/bin/python -c "from visemeflow.ops.serve import render_prefect_yaml as r; open('prefect.yaml','w').write(r())"`."""
    from visemeflow.flows.stages import STAGES as TABLE

    assert (REPO / "prefect.yaml").read_text() == serve_module.render_prefect_yaml()
    assert tuple(s.name for s in TABLE) == STAGES
    for stage in TABLE:
        assert stage.flow().name == stage.name  # the table names each flow as Prefect does


def test_prefect_yaml_names_existing_flows_with_the_same_schedule():
    from prefect.cli.deploy._models import PrefectYamlModel

    config = yaml.safe_load((REPO / "prefect.yaml").read_text())
    PrefectYamlModel.model_validate(config)
    deployments = config["deployments"]
    names = set()
    for d in deployments:
        assert d["entrypoint"].startswith("visemeflow/ops/pool.py:") and (REPO / d["entrypoint"].split(":")[0]).is_file()
        flow = flow_of(d["entrypoint"])
        names.add(flow.name)
        assert d["work_pool"]["name"] == "visemeflow" and d["name"] == "pool"
        params = d["parameters"]  # flat: each a parameter of the flow, merged one by one over a run's
        assert params["store"] == "visemeflow-out/store" and set(params) <= set(flow.parameters.properties)
        if flow.name in ("pipeline", "ingest"):
            assert params["corpus"]
    assert names == set(STAGES)
    (pipeline,) = [d for d in deployments if d["entrypoint"].endswith(":pipeline_flow")]
    assert pipeline["schedules"] == [{"cron": serve_module.DEFAULT_CRON, "timezone": "UTC"}]


@pytest.fixture
def script_loads(monkeypatch):
    """Prefect loads a `path.py:name` entrypoint as a script module (`pool`) and puts its folder first on sys.path,
    for good: both are undone after the test."""
    monkeypatch.setattr(sys, "path", list(sys.path))
    yield
    if getattr(sys.modules.get("pool"), "__file__", "").endswith(os.path.join("ops", "pool.py")):
        del sys.modules["pool"]


def test_every_pool_entrypoint_loads_with_prefects_loader_as_a_flat_flow_named_as_its_stage(script_loads):
    """What `prefect deploy` and a worker's engine do with prefect.yaml's entrypoints: load the file as a script and
    read the flow's schema. Each is the stage's flow, flat as the served one, and no other flow is built."""
    from prefect.flows import load_flow_from_entrypoint

    from visemeflow.flows.stages import STAGES as TABLE

    for stage in TABLE:
        path, name = serve_module.pool_entrypoint(stage).split(":")
        pool = load_flow_from_entrypoint(f"{REPO / path}:{name}")
        own = stage.flow()
        assert pool.name == own.name == stage.name and pool.fn is not own.fn
        form = pool.parameters.model_dump()
        model = serve_module.params_model(own.fn)
        assert list(form["properties"]) == list(model.model_fields) and "params" not in form["properties"]
        assert form == serve_module.served_flow(name).parameters.model_dump()  # the served form, the same builder
        assert pool.flow_run_name == serve_module.served_run_name(own.flow_run_name)
        assert pool is importlib.import_module("visemeflow.ops.pool").__getattr__(name)  # built once, either way
    with pytest.raises(AttributeError, match="no attribute 'nothing_flow'"):
        importlib.import_module("visemeflow.ops.pool").nothing_flow


def test_pool_entrypoints_check_paths_only_where_the_workers_environment_names_roots(tmp_path, monkeypatch):
    """A worker has no `serve --store` to take folders from: unset, the pool entrypoints run the stage as the stage
    flows did; set (the worker's environment, or the pool's job variables), they refuse paths elsewhere."""
    from visemeflow.flows.params import RerunParams

    from prefect import flow

    seen = []

    @flow(name="rerun")
    def recording(params: RerunParams) -> dict:
        seen.append(params)
        return {"ok": 1}

    pool = serve_module.flat_flow(recording, "visemeflow.ops.pool", serve_module.roots_if_set)
    outside = tmp_path.parent / "elsewhere"
    monkeypatch.delenv(ROOTS_ENV, raising=False)
    assert pool.fn(**pool.validate_parameters({"utterance_id": "spk/a", "store": str(outside)})) == {"ok": 1}
    assert seen == [RerunParams(utterance_id="spk/a", store=outside)] and pool.__module__ == "visemeflow.ops.pool"
    monkeypatch.setenv(ROOTS_ENV, str(tmp_path))
    with pytest.raises(PathOutsideRootsError, match="flow parameter store = "):
        pool.fn(**pool.validate_parameters({"utterance_id": "spk/a", "store": str(outside)}))
    assert len(seen) == 1
    # a store on object storage: a run confined to folders refuses it, one confined to its prefix takes it (and
    # nothing beside or above it), an unconfined one takes it
    with pytest.raises(PathOutsideRootsError, match="outside the prefixes on object storage"):
        pool.fn(**pool.validate_parameters({"utterance_id": "spk/a", "store": "s3://bucket/store"}))
    monkeypatch.setenv(URL_ROOTS_ENV, "s3://bucket/store\ns3://corpora/c1")
    assert pool.fn(**pool.validate_parameters({"utterance_id": "spk/a", "store": "s3://bucket/store"})) == {"ok": 1}
    assert pool.fn(**pool.validate_parameters({"utterance_id": "spk/a", "store": "s3://bucket/store/x"})) == {"ok": 1}
    for elsewhere in ("s3://bucket/store2", "s3://bucket", "s3://corpora/c2"):
        with pytest.raises(PathOutsideRootsError, match=f"flow parameter store = {re.escape(elsewhere)} is outside"):
            pool.fn(**pool.validate_parameters({"utterance_id": "spk/a", "store": elsewhere}))
    monkeypatch.delenv(ROOTS_ENV)
    monkeypatch.delenv(URL_ROOTS_ENV)
    assert pool.fn(**pool.validate_parameters({"utterance_id": "spk/a", "store": "s3://bucket/store"})) == {"ok": 1}
    assert seen[-1].store == "s3://bucket/store"


@pytest.mark.flow
def test_a_pool_deployment_run_with_param_keeps_the_store_prefect_yaml_names(tmp_path, prefect_harness, monkeypatch,
                                                                            script_loads):
    """prefect.yaml's `rerun/pool` on the test server: `prefect deploy` from the folder holding the file and the
    package, `prefect deployment run 'rerun/pool' --param utterance_id=...`, then the flow run executed as a process
    worker's engine does (`prefect.engine`: the deployment's pull step, its entrypoint, the run's parameters). The
    run's parameters are the override merged over the deployment's flat defaults, so the run keeps the store
    prefect.yaml names (relative to the folder deployed from) and processes the utterance there.

    The CLI runs in this process (Prefect's `invoke_and_assert`) and so does the flow run, rather than a worker's
    subprocess: each subprocess would import Prefect and the stage's flow again (about 10 s each)."""
    import shutil

    from factories import make_corpus
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.actions import WorkPoolCreate
    from prefect.exceptions import ObjectAlreadyExists
    from prefect.flow_engine import load_flow, run_flow
    from prefect.testing.cli import invoke_and_assert

    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.params import IngestParams, RerunParams
    from visemeflow.procedural import ProceduralConfig
    from visemeflow.storage import Store
    from visemeflow.tasks.procedural import default_variant

    work = tmp_path / "work"  # the folder deployed from: prefect.yaml and the package, as at the repository root
    work.mkdir()
    (work / "visemeflow").symlink_to(REPO / "visemeflow")
    shutil.copyfile(REPO / "prefect.yaml", work / "prefect.yaml")
    (rerun_defaults,) = [d["parameters"] for d in yaml.safe_load((work / "prefect.yaml").read_text())["deployments"]
                         if d["entrypoint"].endswith(":rerun_flow")]
    store = work / rerun_defaults["store"]
    corpus = make_corpus(tmp_path / "corpus", {"spk/a": [("", 0.0, 0.2), ("AA1", 0.2, 0.5), ("M", 0.5, 0.7)]})
    assert ingest_flow(IngestParams(corpus=corpus, store=store, n_shards=1), return_state=True).is_completed()
    monkeypatch.delenv(ROOTS_ENV, raising=False)
    monkeypatch.chdir(work)
    with get_client(sync_client=True) as client:
        try:
            client.create_work_pool(WorkPoolCreate(name="visemeflow", type="process"))
        except ObjectAlreadyExists:
            pass
        # Prefect picks a prefect.yaml deployment by its entrypoint's attribute: `rerun_flow/pool`
        invoke_and_assert(["--no-prompt", "deploy", "--name", "rerun_flow/pool"], echo=False)
        created = invoke_and_assert(["deployment", "run", "rerun/pool", "--param", "utterance_id=spk/a"], echo=False)
        run_id = re.search(r"UUID: ([0-9a-f-]{36})", created.stdout).group(1)
        deployment = client.read_deployment_by_name("rerun/pool")
        run = client.read_flow_run(run_id)
        assert deployment.entrypoint == "visemeflow/ops/pool.py:rerun_flow"
        assert deployment.parameters == {"store": rerun_defaults["store"]} == {"store": "visemeflow-out/store"}
        assert "params" not in deployment.parameter_openapi_schema["properties"]
        assert run.parameters == {"store": rerun_defaults["store"], "utterance_id": "spk/a"}
        assert RerunParams.model_validate(run.parameters) == RerunParams(utterance_id="spk/a",
                                                                         store=rerun_defaults["store"])
        monkeypatch.chdir(tmp_path)  # the pull step `prefect deploy` recorded goes back to `work`
        flow = load_flow(run)
        assert flow.name == "rerun" and flow.fn.__name__ == "rerun_flow" and os.getcwd() == str(work)
        run_flow(flow, flow_run=run)
        run = client.read_flow_run(run_id)
    assert run.state.is_completed(), run.state
    assert run.name == "rerun(spk/a:procedural)"
    assert Store(store).has_curves("procedural", default_variant(ProceduralConfig()), "spk/a")


def test_serve_serves_every_deployment_on_the_configured_api(tmp_path, monkeypatch):
    served, lines = [], []
    monkeypatch.setattr("prefect.serve", lambda *deployments, **kwargs: served.extend(deployments))
    with temporary_settings(updates={PREFECT_API_URL: "http://127.0.0.1:4999/api"}):
        serve_module.serve_stages(tmp_path / "store", tmp_path, port=1, echo=lines.append)
    assert {d.full_name for d in served} == {f"{stage}/served" for stage in STAGES}
    assert "http://127.0.0.1:4999" in lines[0]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_server_serve_starts_has_its_own_home_auth_csrf_and_cors_for_its_ui_only(tmp_path, monkeypatch):
    """The settings are read back through Prefect itself, so a misspelt name (silently ignored) fails here."""
    from prefect.settings import Settings

    for name, value in server_environment(tmp_path / "home", 4321, "visemeflow:s3cret").items():
        monkeypatch.setenv(name, value)
    settings = Settings()
    assert settings.home == tmp_path / "home"
    assert settings.server.api.auth_string.get_secret_value() == "visemeflow:s3cret"
    assert settings.server.api.csrf_protection_enabled is True
    assert settings.server.api.cors_allowed_origins == "http://127.0.0.1:4321,http://localhost:4321"
    assert "*" not in settings.server.api.cors_allowed_methods + settings.server.api.cors_allowed_headers
    assert settings.server.ui.api_url == "http://127.0.0.1:4321/api"


def test_a_second_serve_of_one_store_is_refused_not_sharing_its_database(tmp_path, monkeypatch):
    monkeypatch.delenv("PREFECT_API_URL", raising=False)
    home = tmp_path / "store" / SERVE_DIR
    home.mkdir(parents=True)
    with temporary_settings(restore_defaults={PREFECT_API_URL}), home_lock(home):
        with pytest.raises(ServerStartError, match=rf"another `visemeflow serve` \(pid {os.getpid()}\) runs on"):
            with ensure_server(home, free_port()):
                pytest.fail("a second server started on the same Prefect database")


def test_a_port_in_use_is_refused_not_shared(tmp_path, monkeypatch):
    """Another serve's server there holds that serve's deployments: using it would re-point them."""
    monkeypatch.delenv("PREFECT_API_URL", raising=False)
    with socket.socket() as busy, temporary_settings(restore_defaults={PREFECT_API_URL}):
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(ServerStartError, match=f"port {port} on 127.0.0.1 is in use"):
            with ensure_server(tmp_path / "home", port):
                pytest.fail("serve used the server on a port it did not start")
    assert not (tmp_path / "home").exists()


def test_served_flow_runs_name_paths_under_the_roots_only(tmp_path):
    from visemeflow.flows.predict import PredictParams
    from visemeflow.rig import demo_rig_path

    root, elsewhere = tmp_path / "root", tmp_path / "elsewhere"
    (root / "audio").mkdir(parents=True)
    elsewhere.mkdir()
    (root / "audio" / "link.wav").symlink_to(elsewhere / "secret.wav")
    inside = PredictParams(store=root / "store", audio=[root / "audio" / "a.wav"], out=root / "out")
    check_paths_within({"params": inside}, [root])
    check_paths_within({"character": demo_rig_path()}, [root])  # the shipped demo rig, every character's default
    for params, name in ((PredictParams(store=root / "store", audio=[root / "audio" / "a.wav", elsewhere / "b.wav"]),
                          "params.audio[1]"),
                         (PredictParams(store=root / "store", audio=[root / "audio" / "link.wav"]), "params.audio[0]"),
                         (PredictParams(store=root / ".." / "elsewhere", audio=[root / "a.wav"]), "params.store")):
        with pytest.raises(PathOutsideRootsError, match=rf"flow parameter {re.escape(name)} = .* is outside the "
                                                        rf"folders `visemeflow serve` was started with \({root}\)"):
            check_paths_within({"params": params}, [root])
    with pytest.raises(PathOutsideRootsError, match=ROOTS_ENV):
        check_paths_within({"params": inside}, [])


def test_a_served_run_sends_no_work_to_a_dask_scheduler_named_in_its_parameters(tmp_path):
    from visemeflow.flows.params import PipelineParams, RunnerConfig

    root = tmp_path / "root"
    check_paths_within({"params": PipelineParams(corpus=root / "c", store=root / "s",
                                                 runner=RunnerConfig(kind="dask", dask_workers=2))}, [root])
    for address in ("203.0.113.7:8786", "tcp://203.0.113.7:8786", "localhost:8786"):
        params = PipelineParams(corpus=root / "c", store=root / "s", runner=RunnerConfig(dask_address=address))
        with pytest.raises(PathOutsideRootsError, match=rf"params\.runner\.dask_address = {re.escape(address)}: a "
                                                        r"served run sends no work to a Dask scheduler"):
            check_paths_within({"params": params}, [root])


def test_model_sources_given_as_strings_are_checked_when_they_name_a_local_folder(tmp_path):
    """`wav2vec2_model` and `whisper_source` take a local folder or a hub id: a folder is a path like any other."""
    from visemeflow.flows.params import TrainParams
    from visemeflow.learning.train import TrainConfig

    root = tmp_path / "root"
    hub = TrainParams(store=root / "store", config=TrainConfig(preset="wav2vec2-blstm", wav2vec2_model="org/model"))
    check_paths_within({"params": hub}, [root])
    local = TrainConfig(preset="wav2vec2-blstm", wav2vec2_model=str(tmp_path / "weights"))
    with pytest.raises(PathOutsideRootsError, match=r"params\.config\.wav2vec2_model = "):
        check_paths_within({"params": TrainParams(store=root / "store", config=local)}, [root])


def test_the_served_entrypoints_check_their_paths_before_the_stage_runs(tmp_path, monkeypatch):
    """Prefect's engine imports a served run's flow from its deployment's entrypoint: that flow is the confined one,
    with the stage's own form."""
    from prefect.flows import load_flow_from_entrypoint

    outside = tmp_path / "elsewhere" / "store"
    monkeypatch.setenv(ROOTS_ENV, str(tmp_path / "root"))
    for deployment in build_deployments(tmp_path / "root" / "store", None):
        module, name = deployment.entrypoint.rsplit(".", 1)
        served = load_flow_from_entrypoint(deployment.entrypoint)
        stage = getattr(importlib.import_module(serve_module.SERVED_FLOWS[name]), name)
        assert module == "visemeflow.ops.serve" and served.fn is not stage.fn
        assert served.name == stage.name == deployment.flow_name
        assert list(served.parameters.properties) == list(serve_module.params_model(stage.fn).model_fields)
    procedural = load_flow_from_entrypoint("visemeflow.ops.serve.procedural_flow")
    with pytest.raises(PathOutsideRootsError, match=rf"flow parameter store = {re.escape(str(outside))} is outside"):
        procedural.fn(**procedural.validate_parameters({"store": str(outside)}))
    assert not outside.exists()


def test_a_served_rerun_refuses_recorded_settings_that_name_paths_outside_the_roots(tmp_path, monkeypatch):
    """A served rerun repeats the settings its stage last ran with, read from the store (configs/<stage>.json, which
    a run from the command line, or anyone who can write into the store, wrote): a path in them outside serve's
    folders is refused before the stage reads or writes it, as the run's own parameters are."""
    from prefect.flows import load_flow_from_entrypoint

    from visemeflow.storage import Store

    root, elsewhere = tmp_path / "root", tmp_path / "elsewhere"
    store = Store(root / "store")
    monkeypatch.setenv(ROOTS_ENV, str(root))
    rerun = load_flow_from_entrypoint("visemeflow.ops.serve.rerun_flow")

    def run(stage):
        return rerun.fn(**rerun.validate_parameters({"store": str(store.root), "utterance_id": "spk/a",
                                                     "stage": stage}))

    for stage, settings, name, path in (
            ("animate", {"characters": [str(root / "good.glb"), str(elsewhere / "char.glb")], "source": "procedural",
                         "variant": "v", "out": str(root / "out")}, r"characters\[1\]", elsewhere / "char.glb"),
            ("animate", {"characters": [str(root / "good.glb")], "source": "procedural", "variant": "v",
                         "out": str(elsewhere / "autostart")}, "out", elsewhere / "autostart"),
            ("ingest", {"corpus": str(elsewhere / "corpus")}, "corpus", elsewhere / "corpus")):
        store.write_run_config(stage, settings)
        with pytest.raises(PathOutsideRootsError, match=rf"the settings {stage} last ran with \(configs/{stage}\.json "
                                                        rf"in the store\), which this run repeats: {name} = "
                                                        rf"{re.escape(str(path))} is outside the folders"):
            run(stage)
    assert not elsewhere.exists()
    # inside the roots, the same rerun goes on to the stage (which finds no such corpus)
    store.write_run_config("ingest", {"corpus": str(root / "corpus")})
    with pytest.raises(FileNotFoundError, match=f"corpus {re.escape(str(root / 'corpus'))} does not exist"):
        run("ingest")


@pytest.mark.server
def test_ensure_server_starts_a_local_server_registers_the_forms_and_stops(tmp_path, monkeypatch):
    from prefect.client.orchestration import get_client

    port = free_port()
    monkeypatch.setenv("PREFECT_HOME", str(tmp_path / "prefect-home"))  # this process's, not the server's
    monkeypatch.delenv("PREFECT_API_URL", raising=False)
    monkeypatch.delenv("PREFECT_API_AUTH_STRING", raising=False)
    corpus, home = tmp_path / "corpus", tmp_path / "store" / SERVE_DIR
    corpus.mkdir()
    with temporary_settings(restore_defaults={PREFECT_API_URL, PREFECT_API_AUTH_STRING}):
        with ensure_server(home, port) as api:
            api_url = api.url
            assert api_url == f"http://127.0.0.1:{port}/api" and api_healthy(api_url)
            assert os.environ["PREFECT_API_URL"] == api_url and PREFECT_API_URL.value() == api_url
            auth = api.auth_file.read_text()
            assert api.auth_file == home / AUTH_FILE and stat.S_IMODE(api.auth_file.stat().st_mode) == 0o600
            assert os.environ["PREFECT_API_AUTH_STRING"] == auth == PREFECT_API_AUTH_STRING.value()
            assert httpx.get(f"{api_url}/deployments/count").status_code == 401  # without the auth string
            for deployment in build_deployments(tmp_path / "store", corpus):
                deployment.apply()
            with get_client(sync_client=True) as client:
                rerun = client.read_deployment_by_name("rerun/served")
                pipeline = client.read_deployment_by_name("pipeline/served")
        assert not api_healthy(api_url)
        assert "PREFECT_API_URL" not in os.environ and not PREFECT_API_URL.value()
        assert "PREFECT_API_AUTH_STRING" not in os.environ
    assert (home / "prefect.db").is_file()  # the server's own database, not the one in PREFECT_HOME
    assert not (tmp_path / "prefect-home" / "prefect.db").exists()
    form = rerun.parameter_openapi_schema["properties"]  # flat: each field of RerunParams a parameter
    assert {"utterance_id", "stage", "force", "store"} == set(form) and "params" not in form
    assert rerun.parameter_openapi_schema["required"] == ["utterance_id"]
    assert [s.schedule.cron for s in pipeline.schedules] == [serve_module.DEFAULT_CRON]
    assert pipeline.parameters["corpus"] == str(corpus)


@pytest.mark.server
def test_serve_stops_its_server_on_sigterm_as_under_systemd(tmp_path):
    """systemd stops a service with SIGTERM: `visemeflow serve` must exit and take its Prefect server with it."""
    import signal
    import subprocess
    import sys
    import time

    port = free_port()
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    env.update(PREFECT_HOME=str(tmp_path / "prefect-home"), PREFECT_SERVER_ANALYTICS_ENABLED="false")
    corpus = tmp_path / "corpus"
    corpus.mkdir()
    log = (tmp_path / "serve.log").open("w+")
    serve = subprocess.Popen([sys.executable, "-m", "visemeflow.cli", "serve", "--store", str(tmp_path / "store"),
                              "--corpus", str(corpus), "--port", str(port)], env=env, stdout=log,
                             stderr=subprocess.STDOUT)
    api_url = f"http://127.0.0.1:{port}/api"
    try:
        deadline = time.monotonic() + 240
        while "stop with Ctrl-C" not in (tmp_path / "serve.log").read_text() and serve.poll() is None:
            assert time.monotonic() < deadline, (tmp_path / "serve.log").read_text()
            time.sleep(0.5)
        while "being served" not in (tmp_path / "serve.log").read_text() and serve.poll() is None:
            assert time.monotonic() < deadline, (tmp_path / "serve.log").read_text()   # Prefect's runner is up:
            time.sleep(0.5)                                                             # its SIGTERM handler runs
        assert serve.poll() is None, (tmp_path / "serve.log").read_text()
        assert api_healthy(api_url)
        serve.send_signal(signal.SIGTERM)
        assert serve.wait(timeout=60) == 0, (tmp_path / "serve.log").read_text()
        assert not api_healthy(api_url)  # the server it started is gone too
        said = (tmp_path / "serve.log").read_text()
        assert "RuntimeWarning" not in said, said   # Prefect's runner's stop, unawaited: filtered, nothing more said
    finally:
        if serve.poll() is None:
            serve.kill()
        import psutil

        for process in psutil.process_iter(["cmdline"]):  # a server left behind by a failure here
            if "--port" in (cmd := process.info["cmdline"] or []) and str(port) in cmd and "server" in cmd:
                process.kill()


def test_served_forms_are_flat_each_field_a_parameter_with_its_type_default_and_description():
    """Prefect merges a run's parameters over the deployment's one top-level name at a time: flat, a run naming
    `utterance_id` only keeps the served `store`; the CLI's `--param utterance_id=...` is accepted."""
    from prefect.exceptions import ParameterTypeError

    from visemeflow.flows.params import PipelineParams, RerunParams

    from prefect.utilities.callables import parameter_schema

    rerun = serve_module.served_flow("rerun_flow")
    form = rerun.parameters.model_dump()
    assert parameter_schema(rerun).model_dump() == form  # what `to_deployment` sends the server as the form
    assert list(form["properties"]) == list(RerunParams.model_fields) and form["required"] == ["utterance_id"]
    assert form["properties"]["force"]["default"] is True
    assert form["properties"]["utterance_id"]["description"] == RerunParams.model_fields["utterance_id"].description
    assert set(form["properties"]["stage"]["enum"]) == {"ingest", "procedural", "landmarks", "track", "animate"}
    assert rerun.flow_run_name == "rerun({utterance_id}:{stage})"  # the stage's template, on flat parameters
    assert rerun.validate_parameters({"utterance_id": "spk/a", "store": "/s"}) == {
        "utterance_id": "spk/a", "stage": "procedural", "store": serve_module.Path("/s"), "force": True}
    pipeline = serve_module.served_flow("pipeline_flow")
    shards = pipeline.parameters.properties["n_shards"]
    assert (shards["minimum"], shards["maximum"], shards["default"]) == (1, 4096, 8)  # the field's constraints
    with pytest.raises(ParameterTypeError, match="n_shards"):
        pipeline.validate_parameters({"corpus": "/c", "n_shards": 0})
    with pytest.raises(ParameterTypeError, match="utterance_id"):
        rerun.validate_parameters({"store": "/s"})
    assert set(pipeline.parameters.properties) == set(PipelineParams.model_fields)


def test_the_served_flow_hands_the_stage_the_model_its_flat_parameters_make(tmp_path, monkeypatch):
    """The confined copy builds the stage's own params model from the flat parameters and calls the stage with it."""
    from visemeflow.flows.params import RerunParams

    from prefect import flow

    seen = []

    @flow(name="rerun")
    def recording(params: RerunParams) -> dict:
        seen.append(params)
        return {"ok": 1}

    monkeypatch.setenv(ROOTS_ENV, str(tmp_path))
    served = serve_module.confined(recording)
    store = tmp_path / "store"
    assert served.fn(**served.validate_parameters({"utterance_id": "spk/a", "store": str(store)})) == {"ok": 1}
    assert seen == [RerunParams(utterance_id="spk/a", store=store)]
    with pytest.raises(PathOutsideRootsError, match="flow parameter store = "):
        served.fn(**served.validate_parameters({"utterance_id": "spk/a", "store": str(tmp_path.parent / "x")}))
    assert len(seen) == 1  # refused before the stage ran


@pytest.mark.server
def test_the_prefect_cli_runs_served_deployments_with_flat_or_partial_parameters_on_the_served_store(tmp_path):
    """docs/serve.md's commands against a real `visemeflow serve`: `--param utterance_id=...` is accepted, and a
    run naming some fields only (`--param` or a partial `--params`) runs on the store `serve --store` set."""
    import json
    import subprocess
    import sys
    import time

    from factories import make_corpus
    from prefect.client.orchestration import get_client

    from visemeflow.procedural import ProceduralConfig
    from visemeflow.storage import Store
    from visemeflow.tasks.procedural import default_variant

    port, api_url = (port := free_port()), f"http://127.0.0.1:{port}/api"
    store, work = tmp_path / "store", tmp_path / "work"  # work: serve's folder, where the default store would go
    corpus = make_corpus(tmp_path / "corpus", {"spk/a": [("", 0.0, 0.2), ("AA1", 0.2, 0.5), ("M", 0.5, 0.7)]})
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "PREFECT_API_AUTH_STRING")}
    env.update(PREFECT_HOME=str(tmp_path / "prefect-home"), PREFECT_SERVER_ANALYTICS_ENABLED="false",
               PREFECT_RUNNER_POLL_FREQUENCY="2")
    said = tmp_path / "serve.log"
    serve = start_serve(["--store", str(store), "--corpus", str(corpus), "--port", str(port), "--cron", ""], env,
                        work, said)
    try:
        auth = (store / SERVE_DIR / AUTH_FILE).read_text()
        cli_env = {**env, "PREFECT_API_URL": api_url, "PREFECT_API_AUTH_STRING": auth}

        def deployment_run(*args: str) -> subprocess.CompletedProcess:
            return subprocess.run([sys.executable, "-m", "prefect", "deployment", "run", *args], env=cli_env, cwd=work,
                                  capture_output=True, text=True, timeout=120)

        with temporary_settings(updates={PREFECT_API_URL: api_url, PREFECT_API_AUTH_STRING: auth}):
            with get_client(sync_client=True) as client:
                for args in (["ingest/served"],  # no parameters at all: the served store and corpus
                             ["rerun/served", "--param", "utterance_id=spk/a"],
                             ["rerun/served", "--params", json.dumps({"utterance_id": "spk/a", "stage": "ingest"})]):
                    created = deployment_run(*args)
                    assert created.returncode == 0, (args, created.stdout, created.stderr)
                    run_id = re.search(r"UUID: ([0-9a-f-]{36})", created.stdout).group(1)
                    deadline = time.monotonic() + 240
                    while not (run := client.read_flow_run(run_id)).state.is_final():
                        assert time.monotonic() < deadline, (args, run.state, said.read_text())
                        time.sleep(1)
                    assert run.state.is_completed(), (args, run.state, said.read_text())
                nested = deployment_run("rerun/served", "--params", json.dumps({"params": {"utterance_id": "spk/a"}}))
                assert nested.returncode != 0 and "params" in nested.stdout  # the old nested form is refused
                rerun = client.read_deployment_by_name("rerun/served")
                runs = [r for r in client.read_flow_runs() if r.deployment_id == rerun.id]
    finally:
        stop_process(serve)
    assert sorted(r.name for r in runs) == ["rerun(spk/a:ingest)", "rerun(spk/a:procedural)"]
    for run in runs:
        assert run.state.is_completed() and run.parameters["store"] == str(store), (run.name, run.parameters)
    assert Store(store).has_curves("procedural", default_variant(ProceduralConfig()), "spk/a")
    assert not (work / "visemeflow-out").exists()  # nothing ran on the default store


def test_prefects_scheduler_makes_runs_of_the_served_schedule(tmp_path, prefect_harness):
    """`serve --cron` registered the pipeline's schedule, but no scheduled run was ever made: Prefect 3.8's scheduler
    fails on SQLAlchemy 2.1 ("Can't evaluate bulk DML statement", logged by the server every loop), so the nightly
    pipeline never ran (a new user's report). SQLAlchemy is pinned below 2.1 (pyproject.toml). Here the scheduler's
    own pass runs on the served pipeline deployment and makes its runs."""
    import asyncio

    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import DeploymentFilter, DeploymentFilterId
    from prefect.server.services.scheduler import schedule_deployments

    corpus, store = tmp_path / "corpus", tmp_path / "store"
    corpus.mkdir()
    pipeline = next(d for d in build_deployments(store, corpus, "*/5 * * * *") if d.full_name == "pipeline/served")
    deployment_id = pipeline.apply()

    async def scheduled():
        await schedule_deployments()
        async with get_client() as client:
            runs = await client.read_flow_runs(deployment_filter=DeploymentFilter(
                id=DeploymentFilterId(any_=[deployment_id])))
        return [r.state_name for r in runs]

    states = asyncio.run(scheduled())
    assert len(states) >= 3 and set(states) == {"Scheduled"}


def test_flow_run_names_print_in_prefects_cli():
    """The docs send users to `prefect flow-run ls`; a run named `procedural[/tmp/store]` crashed it (rich reads
    `[/tmp/store]` as a closing markup tag: MarkupError). Every stage's run name, with a path in it, prints whole."""
    import io

    from rich.console import Console
    from rich.table import Table

    for stage in STAGES:
        flow = flow_of(f"visemeflow.flows.{'animate' if stage in ('speak', 'preview') else stage}:{stage}_flow")
        name = re.sub(r"\{[^}]*\}", "/tmp/my store", flow.flow_run_name)
        table = Table()
        table.add_column("name")
        table.add_row(name)
        out = io.StringIO()
        Console(file=out, width=200).print(table)
        assert name in out.getvalue(), (stage, name)
