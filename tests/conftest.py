"""Shared pytest set-up: tests marked ``slow`` are deselected unless ``--run-slow``; tests
marked ``needs_program(present, reason)`` skip, saying why, where a system program is
missing, and fail instead under CI (``CI=true``), which installs them: a skip there would
hide a test that never ran."""

from __future__ import annotations

import os

import pytest

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--run-slow", action="store_true", help="also run tests marked slow")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--run-slow"):
        return
    slow = [item for item in items if "slow" in item.keywords]
    if slow:
        config.hook.pytest_deselected(items=slow)
        items[:] = [item for item in items if "slow" not in item.keywords]


def pytest_runtest_setup(item: pytest.Item) -> None:
    for mark in item.iter_markers("needs_program"):
        present, reason = mark.args
        if not present:
            if IN_CI:
                pytest.fail(f"{reason}; under CI this test must run", pytrace=False)
            pytest.skip(reason)


@pytest.fixture
def logging_as_found():
    """A CLI's ``main`` configures logging once, onto the stderr of the test that first
    calls it: undo that afterwards, so later tests' captured stderr still gets the log
    lines."""
    import logging

    from edge.core import logs

    root = logging.getLogger()
    handlers, level, configured = list(root.handlers), root.level, logs._configured
    yield
    for handler in [h for h in root.handlers if h not in handlers]:
        root.removeHandler(handler)
    root.setLevel(level)
    logs._configured = configured
