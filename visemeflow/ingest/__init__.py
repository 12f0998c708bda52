"""Corpus discovery and per-utterance ingestion: alignment + audio to `utterances` and `phones` rows."""

from visemeflow.ingest.config import IngestConfig
from visemeflow.ingest.corpus import CorpusEntry, DiscoveryReject, discover_corpus
from visemeflow.ingest.utterance import IngestedUtterance, IngestError, ingest_utterance

__all__ = [
    "CorpusEntry",
    "DiscoveryReject",
    "IngestConfig",
    "IngestError",
    "IngestedUtterance",
    "discover_corpus",
    "ingest_utterance",
]
