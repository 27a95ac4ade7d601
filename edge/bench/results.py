"""One results file for both benches: ``results.json``, ``results.md`` and ``raw.json``.

``vt-edge bench`` starts a file with the runtime's phases; ``vt-train bench --merge-into``
adds the training side's (torch, training) to it; ``make bench`` runs the two. The file:

- ``host``: the machine and the library versions, load average at the start;
- ``run``: when, which command(s), settings, the phases run and the CPU during each
  (``phase_cpu``: cores busy on the host, how many of them by the bench, how many by
  other processes), duration, load average at the end, and what a phase adds (the load);
- one key per figure (:mod:`edge.bench.figures`), each with ``host_cores_busy`` during its
  phase;
- ``sections``: titled markdown text the phases add (how to read their figures);
- ``run.baseline`` (optional): an earlier run's figures (p50, p99), rendered as a "Before
  and after" table;
- ``notes``: what the phases noticed, then one line per missed target with why.

``results.md`` is rendered from ``results.json`` alone, so either side can write both;
``raw.json`` holds every sample a phase keeps (every press). Every file is replaced
atomically.
"""

from __future__ import annotations

import contextlib
import datetime
import importlib.metadata
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from edge.bench.figures import Figure, explain, is_figure, short, target_text
from edge.bench.proc import host_cpu_s, own_tree_cpu_s
from edge.core.atomic import atomic_write_text

ROOT = Path(__file__).resolve().parents[2]
RESULTS, MARKDOWN, RAW = "results.json", "results.md", "raw.json"
# Keys of a figure that the "What each figure is" list does not repeat.
_TABLE_KEYS = ("p50", "p99", "max", "n", "unit", "target", "met", "what", "host_cores_busy")


def progress(msg: str) -> None:
    print(f"[bench {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _cpu_model() -> str:
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def version(dist: str) -> str | None:
    """The installed version of distribution ``dist``, None if absent (nothing imported)."""
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def host_info() -> dict[str, Any]:
    commit = None
    with contextlib.suppress(OSError, subprocess.SubprocessError):
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, text=True,
                                capture_output=True, timeout=5).stdout.strip() or None
    return {
        "cpu_model": _cpu_model(),
        "cores": os.cpu_count(),
        "cores_usable": len(os.sched_getaffinity(0)),
        "python": platform.python_version(),
        "implementation": platform.python_implementation(),
        "kernel": platform.release(),
        "numpy": np.__version__,
        "onnxruntime": version("onnxruntime"),
        "torch": version("torch"),
        "aiohttp": version("aiohttp"),
        "loadavg_start": list(os.getloadavg()),
        "switch_interval_s": sys.getswitchinterval(),
        "git_commit": commit,
    }


@dataclass
class PhaseResult:
    """What one phase measured."""

    figures: dict[str, Figure]
    notes: list[str] = field(default_factory=list)
    run: dict[str, Any] = field(default_factory=dict)  # added to ``run`` (e.g. the load)
    raw: dict[str, Any] = field(default_factory=dict)  # added to raw.json (e.g. every press)
    sections: dict[str, str] = field(default_factory=dict)  # title -> markdown


CpuMark = tuple[float, tuple[float, float], float]


def cpu_mark() -> CpuMark:
    return time.monotonic(), host_cpu_s(), own_tree_cpu_s()


def cpu_since(mark: CpuMark) -> dict[str, float]:
    """Cores busy on the host since ``mark``, and how many by processes not the bench's."""
    wall = time.monotonic() - mark[0]
    ours = (own_tree_cpu_s() - mark[2]) / wall
    host = (host_cpu_s()[0] - mark[1][0]) / wall
    return {"wall_s": round(wall, 1), "host_cores_busy": round(host, 2),
            "bench_cores": round(ours, 2), "other_cores": round(max(0.0, host - ours), 2)}


class Results:
    """The results file in memory; phases add to it, :meth:`write` replaces the files."""

    def __init__(self, data: Mapping[str, Any], raw: dict[str, Any] | None = None) -> None:
        self.host: dict[str, Any] = dict(data["host"])
        self.run: dict[str, Any] = dict(data["run"])
        self.run.setdefault("phases", [])
        self.run.setdefault("phase_cpu", {})
        self.figures: dict[str, Figure] = {k: v for k, v in data.items() if is_figure(v)}
        self.sections: dict[str, str] = dict(data.get("sections", {}))
        self.notes: list[str] = list(data.get("notes", []))
        self.raw = raw  # None: loaded to add phases to; raw.json is left as it is
        self._started = time.monotonic()
        self._duration_before = float(self.run.get("duration_s") or 0.0)
        self._new: list[str] = []  # figures measured by this process (explained on write)

    @classmethod
    def start(cls, command: str, quick: bool, settings: dict[str, Any]) -> Results:
        host = host_info()
        run = {"quick": quick, "settings": settings, "phases": [],
               "started_at": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
               "command": command, "phase_cpu": {}}
        progress(f"{'quick' if quick else 'full'} run on {host['cpu_model']} "
                 f"({host['cores']} cores), load average {host['loadavg_start']}")
        return cls({"host": host, "run": run}, raw={})

    @classmethod
    def load(cls, path: str | Path) -> Results:
        """An existing ``results.json``, to add phases to (its raw.json stays as it is)."""
        try:
            data = json.loads(Path(path).read_text())
            return cls(data)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{path}: not a bench results file ({exc})") from None

    def set_baseline(self, path: str | Path) -> bool:
        """Keep the figures of an earlier ``results.json`` to compare with; False (said on
        stderr) if there is none to read."""
        try:
            data = json.loads(Path(path).read_text())
            figures = {k: {"p50": v["p50"], "p99": v["p99"], "unit": v["unit"]}
                       for k, v in data.items() if is_figure(v)}
            self.run["baseline"] = {
                "path": str(path), "commit": data["host"].get("git_commit"),
                "started_at": data["run"].get("started_at"), "figures": figures}
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            progress(f"no baseline to compare with: {path}: {exc}")
            return False
        return True

    def add_command(self, command: str, settings_key: str, settings: dict[str, Any]) -> None:
        """Record that ``command`` (with ``settings``) adds its phases to this file."""
        self.run["command"] = f"{self.run.get('command', '')} && {command}".lstrip(" &")
        self.run[settings_key] = settings

    def run_phase(self, name: str, measure: Callable[[], PhaseResult]) -> None:
        """Run one phase, accounting the CPU on the host while it ran."""
        if name in self.run["phases"]:
            raise ValueError(f"phase {name!r} is already in these results")
        before = cpu_mark()
        result = measure()
        cpu = cpu_since(before)
        self.run["phases"].append(name)
        self.run["phase_cpu"][name] = cpu
        for key, fig in result.figures.items():
            fig["host_cores_busy"] = cpu["host_cores_busy"]
            self.figures[key] = fig
            self._new.append(key)
        self.notes += result.notes
        self.run.update(result.run)
        self.sections.update(result.sections)
        if result.raw:
            if self.raw is None:
                raise ValueError(f"phase {name!r} keeps raw samples: start a new file")
            self.raw.update(result.raw)
        progress(f"{name}: host {cpu['host_cores_busy']:.2f} of {self.host['cores']} cores "
                 f"busy, {cpu['other_cores']:.2f} of them by other processes")

    def order(self, keys: Iterable[str]) -> None:
        """Figures named in ``keys`` first, in that order (the table's order)."""
        keys = [k for k in keys if k in self.figures]
        rest = [k for k in self.figures if k not in keys]
        self.figures = {k: self.figures[k] for k in [*keys, *rest]}

    def to_json(self) -> dict[str, Any]:
        return {"host": self.host, "run": self.run, **self.figures,
                "sections": self.sections, "notes": self.notes}

    def write(self, out: str | Path, why: Mapping[str, str] | None = None) -> str:
        """Explain the missed targets of the figures measured here (``why[key]``), then
        replace ``results.json``, ``raw.json`` (if phases here kept raw samples) and
        ``results.md``; returns the markdown."""
        out = Path(out)
        self.notes += explain({k: self.figures[k] for k in self._new}, why or {})
        self._new = []
        self.run["duration_s"] = self._duration_before + time.monotonic() - self._started
        self.run["loadavg_end"] = list(os.getloadavg())
        if self.raw:
            atomic_write_text(out / RAW, json.dumps(self.raw, indent=1, default=_plain) + "\n")
        data = self.to_json()
        atomic_write_text(out / RESULTS, json.dumps(data, indent=1, default=_plain) + "\n")
        md = markdown(data)
        atomic_write_text(out / MARKDOWN, md)
        return md


def _plain(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def _cell(value: Any, unit: str) -> str:
    if value is None:
        return "-"
    if unit == "ratio":
        return f"{value:.1f}x"
    if isinstance(value, int) or (float(value).is_integer() and abs(value) > 10):
        return f"{value:g}"
    return f"{value:.3g}" if abs(value) < 100 else f"{value:.0f}"


def _before_after(baseline: Mapping[str, Any] | None,
                  figs: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """The "Before and after" section: each figure of both runs, p50 and p99."""
    if not baseline:
        return []
    before = baseline.get("figures", {})
    lines = ["", "## Before and after", "",
             f"Against `{baseline.get('path')}`: commit {baseline.get('commit')}, "
             f"{baseline.get('started_at')} (p50 and p99, before -> now).", "",
             "| figure | p50 before | p50 now | p99 before | p99 now | unit |",
             "| --- | ---: | ---: | ---: | ---: | --- |"]
    for key, f in figs.items():
        b = before.get(key)
        if b is None:
            continue
        unit = f["unit"]
        lines.append(f"| `{key}` | {_cell(b['p50'], unit)} | {_cell(f['p50'], unit)} | "
                     f"{_cell(b['p99'], unit)} | {_cell(f['p99'], unit)} | {unit} |")
    return lines


def markdown(results: Mapping[str, Any]) -> str:
    """``results.md``: from a ``results.json`` alone."""
    host, run = results["host"], results["run"]
    figs = {k: v for k, v in results.items() if is_figure(v)}
    lines = [
        "# vtzero bench",
        "",
        f"{'QUICK run (smoke test: figures are not representative). ' if run['quick'] else ''}"
        f"{run['started_at']}, {run['duration_s']:.0f} s. Host: {host['cpu_model']}, "
        f"{host['cores']} cores, Python {host['python']}, onnxruntime {host['onnxruntime']}, "
        f"numpy {host['numpy']}, torch {host['torch']}; load average at start "
        f"{', '.join(f'{v:.2f}' for v in host['loadavg_start'])}, at end "
        f"{', '.join(f'{v:.2f}' for v in run['loadavg_end'])}. Commit {host['git_commit']}. "
        f"Command: `{run['command']}`.",
        "",
        "CPU during each phase (cores busy on the host / of them by processes outside the "
        "bench): " + "; ".join(f"{name} {c['host_cores_busy']:.2f} / {c['other_cores']:.2f}"
                               for name, c in run.get("phase_cpu", {}).items()) + ".",
        "",
        "| figure | p50 | p99 | max | n | unit | target | met |",
        "| --- | ---: | ---: | ---: | ---: | --- | --- | --- |",
    ]
    for key, f in figs.items():
        met = {True: "yes", False: "**NO**", None: "-"}[f["met"]]
        lines.append(f"| `{key}` | {_cell(f['p50'], f['unit'])} | {_cell(f['p99'], f['unit'])} "
                     f"| {_cell(f['max'], f['unit'])} | {f['n']} | {f['unit']} | "
                     f"{target_text(f['target'])} | {met} |")
    lines += _before_after(run.get("baseline"), figs)
    for title, text in results.get("sections", {}).items():
        lines += ["", f"## {title}", "", text.rstrip("\n")]
    lines += ["", "## What each figure is", ""]
    for key, f in figs.items():
        extra = {k: v for k, v in f.items() if k not in _TABLE_KEYS}
        detail = ", ".join(f"{k} {short(v)}" for k, v in extra.items())
        lines.append(f"- `{key}`: {f.get('what', '')}" + (f" ({detail})" if detail else ""))
    notes = results.get("notes", [])
    if notes:
        lines += ["", "## Notes", ""] + [f"- {n}" for n in notes]
    return "\n".join(lines) + "\n"
