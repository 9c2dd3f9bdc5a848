# drive-commission: `make run` and `make test` set everything up on a machine with Python and make.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
OUT    ?= commissioning/make-run
BENCH  ?= bench/bench_*.py
# what a wheel is built from (also the Dockerfile's COPY); built in a copy, so no stale build/ leaks in
SHIPPED := pyproject.toml README.md src sim_drive configs drivers
PIP_FLAGS := --quiet --disable-pip-version-check

.PHONY: run test bench wheel-check clean browser

# The install compiles numba's kernels once (commission --warm-cache), so that the first
# `make run` does not sit silent for half a minute.
$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install $(PIP_FLAGS) -e ".[test]"
	$(BIN)/commission --warm-cache
	@touch $(STAMP)

## run: a full commissioning against the built-in simulated drive
run: $(STAMP)
	$(BIN)/commission --sim --config configs/default.yaml --out $(OUT)

## browser: Debian's Chromium, which the report test renders report.html in (needs root or sudo)
browser:
	@command -v chromium >/dev/null 2>&1 || { \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		$$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq chromium; }

## test: the test suite, one worker per core (at most 4: each identification runs 2 threads); a test
## file stays on one worker, so the identifications its tests share are made once
test: $(STAMP) browser
	$(BIN)/python -m pytest -q -n auto --maxprocesses 4 --dist loadfile

## bench: accuracy and speed benchmarks (figures printed and appended to bench/results/RESULTS.md)
bench: $(STAMP)
	$(BIN)/python bench/record.py $(BENCH)

## wheel-check: build the wheel, install it into a fresh venv, commission the simulated drive
## (directly and over CANopen) from a folder outside the source tree
wheel-check: $(STAMP)
	@set -eu; tmp=$$(mktemp -d); trap 'rm -rf "$$tmp"' EXIT; \
	echo "wheel-check: building the wheel"; \
	mkdir "$$tmp/tree"; cp -a $(SHIPPED) "$$tmp/tree"; \
	$(BIN)/python -m pip wheel $(PIP_FLAGS) --no-deps --wheel-dir "$$tmp/dist" "$$tmp/tree"; \
	echo "wheel-check: installing it into a fresh venv"; \
	$(PYTHON) -m venv "$$tmp/venv"; \
	"$$tmp/venv/bin/python" -m pip install $(PIP_FLAGS) "$$tmp"/dist/*.whl; \
	cd "$$tmp"; unset COMMISSION_DRIVERS; \
	venv/bin/python -c "import commission, sim_drive, sys; \
	  assert all(m.__file__.startswith(sys.prefix) for m in (commission, sim_drive)), 'imported from the source tree'"; \
	venv/bin/commission --warm-cache; \
	for link in direct canopen; do \
	  echo "wheel-check: commission --sim --sim-link $$link"; \
	  venv/bin/commission --sim --sim-link $$link --out "out-$$link" > "out-$$link.txt"; \
	  for f in result.json controller.json report.html; do \
	    test -s "out-$$link/$$f" || { echo "wheel-check: --sim-link $$link left no $$f"; exit 1; }; \
	  done; \
	  tail -n 1 "out-$$link.txt"; \
	done; \
	echo "wheel-check: commission --replay (fleet mode: both runs' logs on a local Dask cluster)"; \
	venv/bin/commission --replay out-direct/run.mcap out-canopen/run.mcap --workers 1 --out fleet > fleet.txt; \
	test -s fleet/fleet.parquet && test -s fleet/fleet.html || { echo "wheel-check: fleet mode left no table or page"; exit 1; }; \
	tail -n 1 fleet.txt; \
	echo "wheel-check: ok"

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info .pytest_cache commissioning
