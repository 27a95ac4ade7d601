"""Shared pytest set-up: tests marked ``slow`` are deselected unless ``--run-slow``; tests
marked ``needs_program(present, reason)`` skip, saying why, where a system program is
missing, and fail instead under CI (``CI=true``), which installs them: a skip there would
hide a test that never ran. Under pytest-xdist (``-n N --dist loadgroup``, as ``make test``
runs), the tests that share one of our module- or session-wide fixtures are put in one
``xdist_group``, so that fixture (a daemon, a recorded dataset, a trained model) is built
once, on one worker; every other test goes to whichever worker is free."""

from __future__ import annotations

import os
import signal
import sys

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
    if hasattr(config, "workerinput"):  # an xdist worker: hand the long tests out first
        items.sort(key=_long_first)


SHARED_SCOPES = ("class", "module", "package", "session")
# The directories of the long end-to-end tests (collect, train, the lab's path, processes
# killed and restarted). xdist hands out the groups, largest first, then single tests in
# this order: a long test handed out last would run on alone while the other workers idle.
LONG_FIRST = ("tests/tools/", "tests/faults/", "tests/daemon/")


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
