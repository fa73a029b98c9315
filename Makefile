# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
OUT    ?= runs/demo

.PHONY: demo test install bench bench-suite results results-quick clean lab

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[test]"
	@# JupyterLab saves no widget state with a notebook: reopened without its kernel, the app's place shows its
	@# picture and status (plain outputs), not ~60 controls that cannot work (README, "What a saved notebook keeps")
	mkdir -p $(VENV)/share/jupyter/lab/settings
	echo '{"@jupyter-widgets/jupyterlab-manager:plugin": {"saveState": false}}' > $(VENV)/share/jupyter/lab/settings/overrides.json
	@# the numba kernels compiled once here (cached beside the sources), not silently in the first run
	$(PY) -m slamkit.warmup
	touch $@

install: $(VENV)/.installed

demo: install
	$(VENV)/bin/slamkit run default --out $(OUT)

# the test files spread over TEST_WORKERS processes (pytest-xdist; 0 runs them in this process); the 25
# slowest tests listed at the end
TEST_WORKERS ?= 2
test: install
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile --durations=25

bench: install
	$(PY) benchmarks/bench_slam.py

# the hard-motion suite (issue 17): SUITE_ARGS="--quick" for the day-to-day subset
bench-suite: install
	$(PY) benchmarks/bench_suite.py $(SUITE_ARGS)

# docs/results.md regenerated from today's code on the data present (~30 min target); results-quick: < 5 min
results: install
	PYTHONPATH=$(CURDIR) nice -n 5 $(PY) benchmarks/make_results.py

results-quick: install
	PYTHONPATH=$(CURDIR) $(PY) benchmarks/make_results.py --quick

# JupyterLab (in the test extra) from the project's venv, on 127.0.0.1 only, opened on the notebooks folder
lab: install
	$(PY) -m jupyter lab --ip=127.0.0.1 --notebook-dir=notebooks $(if $(filter 0,$(shell id -u)),--allow-root)

clean:
	rm -rf $(VENV) runs .pytest_cache
