"""Shared pytest set-up: tests marked ``slow`` are deselected unless ``--run-slow``; tests
marked ``needs_program(present, reason)`` skip, saying why, where a system program is
missing, and fail instead under CI (``CI=true``), which installs them: a skip there would
hide a test that never ran. Under pytest-xdist (``-n N --dist loadgroup``, as ``make test``
runs), the tests that share one of our module- or session-wide fixtures are put in one
``xdist_group``, so that fixture (a daemon, a recorded dataset, a trained model) is built
once, on one worker; every other test goes to whichever worker is free.

Tests that start a daemon, a process, an emulator or train a model are marked
``integration`` here, from what the test and its fixtures use (:data:`INTEGRATION`); the rest
are the one-minute tier, ``make test-unit`` (``-m "not integration"``). A test whose cost the
rule cannot see carries ``@pytest.mark.integration`` itself."""

from __future__ import annotations

import inspect
import os
import signal
import sys
import types

import pytest

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")

# Bytecode is cached for the test run even where the shell sets PYTHONDONTWRITEBYTECODE: with
# it, every xdist worker rewrote every test module's asserts again (~6 s of CPU each at
# collection) and every command a test starts (vt-edge run, collect, sim serve, ...: about
# a hundred) compiled the project's modules again, on a two-core host whose suite is
# CPU-bound. What a test runs is unchanged; the caches go to the ignored __pycache__/.
sys.dont_write_bytecode = False
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)


# Ctrl-C reaches the commands the tests start, whatever started the suite. A suite run in the
# background (`make test &` in a script, nohup, a CI runner's job) has SIGINT ignored, as
# POSIX has it, and an ignored signal stays ignored in every child: `vt-edge collect` and
# `pose` then sat out the tests' Ctrl-C (exit 0 after the whole plan, or a prompt waiting
# 30 s). A handled signal is reset to its default in a child, so handling it here is enough.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--run-slow", action="store_true", help="also run tests marked slow")


# Before xdist's own hook, which reads the groups into the test ids.
@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if not config.getoption("--run-slow"):
        slow = [item for item in items if "slow" in item.keywords]
        if slow:
            config.hook.pytest_deselected(items=slow)
            items[:] = [item for item in items if "slow" not in item.keywords]
    _group_shared_fixtures(items)
    for item in items:
        if _uses_integration(item):
            item.add_marker(pytest.mark.integration)
    if hasattr(config, "workerinput"):  # an xdist worker: hand the long tests out first
        items.sort(key=_long_first)


SHARED_SCOPES = ("class", "module", "package", "session")
# The directories of the long end-to-end tests (collect, train, the lab's path, processes
# killed and restarted). xdist hands out the groups, largest first, then single tests in
# this order: a long test handed out last would run on alone while the other workers idle.
LONG_FIRST = ("tests/lab/", "tests/ops/", "tests/faults/", "tests/app/", "tests/runtime/",
              "tests/interfaces/", "tests/recordings/")


def _long_first(item: pytest.Item) -> int:
    return next((i for i, d in enumerate(LONG_FIRST) if item.nodeid.startswith(d)),
                len(LONG_FIRST))


def _group_shared_fixtures(items: list[pytest.Item]) -> None:
    """One ``xdist_group`` per set of tests joined by a wide-scoped fixture defined under
    tests/ (a test using two such fixtures joins both sets), named after the module or
    conftest directory that defines one of them."""
    parent: dict[str, str] = {}

    def find(owner: str) -> str:
        while parent.setdefault(owner, owner) != owner:
            owner = parent[owner]
        return owner

    owners_of: dict[pytest.Item, list[str]] = {}
    for item in items:
        info = getattr(item, "_fixtureinfo", None)
        if info is None:
            continue
        owners = sorted({f"{d.baseid}::{d.argname}" for name in item.fixturenames
                         for d in info.name2fixturedefs.get(name, ())
                         if d.scope in SHARED_SCOPES and d.baseid.startswith("tests")})
        for other in owners[1:]:
            parent[find(other)] = find(owners[0])
        if owners:
            owners_of[item] = owners
    for item, owners in owners_of.items():
        item.add_marker(pytest.mark.xdist_group(find(owners[0]).split("::")[0]))


# What makes a test an integration test: the modules that start a daemon (serve's assemble,
# the Daemon harness), a process (subprocess, the commands, the compute worker's pool), an
# emulator (the robot, the Dynamixel and XELA emulators, the virtual robot and the recorder
# that presses on it, the MQTT broker) or train a model (torch: its import alone takes
# seconds). A test is one when it, its fixtures or the test-module helpers they call name
# or import anything from these.
INTEGRATION = frozenset({
    "subprocess", "multiprocessing", "edge.app", "edge.sim.robot",
    "edge.sim.dxl_emulator", "edge.sim.xela_server", "edge.sim.virtual", "edge.lab.record",
    "tests.support.daemon", "tests.support.processes", "tests.support.mosquitto",
    "tests.support.presses", "tests.support.lab_data", "train.learn.trainer", "train.ship.release",
    "train.ship.build", "torch", "edge.runtime.compute.ComputeWorker",
})
# A test of the unit tier slower than this is named at the end of the run: mark it (or what
# it uses) integration, or make it cheaper. Generous: the tier's tests take milliseconds.
UNIT_TEST_BUDGET_S = 5.0


def _uses_integration(item: pytest.Item) -> bool:
    if item.get_closest_marker("integration"):
        return True
    functions = [getattr(item, "function", None)]
    info = getattr(item, "_fixtureinfo", None)
    if info is not None:
        functions += [d.func for name in item.fixturenames
                      for d in info.name2fixturedefs.get(name, ()) if d.baseid.startswith("tests")]
    return any(_names_integration(f, set()) for f in functions if f is not None)


def _names_integration(obj: object, seen: set[int]) -> bool:
    """Whether a function (or a class's methods) defined under tests/ names anything from
    :data:`INTEGRATION`, directly or through the tests' own helpers it names."""
    obj = inspect.unwrap(getattr(obj, "__func__", obj))
    if id(obj) in seen:
        return False
    seen.add(id(obj))
    if isinstance(obj, type):
        return any(_names_integration(v, seen) for v in vars(obj).values()
                   if inspect.isfunction(v))
    code = getattr(obj, "__code__", None)
    if code is None:
        return False
    found = _global_names(code)
    if any(_in_integration(name) for name in found):  # an import inside the function
        return True
    for name in found:
        value = obj.__globals__.get(name)
        module = value.__name__ if isinstance(value, types.ModuleType) else getattr(
            value, "__module__", None)
        if module is None:
            continue
        if _in_integration(f"{module}.{getattr(value, '__qualname__', '')}"):
            return True
        if module.startswith("tests.") and (inspect.isfunction(value) or isinstance(value, type)) \
                and _names_integration(value, seen):
            return True
    return False


def _in_integration(name: str) -> bool:
    """``name`` (a module, or a module's class or function) or a package above it is in
    :data:`INTEGRATION`."""
    parts = name.split(".")
    return any(".".join(parts[:n]) in INTEGRATION for n in range(1, len(parts) + 1))


def _global_names(code: types.CodeType) -> set[str]:
    names = set(code.co_names)
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            names |= _global_names(const)
    return names


_slow_units: list[tuple[str, float]] = []


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    # On xdist's controller too: the reports carry each test's keywords and duration.
    if (report.when == "call" and report.duration > UNIT_TEST_BUDGET_S
            and "integration" not in report.keywords):
        _slow_units.append((report.nodeid, report.duration))


def pytest_terminal_summary(terminalreporter) -> None:
    if _slow_units:
        terminalreporter.section("unit tests over their budget")
        for nodeid, took in _slow_units:
            terminalreporter.write_line(
                f"{nodeid}: {took:.1f} s > {UNIT_TEST_BUDGET_S} s: mark it integration "
                "(tests/conftest.py) or make it cheaper")


def pytest_configure(config: pytest.Config) -> None:
    """Refuse a pytest that xdist's groups do not work with. pytest 9.2 keeps a test's id
    where pytest-xdist 3.8 does not write the group, so ``--dist loadgroup`` silently
    groups nothing: every worker builds every shared fixture (a recorded dataset three
    times over) and the suite takes twice as long, with nothing failing."""
    if config.getoption("dist", "no") == "loadgroup" and pytest.version_tuple[:2] >= (9, 2):
        import xdist

        if tuple(int(p) for p in xdist.__version__.split(".")[:2]) <= (3, 8):
            raise pytest.UsageError(
                f"pytest {pytest.__version__} with pytest-xdist {xdist.__version__} ignores "
                "--dist loadgroup; install the dev extra's versions: pip install -e '.[dev]'")


def pytest_runtest_setup(item: pytest.Item) -> None:
    for mark in item.iter_markers("needs_program"):
        present, reason = mark.args
        if not present:
            if IN_CI:
                pytest.fail(f"{reason}; under CI this test must run", pytrace=False)
            pytest.skip(reason)


@pytest.fixture(autouse=True)
def logging_as_found():
    """A CLI's ``main`` configures logging once, onto the stderr of the test that first
    calls it: undo that afterwards, so later tests' captured stderr still gets the log
    lines. For every test: under xdist any test may follow one that called a ``main``."""
    import logging

    from edge.core import logs

    root = logging.getLogger()
    handlers, level, configured = list(root.handlers), root.level, logs._configured
    yield
    for handler in [h for h in root.handlers if h not in handlers]:
        root.removeHandler(handler)
    root.setLevel(level)
    logs._configured = configured
