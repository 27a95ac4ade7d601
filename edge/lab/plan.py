"""A collection plan: one TOML file for a whole dataset of presses (``vt-edge collect --plan``).

::

    [dataset]
    name = "lab_reference"      # the dataset's name (dataset.json "dataset")
    recorder = "A. Tanaka"      # who presses (default: the login name)
    robot = "arm-1"             # the robot (default: the host name; the emulated robot: none)
    presses = 10                # default presses per class
    photo = false               # default: a photo per kept press
    val = ["wood_cube"]         # validation classes (split "val"); the others are "train"
    # test = true               # instead: a test set (every class split "test"), no val

    [[class]]
    label = "otedama"
    description = "otedama (a small Japanese cloth beanbag filled with beans)"
    x_th = 0.003                # optional; default the configuration's [press] x_th
    presses = 12                # optional; default [dataset] presses
    photo = true                # optional; default [dataset] photo

The sensor model comes from the xela_server stream at collect time, not from the plan.
"""

from __future__ import annotations

import getpass
import hashlib
import json
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from edge.core.descriptions import check_description
from edge.core.errors import ConfigError, DescriptionError

Split = Literal["train", "val", "test"]
# More presses than this of one class is a typo (the paper takes 10).
MAX_PRESSES = 1000
_DATASET_KEYS = {"name", "recorder", "robot", "presses", "photo", "val", "test"}
_CLASS_KEYS = {"label", "description", "presses", "x_th", "photo"}


@dataclass(frozen=True)
class PlanClass:
    label: str
    description: str
    split: Split
    presses: int
    x_th: float | None  # None: the configuration's [press] x_th
    photo: bool

    def threshold(self, default_x_th: float) -> float:
        return default_x_th if self.x_th is None else self.x_th


@dataclass(frozen=True)
class Plan:
    name: str
    classes: tuple[PlanClass, ...]
    recorder: str  # who presses
    robot: str | None  # None: the host name on a robot
    sha256: str  # of the plan file (of the plan's content for a plan of one class)
    source: str  # the file, or "--label ..." for a plan of one class

    def get(self, label: str) -> PlanClass:
        for c in self.classes:
            if c.label == label:
                return c
        raise KeyError(label)

    @property
    def single(self) -> bool:
        """A plan of one class from the command line (``--label``)."""
        return self.source.startswith("--label")


def _login() -> str:
    try:
        return getpass.getuser()
    except (KeyError, OSError):  # no login name (a container without a passwd entry)
        return "unknown"


def check_label(label: object, where: str) -> str:
    if not isinstance(label, str) or not label or not label.replace("_", "").isalnum():
        raise ConfigError(f"{where}: label = {label!r}: use letters, digits and underscores")
    return label


def _typed(value: Any, kind: type, where: str, field: str, what: str) -> Any:
    # bool is an int to Python, never to a plan.
    ok = isinstance(value, kind) and not (kind is not bool and isinstance(value, bool))
    if not ok:
        raise ConfigError(f"{where}: {field} = {value!r}: must be {what}")
    return value


def _presses(value: Any, where: str) -> int:
    n = _typed(value, int, where, "presses", "a whole number")
    if not 1 <= n <= MAX_PRESSES:
        raise ConfigError(f"{where}: presses = {n}: must be 1..{MAX_PRESSES}")
    return n


def _x_th(value: Any, where: str) -> float | None:
    if value is None:
        return None
    x = float(_typed(value, (int, float), where, "x_th", "a number (tactile units)"))
    if not (math.isfinite(x) and 0 < x < 1):
        raise ConfigError(f"{where}: x_th = {x}: must be in (0, 1) (e.g. 0.004; 0.003 for "
                          "a fragile object)")
    return x


def _unknown(table: dict, allowed: set[str], where: str) -> None:
    extra = sorted(set(table) - allowed)
    if extra:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(extra)}; allowed: "
                          f"{', '.join(sorted(allowed))}")


def parse_plan(data: dict, source: str, sha256: str) -> Plan:
    """The plan in ``data`` (a parsed TOML document); ConfigError naming the field."""
    _unknown(data, {"dataset", "class"}, source)
    ds = data.get("dataset")
    if not isinstance(ds, dict):
        raise ConfigError(f"{source}: no [dataset] table (name, and val or test)")
    where = f"{source} [dataset]"
    _unknown(ds, _DATASET_KEYS, where)
    name = ds.get("name")
    if not isinstance(name, str) or not name.strip():
        raise ConfigError(f"{where}: name = {name!r}: name the dataset, e.g. \"lab_reference\"")
    recorder = _typed(ds.get("recorder", _login()), str, where, "recorder", "a name")
    robot = ds.get("robot")
    if robot is not None:
        _typed(robot, str, where, "robot", "a name")
    presses = _presses(ds.get("presses", 10), where)
    photo = _typed(ds.get("photo", False), bool, where, "photo", "true or false")
    test = _typed(ds.get("test", False), bool, where, "test", "true or false")
    val = ds.get("val", [])
    if not isinstance(val, list) or not all(isinstance(v, str) for v in val):
        raise ConfigError(f"{where}: val = {val!r}: must be a list of class labels")
    if test and val:
        raise ConfigError(f"{where}: a test set (test = true) has no validation classes (val)")
    rows = data.get("class")
    if not isinstance(rows, list) or not rows:
        raise ConfigError(f"{source}: no [[class]] tables: list the objects to press")
    classes: list[PlanClass] = []
    for i, row in enumerate(rows, 1):
        cwhere = f"{source} [[class]] {i}"
        if not isinstance(row, dict):
            raise ConfigError(f"{cwhere}: must be a table")
        label = check_label(row.get("label"), cwhere)
        cwhere = f"{source} class {label!r}"
        _unknown(row, _CLASS_KEYS, cwhere)
        if any(c.label == label for c in classes):
            raise ConfigError(f"{cwhere}: listed twice")
        try:
            description = check_description(row.get("description", ""), label)
        except DescriptionError as exc:
            raise ConfigError(f"{source}: {exc}") from None
        split: Split = "test" if test else "val" if label in val else "train"
        classes.append(PlanClass(
            label, description, split, _presses(row.get("presses", presses), cwhere),
            _x_th(row.get("x_th"), cwhere),
            _typed(row.get("photo", photo), bool, cwhere, "photo", "true or false")))
    unknown_val = [v for v in val if all(c.label != v for c in classes)]
    if unknown_val:
        raise ConfigError(f"{where}: val names {', '.join(unknown_val)}, which no [[class]] "
                          "has")
    if not test and not val:
        raise ConfigError(f"{where}: no validation classes: list some in val (the paper holds "
                          "out 5 of 32), or say test = true for a test set")
    return Plan(name.strip(), tuple(classes), recorder, robot, sha256, source)


def load_plan(path: str | Path) -> Plan:
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"plan {path}: cannot read: {exc.strerror or exc}") from None
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"plan {path}: not valid TOML: {exc}") from None
    return parse_plan(data, str(path), hashlib.sha256(raw).hexdigest())


def plan_of_one(label: str, presses: int, *, description: str | None = None,
                x_th: float | None = None, photo: bool = False, name: str = "collected",
                split: Split = "train") -> Plan:
    """Single-object collect (``--label NAME --presses N``) as a plan of one class."""
    source = f"--label {label}"
    check_label(label, source)
    where = f"{source}"
    try:
        desc = check_description(description or label.replace("_", " "), label)
    except DescriptionError as exc:
        raise ConfigError(f"{exc} (pass --description)") from None
    cls = PlanClass(label, desc, split, _presses(presses, where), _x_th(x_th, where), photo)
    content = json.dumps({"name": name, "class": cls.__dict__}, sort_keys=True)
    return Plan(name, (cls,), _login(), None,
                hashlib.sha256(content.encode()).hexdigest(), source)
