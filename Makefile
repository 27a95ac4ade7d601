# Two commands: `make run` (the main job) and `make test`. Each creates .venv if missing and
# installs what it needs; the install is skipped while pyproject.toml is unchanged.
# `make test-slow` runs the slow tier (soak and measurement tests); CI runs both.
# `make test-unit` runs the one-minute part of `make test`, for an answer while editing.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: run test test-unit test-slow bench lint clean

# --no-compile: byte-compiling every installed module (torch's thousands) was half the
# install's time (63 s against 35 s on 2 cores). What the daemon, training and the tests
# import is compiled once here instead, before parallel test workers would each compile it.
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet --no-compile -e '.[dev]'
	$(PY) -c 'import edge.cli, train.cli, torch, onnxruntime, scipy.signal, aiohttp, hypothesis'
	touch $(STAMP)

run: $(STAMP)
	$(PY) -m edge demo

# The behaviour tier on TEST_WORKERS workers (pytest-xdist). More workers than cores pays
# while tests wait on the emulated robot, but the suite keeps both cores busy and each
# worker collects every module again: on 2 cores 4 workers take the wall of 5 (367 s
# against 364 s on a fresh clone) for 11 % less CPU, and 3 are slower. Tests sharing a
# module- or session-wide fixture stay on one worker (tests/conftest.py).
TEST_WORKERS ?= 4

test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadgroup

# The tests that need no daemon, process, emulator or trained model (tests/conftest.py marks
# the others integration, from what each uses): a part of `make test`, not a tier beside it.
# Two workers: their waits overlap, and each more worker collects every module again.
UNIT_WORKERS ?= 2

test-unit: $(STAMP)
	$(PY) -m pytest -q -n $(UNIT_WORKERS) --dist loadgroup -m "not integration"

# The slow tier, one test at a time: its measurements must not share the cores with others.
test-slow: $(STAMP)
	$(PY) -m pytest -q --run-slow -m slow

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
