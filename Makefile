# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
OUT    ?= runs/demo

.PHONY: demo test install bench bench-suite clean

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

bench-suite: install
	PYTHONPATH=$(CURDIR) nice -n 5 $(PY) benchmarks/bench_suite.py $(SUITE_ARGS)

clean:
	rm -rf $(VENV) runs .pytest_cache
