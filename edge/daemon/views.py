"""Episodes as the services beside the press read them (MQTT, MCAP, the operator page).

The store's episodes are read through its public methods; whether it hands out a dict or a
typed episode, these services see the episode's JSON keys (the keys on disk).
"""

from __future__ import annotations

import dataclasses
from typing import Any


def as_dict(episode: Any) -> dict[str, Any]:
    """The episode as its JSON keys, whether the store gives a dict or a typed episode."""
    if isinstance(episode, dict):
        return episode
    for method in ("to_dict", "as_dict", "to_json_dict"):
        if callable(getattr(episode, method, None)):
            return dict(getattr(episode, method)())
    if dataclasses.is_dataclass(episode) and not isinstance(episode, type):
        return dataclasses.asdict(episode)
    return dict(vars(episode))
