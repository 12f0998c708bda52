"""The `evaluate` flow: models judged on the validation set and on augmented copies of it (paper 5.2, Tables 1-3),
by L1 x 100 against the target curves and, on validation utterances with phones, by real-speech metrics that need
no curve truth (closure recall of MBP and FFF, activation agreement: `visemeflow.learning.realspeech`), and by
what the viewer sees of the same curves: lips closed at b/p/m, lip-teeth contact at f/v and the vowel opening,
measured in millimetres on the demo character's mesh after the closure rule (`visemeflow.learning.lipscore`). The
report opens with one line per model that puts the top-viseme closure score beside the lips on the mesh (a constant
mean curve can top every b/p/m with MBP and still never close the mouth).

The name `phones` joins the models as the baseline that needs no training (curves of phones recognised in the
audio; `visemeflow.tasks.models`).

Models run on `params.device` in float32; the device is not part of the evaluation tasks' cache key (metrics computed
on the CPU stay valid for a GPU run). A device this machine does not have fails first, in one line.

A model that is not in the store or cannot be loaded is a reject (stage `evaluate`, naming the model and its file)
and the others are judged; with none left, the flow stops with every model's reason."""

import pickle
import traceback

from prefect import flow, get_run_logger
from prefect.artifacts import create_markdown_artifact
from prefect.states import Completed, Failed, State

from visemeflow.logs import SUMMARISED
from visemeflow.flows.common import replace_stage_rejects
from visemeflow.flows.errors import StageFailed
from visemeflow.flows.params import EvaluateParams
from visemeflow.flows.predict import ensure_model
from visemeflow.flows.train import training_rows
from visemeflow.learning.default_model import is_shipped
from visemeflow.learning.device import check_device_here
from visemeflow.learning.robustness import robustness_table, table_csv, table_markdown
from visemeflow.learning.robustness_table import TABLE_RUNS
from visemeflow.learning.train import load_model
from visemeflow.tasks.progress import Progress
from visemeflow.procedural.recognised import RECOGNISED_MODEL
from visemeflow.schemas import C
from visemeflow.storage import Store
from visemeflow.tasks.common import reject_row
from visemeflow.tasks.evaluate import augmented_task_for, evaluation_task_for
from visemeflow.tasks.models import is_trained, model_hash

STAGE = "evaluate"
# what naming or loading a model that cannot be evaluated raises: not in the store (LookupError), not a visemeflow
# model (ValueError, as `learning.train.ModelFileError`; torch's unpickler on another file: UnpicklingError, EOFError,
# KeyError), unreadable (OSError)
MODEL_ERRORS = (LookupError, ValueError, OSError, EOFError, pickle.UnpicklingError)


def check_model(store: Store, model: str) -> dict | None:
    """The lineage of a trained model of the store (None for `phones`), once it has loaded; installs a shipped
    model when it is named. A MODEL_ERRORS error when it is missing or cannot be loaded."""
    if not is_trained(model):
        return None
    if is_shipped(model):
        ensure_model(store, model)
    if not store.has_model(model):
        known = store.model_names()
        raise LookupError(f"no trained model named {model} in {store.root}; "
                          f"known models: {', '.join(known) or 'none (run visemeflow train first)'}")
    return load_model(store.model_file(model))[2]


def model_reject(store: Store, model: str, exc: BaseException, trace: str = "") -> dict:
    """The reject row of a model that could not be evaluated, naming the model, its file and the reason."""
    path = store.model_path(model) if is_trained(model) else None
    where = f"model {model} ({path})" if path is not None and path.exists() else f"model {model}"
    reason = str(exc) or type(exc).__name__
    return reject_row(None, STAGE, type(exc).__name__, f"{where}: {reason}{trace}", str(path) if path else None)


def validation_phones(store: Store, rows: list[dict]) -> dict[str, list[dict]]:
    """utterance id -> its phone rows (`start_s`, `end_s`, `viseme`, in time order) for the rows that have phones."""
    ids = [r[C.UTTERANCE_ID] for r in rows]
    table = store.read_table("phones", utterance_ids=ids).select(
        [C.UTTERANCE_ID, C.INDEX, C.PART, C.START_S, C.END_S, C.VISEME])
    phones: dict[str, list[dict]] = {}
    for r in sorted(table.to_pylist(), key=lambda r: (r[C.UTTERANCE_ID], r[C.START_S], r[C.INDEX], r[C.PART])):
        phones.setdefault(r[C.UTTERANCE_ID], []).append(
            {C.START_S: r[C.START_S], C.END_S: r[C.END_S], C.VISEME: r[C.VISEME]})
    return phones


def _realspeech_counts(results: list[dict], n_utterances: int) -> str | None:
    """'On N validation utterances with phones: b/p/m ..., f/v ..., non-silent ... phones' (None: nothing scored)."""
    counts = next((r["realspeech"]["validation"] for r in results if r.get("realspeech", {}).get("validation")), None)
    if counts is None:
        return None
    text = (f"On {n_utterances} validation utterances with phones: {counts['mbp_closure'][1]} b/p/m, "
            f"{counts['fff_closure'][1]} f/v and {counts['agreement'][1]} non-silent phones.")
    lips = next((r["lips"]["validation"] for r in results if r.get("lips", {}).get("validation")), None)
    if lips is not None:
        text += f" Lips: {lips['bilabials']} b/p/m, {lips['labiodentals']} f/v, {lips['vowels']} vowels scored."
    return text



def _warn_phones_language(store: Store, val: list[dict], logger) -> None:
    """Warn (terminal and log) when `phones`, whose recogniser knows English only, is judged on utterances whose
    `language` (from the manifest or the ingest config) is another: its errors there are the recogniser's."""
    ids = {r[C.UTTERANCE_ID] for r in val}
    table = store.read_table("utterances").select([C.UTTERANCE_ID, C.LANGUAGE]).to_pylist()
    other = sorted({str(r[C.LANGUAGE]) for r in table if r[C.UTTERANCE_ID] in ids and r[C.LANGUAGE]
                    and str(r[C.LANGUAGE]).lower().replace("_", "-").split("-")[0] not in ("en", "eng")})
    if other:
        n = sum(1 for r in table if r[C.UTTERANCE_ID] in ids and str(r[C.LANGUAGE]) in other)
        logger.warning("`%s`: the phone recogniser (pocketsphinx) knows English only, but %d validation utterances "
                       "are in %s: its scores there measure the wrong language's phones", RECOGNISED_MODEL, n,
                       ", ".join(other))

@flow(name="evaluate", flow_run_name="evaluate({params.models})")
def evaluate_flow(params: EvaluateParams) -> State:
    """L1 x 100 of each model on validation and on each augmented condition; metrics, a table artifact and files.
    A model that cannot be evaluated is a reject and the others are judged."""
    check_device_here(params.device)   # torch is asked only for cuda: a cached run never loads it
    store = Store(params.store)
    logger = get_run_logger()
    rejects, usable, lineages = {}, [], {}   # rejects: model -> its reject row
    for model in params.models:
        try:
            lineages[model] = check_model(store, model)
        except MODEL_ERRORS as exc:
            rejects[model] = model_reject(store, model, exc)
            logger.warning("evaluate: rejected %s", rejects[model][C.MESSAGE], extra=SUMMARISED)
            continue
        usable.append(model)
    if not usable:
        replace_stage_rejects(store, STAGE, list(rejects.values()), 1)
        raise LookupError("no model to evaluate: " + "; ".join(r[C.MESSAGE] for r in rejects.values()))
    trained = [m for m in usable if is_trained(m)]
    lineage = lineages[trained[0]] if trained else {}
    source = params.source or lineage.get("source", "tracked")
    variant = params.variant or lineage.get("variant")
    if not variant:
        raise LookupError(f"the model {trained[0]} has no curve variant in its lineage; pass --variant" if trained
                          else f"`{RECOGNISED_MODEL}` alone has no training curves to name the targets; pass --variant")
    hashes = {m: model_hash(store, m) for m in usable}
    _, val, _ = training_rows(store, source, variant)
    if not val:   # a Failed run with one line, not an exception (whose traceback Prefect would print)
        message = (f"no validation utterance in {store.root} has {source} curves of variant {variant!r}; evaluate "
                   f"judges the `val` split (about 10% of the ids, or a manifest's `split` column)")
        logger.error("evaluate: %s", message)
        return Failed(message=message, data=StageFailed(f"evaluate: {message}", {"models": len(usable),
                                                                                 "validation_utterances": 0}))
    if RECOGNISED_MODEL in usable:
        _warn_phones_language(store, val, logger)

    aug_futures = {
        cond: augmented_task_for(store, val, cond, params.seed, params.augment).submit(
            str(store.root), cond, params.seed, params.augment, val)
        for cond in params.conditions
    }
    augmented = {cond: f.result() for cond, f in aug_futures.items()}
    targets = {r[C.UTTERANCE_ID]: store.curves_provenance(source, variant, r[C.UTTERANCE_ID]) for r in val}
    phones = validation_phones(store, val)
    futures = {
        m: evaluation_task_for(store, m).submit(str(store.root), m, hashes[m], val, augmented, source, variant,
                                                targets, phones, params.device)
        for m in usable
    }
    results, unexpected = [], 0
    line = Progress(STAGE, len(futures), unit="models")  # each model: every condition, minutes on a large set
    for model, future in futures.items():
        try:
            results.append(future.result())
        except MODEL_ERRORS as exc:
            rejects[model] = model_reject(store, model, exc)
        except Exception as exc:  # a bug met on one model: the others are judged, the flow ends Failed
            trace = "".join(traceback.format_exception(exc))
            logger.error("evaluate[%s]: unexpected %s\n%s", model, type(exc).__name__, trace)
            rejects[model] = model_reject(store, model, exc, "\n" + trace)
            unexpected += 1
        line.advance(failed=model in rejects)
    line.close()
    replace_stage_rejects(store, STAGE, list(rejects.values()), 1)
    judged = [r["model"] for r in results]
    counts = {"models": len(params.models), "judged": len(judged), "rejected": len(rejects)}
    if not results:
        message = f"{STAGE}: no model could be evaluated: " + "; ".join(
            r[C.MESSAGE].split("\n", 1)[0] for r in rejects.values())
        return Failed(message=message, data=StageFailed(message, counts))

    runs = {"evaluate", *TABLE_RUNS}
    metrics = [r for m in judged for r in store.read_metrics(m).to_pylist() if r[C.RUN] in runs]
    table = robustness_table(metrics, presets={r["model"]: r["preset"] for r in results},
                             augmented={r["model"]: r["train_augment"] for r in results})
    title = f"Validation L1 x 100 on {len(val)} utterances ({source}/{variant}); in brackets: ratio to validation"
    markdown = table_markdown(table, title, note=_realspeech_counts(results, len(phones)))
    md = store.write_report_text("robustness.md", markdown)
    csv = store.write_report_text("robustness.csv", table_csv(table))
    create_markdown_artifact(key="robustness-table", markdown=markdown,
                             description="Paper Tables 1-3 format: validation and augmented conditions")
    logger.info("evaluate: %d models on %d utterances x %d conditions -> %s; %d rejected", len(results), len(val),
                len(params.conditions), md, len(rejects))
    summary = {"table": table, "markdown": str(md), "csv": str(csv), "validation_utterances": len(val),
               "source": source, "variant": variant, "models": judged, "rejected": len(rejects),
               "rejects": [{"model": m, "reason": r[C.MESSAGE]} for m, r in rejects.items()]}
    if unexpected:
        message = (f"{STAGE}: {unexpected} of {len(params.models)} models failed with an unexpected error (tracebacks "
                   "in the run's logs; reasons in the rejects table)")
        return Failed(message=message, data=StageFailed(message, counts))
    return Completed(message=f"{STAGE}: {len(judged)} of {len(params.models)} models judged", data=summary)
