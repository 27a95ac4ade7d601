import subprocess
import sys


def _log_line(env_extra):
    code = ("import logging; from edge.core.logs import setup_logging; setup_logging(); "
            "logging.getLogger('edge.x').info('hello %s', 'there')")
    import os
    env = {k: v for k, v in os.environ.items() if k != "JOURNAL_STREAM"}
    env.update(env_extra)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         check=True)
    return out.stderr.strip()


def test_journal_lines_have_no_timestamp():
    assert _log_line({"JOURNAL_STREAM": "8:1234"}) == "INFO edge.x: hello there"


def test_terminal_lines_have_a_timestamp():
    line = _log_line({})
    assert line.endswith("INFO edge.x: hello there")
    assert line[:4].isdigit()


def test_lines_go_to_stderr_as_it_is_when_logged():
    """A caller that swaps sys.stderr after logging was set up (a test capturing a command's
    output) reads what was logged since."""
    code = ("import io, logging, sys; from edge.core.logs import setup_logging; "
            "setup_logging(); real = sys.stderr; sys.stderr = io.StringIO(); "
            "logging.getLogger('edge.x').error('refused'); text = sys.stderr.getvalue(); "
            "sys.stderr = real; print(text.strip())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip().endswith("ERROR edge.x: refused") and out.stderr == ""
