"""Every `vt-edge` and `vt-train` command line in README.md and docs/*.md is accepted by the
real parsers, so the docs cannot drift from the command line.

A command line is a line of a fenced code block or an inline code span whose program is
``vt-edge`` or ``vt-train`` (any directory, after ``sudo`` and ``NAME=value`` settings). The
docs' placeholders are read as a reader would: ``[...]`` is an optional part (taken), ``A|B``
alternatives (each tried), ``...`` "and so on" (dropped). A span that names a command without
any option (``vt-edge run``, ``vt-edge calibrate threshold``) is a mention: it must name a
real command, and may leave out the arguments that command requires.
"""

from __future__ import annotations

import argparse
import itertools
import re
import shlex
from pathlib import Path

import pytest

from edge.cli import _resolve_config
from edge.cli import build_parser as edge_parser
from train.cli import build_parser as train_parser

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PARSERS = {"vt-edge": edge_parser, "vt-train": train_parser}
FENCE = re.compile(r"^ *```[^\n]*\n(.*?)^ *```", re.S | re.M)
SPAN = re.compile(r"`([^`]+)`")
MISSING = "the following arguments are required"


class Refused(Exception):
    pass


def _commands(text: str) -> list[tuple[str, bool]]:
    """(command line, from a span) for every command line in a Markdown text."""
    found = []
    for block in FENCE.findall(text):
        for line in block.replace("\\\n", " ").splitlines():
            found.append((line, False))
    prose = FENCE.sub("", text)
    found += [(" ".join(span.split()), True) for span in SPAN.findall(prose)]
    out = []
    for line, in_span in found:
        try:
            words = shlex.split(line, comments=True)
        except ValueError:  # a quote left open in prose: not a command line
            continue
        for part in _split_commands(words):
            while part and (part[0] == "sudo" or re.fullmatch(r"[A-Z_]+=\S*", part[0])):
                part = part[1:]
                if part and part[0] == "-u":
                    part = part[2:]
            if part and Path(part[0]).name in PARSERS:
                out.append((shlex.join([Path(part[0]).name, *part[1:]]), in_span))
    return out


def _split_commands(words: list[str]) -> list[list[str]]:
    parts: list[list[str]] = [[]]
    for w in words:
        if w in ("&&", "||", ";", "|"):
            parts.append([])
        else:
            parts[-1].append(w)
    return parts


def _variants(command: str) -> list[list[str]]:
    """The command lines a documented one stands for (see the module's docstring)."""
    words = [w.strip("[]") for w in shlex.split(command) if w.strip("[]") not in ("", "...")]
    words = [w.removesuffix("...") for w in words]
    choices = [w.split("|") if "|" in w and not w.startswith("|") else [w] for w in words]
    return [list(c) for c in itertools.product(*choices)]


def _documented() -> list[tuple[str, str, bool]]:
    out = []
    for doc in DOCS:
        for command, in_span in _commands(doc.read_text(encoding="utf-8")):
            out.append((doc.name, command, in_span))
    return out


def _parse(words: list[str], monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(self: argparse.ArgumentParser, message: str) -> None:
        raise Refused(message)

    monkeypatch.setattr(argparse.ArgumentParser, "error", refuse)
    parser = PARSERS[words[0]]()
    args = parser.parse_args(words[1:])
    if words[0] == "vt-edge":
        _resolve_config(parser, args)


DOCUMENTED = _documented()


def test_the_docs_hold_command_lines():
    # The extraction itself: both programs, in prose and in code blocks, in several files.
    print(f"{len(DOCUMENTED)} command lines")
    assert len(DOCUMENTED) >= 60
    assert {c.split()[0] for _, c, _ in DOCUMENTED} == {"vt-edge", "vt-train"}
    assert {d for d, _, _ in DOCUMENTED} >= {"README.md", "hardware.md"}
    assert any(not span for _, _, span in DOCUMENTED)


@pytest.mark.parametrize(("doc", "command", "in_span"), DOCUMENTED,
                         ids=[f"{d}:{c}" for d, c, _ in DOCUMENTED])
def test_a_documented_command_line_parses(doc, command, in_span, monkeypatch):
    for words in _variants(command):
        try:
            _parse(words, monkeypatch)
        except Refused as exc:
            mention = in_span and not any(w.startswith("-") for w in words[1:])
            if not (mention and MISSING in str(exc)):
                pytest.fail(f"{doc}: `{' '.join(words)}`: {exc}")
        except SystemExit as exc:  # --help, --version
            assert exc.code == 0


def test_the_parser_check_refuses_what_the_cli_refuses(monkeypatch):
    # The check can fail: a wrong option, a wrong choice, an option written as a mention.
    for bad in ("vt-edge episodes list --bogus", "vt-edge sim record --dataset bricks "
                "--out x", "vt-train build --nope", "vt-edge collect --plan"):
        with pytest.raises(Refused):
            _parse(shlex.split(bad), monkeypatch)
