"""Run summaries and rejects published as Prefect artifacts, readable in the UI."""

import pyarrow as pa
from prefect.artifacts import create_markdown_artifact, create_table_artifact

from visemeflow.schemas import C

MAX_REJECT_ROWS = 200


def publish_stage_summary(stage: str, totals: dict[str, int], extra: dict[str, object] | None = None) -> None:
    rows = [{"what": k, "value": v} for k, v in {**totals, **(extra or {})}.items()]
    create_table_artifact(key=f"{stage}-summary", table=rows, description=f"{stage}: what this run did")


def publish_rejects(stage: str, rejects: pa.Table) -> None:
    """The rejects of a stage as a markdown table (first rows), or a line saying there are none."""
    if rejects.num_rows == 0:
        markdown = f"# {stage}: no rejects\n"
    else:
        rows = rejects.slice(0, MAX_REJECT_ROWS).to_pylist()
        lines = [f"# {stage}: {rejects.num_rows} rejected", "", "| utterance | error | message |", "|---|---|---|"]
        for r in rows:
            message = str(r[C.MESSAGE]).replace("|", "\\|").replace("\n", " ")
            lines.append(f"| {r[C.UTTERANCE_ID] or '-'} | {r[C.ERROR_TYPE]} | {message} |")
        if rejects.num_rows > MAX_REJECT_ROWS:
            lines.append(f"\n... and {rejects.num_rows - MAX_REJECT_ROWS} more in the store's rejects table")
        markdown = "\n".join(lines) + "\n"
    create_markdown_artifact(key=f"{stage}-rejects", markdown=markdown, description=f"{stage}: rejected inputs")
