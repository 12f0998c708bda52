"""A video without an alignment is ingested, not rejected: discovery keeps it, its utterances row says it has no
alignment (NO_ALIGNMENT), its audio is the video's audio track, the procedural stage skips it saying so, and the
rest of the corpus is exactly as without it."""

import shutil
from pathlib import Path

import numpy as np
import pytest

from factories import SHARED_DATA, make_corpus, write_wav
from visemeflow.ingest import IngestConfig, IngestError, discover_corpus, ingest_utterance
from visemeflow.schemas import C
from visemeflow.schemas.tables import NO_ALIGNMENT, has_alignment
from visemeflow.storage import Store
from visemeflow.tracking.video import write_video

HELLO = [("sil", 0.0, 0.2), ("HH", 0.2, 0.3), ("AH0", 0.3, 0.45), ("L", 0.45, 0.55), ("OW1", 0.55, 0.8),
         ("", 0.8, 1.0)]
CONFIG = IngestConfig()


def talking_clip(path: Path, seconds: float = 1.0, fps: float = 25.0, rate: int = 16000, audio: bool = True) -> Path:
    """A small clip with (or without) a 220 Hz audio track."""
    n = int(round(seconds * fps))
    frames = np.zeros((n, 32, 32, 3), dtype=np.uint8)
    frames[:, 8:24, 8:24] = np.linspace(0, 255, n, dtype=np.uint8)[:, None, None, None]
    tone = (0.1 * np.sin(2 * np.pi * 220 * np.arange(int(seconds * rate)) / rate)).astype(np.float32)
    return write_video(path, frames, fps, audio=tone if audio else None, audio_rate=rate if audio else None)


def corpus_with_videos(root: Path) -> Path:
    make_corpus(root, {"spk/aligned": HELLO})
    talking_clip(root / "spk" / "clip.mp4")                 # video only: its audio track is the audio
    talking_clip(root / "spk" / "dub.mp4")                  # video + an audio file beside it
    write_wav(root / "spk" / "dub.wav", 1.0, 22050)
    write_wav(root / "spk" / "lonely.wav", 0.5)              # audio only: still a reject
    return root


def test_discovery_keeps_a_video_without_alignment(tmp_path):
    corpus = corpus_with_videos(tmp_path / "c")
    found = discover_corpus(corpus)
    by_id = {e.utterance_id: e for e in found.entries}
    assert set(by_id) == {"spk/aligned", "spk/clip", "spk/dub"}
    clip = by_id["spk/clip"]
    assert clip.alignment_path == "" and clip.alignment_format == NO_ALIGNMENT and not clip.has_alignment
    assert clip.audio_path == clip.video_path == str((corpus / "spk" / "clip.mp4").resolve())
    assert by_id["spk/dub"].audio_path.endswith("dub.wav") and by_id["spk/dub"].video_path.endswith("dub.mp4")
    assert by_id["spk/aligned"].alignment_format == "textgrid" and by_id["spk/aligned"].has_alignment
    (reject,) = found.rejects
    assert (reject.utterance_id, reject.error_type) == ("spk/lonely", "MissingAlignment")
    assert str(corpus / "spk" / "lonely.wav") in reject.message
    assert discover_corpus(corpus, only="spk/clip").entries == (clip,)


def test_unaligned_row_has_no_alignment_and_no_phones(tmp_path):
    corpus = corpus_with_videos(tmp_path / "c")
    by_id = {e.utterance_id: e for e in discover_corpus(corpus).entries}
    clip = ingest_utterance(by_id["spk/clip"], CONFIG)
    u = clip.utterance
    assert clip.phones == []
    assert u[C.ALIGNMENT_FORMAT] == NO_ALIGNMENT and u[C.ALIGNMENT_PATH] == "" and u[C.INVENTORY] is None
    assert u[C.SAMPLE_RATE] == 16000 and u[C.FPS] == 25 and u[C.N_FRAMES] == 25
    assert u[C.DURATION_S] == pytest.approx(1.0, abs=0.05) and u[C.LANGUAGE] is None
    assert not has_alignment(u)
    dub = ingest_utterance(by_id["spk/dub"], CONFIG).utterance
    assert dub[C.SAMPLE_RATE] == 22050 and dub[C.AUDIO_PATH].endswith("dub.wav")
    aligned = ingest_utterance(by_id["spk/aligned"], CONFIG)
    assert has_alignment(aligned.utterance) and aligned.utterance[C.INVENTORY] == "arpabet"
    # the rows fit the table schemas
    from visemeflow.schemas import UTTERANCES, table_from_rows

    assert table_from_rows([u, dub, aligned.utterance], UTTERANCES).num_rows == 3


def test_has_alignment_on_partial_rows():
    assert has_alignment({C.ALIGNMENT_FORMAT: "textgrid", C.ALIGNMENT_PATH: "a.TextGrid"})
    assert not has_alignment({C.ALIGNMENT_FORMAT: NO_ALIGNMENT, C.ALIGNMENT_PATH: ""})
    assert has_alignment({C.ALIGNMENT_PATH: "/x/a.lab"}) and not has_alignment({C.ALIGNMENT_PATH: ""})
    assert not has_alignment({})


def test_video_without_audio_track_is_a_reject_naming_it(tmp_path):
    corpus = tmp_path / "c"
    silent = talking_clip(corpus / "spk" / "mute.mp4", audio=False)
    (entry,) = discover_corpus(corpus).entries
    with pytest.raises(IngestError) as info:
        ingest_utterance(entry, CONFIG)
    assert info.value.error_type == "MissingAudio" and info.value.path == str(silent.resolve())
    assert "spk/mute" in str(info.value) and "no audio track" in str(info.value)


def test_manifest_rows_with_a_video_need_no_alignment(tmp_path):
    talking_clip(tmp_path / "v" / "one.mp4")
    write_wav(tmp_path / "v" / "two.wav", 1.0)
    (tmp_path / "m.csv").write_text("utterance_id,video,audio\nA/one,v/one.mp4,\nA/two,,v/two.wav\n")
    found = discover_corpus(tmp_path / "m.csv")
    (entry,) = found.entries
    assert entry.utterance_id == "A/one" and entry.alignment_format == NO_ALIGNMENT
    assert entry.audio_path == entry.video_path
    (reject,) = found.rejects
    assert (reject.utterance_id, reject.error_type) == ("A/two", "MissingInput")
    assert ingest_utterance(entry, CONFIG).utterance[C.N_FRAMES] == 25


def test_real_grid_clip_without_its_alignment(tmp_path):
    """A GRID clip (.mpg with MPEG audio inside) without its .align: ingested from the video alone."""
    source = SHARED_DATA / "grid_s1" / "video" / "bbaf2n.mpg"
    assert source.is_file(), f"shared data missing: {source}"
    folder = tmp_path / "c" / "s1"
    folder.mkdir(parents=True)
    shutil.copyfile(source, folder / "bbaf2n.mpg")
    (entry,) = discover_corpus(tmp_path / "c").entries
    u = ingest_utterance(entry, CONFIG).utterance
    assert u[C.ALIGNMENT_FORMAT] == NO_ALIGNMENT and u[C.FPS] == 25 and u[C.N_FRAMES] == 75
    assert u[C.SAMPLE_RATE] == 44100 and u[C.AUDIO_PATH] == u[C.VIDEO_PATH]


def test_variable_frame_rate_clip_is_ingested_on_its_30_fps_grid(tmp_path):
    """talking_heads/1.mp4 shows 135 frames on a 30 fps grid with gaps (its container's average rate is 22.13 fps):
    its utterance is on the grid of the frames' time stamps, 30 fps from the audio's start to the last frame."""
    source = SHARED_DATA / "talking_heads" / "1.mp4"
    assert source.is_file(), f"shared data missing: {source}"
    folder = tmp_path / "c" / "th"
    folder.mkdir(parents=True)
    shutil.copyfile(source, folder / "one.mp4")
    (entry,) = discover_corpus(tmp_path / "c").entries
    u = ingest_utterance(entry, CONFIG).utterance
    assert u[C.ALIGNMENT_FORMAT] == NO_ALIGNMENT
    assert u[C.FPS] == pytest.approx(30.0, abs=1e-6) and u[C.N_FRAMES] == 184


@pytest.mark.flow
@pytest.mark.usefixtures("prefect_harness")
def test_flows_ingest_it_procedural_skips_it_and_nothing_else_changes(tmp_path):
    from visemeflow.flows.ingest import ingest_flow
    from visemeflow.flows.params import IngestParams, ProceduralParams
    from visemeflow.flows.procedural import procedural_flow

    corpus = corpus_with_videos(tmp_path / "c")
    (corpus / "spk" / "lonely.wav").unlink()
    baseline = make_corpus(tmp_path / "baseline", {"spk/aligned": HELLO})
    stores = {}
    for name, root in (("with", corpus), ("without", baseline)):
        store = tmp_path / f"store-{name}"
        ingest = ingest_flow(IngestParams(corpus=root, store=store, n_shards=2))
        procedural = procedural_flow(ProceduralParams(store=store, n_shards=2))
        stores[name] = (Store(store), ingest, procedural)
    store, ingest, procedural = stores["with"]
    rows = {r[C.UTTERANCE_ID]: r for r in store.read_table("utterances").to_pylist()}
    assert set(rows) == {"spk/aligned", "spk/clip", "spk/dub"}
    assert [uid for uid, r in rows.items() if not has_alignment(r)] == ["spk/clip", "spk/dub"]
    assert ingest["ingested"] == 3 and ingest["rejected"] == 0 and ingest["unaligned"] == 2
    assert procedural["generated"] == 1 and procedural["skipped_unaligned"] == 2 and procedural["rejected"] == 0
    assert store.curve_ids("procedural", "jali") == ["spk/aligned"]
    assert store.read_table("rejects").num_rows == 0
    # the aligned utterance is exactly as in a corpus without the videos
    base = stores["without"][0]
    assert store.read_table("phones").to_pylist() == base.read_table("phones").to_pylist()
    paths = (C.AUDIO_PATH, C.ALIGNMENT_PATH)  # the same files in another folder
    assert {k: v for k, v in rows["spk/aligned"].items() if k not in paths} == \
        {k: v for k, v in base.read_table("utterances").to_pylist()[0].items() if k not in paths}
    assert store.read_curves("spk/aligned", "procedural").to_pylist() == \
        base.read_curves("spk/aligned", "procedural").to_pylist()
    # a video removed from the corpus goes from the store on the next ingest (it is no captured take)
    (corpus / "spk" / "clip.mp4").unlink()
    ingest_flow(IngestParams(corpus=corpus, store=store.root, n_shards=2))
    assert sorted(store.read_table("utterances").column(C.UTTERANCE_ID).to_pylist()) == ["spk/aligned", "spk/dub"]
