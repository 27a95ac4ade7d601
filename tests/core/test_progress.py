"""Progress of long commands: whole lines when stderr is not a terminal, a bar when it is."""

import io
import re
import subprocess
import sys

from edge.core.progress import Progress

LINE = re.compile(r"^record cube: (\d+)/8 presses, \d+\.\d s(, .*)?$")


def test_not_a_terminal_gives_one_whole_line_per_update():
    out = io.StringIO()
    with Progress("record cube", 8, "presses", stream=out, every_s=0.0) as bar:
        for i in range(8):
            bar.update(1, f"press {i}" if i % 2 else None)
    text = out.getvalue()
    assert "\r" not in text and "\x1b" not in text
    lines = text.splitlines()
    assert len(lines) == 8 and text.endswith("\n")  # the close repeats nothing
    assert [int(LINE.match(line).group(1)) for line in lines] == list(range(1, 9))
    assert lines[1].endswith(", press 1") and lines[2].endswith(", press 1")


def test_not_a_terminal_is_periodic_and_always_ends_with_the_final_state():
    out = io.StringIO()
    with Progress("record cube", 8, "presses", stream=out, every_s=3600.0) as bar:
        for _ in range(8):
            bar.update()
    lines = out.getvalue().splitlines()
    assert len(lines) == 1 and LINE.match(lines[0]).group(1) == "8"


def test_a_terminal_gets_a_bar_redrawn_in_place():
    class Tty(io.StringIO):
        def isatty(self):
            return True

    out = Tty()
    with Progress("record cube", 8, "presses", stream=out) as bar:
        for _ in range(8):
            bar.update(1, "ok")
    text = out.getvalue()
    assert "\r" in text and "8/8" in text and "ok" in text


def test_disabled_prints_nothing():
    out = io.StringIO()
    with Progress("x", 3, stream=out, every_s=0.0, enabled=False) as bar:
        bar.update(3)
    assert out.getvalue() == ""


def test_sim_record_in_a_log_prints_lines_not_a_run_together_line(tmp_path):
    out = subprocess.run([sys.executable, "-m", "edge", "sim", "record", "--dataset", "cube",
                          "--presses", "2", "--out", str(tmp_path), "--workers", "1"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    progress = [line for line in out.stderr.splitlines() if line.startswith("record cube")]
    assert progress and "\r" not in out.stderr
    assert all(LINE.match(line) for line in progress), progress
    assert progress[-1].startswith("record cube: 8/8 presses")
