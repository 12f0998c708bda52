"""Corpus discovery and per-utterance ingestion: alignment + audio to `utterances` and `phones` rows."""

from visemeflow.ingest.config import IngestConfig
from visemeflow.ingest.corpus import CorpusEntry, CorpusError, DiscoveryReject, check_corpus, discover_corpus
from visemeflow.ingest.utterance import IngestedUtterance, IngestError, ingest_utterance

__all__ = [
    "CorpusEntry",
    "CorpusError",
    "DiscoveryReject",
    "IngestConfig",
    "IngestError",
    "IngestedUtterance",
    "check_corpus",
    "discover_corpus",
    "ingest_utterance",
]
