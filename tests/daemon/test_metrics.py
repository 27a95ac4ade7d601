"""Prometheus text of the daemon's counters."""

from types import SimpleNamespace

from edge.daemon.metrics import Metrics
from edge.daemon.sensor import SamplerStats


def test_stops_and_their_fallbacks_are_counted_when_there_is_a_bus():
    sensor = SimpleNamespace(frames=10, stale_events=0)
    text = Metrics().render(SamplerStats(), sensor, SimpleNamespace(stops=7, stop_fallbacks=1))
    assert "vtzero_stops_total 7\n" in text and "vtzero_stop_fallbacks_total 1\n" in text
    assert "vtzero_stops_total" not in Metrics().render(SamplerStats(), sensor)
