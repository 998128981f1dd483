# volpuzzle: `make demo` sets up and builds the quarter torus; `make test` runs the tests.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
SPECS := $(wildcard specs/*.yaml)
OUTS := $(patsubst specs/%.yaml,out/%/report.json,$(SPECS))

.PHONY: setup demo test test-fast lint paper bench models slicer-check clean
.DELETE_ON_ERROR:

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet -e '.[test,batch]'
	touch $@

# The package's own bytecode, compiled once: with PYTHONDONTWRITEBYTECODE set (as spawned workers inherit), every
# process would otherwise compile its ~40 modules from source, ~0.5 CPU s each (the build and each of its workers).
$(VENV)/.bytecode: $(VENV)/.installed $(wildcard volpuzzle/*.py volpuzzle/*/*.py)
	$(PY) -m compileall -q volpuzzle
	touch $@

setup: $(VENV)/.installed $(VENV)/.bytecode

demo: setup
	$(VENV)/bin/volpuzzle build specs/quarter-torus.yaml --force

test: setup
	$(PY) -m pytest

# The quick loop while working: everything but the tests marked slow (end-to-end builds over ~3 s), under a minute.
test-fast: setup
	$(PY) -m pytest -m "not slow"

lint: setup
	$(VENV)/bin/ruff check .

# Any spec as a file target, so that `make -j` runs a print batch.
out/%/report.json: specs/%.yaml $(VENV)/.installed $(VENV)/.bytecode
	$(VENV)/bin/volpuzzle build $< -o out/$* --force

paper: $(OUTS)
	@for d in $(patsubst %/report.json,%,$(OUTS)); do $(VENV)/bin/volpuzzle check $$d || exit 1; done

bench: setup
	$(PY) scripts/bench_spline.py
	$(PY) scripts/bench.py

models: setup
	$(PY) scripts/make_models.py

# A real slicer as a test: every plate of every spec sliced by PrusaSlicer without supports, with the settings in
# slicer/prusaslicer.ini and the plate kept as laid out; any refusal or warning fails. Installs PrusaSlicer from
# Debian's packages when missing (needs root and apt). CPU heavy: SPECS=specs/a.yaml limits it to some specs.
slicer-check: $(OUTS)
	@command -v prusa-slicer >/dev/null || (apt-get install -y prusa-slicer >/dev/null 2>&1 || \
		(apt-get update >/dev/null 2>&1 && apt-get install -y prusa-slicer >/dev/null))
	$(PY) scripts/slicer_check.py $(patsubst %/report.json,%,$(OUTS))

clean:
	rm -rf out
