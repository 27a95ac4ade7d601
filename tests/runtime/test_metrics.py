"""Prometheus text of the daemon's counters."""

from dataclasses import dataclass
from types import SimpleNamespace

from edge.hw.contracts import BusStatus
from edge.runtime.metrics import Metrics
from edge.runtime.sensor import SamplerStats


@dataclass(frozen=True)
class Bus:
    fault: str | None = None
    torque_on: bool = True
    stops: int = 7
    stop_fallbacks: int = 1


def test_stops_and_their_fallbacks_are_counted_when_there_is_a_bus():
    sensor = SimpleNamespace(frames=10, stale_events=0)
    assert isinstance(Bus(), BusStatus)
    text = Metrics().render(SamplerStats(), sensor, Bus())
    assert "vtzero_stops_total 7\n" in text and "vtzero_stop_fallbacks_total 1\n" in text
    assert "vtzero_stops_total" not in Metrics().render(SamplerStats(), sensor)


def test_familiarity_is_a_histogram_and_unfamiliar_presses_a_counter():
    metrics = Metrics()
    for familiarity, unfamiliar in ((3.0, False), (40.0, False), (97.0, True), (None, False)):
        metrics.observe_familiarity(familiarity, unfamiliar)
    text = metrics.render(SamplerStats(), SimpleNamespace(frames=0, stale_events=0))
    print(text)
    assert 'vtzero_familiarity_percentile_bucket{le="5"} 1\n' in text
    assert 'vtzero_familiarity_percentile_bucket{le="95"} 2\n' in text
    assert 'vtzero_familiarity_percentile_bucket{le="+Inf"} 3\n' in text
    assert "vtzero_familiarity_percentile_count 3\n" in text
    assert "vtzero_unfamiliar_presses_total 1\n" in text
