"""Prefect artifacts (run summaries, rejects) and, later, the static HTML report."""
