# dynslam: `make demo` and `make test` do all the set-up on a fresh machine.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
DYNSLAM := $(VENV)/bin/dynslam
TESTENV := MPLBACKEND=Agg ORT_DISABLE_TELEMETRY=1 PYTHONHASHSEED=0

.PHONY: install test demo tables bench bench-cuda lint clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q -e ".[test,view]"
	touch $@

# The tests also cover the optional Ray executor, so they install the `ray` extra.
$(VENV)/.installed-ray: $(VENV)/.installed
	$(PY) -m pip install -q -e ".[test,view,ray]"
	touch $@

# The test suite; HOME goes to a temp folder because evo and onnxruntime write there on import.
test: install $(VENV)/.installed-ray
	@tmp=$$(mktemp -d); HOME=$$tmp $(TESTENV) $(PY) -m pytest -q $(PYTEST_ARGS); rc=$$?; rm -rf $$tmp; exit $$rc

# The main job on the built-in synthetic default scene.
demo: install
	$(DYNSLAM) demo

tables: install
	$(DYNSLAM) tables

bench: install
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

# On a machine with a GPU: the CUDA tests, the limit table on CUDA and the Bonn clip (../shared) on CUDA, three rounds.
bench-cuda: install
	@tmp=$$(mktemp -d); HOME=$$tmp $(TESTENV) $(PY) -m pytest -q tests/test_run_cuda.py; rc=$$?; rm -rf $$tmp; [ $$rc -eq 0 ] || exit $$rc
	$(PY) benchmarks/bench_limits.py --device cuda --threads 2
	$(PY) benchmarks/bench_dynamic.py --presets "" --device cuda --threads 2 --repeats 3

lint: install
	$(PY) -m pip install -q ruff
	$(VENV)/bin/ruff check dynslam_cli tests benchmarks

clean:
	rm -rf $(VENV) .pytest_cache
