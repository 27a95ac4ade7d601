"""The pads behind the tactile channels: how many, and each pad's grid of taxels.

Channel order everywhere: ``(pad * taxels_per_pad + taxel) * 3 + axis``, taxels row-major
from the top left, axes x, y, z (``pad * 48 + taxel * 3 + axis`` on two XR1944 pads, 4 x 4
taxels). The configuration's ``[sensor]`` (pads, taxels_per_pad, taxel_rows) gives it; a
recording of other pads than two 4 x 4 ones names its layout in its metadata
(``extra["layout"]``), so an export made far from the robot still splits its channels right.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

AXES = ("x", "y", "z")
# Recordings' metadata key for a layout other than the XR1944's.
EXTRA_KEY = "layout"


@dataclass(frozen=True)
class PadLayout:
    pads: int = 2
    rows: int = 4
    cols: int = 4

    @property
    def taxels(self) -> int:
        return self.rows * self.cols

    @property
    def channels(self) -> int:
        return self.pads * self.taxels * len(AXES)

    @classmethod
    def of(cls, sensor: Any) -> PadLayout:
        """The layout of a ``[sensor]`` section (:class:`edge.core.config.SensorConfig`)."""
        return cls(sensor.pads, sensor.taxel_rows, sensor.taxels_per_pad // sensor.taxel_rows)

    def extra(self) -> dict[str, Any]:
        """What a recording's metadata says of it: nothing for the XR1944's (the recordings
        made before other layouts stay as they were)."""
        if self == XR1944:
            return {}
        return {EXTRA_KEY: {"pads": self.pads, "taxel_rows": self.rows,
                            "taxels_per_pad": self.taxels}}

    @classmethod
    def of_recording(cls, extra: dict[str, Any], channels: int) -> PadLayout:
        """The layout of a recording's ``channels`` from its metadata ``extra``: 4 x 4 pads
        (as many as the channels make) when it names none, else one row of taxels."""
        raw = extra.get(EXTRA_KEY)
        if isinstance(raw, dict):
            pads, rows, taxels = (raw.get(k) for k in ("pads", "taxel_rows", "taxels_per_pad"))
            if (all(type(v) is int and v > 0 for v in (pads, rows, taxels))
                    and taxels % rows == 0 and pads * taxels * 3 == channels):
                return cls(pads, rows, taxels // rows)
        if channels % (XR1944.taxels * 3) == 0:
            return cls(channels // (XR1944.taxels * 3), XR1944.rows, XR1944.cols)
        return cls(1, 1, channels // 3)

    def names(self) -> list[str]:
        """One name per channel: ``pad0_taxel00_x``."""
        return [f"pad{p}_taxel{t:02d}_{a}" for p in range(self.pads)
                for t in range(self.taxels) for a in AXES]

    def text(self) -> str:
        return f"{self.pads} pad{'s' * (self.pads != 1)} of {self.rows} x {self.cols} taxels"


XR1944 = PadLayout()
