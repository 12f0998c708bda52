"""`visemeflow serve`: a locked-down local Prefect server when none is configured, and a deployment of every stage.

The `pipeline` deployment runs on a cron schedule; since every stage caches on content hashes, a scheduled run
reprocesses only what changed. The other stages and `rerun` (one utterance, one stage) are deployments without a
schedule, run from the UI's forms or `prefect deployment run`. A served deployment's parameters are the fields of its
stage's params model, flat (`--param utterance_id=...`), with the served store as a default that a run naming other
fields keeps (docs/serve.md). prefect.yaml's work-pool deployments (`render_prefect_yaml`) deploy the same flat flows
from visemeflow/ops/pool.py (`pool_flow`).

The server `serve` starts answers only callers holding its auth string, asks every change for a CSRF token, and
allows cross-origin calls from its own UI only. Its database, log and auth string live in `<store>/.prefect-serve/`
(mode 0700; for a store on object storage, in `~/.local/state/visemeflow/serve/<digest of its URL>/` on the machine
serve runs on): two serves never share a database, and a second serve of one store is refused (on that machine). A
served flow run may name paths only under the folders `serve` was started with, and URLs only under its prefixes
(the store's and the corpus's on object storage).
"""

import ctypes
import errno
import fcntl
import functools
import importlib
import inspect
import json
import logging
import os
import secrets
import signal
import socket
import stat
import subprocess
import sys
import _thread
import threading
import warnings
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import Annotated

import httpx
from prefect import Flow
from prefect.deployments.runner import EntrypointType, RunnerDeployment
from prefect.settings import PREFECT_API_AUTH_STRING, PREFECT_API_URL, PREFECT_UI_URL, temporary_settings
from prefect.utilities.callables import parameter_schema
from pydantic import BaseModel, TypeAdapter

from visemeflow.location import is_url, parse_root
from visemeflow.ops.prefect_db import seed_home
from visemeflow.flows.stages import STAGES, Stage
from visemeflow.flows.common import recorded_settings_check
from visemeflow.storage import Store

DEFAULT_CRON = "0 3 * * *"
DEFAULT_PORT = 4200
DEPLOYMENT = "served"
TAGS = ["visemeflow"]
SERVE_DIR = ".prefect-serve"
AUTH_FILE = "auth-string"
LOG_FILE = "server.log"
LOCK_FILE = "serve.lock"
ROOTS_ENV = "VISEMEFLOW_SERVE_ROOTS"
URL_ROOTS_ENV = "VISEMEFLOW_SERVE_URL_ROOTS"   # prefixes on object storage, one a line (a URL holds `:`)
PR_SET_PDEATHSIG = 1  # linux/prctl.h
# What the UI sends (prefect/server/ui assets); cross-origin only from the UI's own origin.
CORS_METHODS = "GET,POST,PUT,PATCH,DELETE"
CORS_HEADERS = "Authorization,Content-Type,X-Prefect-UI,Prefect-Csrf-Token,Prefect-Csrf-Client,Prefect-Csrf-Retry-Count"

# String fields naming a local folder or else a hub id (TrainConfig): checked as paths when they name a local one.
PATH_OR_NAME = frozenset({"wav2vec2_model", "whisper_source"})

# The served deployments' entrypoints: `visemeflow.ops.serve.<name>` (see `__getattr__`), module of each stage's flow.
SERVED_FLOWS = {stage.flow_attr: stage.module for stage in STAGES}
# The work-pool deployments' entrypoints (prefect.yaml): `visemeflow/ops/pool.py:<name>`, the same flat flows.
POOL_MODULE = "visemeflow.ops.pool"
POOL_NAME = "pool"


class ServerStartError(RuntimeError):
    """The local Prefect server was not started, or did not answer its health check; the message says why."""


class PathOutsideRootsError(ValueError):
    """A served flow run names a path outside the folders `visemeflow serve` was started with."""


Root = Path | str
"""Where served runs may name inputs and outputs: a folder, or a prefix on object storage (`s3://bucket/store`)."""


def _location(value: Path | str) -> Path | str:
    """A store or corpus as given: a URL stays text (normalised), a path is resolved."""
    return parse_root(str(value)) if is_url(str(value)) else Path(value).resolve()


def last_ingested_corpus(store: Path | str) -> Path | str | None:
    """The corpus the store's last ingest run read, if any (its URL where it lies on object storage)."""
    run = Store(store).read_run_config("ingest")
    return _location(run["corpus"]) if run and run.get("corpus") else None


# The stages whose served deployments take the settings they last ran with (`configs/<stage>.json`) as their
# defaults, and for the pipeline, which of its fields each stage's recorded config fills.
RECORDED_DEFAULTS = ("ingest", "procedural", "landmarks", "track")
PIPELINE_FIELDS = {"ingest": "ingest", "procedural": "procedural", "landmarks": "landmarks", "track": "tracking"}


def recorded_settings(store: Root) -> dict[str, dict]:
    """The settings of `RECORDED_DEFAULTS`' stages as the store records them ({} for a stage that never ran); a
    store that cannot be read now gives {} with a warning (the deployments then have the code's defaults)."""
    try:
        read = Store(store).read_run_config
        return {stage: settings for stage in RECORDED_DEFAULTS if (settings := read(stage))}
    except Exception as exc:  # noqa: BLE001 - an object store's client raises its own types (no credentials, ...)
        logging.getLogger(__name__).warning("the settings recorded in %s cannot be read (%s): the served "
                                            "deployments get the code's defaults", store, exc)
        return {}


def recorded_defaults(recorded: dict[str, dict], stage: str) -> dict:
    """The served deployment's defaults for `stage` from the settings the store's stages last ran with
    (`recorded_settings`): their configs (and shard count, and the procedural variant), never a path. A schedule
    made with the defaults of the code would run `pipeline --fps 25 --tolerance 0.5` of yesterday at 30 fps and
    0.1 s: every utterance read again, and the curves of another rate. Nothing recorded: {} (the code's defaults)."""
    read = recorded.get
    if stage == "pipeline":
        out: dict = {}
        for name, field in PIPELINE_FIELDS.items():
            settings = read(name)
            if settings and settings.get("config") is not None:
                out[field] = settings["config"]
        ingest = read("ingest")
        if ingest and ingest.get("n_shards"):
            out["n_shards"] = ingest["n_shards"]
        return out
    if stage not in RECORDED_DEFAULTS:
        return {}
    settings = read(stage) or {}
    keys = ("config", "n_shards", "variant") if stage == "procedural" else ("config", "n_shards")
    return {k: settings[k] for k in keys if settings.get(k) is not None}


# The recorded defaults each served deployment was given when `serve` started (`build_deployments`): stage ->
# (its store, those defaults); `serve` hands them to the processes that run its flows in GIVEN_ENV (JSON). A run that
# leaves such a field as serve gave it takes what the store records at the run's start instead (`settings_now`).
_SERVE_START: dict[str, tuple[str, dict]] = {}
GIVEN_ENV = "VISEMEFLOW_SERVE_GIVEN"


@contextmanager
def using_given_defaults() -> Iterator[None]:
    """Flow runs of this process's deployments (processes it starts) know the defaults `build_deployments` gave."""
    with _environment({GIVEN_ENV: json.dumps({k: list(v) for k, v in _SERVE_START.items()})}):
        yield


def _serve_start() -> dict[str, tuple[str, dict]]:
    raw = os.environ.get(GIVEN_ENV)
    if not raw:
        return _SERVE_START
    try:
        return {k: (str(v[0]), dict(v[1])) for k, v in json.loads(raw).items()}
    except (ValueError, TypeError, IndexError, AttributeError):   # not ours: as if none were given
        return {}


def _auto_scheduled() -> bool:
    """Whether the flow run this code runs in was made by its deployment's schedule (not by hand)."""
    from prefect.context import FlowRunContext

    context = FlowRunContext.get()
    return bool(context and context.flow_run and context.flow_run.auto_scheduled)


def settings_now(stage: str, fields: dict, model: type[BaseModel]) -> dict:
    """`fields` of a scheduled run of `stage` served by `serve`, with the fields of `recorded_defaults` replaced by
    what the store records now, where the run leaves all of them as `serve` set them at its start (the recorded
    values then, or the code's defaults where nothing was recorded). The nightly pipeline after `pipeline --fps 25`
    by hand runs at 25 fps, even when serve started at 30. A run started by hand runs what its form says; a schedule
    whose defaults someone edited in the UI keeps them all (the settings are taken as one set, never mixed: a
    procedural config with another config's variant name). Settings the store records that do not validate, a store
    that cannot be read now, fields of another store, a stage serve gave no defaults: the fields as they are."""
    start = _serve_start().get(stage)
    if start is None or str(fields.get("store")) != str(start[0]) or not _auto_scheduled():
        return fields
    store, given = start
    try:
        now = recorded_defaults(recorded_settings(store), stage)
        changed = {}
        for key in sorted(set(now) | set(given)):
            field = model.model_fields.get(key)
            if key not in fields or field is None:
                continue
            adapter = TypeAdapter(Annotated[field.annotation, *field.metadata] if field.metadata   # its bounds
                                  else field.annotation)
            was = given[key] if key in given else field.get_default(call_default_factory=True)
            value = now[key] if key in now else field.get_default(call_default_factory=True)
            if adapter.dump_json(adapter.validate_python(fields[key])) != adapter.dump_json(
                    adapter.validate_python(was)):
                return fields   # someone chose this run's settings: as they are
            if adapter.dump_json(adapter.validate_python(value)) != adapter.dump_json(adapter.validate_python(was)):
                changed[key] = value
    except Exception as exc:  # noqa: BLE001 - a store config edited by hand, an unreadable store: the run as given
        logging.getLogger(__name__).warning("%s: the settings %s records now are not used (%s: %s); the run has the "
                                            "settings serve started with", stage, store, type(exc).__name__, exc)
        return fields
    return {**fields, **changed}


def serve_roots(store: Root, corpus: Root | None, extra: Sequence[Path] = ()) -> list[Root]:
    """Where served flow runs may name paths: the store, the corpus (a manifest's folder) and `extra` folders;
    a store or corpus on object storage is its URL prefix (a manifest's: the prefix it lies under)."""
    roots: list[Root] = [_location(store), *(Path(p).resolve() for p in extra)]
    if corpus is not None:
        corpus = _location(corpus)
        if isinstance(corpus, str):
            roots.append(corpus.rsplit("/", 1)[0] if corpus.lower().endswith(".csv") else corpus)
        else:
            roots.append(corpus.parent if corpus.is_file() else corpus)
    folders = sorted({r for r in roots if isinstance(r, Path)})
    return [*folders, *sorted({r for r in roots if isinstance(r, str)})]


def roots_from_environment() -> list[Root]:
    folders = [Path(p) for p in os.environ.get(ROOTS_ENV, "").split(os.pathsep) if p]
    return [*folders, *(u for u in os.environ.get(URL_ROOTS_ENV, "").splitlines() if u.strip())]


@contextmanager
def using_roots(roots: Sequence[Root]) -> Iterator[None]:
    """Served flow runs (processes this one starts) may name paths under `roots` only."""
    with _environment({ROOTS_ENV: os.pathsep.join(str(r) for r in roots if isinstance(r, Path)),
                       URL_ROOTS_ENV: "\n".join(r for r in roots if isinstance(r, str))}):
        yield


def _leaves(value: object, name: str, field: str | None = None) -> Iterator[tuple[str, object, str | None]]:
    """Every leaf inside a parameter value (pydantic models, lists, dicts), with where it sits (`params.store`) and
    the model field that holds it directly (None inside a list or dict)."""
    if isinstance(value, BaseModel):
        for key in type(value).model_fields:
            yield from _leaves(getattr(value, key), f"{name}.{key}", key)
    elif isinstance(value, Mapping):
        for key, item in value.items():
            yield from _leaves(item, f"{name}[{key!r}]")
    elif isinstance(value, (list, tuple, set, frozenset)):
        for i, item in enumerate(value):
            yield from _leaves(item, f"{name}[{i}]")
    else:
        yield name, value, field


def urls_in(value: object, name: str) -> Iterator[tuple[str, str]]:
    """Every URL (text with a scheme, `s3://...`) inside a parameter value, with where it sits."""
    return ((where, leaf) for where, leaf, _ in _leaves(value, name) if isinstance(leaf, str) and is_url(leaf))


def _under_prefix(url: str, prefixes: Sequence[str]) -> bool:
    """`url` is one of `prefixes` or lies below one, with no `.` or `..` segment (a key may hold them literally,
    and a reader that resolves them would leave the prefix)."""
    scheme, _, rest = url.partition("://")
    if any(part in (".", "..") for part in rest.split("/")):
        return False
    text = f"{scheme.lower()}://{rest}".rstrip("/")
    return any(text == p.rstrip("/") or text.startswith(p.rstrip("/") + "/") for p in prefixes)


def paths_in(value: object, name: str) -> Iterator[tuple[str, Path]]:
    """Every path inside a parameter value (pydantic models, lists, dicts), with where it sits (`params.store`)."""
    for where, leaf, field in _leaves(value, name):
        if isinstance(leaf, PurePath):
            yield where, Path(leaf)
        elif field in PATH_OR_NAME and isinstance(leaf, str) and _local_path(leaf):
            yield where, Path(leaf).expanduser()


def _local_path(text: str) -> bool:
    return text.startswith(("/", "~", ".")) or Path(text).expanduser().exists()


def check_paths_within(parameters: Mapping[str, object], roots: Sequence[Root]) -> None:
    """PathOutsideRootsError for the first path parameter outside the folders of `roots` (the shipped demo rig is
    always allowed), the first URL outside its prefixes (`s3://bucket/store`), or a Dask scheduler's address."""
    from visemeflow.rig import demo_rig_path

    prefixes = [r for r in roots if isinstance(r, str)]
    roots = [r for r in roots if isinstance(r, Path)]
    for name, value, field in (found for key, value in parameters.items() for found in _leaves(value, key)):
        if field == "dask_address" and value:   # `host:port` has no scheme, yet Dask connects to it
            raise PathOutsideRootsError(
                f"flow parameter {name} = {value}: a served run sends no work to a Dask scheduler named in its "
                f"parameters (its tasks would run, and read the store, on that host); use runner.kind dask for a "
                f"local cluster, or run `visemeflow pipeline --dask-address` from the command line")
    for name, url in (found for key, value in parameters.items() for found in urls_in(value, key)):
        if not _under_prefix(url, prefixes):
            allowed = ", ".join(prefixes) or "none"
            raise PathOutsideRootsError(
                f"flow parameter {name} = {url} is outside the prefixes on object storage `visemeflow serve` was "
                f"started with ({allowed}; {URL_ROOTS_ENV}); serve that store, or run it from the command line")
    shipped = {demo_rig_path().resolve()}
    for name, path in (found for key, value in parameters.items() for found in paths_in(value, key)):
        resolved = path.resolve()  # through links: a link inside a root to a file elsewhere is elsewhere
        if resolved in shipped or any(resolved.is_relative_to(root) for root in roots):
            continue
        allowed = ", ".join(map(str, roots)) or f"none, {ROOTS_ENV} is not set: these entrypoints run under `serve`"
        shown = path if resolved == path else f"{path} (resolved {resolved})"
        raise PathOutsideRootsError(
            f"flow parameter {name} = {shown} is outside the folders `visemeflow serve` was started with "
            f"({allowed}); restart serve with `--root FOLDER` to allow another folder")


def flat_signature(model: type[BaseModel]) -> inspect.Signature:
    """One keyword parameter per field of `model`, with its type, constraints, description and default.

    Why flat: Prefect merges a run's parameters over its deployment's defaults one top-level name at a time and the
    CLI accepts only top-level names, so with a single `params` object `prefect deployment run --param
    utterance_id=...` was refused and a partial `--params '{"params": {...}}'` replaced the whole object, dropping
    the store `serve --store` had set. Flat, each field is merged on its own and the served store stays unless named.
    """
    parameters = []
    for name, info in model.model_fields.items():
        annotation = Annotated[(info.annotation, *info.metadata)] if info.metadata else info.annotation
        default = (inspect.Parameter.empty if info.is_required()
                   else info.get_default(call_default_factory=True, validated_data={}))
        parameters.append(inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, annotation=annotation,
                                            default=default))
    return inspect.Signature(parameters)


def documented(doc: str | None, model: type[BaseModel]) -> str:
    """`doc` with an `Args:` section describing each field of `model`: Prefect's forms take a parameter's
    description from its flow's docstring."""
    lines = [f"    {name}: {' '.join(info.description.split())}" for name, info in model.model_fields.items()
             if info.description]
    return "\n\n".join(part for part in (inspect.cleandoc(doc or ""), "Args:\n" + "\n".join(lines) if lines else "")
                       if part)


def params_model(fn: Callable) -> type[BaseModel]:
    """The pydantic model of a stage flow's single parameter `params`."""
    (parameter,) = inspect.signature(fn, eval_str=True).parameters.values()  # annotations may be strings
    return parameter.annotation


# The fields of recorded stage settings (`flows.params.SETTINGS`) that name files or folders; `rig` may be a name.
RECORDED_PATHS = frozenset({"corpus", "characters", "mapping", "out", "takes", "channel_table", "names", "rig"})


def check_settings_within(stage: str, settings: BaseModel, roots: Sequence[Root]) -> None:
    """PathOutsideRootsError for the first path of the settings `stage` last ran with (read from the store, as a
    served `rerun` repeats them) outside `roots`: a store's `configs/<stage>.json` written by a run from the command
    line, or by anyone who can write into the store, must not take a served run outside serve's folders."""
    named: dict[str, object] = {}
    for field in RECORDED_PATHS & set(type(settings).model_fields):
        value = getattr(settings, field)
        for i, text in enumerate(value if isinstance(value, list) else [value]):
            if not isinstance(text, str) or not text or (field == "rig" and not _local_path(text)):
                continue
            where = f"{field}[{i}]" if isinstance(value, list) else field
            named[where] = text if is_url(text) else Path(text).expanduser()
    try:
        check_paths_within(named, roots)
    except PathOutsideRootsError as exc:
        raise PathOutsideRootsError(
            f"the settings {stage} last ran with (configs/{stage}.json in the store), which this run repeats: "
            + str(exc).removeprefix("flow parameter ")) from None


def served_run_name(template: object) -> object:
    """The stage's run name template on flat parameters: `rerun({params.utterance_id})` -> `rerun({utterance_id})`."""
    return template.replace("{params.", "{") if isinstance(template, str) else template


def flat_flow(flow: Flow, module: str, roots: Callable[[], Sequence[Root] | None]) -> Flow:
    """A copy of a stage's `flow` whose parameters are the fields of its `params` model (`flat_signature`), named
    as the stage and importable as `module.<attribute>`: it builds the model from the flat fields, checks every path
    in it against `roots()` (None: no check) before it runs a line of the stage, and calls the stage with it.

    Serve's confined copies (`confined`) and the work-pool entrypoints of prefect.yaml (`pool_flow`) are both this.
    """
    fn = flow.fn
    model = params_model(fn)

    @functools.wraps(fn)
    def checked(**fields):
        params = model.model_validate(settings_now(flow.name, fields, model))
        allowed = roots()
        if allowed is None:
            return fn(params)
        check_paths_within(dict(params), allowed)
        token = recorded_settings_check.set(lambda stage, settings: check_settings_within(stage, settings, allowed))
        try:
            return fn(params)
        finally:
            recorded_settings_check.reset(token)

    checked.__signature__ = flat_signature(model)  # Prefect's form, validation and CLI read this signature
    checked.__annotations__ = {}  # not the stage's `params: Model`, which `functools.wraps` copied
    checked.__doc__ = documented(fn.__doc__, model)
    del checked.__wrapped__  # else inspect.signature would follow it back to the stage's `params`
    copy = flow.with_options(flow_run_name=served_run_name(flow.flow_run_name))
    copy.fn = checked
    copy.__wrapped__, copy.__doc__ = checked, checked.__doc__  # `to_deployment` reads the schema off the flow itself
    copy.parameters = parameter_schema(checked)
    copy.__module__ = module  # the deployment's entrypoint: a run started from the database gets this copy too
    return copy


def confined(flow: Flow) -> Flow:
    """The served copy of `flow` (`flat_flow`), importable from this module, that checks every path among its
    parameters against ROOTS_ENV (unset: none is allowed) before it runs a line of the stage."""
    return flat_flow(flow, __name__, roots_from_environment)


def roots_if_set() -> list[Root] | None:
    """The pool entrypoints' roots: ROOTS_ENV's folders (and URL_ROOTS_ENV's prefixes) where the worker's
    environment sets either, else no check."""
    return roots_from_environment() if os.environ.get(ROOTS_ENV) or os.environ.get(URL_ROOTS_ENV) else None


def stage_flow(name: str) -> Flow:
    """A stage's own flow, by the name of the flow object (`procedural_flow`); imports its module."""
    return getattr(importlib.import_module(SERVED_FLOWS[name]), name)


@functools.cache
def served_flow(name: str) -> Flow:
    """The confined copy of a stage's flow, by the name of the flow object (`procedural_flow`)."""
    return confined(stage_flow(name))


@functools.cache
def pool_flow(name: str) -> Flow:
    """The flat copy of a stage's flow that prefect.yaml deploys (`visemeflow/ops/pool.py:procedural_flow`); it
    checks paths only where the worker's environment sets ROOTS_ENV (`roots_if_set`)."""
    return flat_flow(stage_flow(name), POOL_MODULE, roots_if_set)


def __getattr__(name: str) -> Flow:
    """`visemeflow.ops.serve.procedural_flow` and the like: the entrypoints Prefect's engine imports for a served run."""
    if name in SERVED_FLOWS:
        return served_flow(name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def build_deployments(
    store: Root, corpus: Root | None, cron: str | None = DEFAULT_CRON, timezone: str = "UTC",
) -> list[RunnerDeployment]:
    """A deployment of every stage of `STAGES` (the pipeline on `cron` in `timezone`); the store is their default.
    Each runs the stage confined to the folders `serve` allows (`confined`).

    Without `corpus`, the pipeline and ingest deployments default to the corpus the store last ingested; with
    neither, they have no default corpus and the pipeline no schedule (a run would have nothing to read). The
    pipeline and the stages it runs default to the settings the store's stages last ran with (`recorded_defaults`).
    """
    from prefect.schedules import Cron

    store = _location(store)
    corpus = _location(corpus) if corpus else last_ingested_corpus(store)
    on_store = {"store": str(store)}
    on_corpus = {"store": str(store), "corpus": str(corpus)} if corpus else on_store
    recorded = recorded_settings(store)

    def deployment(stage: Stage) -> RunnerDeployment:
        scheduled = stage.scheduled and corpus and cron
        given = recorded_defaults(recorded, stage.name)
        if stage.name in RECORDED_DEFAULTS or stage.name == "pipeline":
            _SERVE_START[stage.name] = (str(store), given)
        parameters = {**(on_corpus if stage.on_corpus else on_store), **given}
        return served_flow(stage.flow_attr).to_deployment(
            DEPLOYMENT, parameters=parameters, tags=TAGS,
            entrypoint_type=EntrypointType.MODULE_PATH, description=stage.description or None,
            schedule=Cron(cron, timezone=timezone) if scheduled else None,
            concurrency_limit=1 if stage.scheduled else None,
        )

    return [deployment(stage) for stage in STAGES]


PREFECT_YAML_HEAD = """\
# The deployments `visemeflow serve` serves from one process, for a work pool and its workers instead.
# Made from visemeflow/flows/stages.py by `visemeflow.ops.serve.render_prefect_yaml` (tests/test_serve.py checks
# that this file is what it renders). From the repository root, with a server running and PREFECT_API_URL
# pointing at it:
#
#   .venv/bin/prefect work-pool create visemeflow --type process
#   .venv/bin/prefect --no-prompt deploy --all
#   .venv/bin/prefect worker start --pool visemeflow
#
# As with `serve`, each deployment's parameters are the fields of its stage's params model, flat, and a run that
# names some of them keeps the others' defaults below (the store among them):
#
#   .venv/bin/prefect deployment run 'rerun/pool' --param utterance_id=spk1/utt001 --param stage=track
#   .venv/bin/prefect deployment run 'pipeline/pool' --param n_shards=16
#
# With no pull step given, `prefect deploy` records the folder it ran in as the workers' working directory, so the
# relative paths below are relative to the repository root. Every stage caches on content hashes: the scheduled
# pipeline run reprocesses only what changed. Deployments are named `pool` (`pipeline/pool`, `rerun/pool`, ...),
# the served ones `served`, so both can live on one server. The entrypoints (visemeflow/ops/pool.py) check the
# paths a run names only where the worker's environment sets VISEMEFLOW_SERVE_ROOTS (folders, `:`-separated).
"""


def pool_entrypoint(stage: Stage) -> str:
    """`visemeflow/ops/pool.py:rerun_flow`: the stage's flat flow, as prefect.yaml names it."""
    return f"{POOL_MODULE.replace('.', '/')}.py:{stage.flow_attr}"


def render_prefect_yaml(store: str = "visemeflow-out/store", corpus: str = "visemeflow-out/demo-corpus") -> str:
    """prefect.yaml: a `pool` deployment of every stage of `STAGES` on the `visemeflow` work pool, the pipeline on
    DEFAULT_CRON (UTC). Its entrypoint is the stage's flat flow in visemeflow/ops/pool.py (`pool_flow`), its default
    parameters `store` (and `corpus` where the stage reads one), flat as the served deployments'."""
    import prefect
    import yaml

    deployments = []
    for stage in STAGES:
        params = {"store": store, **({"corpus": corpus} if stage.on_corpus else {})}
        d: dict = {"name": POOL_NAME, "entrypoint": pool_entrypoint(stage)}
        if stage.description:
            d["description"] = stage.description
        d.update({"tags": list(TAGS), "parameters": params})
        if stage.scheduled:
            d["schedules"] = [{"cron": DEFAULT_CRON, "timezone": "UTC"}]
            d["concurrency_limit"] = 1
        d["work_pool"] = {"name": "visemeflow", "job_variables": {}}
        deployments.append(d)
    body = {"name": "visemeflow", "prefect-version": prefect.__version__, "build": None, "push": None, "pull": None,
            "deployments": deployments}
    return PREFECT_YAML_HEAD + yaml.safe_dump(body, sort_keys=False, width=120)


def ui_url(api_url: str) -> str:
    """The UI address of a Prefect API: the configured PREFECT_UI_URL, else the API address without `/api`."""
    configured = PREFECT_UI_URL.value()
    if configured:
        return str(configured)
    return api_url.rstrip("/").removesuffix("/api")


def api_healthy(api_url: str) -> bool:
    try:
        return httpx.get(f"{api_url.rstrip('/')}/health", timeout=2.0).status_code == 200
    except httpx.HTTPError:
        return False


@contextmanager
def _environment(values: Mapping[str, str]) -> Iterator[None]:
    before = {name: os.environ.get(name) for name in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for name, value in before.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


@contextmanager
def using_api(api_url: str, auth_string: str) -> Iterator[str]:
    """This process and the processes it starts (served flow runs, Dask workers) talk to `api_url` with its auth
    string."""
    with _environment({"PREFECT_API_URL": api_url, "PREFECT_API_AUTH_STRING": auth_string}):
        with temporary_settings(updates={PREFECT_API_URL: api_url, PREFECT_API_AUTH_STRING: auth_string}):
            yield api_url


@dataclass(frozen=True)
class ServedApi:
    """The API serve's processes talk to; `log` and `auth_file` are set for a server serve started itself."""

    url: str
    log: Path | None = None
    auth_file: Path | None = None  # none either when PREFECT_API_AUTH_STRING gave the auth string


def server_environment(home: Path, port: int, auth_string: str, ui_api_url: str | None = None) -> dict[str, str]:
    """Settings of the server serve starts: its own Prefect home, basic auth, CSRF tokens, CORS for its UI only.

    `ui_api_url`: the API address the UI calls when it is not this machine's (a reverse proxy's `https://host/api`).
    """
    origins = f"http://127.0.0.1:{port},http://localhost:{port}"
    return {
        "PREFECT_HOME": str(home),
        # the UI is served with the API address it calls; without this it calls port 4200 whatever `port` is
        "PREFECT_SERVER_UI_API_URL": ui_api_url or f"http://127.0.0.1:{port}/api",
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
        "PREFECT_SERVER_API_AUTH_STRING": auth_string,
        "PREFECT_SERVER_API_CSRF_PROTECTION_ENABLED": "true",
        "PREFECT_SERVER_API_CORS_ALLOWED_ORIGINS": origins,
        "PREFECT_SERVER_API_CORS_ALLOWED_METHODS": CORS_METHODS,
        "PREFECT_SERVER_API_CORS_ALLOWED_HEADERS": CORS_HEADERS,
    }


def port_in_use(port: int) -> bool:
    with socket.socket() as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds: TIME_WAIT leaves it free
        try:
            probe.bind(("127.0.0.1", port))
        except OSError:
            return True
    return False


def private_folder(folder: Path) -> Path:
    """`folder`, made with mode 0700 or checked: a real folder of this user (no link), that only this user enters."""
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    info = os.lstat(folder)
    if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid():
        raise ServerStartError(f"{folder} must be a folder of this user, not a link or another user's: serve keeps "
                               "its Prefect database, log and auth string there")
    os.chmod(folder, 0o700)
    return folder


def write_private(path: Path, text: str) -> Path:
    """`text` in a new file of mode 0600 replacing `path` (a link there is replaced, never followed)."""
    temporary = path.with_name(f".{path.name}.{secrets.token_hex(8)}")
    fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
    with os.fdopen(fd, "w") as out:
        out.write(text)
    os.replace(temporary, path)
    return path


@contextmanager
def home_lock(home: Path) -> Iterator[None]:
    """Held while a serve runs on `home`: a second serve there would share its database and re-point its
    deployments (the scheduled pipeline included) at its own store."""
    fd = os.open(home / LOCK_FILE, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            raise ServerStartError(
                f"another `visemeflow serve` (pid {holder}) runs on this store: its Prefect database in {home} holds "
                "that serve's deployments, which a second serve would re-point; stop it first, or serve another "
                "store") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        yield
    finally:
        os.close(fd)


def _dies_with_parent() -> Callable[[], None] | None:
    """A preexec_fn asking Linux to SIGKILL the child when this thread's process dies, even by kill -9."""
    if sys.platform != "linux":
        return None
    prctl = ctypes.CDLL(None, use_errno=True).prctl  # looked up before the fork: the child only calls it
    parent = os.getpid()

    def preexec() -> None:
        if prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL)) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
        if os.getppid() != parent:  # serve died before the request took effect: nobody would stop this server
            os._exit(1)

    return preexec


def start_server(home: Path, port: int, auth_string: str) -> tuple[subprocess.Popen, Path]:
    """`prefect server start` on 127.0.0.1:`port`, locked down, logging to `home`/server.log; killed with this
    process. The caller's thread must outlive the server: Linux sends the signal when the forking thread ends."""
    log = home / LOG_FILE
    ui_api_url = os.environ.get("PREFECT_SERVER_UI_API_URL") or os.environ.get("PREFECT_UI_API_URL")
    seed_home(home)   # a new home's database from the migrated template: no migrations at its first start
    log.unlink(missing_ok=True)
    out = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
    try:
        # its own session, so Ctrl-C in the terminal reaches serve, which stops the server in order
        process = subprocess.Popen(
            [sys.executable, "-m", "prefect", "server", "start", "--host", "127.0.0.1", "--port", str(port)],
            stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True,
            env={**os.environ, **server_environment(home, port, auth_string, ui_api_url)},
            preexec_fn=_dies_with_parent(),
        )
    finally:
        os.close(out)
    return process, log


@contextmanager
def ensure_server(home: Path, port: int = DEFAULT_PORT, timeout_s: float = 180.0) -> Iterator[ServedApi]:
    """The configured Prefect API; else a locked-down `prefect server start` on 127.0.0.1:`port` for the block, its
    database, log and auth string in `home` (PREFECT_API_AUTH_STRING, else a new random one).

    A port already in use is refused rather than shared: another serve's server there holds its own deployments.
    """
    configured = PREFECT_API_URL.value()
    if configured:
        yield ServedApi(str(configured))
        return
    api_url = f"http://127.0.0.1:{port}/api"
    if port_in_use(port):
        raise ServerStartError(f"port {port} on 127.0.0.1 is in use (another `visemeflow serve`?); choose another "
                               "--port, or set PREFECT_API_URL and PREFECT_API_AUTH_STRING to use the server there")
    home = private_folder(home)
    with home_lock(home):
        given = PREFECT_API_AUTH_STRING.value()
        if given:
            auth_string, auth_file = given, None
            (home / AUTH_FILE).unlink(missing_ok=True)  # an earlier serve's would no longer let anyone in
        else:
            auth_string = f"visemeflow:{secrets.token_urlsafe(32)}"
            auth_file = write_private(home / AUTH_FILE, auth_string)
        process, log = start_server(home, port, auth_string)
        try:
            wait_until_healthy(api_url, process, log, timeout_s)
            with using_api(api_url, auth_string):
                yield ServedApi(api_url, log, auth_file)
        finally:
            stop_server(process)


def wait_until_healthy(api_url: str, process: subprocess.Popen, log: Path, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise ServerStartError(f"prefect server exited with code {process.returncode}; its log {log}:\n"
                                   f"{_tail(log)}")
        if api_healthy(api_url):
            return
        time.sleep(0.25)
    stop_server(process)
    raise ServerStartError(f"prefect server did not answer {api_url}/health within {timeout_s:.0f} s; its log {log}:\n"
                           f"{_tail(log)}")


def stop_server(process: subprocess.Popen, grace_s: float = 15.0) -> None:
    """SIGTERM to the server's process group, SIGKILL after `grace_s`."""
    if process.poll() is not None:
        return
    for sig, wait in ((signal.SIGTERM, grace_s), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            return
        try:
            process.wait(timeout=wait)
            return
        except subprocess.TimeoutExpired:
            continue


def _tail(log: Path, lines: int = 30) -> str:
    try:
        return "\n".join(log.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"


@contextmanager
def serving(store: Root) -> Iterator[None]:
    """Held while serve runs on a store on object storage: one serve of a bucket store at a time on any machine (its
    lease in the store, `Store.held`). Two would each schedule the pipeline and hold their own deployments. A
    folder store is guarded by `home_lock` on its database (in the store)."""
    if isinstance(store, Path):
        yield
        return
    from visemeflow.storage import Store, StoreError

    with ExitStack() as stack:
        try:
            stack.enter_context(Store(store).held("serve", f"the store {store}"))
        except StoreError as exc:
            if exc.errno != errno.EBUSY:
                raise
            raise ServerStartError(f"another `visemeflow serve` runs on this store: {exc.strerror}; stop it first, "
                                   "or serve another store") from None
        yield


def serve_home(store: Root) -> Path:
    """Where serve keeps the Prefect database, log and auth string of `store`: `<store>/.prefect-serve/`, or for a
    store on object storage a folder of this user's on this machine named by the URL's digest."""
    if isinstance(store, Path):
        return store / SERVE_DIR
    import hashlib

    state = Path(os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state")
    return state / "visemeflow" / "serve" / hashlib.blake2b(store.encode(), digest_size=12).hexdigest()


def serve_stages(store: Root, corpus: Root | None, cron: str | None = DEFAULT_CRON, timezone: str = "UTC",
                 port: int = DEFAULT_PORT, echo=print, roots: Sequence[Path] = ()) -> None:
    """Serve every deployment until interrupted, with a local server unless PREFECT_API_URL names one; flow runs may
    name paths under the store, the corpus and `roots` only (URLs under the store's and the corpus's prefixes)."""
    from prefect import serve

    def stop(signum: int, frame: object) -> None:  # systemd and `kill` stop with SIGTERM: leave like Ctrl-C does
        raise SystemExit(0)

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, stop)  # until Prefect's runner installs its own, which also exits
    store = _location(store)
    corpus = _location(corpus) if corpus else last_ingested_corpus(store)
    allowed = serve_roots(store, corpus, roots)
    with serving(store), ensure_server(serve_home(store), port) as api, using_roots(allowed):
        deployments = build_deployments(store, corpus, cron, timezone)
        pipeline = deployments[0]
        echo(f"Prefect UI: {ui_url(api.url)}  (API {api.url})")
        if api.log:
            echo(f"server log: {api.log}")
            echo(f"UI login: the auth string in {api.auth_file} (new at every start)" if api.auth_file
                 else "UI login: the auth string in PREFECT_API_AUTH_STRING")
        echo("flow runs may name paths under: " + ", ".join(map(str, allowed)))
        if pipeline.schedules:
            echo(f"pipeline on {pipeline.parameters['corpus']}: cron '{cron}' ({timezone})")
        else:
            echo("pipeline: no schedule (no --corpus and the store has no ingest run); run it from the UI")
        # Prefect's starting message below ends with `prefect deployment run ...`, which another shell can only run
        # with this server's address (and auth string): say how, first
        auth = (f"; export PREFECT_API_AUTH_STRING=\"$(cat {api.auth_file})\"" if api.auth_file else "")
        echo(f"for `prefect deployment run` in another shell: export PREFECT_API_URL={api.url}{auth}  "
             "(docs/serve.md lists every deployment's parameters)")
        echo("stop with Ctrl-C")
        # Prefect's runner answers SIGTERM (systemd's stop) by calling its async `stop` from a sync handler without
        # awaiting it: "RuntimeWarning: coroutine 'Runner.astop' was never awaited" and a tracemalloc hint, on a
        # shutdown that otherwise goes well (the deployments are paused, the process exits 0)
        warnings.filterwarnings("ignore", message="coroutine 'Runner.astop' was never awaited", category=RuntimeWarning)
        with _sigterm_until_gone(), using_given_defaults():   # its runs take the store's settings of their day
            serve(*deployments, print_starting_message=True)


@contextmanager
def _sigterm_until_gone(every_s: float = 3.0):
    """Prefect's runner leaves on SIGTERM by `sys.exit(0)` in its handler; when the signal lands while Python runs
    an object's `__del__` (an asyncio transport's, often), that SystemExit is "ignored" and `serve` ran on: systemd's
    stop hung until its SIGKILL (tests/test_serve.py, about one stop in three once the scheduler made runs). So a
    first SIGTERM starts a thread that sends it again every `every_s` seconds until `serve` has returned; the
    server's own stop after it then runs to its end whatever SIGTERM comes."""
    from prefect.runner import Runner

    original = Runner.handle_sigterm
    started, done = threading.Event(), threading.Event()

    def again() -> None:
        while not done.wait(every_s):
            _thread.interrupt_main(signal.SIGTERM)     # Python's handler again, in the main thread

    def handle_sigterm(self, *args, **kwargs):
        if not started.is_set():
            started.set()
            threading.Thread(target=again, name="sigterm-again", daemon=True).start()
        original(self, *args, **kwargs)

    Runner.handle_sigterm = handle_sigterm
    try:
        yield
    finally:
        # leaving: a SIGTERM sent again now would land in the server's stop below (Prefect's handler then called its
        # runner's stop on a closed loop and the process exited 1), so from here SIGTERM waits for the stop to end
        if started.is_set() and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, lambda signum, frame: None)
        done.set()
        Runner.handle_sigterm = original
