"""Asking the running daemon over its HTTP API, as the commands that go through it do
(``vt-edge episodes retry``, ``vt-edge teach``, ``vt-edge references``): the daemon is the
one owner of the bus and the one writer of its store, so these never act on either
themselves. Standard library only: a command's start stays cheap."""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from collections.abc import Mapping
from typing import Any

from edge.core.config import Config
from edge.core.errors import BadRequest, BusyError, EdgeError, NotFoundError

# What each refusal status means, as the API answers it.
REFUSALS: Mapping[int, type[EdgeError]] = {400: BadRequest, 404: NotFoundError,
                                           409: BusyError}


def daemon_url(cfg: Config) -> str:
    """Where this configuration's daemon listens, as a client on this machine reaches it."""
    host = cfg.api.host
    if host in ("", "0.0.0.0", "::"):
        host = "127.0.0.1"
    if ":" in host:
        host = f"[{host}]"
    return f"http://{host}:{cfg.api.port}"


def ask_daemon(cfg: Config, method: str, path: str, body: dict[str, Any] | None, *,
               timeout_s: float, what: str, url: str | None = None,
               refusals: Mapping[int, type[EdgeError]] = REFUSALS) -> Any:
    """The running daemon's JSON answer to ``method path``. A refusal raises the
    :class:`EdgeError` its status means (``refusals``) with the daemon's one-line reason; no
    daemon answering raises one line saying that ``what`` goes through it."""
    from edge.interfaces.http.api import load_token

    base = url or daemon_url(cfg)
    data = b"" if body is None and method == "POST" else (
        None if body is None else json.dumps(body).encode())
    request = urllib.request.Request(base + path, data=data, method=method)
    if body is not None:
        request.add_header("Content-Type", "application/json")
    token = load_token(cfg.api)
    if token:
        request.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(request, timeout=timeout_s) as resp:
            return json.loads(resp.read())
    except urllib.error.HTTPError as exc:
        try:
            reason = json.loads(exc.read()).get("error", exc.reason)
        except (ValueError, AttributeError):
            reason = exc.reason
        error = refusals.get(exc.code, EdgeError)
        raise error(f"the daemon at {base} refused: HTTP {exc.code}: {reason}") from None
    except (urllib.error.URLError, OSError) as exc:
        why = getattr(exc, "reason", exc)
        raise EdgeError(f"no daemon answers at {base} ({why}): {what} goes through the "
                        "running daemon; start it with `vt-edge run --config FILE` (or give "
                        "--url)") from None
