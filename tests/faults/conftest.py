"""The fault campaign runs with no real VLM key in the environment (tests plant their own)."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def _no_real_api_key(monkeypatch):
    monkeypatch.delenv("VTZERO_VLM_API_KEY", raising=False)
    monkeypatch.delenv("VTZERO_API_TOKEN", raising=False)
