# drive-commission: `make run` and `make test` set everything up on a machine with Python and make.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
OUT    ?= commissioning/make-run

.PHONY: run test bench clean browser

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -e ".[test]"
	@touch $(STAMP)

## run: a full commissioning against the built-in simulated drive
run: $(STAMP)
	$(BIN)/commission --sim --config configs/default.yaml --out $(OUT)

## browser: Debian's Chromium, which the report test renders report.html in (needs root or sudo)
browser:
	@command -v chromium >/dev/null 2>&1 || { \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		$$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq chromium; }

## test: the test suite
test: $(STAMP) browser
	$(BIN)/python -m pytest -q

## bench: accuracy and speed benchmarks (figures printed, not asserted)
bench: $(STAMP)
	@for f in bench/bench_*.py; do echo "== $$f"; $(BIN)/python $$f || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info .pytest_cache commissioning
