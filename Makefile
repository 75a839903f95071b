# One entry point per job. Every target sets up what it needs first (idempotent).
#   make run    - set up, generate a demo clip, run the annotate_clip flow on it, print a SQL summary
#   make test   - set up and run the whole test suite (slow end-to-end tests included; CI runs this)
#   make bench  - set up and run the benchmarks (numbers printed and written to bench/results/)
#   make lock   - re-resolve requirements.lock from pyproject.toml
SHELL := /bin/bash
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
# The CPU torch wheel lives in a local find-links folder on these machines (see ../shared/reference/stack.md).
FIND_LINKS ?= $(or $(PIP_FIND_LINKS),/opt/wheels)
UV_VERSION := 0.13.9
DEMO_DIR ?= data/demo
WAREHOUSE ?= data/warehouse
export CADESTATE_WAREHOUSE ?= $(WAREHOUSE)

.PHONY: setup run test test-fast bench lock clean

setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml requirements.lock
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --disable-pip-version-check uv==$(UV_VERSION)
	$(BIN)/uv pip install -q --python $(BIN)/python --find-links $(FIND_LINKS) -r requirements.lock
	$(BIN)/uv pip install -q --python $(BIN)/python --no-deps --config-settings editable_mode=compat -e .
	touch $@

run: setup
	$(BIN)/cadestate demo make $(DEMO_DIR)
	$(BIN)/cadestate ingest $(DEMO_DIR)
	$(BIN)/cadestate sql "SELECT clip, count(*) AS frames, any_value(width) || 'x' || any_value(height) AS size, \
	  max(abs(timestamp_error_us)) AS max_ts_error_us, \
	  round(max(camera_center[1]) - min(camera_center[1]), 2) AS x_travel_m, \
	  round(avg(camera_center[2]), 2) AS mean_camera_height_m FROM frames GROUP BY clip ORDER BY clip"
	$(BIN)/cadestate sql "SELECT clip, stage, status, round(duration_s, 2) AS seconds, rows_written, config_hash \
	  FROM runs ORDER BY started_at"

test: setup
	$(BIN)/python -m pytest

test-fast: setup
	$(BIN)/python -m pytest -m "not slow"

bench: setup
	$(BIN)/python -m bench

lock:
	$(BIN)/uv pip compile pyproject.toml --extra test --find-links $(FIND_LINKS) --python-version 3.11 -o requirements.lock

clean:
	rm -rf $(VENV) data .pytest_cache
