# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
OUT    ?= runs/demo

.PHONY: demo test install bench bench-suite clean lab

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[test]"
	touch $@

install: $(VENV)/.installed

demo: install
	$(VENV)/bin/slamkit run default --out $(OUT)

test: install
	$(PY) -m pytest -q

bench: install
	$(PY) benchmarks/bench_slam.py

# the hard-motion suite (issue 17): SUITE_ARGS="--quick" for the day-to-day subset
bench-suite: install
	$(PY) benchmarks/bench_suite.py $(SUITE_ARGS)

# JupyterLab (in the test extra) from the project's venv, on 127.0.0.1 only, opened on the notebooks folder
lab: install
	$(PY) -m jupyter lab --ip=127.0.0.1 --notebook-dir=notebooks $(if $(filter 0,$(shell id -u)),--allow-root)

clean:
	rm -rf $(VENV) runs .pytest_cache
