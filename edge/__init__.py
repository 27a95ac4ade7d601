"""vtzero on-robot runtime: press, tactile encoding, VLM recognition. Never imports torch."""

import os

__version__ = "0.1.0"
# The systemd service the daemon runs as (its unit is SERVICE_NAME.service): what a message
# tells a person to stop or reload.
SERVICE_NAME = "vtzero-edge"

# onnxruntime (1.29+) collects telemetry on Linux by default: at the first session it writes a
# device id and an event cache under ~/.cache/Microsoft and uploads from there. A robot must
# not; set before onnxruntime is imported anywhere in vtzero (a value already set wins).
os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")
