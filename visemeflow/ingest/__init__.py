"""Corpus discovery and per-utterance ingestion: alignment + audio to `utterances` and `phones` rows.

The names below are imported from their modules on first use, so `visemeflow.ingest.config` (read by the CLI and
the flows' parameters) imports without the corpus reader and its pandas."""

from visemeflow.lazy import lazy_exports

_EXPORTS = {
    "IngestConfig": ".config",
    "CorpusEntry": ".corpus", "CorpusError": ".corpus", "DiscoveryReject": ".corpus", "check_corpus": ".corpus",
    "discover_corpus": ".corpus",
    "IngestedUtterance": ".utterance", "IngestError": ".utterance", "ingest_utterance": ".utterance",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS)
