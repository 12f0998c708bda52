"""Prefect's cached task results in a store: JSON data written by every persisted task, read back unchanged."""

import importlib
import json
import pkgutil
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest
from prefect import flow, task
from prefect.cache_policies import INPUTS, TASK_SOURCE
from prefect.tasks import Task

import visemeflow.tasks
from visemeflow.tasks.results import StoreJSONSerializer, check_result_record
from visemeflow.tasks.common import RESULT_SERIALIZER, DataOnlyCache


def test_serializer_round_trips_task_reports():
    when = datetime(2026, 11, 25, 16, 30, tzinfo=timezone.utc)
    report = {"utterance_id": "spk1/a", "frames": 47, "fps": 29.97, "ok": True, "none": None, "nan": float("nan"),
              "rejects": [{"time": when, "message": "bad"}], "files": ("a.glb", "b.usda"),
              "path": Path("/s/a.glb"), "score": np.float32(0.5), "count": np.int64(3)}
    back = StoreJSONSerializer().loads(StoreJSONSerializer().dumps(report))
    assert back.pop("nan") != back.get("nan")  # NaN survives as NaN
    assert back == {"utterance_id": "spk1/a", "frames": 47, "fps": 29.97, "ok": True, "none": None,
                    "rejects": [{"time": when, "message": "bad"}], "files": ["a.glb", "b.usda"],
                    "path": "/s/a.glb", "score": 0.5, "count": 3}
    assert type(back["count"]) is int


def test_serializer_keeps_a_failed_task_exception_as_data():
    """Prefect writes the exception of a failed task as its result: stored as a description, not rebuilt."""
    blob = StoreJSONSerializer().dumps(ValueError("s/a.mp4: no face found"))
    back = StoreJSONSerializer().loads(blob)
    assert back == {"error_type": "builtins.ValueError", "message": "s/a.mp4: no face found"}


@pytest.mark.parametrize(("value", "said"), [
    ({"a": object()}, "result['a'] is a builtins.object"),
    ({"by_shard": {3: 1}}, "result['by_shard'] has a int key 3"),
    ({"curves": np.zeros((2, 16))}, "result['curves'] is a numpy.ndarray"),
])
def test_serializer_refuses_what_json_cannot_hold(value, said):
    with pytest.raises(TypeError, match=said.replace("[", r"\[").replace("]", r"\]")):
        StoreJSONSerializer().dumps(value)


def test_serializer_decodes_only_plain_json():
    """A `__class__` field stays data: nothing is imported or built from a record."""
    blob = json.dumps({"__class__": "os.system", "data": "true", "__exc_type__": "SystemExit"}).encode()
    assert StoreJSONSerializer().loads(blob) == {"__class__": "os.system", "data": "true", "__exc_type__": "SystemExit"}


def _persisted_tasks() -> list[Task]:
    found = []
    for info in pkgutil.iter_modules(visemeflow.tasks.__path__):
        module = importlib.import_module(f"visemeflow.tasks.{info.name}")
        found += [v for v in vars(module).values() if isinstance(v, Task) and v.persist_result]
    return found


def test_every_persisted_task_writes_json_and_checks_records_before_reading():
    tasks = _persisted_tasks()
    assert len(tasks) >= 12
    for t in tasks:
        assert t.result_serializer is RESULT_SERIALIZER, t.name
        assert isinstance(t.cache_policy, DataOnlyCache), t.name


def test_combined_policies_keep_the_check_outermost():
    combined = DataOnlyCache(policy=INPUTS) + TASK_SOURCE
    assert isinstance(combined, DataOnlyCache) and not isinstance(combined.policy, DataOnlyCache)
    assert isinstance(DataOnlyCache(policy=INPUTS) - "device", DataOnlyCache)
    with pytest.raises(TypeError, match="policy="):
        DataOnlyCache(INPUTS)


_calls: list[str] = []


@task(cache_policy=DataOnlyCache(policy=INPUTS + TASK_SOURCE), persist_result=True,
      result_serializer=RESULT_SERIALIZER)
def _report(name: str) -> dict:
    _calls.append(name)
    return {"name": name, "time": datetime(2026, 1, 2, tzinfo=timezone.utc), "sizes": (1, 2)}


@flow
def _report_twice(results: str) -> list:
    # not kept in memory, so the hit is read from the record file
    return [_report.with_options(result_storage=Path(results), cache_result_in_memory=False)(n) for n in ("a", "a")]


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_cache_hit_reads_back_the_json_record(tmp_path):
    _calls.clear()
    first, hit = _report_twice(str(tmp_path / "results"))
    assert _calls == ["a"]
    assert hit == first | {"sizes": [1, 2]}
    records = list((tmp_path / "results").iterdir())
    assert len(records) == 1
    check_result_record(records[0])
