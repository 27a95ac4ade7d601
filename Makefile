# Two commands: `make run` (the main job) and `make test`. Each creates .venv if missing and
# installs what it needs; the install is skipped while pyproject.toml is unchanged.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: run test bench lint clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

run: $(STAMP)
	$(PY) -m edge demo

test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -q

# The runtime's figures (vt-edge bench, no torch), then the torch and training ones added to
# the same bench/results.json and results.md (vt-train bench); results.md compares each
# figure with the results the run replaces.
bench: $(STAMP)
	$(PY) -m edge bench --out bench --baseline bench/results.json
	$(PY) -m train bench --merge-into bench/results.json

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

clean:
	rm -rf $(VENV) build *.egg-info
