"""Every bench in bench/ runs to its end on its smallest input and exits 0, so a bench that crashes fails here rather
than at its next run by hand. The benches print their figures; nothing here reads or asserts a timing.

Each runs as its own process (as a person runs it) with one OpenMP thread. A bench whose smallest input still takes
well over a minute on the 2-core machine is listed in SLOW with the reason, and is skipped with that reason unless
VISEMEFLOW_SLOW_BENCHES=1 (then it runs with the arguments given there). Figures and caches go where each bench
puts them (bench/out, git-ignored, or a temporary folder).
"""

import os
import subprocess
import sys

import pytest
from factories import REPO

BENCH = REPO / "bench"
RUN_SLOW = os.environ.get("VISEMEFLOW_SLOW_BENCHES") == "1"

LIBRARIES = {
    "cpu.py": "pins a bench to one core",
    "report.py": "the result table",
    "learning_data.py": "the espeak corpus and cached models of learning.py and robustness.py",
    "mbrola_data.py": "the MBROLA corpus of domain_gap.py",
    "espeak_langs.py": "the Dutch and Czech espeak-ng corpus of encoders.py's `esx` part",
    "judging.py": "the learning benches' loss words and their judge on held-out speech (torch and visemeflow only)",
    "prefect_api.py": "the Prefect server a bench's flows report to",
}
"""Modules of bench/ that only other benches import (they have no `__main__`)."""

QUICK = {
    "animation.py": ["--minutes", "0.05", "--repeats", "1", "--preview-seconds", "0.5", "--no-pin", "--out", "{tmp}"],
    "bones.py": ["--bones", "4", "--iterations", "1", "--init-iterations", "1", "--utterances", "1"],
    "rehash.py": ["--utterances", "20", "--repeats", "1"],
    "devices.py": ["--presets", "fbank-blstm", "--batch-sizes", "1", "--utterances", "2", "--epochs", "2",
                   "--d-model", "16", "--threads", "1"],
    "end_to_end.py": ["--repeats", "1", "--clips", "1", "--no-pin", "--joint", "2"],
    "forcealign.py": ["--utterances", "2"],
    "joint_solver_device.py": ["--clips", "1,2", "--cpu-clips", "1,2", "--frames", "10"],
    "joint_track.py": ["--repeats", "1", "--joint", "2", "--clips", "2", "--grid-only", "--no-pin", "--reference"],
    "ingest_procedural.py": ["--utterances", "25", "--speakers", "2", "--skip-peer", "--no-install"],
    "landmarks.py": ["--repeats", "1", "--no-pin", "--clips", "1"],
    "learning.py": ["--english", "20", "--mandarin", "10", "--epochs", "1", "--presets", "fbank-blstm", "--sizes", "",
                    "--threads", "1"],
    "lips.py": ["--quick", "--threads", "1"],
    "memory.py": ["--minutes", "0.1"],
    "pauses.py": ["--quick"],
    "memory_tracking.py": ["--seconds", "0.2", "--side", "360"],
    "onnx.py": ["--presets", "fbank-blstm", "--repeats", "1"],
    "rendering.py": ["--frames", "2", "--reference-frames", "1"],
    "robustness.py": ["--english", "20", "--mandarin", "10", "--epochs", "1", "--presets", "fbank-blstm",
                      "--augmented", "", "--threads", "1"],
    "rotation.py": ["--takes", "1", "--repeats", "1", "--calls", "20"],
    "textgrid_readers.py": ["--repeat", "1"],
    "tracking.py": ["--utterances", "1", "--faithful-frames", "1", "--flow-sizes", "fast:160"],
    "track_tasks.py": ["--utterances", "3", "--repeats", "1"],
    "transfer.py": ["--targets", "self,auto"],
    "truth_vs_procedural.py": [],
    "video_closures.py": ["--models", "procedural"],
    "s3_discovery.py": ["--utterances", "20", "--repeats", "1"],
    "syllables.py": ["--models", "default-fbank", "--languages", "cs"],
    "wav2vec2_cache.py": ["--epochs", "1", "--utterances", "2", "--repeats", "1"],
    "whisper_encoder.py": ["--repeats", "1", "--quick"],
}
"""bench -> its arguments for the smallest run ({tmp}: a temporary folder of the test). 1-37 s each on the 2-core
machine otherwise idle (lips, transfer, end_to_end, whisper_encoder, landmarks and tracking the longest), two to four
times that while other jobs ran."""

SLOW = {
    "cli.py": ("starts visemeflow serve and runs about 12 commands, each paying Prefect's start: minutes",
               ["--repeat", "1"]),
    "domain_gap.py": ("its data always include the 700 + 500 utterance espeak corpus (no size flag): many minutes "
                      "on a fresh bench/out", ["--steps", "2", "--recipes", "real", "--losses", "l1",
                                               "--recogniser-bias", "", "--d-model", "16", "--threads", "1"]),
    "encoders.py": ("Whisper-encodes the LJ, FACEGOOD and held-out speech (minutes of audio) before its first step "
                    "on a fresh encoder cache", ["--steps", "2", "--recipes", "lj", "--d-model", "16"]),
    "orchestration.py": ("renders the 25-video demo corpus when missing, starts a Prefect server and a Dask cluster "
                         "and runs the pipeline on them: minutes", ["--repeat", "1"]),
    "s3_store.py": ("renders the 25-video demo corpus when missing, starts Prefect and moto S3 servers and runs the "
                    "pipeline cold five times (folder and S3, one worker and a Dask cluster, the corpus on S3): minutes", []),
    "realspeech.py": ("trains on the fixed 700 + 500 utterance espeak corpus and k-fold LJ models: minutes",
                      ["--espeak-epochs", "1", "--lj-epochs", "1", "--folds", "2", "--threads", "1"]),
    "recogniser.py": ("88 s with --models phones (no size flag): pocketsphinx on all 37 utterances under five "
                      "conditions", ["--models", "phones"]),
    "whisper_tuning.py": ("packs 46 MB of speech and encoder weights, then Whisper-encodes minutes of audio before "
                          "its first step", ["run", "{tmp}/tuning.pt.gz", "--device", "cpu", "--tune", "1",
                                             "--seeds", "0", "--steps", "2", "--cost", "--cost-encoders", "base",
                                             "--cost-steps", "1"]),
    "prompts.py": ("needs the Debian packages asterisk-core-sounds-{en,es,fr,it,ru}{,-wav} (CC-BY-SA-3.0 / CC-BY-3.0 "
                   "telephone prompts, about 100 MB) and Whisper-encodes them", ["--utterances", "1", "--languages",
                                                                              "en,fr"]),
    "thirdlang.py": ("needs the Debian packages fillets-ng-data-nl/-cs (GPL-2 voice recordings) and Whisper-encodes "
                     "them", ["--utterances", "1"]),
}
"""bench -> (why it is not run by default, its smallest arguments)."""

def run_bench(name: str, args: list[str], tmp_path) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PREFECT_LOGGING_LEVEL": "WARNING"}
    argv = [sys.executable, str(BENCH / name), *(a.replace("{tmp}", str(tmp_path)) for a in args)]
    done = subprocess.run(argv, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    out = (done.stdout + done.stderr)[-4000:]
    assert done.returncode == 0, f"bench/{name} {' '.join(args)} exited {done.returncode}; its last output:\n{out}"


def test_every_bench_is_run_or_marked():
    scripts = {p.name for p in BENCH.glob("*.py")}
    listed = set(QUICK) | set(SLOW) | set(LIBRARIES)
    assert scripts - listed == set(), "a new bench: give it its smallest arguments in QUICK (or a reason in SLOW)"
    assert listed - scripts == set(), "listed here but gone from bench/"
    assert not set(QUICK) & set(SLOW)
    for name in LIBRARIES:
        assert "__main__" not in (BENCH / name).read_text(encoding="utf-8"), f"bench/{name} runs: list it in QUICK"


@pytest.mark.parametrize("name", sorted(QUICK))
def test_bench_runs_on_its_smallest_input(name, tmp_path):
    run_bench(name, QUICK[name], tmp_path)


@pytest.mark.parametrize("name", sorted(SLOW))
def test_slow_bench_runs_on_its_smallest_input(name, tmp_path):
    reason, args = SLOW[name]
    if not RUN_SLOW:
        pytest.skip(f"bench/{name}: {reason} (VISEMEFLOW_SLOW_BENCHES=1 runs it)")
    run_bench(name, args, tmp_path)
