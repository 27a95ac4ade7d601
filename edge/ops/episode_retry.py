"""``vt-edge episodes retry ID | --all-failed``: ask the VLM again about episodes that ended
``vlm_error`` or ``invalid_answer``, with their stored description and photo.

The command asks the running daemon (``POST /v1/episodes/{id}/retry``) rather than working on
the store with the configuration's VLM itself: the daemon is the one writer of its store (a
second process answering the same episode would race the daemon's own updates of it), its
VLM client already knows which structured-output mode the server takes, and the answer
reaches the operator page, MQTT and ``/metrics`` like any other. So ``vt-edge run`` must be
up; when it is not, the command says so in one line. The store is only read here, to find
the failed episodes for ``--all-failed``.
"""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from collections.abc import Callable

from edge.core.config import Config
from edge.core.errors import EdgeError, NotFoundError, StateError
from edge.runtime.domain import Status
from edge.runtime.recognition import RE_ASKABLE
from edge.runtime.store import EpisodeStore

# Beyond the VLM's own time for one question (transport retries and the corrective retry
# come from the configuration), what the daemon may take to answer.
RETRY_MARGIN_S = 30.0


def daemon_url(cfg: Config) -> str:
    """Where this configuration's daemon listens, as a client on this machine reaches it."""
    host = cfg.api.host
    if host in ("", "0.0.0.0", "::"):
        host = "127.0.0.1"
    if ":" in host:
        host = f"[{host}]"
    return f"http://{host}:{cfg.api.port}"


def failed_ids(store: EpisodeStore) -> list[str]:
    """The ``vlm_error`` and ``invalid_answer`` episodes, oldest first."""
    return [ep.id for ep in reversed(store.list()) if ep.status in RE_ASKABLE]


def retry_episode(cfg: Config, episode_id: str, url: str | None = None) -> dict:
    """The episode as the daemon stored it after asking again; :class:`NotFoundError`,
    :class:`StateError` or :class:`EdgeError` with the daemon's one-line reason."""
    from edge.interfaces.http.api import load_token

    base = url or daemon_url(cfg)
    token = load_token(cfg.api)
    request = urllib.request.Request(f"{base}/v1/episodes/{episode_id}/retry", data=b"",
                                     method="POST")
    if token:
        request.add_header("Authorization", f"Bearer {token}")
    vlm = cfg.vlm
    timeout_s = (2 * (vlm.max_retries + 1) * vlm.total_timeout_s
                 + vlm.max_retries * vlm.backoff_cap_s + RETRY_MARGIN_S)
    try:
        with urllib.request.urlopen(request, timeout=timeout_s) as resp:
            return json.loads(resp.read())
    except urllib.error.HTTPError as exc:
        try:
            reason = json.loads(exc.read()).get("error", exc.reason)
        except (ValueError, AttributeError):
            reason = exc.reason
        if exc.code == 404:
            raise NotFoundError(f"{reason} (daemon at {base})") from None
        if exc.code == 409:
            raise StateError(reason) from None
        raise EdgeError(f"the daemon at {base} refused the retry of {episode_id}: HTTP "
                        f"{exc.code}: {reason}") from None
    except (urllib.error.URLError, OSError) as exc:
        why = getattr(exc, "reason", exc)
        raise EdgeError(f"no daemon answers at {base} ({why}): the retry is asked through "
                        "the running daemon; start it with `vt-edge run --config FILE` (or "
                        "give --url)") from None


def run_retry(cfg: Config, store: EpisodeStore, episode_id: str | None, all_failed: bool,
              url: str | None = None, out: Callable[[str], None] = print) -> int:
    """0 when every episode asked ends ``done``, else 1; refusals raise (one line)."""
    ids = failed_ids(store) if all_failed else [episode_id or ""]
    if not ids:
        out("no vlm_error or invalid_answer episodes to ask again")
        return 0
    done = 0
    for eid in ids:
        try:
            ep = retry_episode(cfg, eid, url)
        except StateError as exc:
            if not all_failed:
                raise
            out(f"{eid}  skipped: {exc}")  # answered meanwhile (the daemon, another retry)
            continue
        status = ep.get("status")
        done += status == Status.DONE
        why = "" if status == Status.DONE else ep.get("last_error") or ""
        out(f"{eid}  {status:15s} {ep.get('label') or '-':28s} "
            f"{ep.get('structured_output') or '':12s} {why}".rstrip())
    return 0 if done == len(ids) else 1
