"""Edit TOML config files in place, keeping comments and layout (tomlkit), atomically."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import tomlkit

from edge.core.atomic import atomic_write_text
from edge.core.config import config_from_dict
from edge.core.errors import ConfigError


def update(src: str | Path, dest: str | Path, changes: dict[str, dict[str, Any]]) -> None:
    """Write ``src`` with ``changes`` ({table: {key: value}}) applied to ``dest``.

    The result is validated as a whole before it replaces ``dest``.
    """
    try:
        doc = tomlkit.parse(Path(src).read_text(encoding="utf-8"))
    except (OSError, tomlkit.exceptions.ParseError) as exc:
        raise ConfigError(f"{src}: cannot edit: {exc}") from None
    for table, values in changes.items():
        if table not in doc:
            doc[table] = tomlkit.table()
        for key, value in values.items():
            doc[table][key] = value  # type: ignore[index]
    text = tomlkit.dumps(doc)
    import tomllib

    config_from_dict(tomllib.loads(text), source=str(dest))
    atomic_write_text(dest, text)
