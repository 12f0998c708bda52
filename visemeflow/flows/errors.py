"""Errors the flows raise to their callers (importable without Prefect, for the command line)."""


class StageFailed(RuntimeError):
    """A stage that ended Failed: every utterance failed, or some failed in a way that is not bad input (a bug).

    Carries the stage's summary, so a caller that catches it can still report what was done.
    """

    def __init__(self, message: str, summary: dict):
        super().__init__(message)
        self.summary = summary

    def __reduce__(self):
        return (type(self), (str(self), self.summary))


class RerunError(LookupError):
    """`rerun` cannot find the utterance or the stage's earlier run; the message says what to run first."""
