"""Structured output, strictest first (json_schema -> json_object -> none), and the probe
that finds which one a server honours.

A server that refuses a mode (an error that names ``response_format``,
:func:`edge.vlm.transport.refuses_format`) or ignores it (a 200 whose answer is not the
requested JSON) is asked again one mode down; the client keeps the lower mode for the rest
of its life (a client made after SIGHUP starts again from the configured mode).
"""

from __future__ import annotations

import io
import logging
from functools import cache

from edge.vlm.transport import Trace

log = logging.getLogger(__name__)

# Structured-output modes, strictest first: a server that refuses one is sent the next.
STRUCTURED_MODES = ("json_schema", "json_object", "none")
# The probe's question: two made-up candidates and, where the prompt needs one, a tiny photo.
PROBE_CANDIDATES = ("red_cube", "blue_ball")
PROBE_DESCRIPTION = "wood cube"
PROBE_IMAGE_SIDE_PX = 64


class StructuredOutput:
    """The structured-output mode a client sends its next question with."""

    def __init__(self, configured: str, url: str) -> None:
        self.mode = configured
        self.url = url

    def step_down(self, mode: str, trace: Trace, verb: str, why: str) -> None:
        """The next mode after the server ``verb`` ("refused" or "ignored") ``mode``, for
        this client's life; logged once (questions in flight together may each meet it)."""
        trace.stepped_down.append(mode)
        trace.reasons.append(f"{verb} ({why})")
        lower = STRUCTURED_MODES[STRUCTURED_MODES.index(mode) + 1]
        if self.mode == mode:
            self.mode = lower
            log.warning("VLM at %s %s structured output %s (%s); asking with %s from now on "
                        "(set vlm.structured_output = %r to start there)", self.url, verb,
                        mode, why, lower, lower)


@cache
def probe_image() -> bytes:
    """A small grey JPEG: enough for a server to accept an image, cheap to send."""
    from PIL import Image

    out = io.BytesIO()
    Image.new("RGB", (PROBE_IMAGE_SIDE_PX, PROBE_IMAGE_SIDE_PX), (128, 128, 128)).save(
        out, "JPEG", quality=80)
    return out.getvalue()
