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

from collections.abc import Callable

from edge.core.config import Config
from edge.core.errors import StateError
from edge.ops.daemon_http import REFUSALS, ask_daemon
from edge.runtime.domain import Status
from edge.runtime.recognition import RE_ASKABLE
from edge.runtime.store import EpisodeStore

# Beyond the VLM's own time for one question (transport retries and the corrective retry
# come from the configuration), what the daemon may take to answer.
RETRY_MARGIN_S = 30.0


def failed_ids(store: EpisodeStore) -> list[str]:
    """The ``vlm_error`` and ``invalid_answer`` episodes, oldest first."""
    return [ep.id for ep in reversed(store.list()) if ep.status in RE_ASKABLE]


def retry_episode(cfg: Config, episode_id: str, url: str | None = None) -> dict:
    """The episode as the daemon stored it after asking again; :class:`NotFoundError`,
    :class:`StateError` or :class:`EdgeError` with the daemon's one-line reason."""
    vlm = cfg.vlm
    timeout_s = (2 * (vlm.max_retries + 1) * vlm.total_timeout_s
                 + vlm.max_retries * vlm.backoff_cap_s + RETRY_MARGIN_S)
    return ask_daemon(cfg, "POST", f"/v1/episodes/{episode_id}/retry", None,
                      timeout_s=timeout_s, what="the retry", url=url,
                      refusals={**REFUSALS, 409: StateError})


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
