"""Fixtures: a fake VLM server on loopback, no real API key in the environment."""

from __future__ import annotations

import pytest
import pytest_asyncio

from edge.sim.fake_vlm import FakeVLM
from tests.vlm.helpers import MODEL, image_bytes


@pytest.fixture(autouse=True)
def _no_real_api_key(monkeypatch):
    monkeypatch.delenv("VTZERO_VLM_API_KEY", raising=False)


@pytest_asyncio.fixture
async def fake():
    async with FakeVLM(model=MODEL) as server:
        yield server


@pytest.fixture
def jpeg() -> bytes:
    return image_bytes()
