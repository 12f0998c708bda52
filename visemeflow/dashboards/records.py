"""A record, in the store, of the animation packages written outside it (`animate`/`speak --out DIR`), and of the
audio files `predict` read.

The store's own packages are found by listing `animations/`; a package written with `--out` lies wherever the user
asked, so without a record the report cannot list it. `record_packages` (called by the animate flow, which `speak`
runs) keeps one entry per package folder, the latest run's, with the audio it plays; `recorded_packages` gives back
the entries whose folders still exist. The record is one small JSON report file (`reports/packages-outside-store.json`,
through `Store.report_path`), replaced atomically under a store lock, so two `speak` runs at once both land in it.
It keeps the newest `MAX_RECORDED` packages: an old entry falls off rather than the file growing without bound.
No Prefect import: the dashboard reads it without loading the orchestrator.

Predicted curves record only their audio's content hash; `record_predicted_audio` (called by the predict flow) keeps
the path each `predict/<name>` was read from (`reports/predicted-audio.json`, the newest `MAX_RECORDED`), so the
dashboard can draw the curves over their audio; `recorded_predicted_audio` gives back those whose file still exists.
"""

import json
from collections.abc import Iterable, Mapping
from datetime import UTC, datetime
from pathlib import Path

from visemeflow.location import is_url
from visemeflow.storage import Store

RECORD_NAME = "packages-outside-store.json"
PREDICTED_AUDIO_NAME = "predicted-audio.json"
MAX_RECORDED = 1000


def _read(store: Store) -> list[dict]:
    """The stored entries, newest last; an unreadable or foreign file counts as no record (it is rewritten)."""
    try:
        data = json.loads(store.report_path(RECORD_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return []
    entries = data.get("packages") if isinstance(data, dict) else None
    if not isinstance(entries, list):
        return []
    return [e for e in entries if isinstance(e, dict) and isinstance(e.get("folder"), str)
            and isinstance(e.get("utterance_id"), str)]


def record_packages(store: Store, reports: Iterable[Mapping], audio: Mapping[str, str | None] | None = None) -> int:
    """Add the packages of `reports` (the animate task's reports: utterance_id, character, folder) to the record,
    each with the audio file it plays (`audio`, by utterance id); returns how many entries the record now holds."""
    now = datetime.now(UTC).isoformat(timespec="seconds")
    fresh = []
    for r in reports:
        uid = str(r["utterance_id"])
        sound = (audio or {}).get(uid)
        fresh.append({"folder": str(Path(r["folder"]).resolve()), "utterance_id": uid,
                      "character": str(r.get("character") or ""),
                      "audio": (sound if is_url(sound) else str(Path(sound).resolve())) if sound else None,
                      "written": now})
    if not fresh:
        return len(_read(store))
    with store.locked("packages-outside-store"):
        written = {e["folder"] for e in fresh}
        entries = [e for e in _read(store) if e["folder"] not in written] + fresh
        entries = entries[-MAX_RECORDED:]
        store.write_report_text(RECORD_NAME, json.dumps({"packages": entries}, indent=1, ensure_ascii=False))
    return len(entries)


def recorded_packages(store: Store) -> list[dict]:
    """Recorded packages whose folders still exist, newest first, `folder` as a Path (a package moved or deleted
    since is not listed)."""
    return [{**e, "folder": Path(e["folder"])} for e in reversed(_read(store)) if Path(e["folder"]).is_dir()]


def _read_predicted(store: Store) -> dict[str, str]:
    try:
        data = json.loads(store.report_path(PREDICTED_AUDIO_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    audio = data.get("audio") if isinstance(data, dict) else None
    if not isinstance(audio, dict):
        return {}
    return {u: a for u, a in audio.items() if isinstance(u, str) and isinstance(a, str)}


def record_predicted_audio(store: Store, audio: Mapping[str, str]) -> int:
    """Remember the audio file of each predicted utterance (`{utterance_id: path}`); returns the entries kept."""
    fresh = {str(uid): str(Path(path).resolve()) for uid, path in audio.items() if path}
    if not fresh:
        return len(_read_predicted(store))
    with store.locked("predicted-audio"):
        entries = {u: a for u, a in _read_predicted(store).items() if u not in fresh}
        entries.update(fresh)
        entries = dict(list(entries.items())[-MAX_RECORDED:])
        store.write_report_text(PREDICTED_AUDIO_NAME, json.dumps({"audio": entries}, indent=1, ensure_ascii=False))
    return len(entries)


def recorded_predicted_audio(store: Store) -> dict[str, str]:
    """`{utterance_id: path}` of the recorded predicted audio whose file still exists."""
    return {u: a for u, a in _read_predicted(store).items() if Path(a).is_file()}


__all__ = ["MAX_RECORDED", "PREDICTED_AUDIO_NAME", "RECORD_NAME", "record_packages", "record_predicted_audio",
           "recorded_packages", "recorded_predicted_audio"]
