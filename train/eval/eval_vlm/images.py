"""The picture sent with a press's question: a user's photo, the photo taken beside the
press, or the simulated camera's picture of its label; each checked before the first
question."""

from __future__ import annotations

import functools
from pathlib import Path

from edge.core.config import VLMConfig
from edge.core.errors import EvalVLMError, ImageError
from edge.vlm.images import prepare_image

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
PHOTO_BESIDE = "photos beside the presses"
SIM_CAMERA = "simulated camera (edge.sim.camera.render)"


class ImageSource:
    """The picture of a press: a user's photo in ``--images`` (per press, else per class);
    without it the photo ``vt-edge collect`` took beside the press (same stem), else the
    simulated camera's picture of its label."""

    def __init__(self, directory: Path | None = None, vlm: VLMConfig | None = None) -> None:
        self.directory = directory
        self.vlm = vlm or VLMConfig()
        if directory is not None and not directory.is_dir():
            raise EvalVLMError(f"--images {directory}: not a directory")
        self.used: dict[str, dict[str, int]] = {}  # per set: source -> pictures

    @property
    def name(self) -> str:
        if self.directory is not None:
            return str(self.directory)
        if not self.used:
            return SIM_CAMERA
        return "; ".join(f"{dataset}: " + ", ".join(
            f"{source} ({n})" if len(counts) > 1 else source for source, n in counts.items())
            for dataset, counts in self.used.items())

    def _count(self, dataset: str, source: str) -> None:
        counts = self.used.setdefault(dataset, {})
        counts[source] = counts.get(source, 0) + 1

    @staticmethod
    def beside(press_path: Path) -> Path | None:
        """The photo collect saved beside a press: ``<label>_NNN.jpg`` (.jpeg, .png)."""
        stem = press_path.name.split(".")[0]
        for suffix in IMAGE_SUFFIXES:
            path = press_path.with_name(stem + suffix)
            if path.is_file():
                return path
        return None

    def path_for(self, dataset: str, press: str, label: str) -> Path | None:
        assert self.directory is not None
        stem = Path(press).name.split(".")[0]
        for folder in (self.directory / dataset, self.directory):
            for name in (stem, label):
                for suffix in IMAGE_SUFFIXES:
                    path = folder / f"{name}{suffix}"
                    if path.is_file():
                        return path
        return None

    def get(self, dataset: str, press: str, label: str, press_path: Path | None = None
            ) -> bytes:
        if self.directory is None:
            photo = self.beside(press_path) if press_path is not None else None
            self._count(dataset, PHOTO_BESIDE if photo else SIM_CAMERA)
            if photo is not None:
                return _read_image(photo, self.vlm.max_image_side_px, self.vlm.max_image_bytes)
            return _rendered(label)
        path = self.path_for(dataset, press, label)
        if path is None:
            raise EvalVLMError(
                f"no photo of {dataset}/{press} in {self.directory}: expected "
                f"{Path(press).name.split('.')[0]}.jpg or {label}.jpg (or .jpeg/.png) in "
                f"{self.directory / dataset} or {self.directory}")
        return _read_image(path, self.vlm.max_image_side_px, self.vlm.max_image_bytes)


@functools.lru_cache(maxsize=256)
def _rendered(label: str) -> bytes:
    from edge.sim.camera import render

    try:
        return render(label)
    except KeyError:
        raise EvalVLMError(f"the simulated camera has no picture of {label!r}: give --images "
                           "DIR with photos for real data") from None


@functools.lru_cache(maxsize=256)
def _read_image(path: Path, max_side_px: int, max_bytes: int) -> bytes:
    """A photo's bytes, checked now (as the client will prepare it) so that a bad file
    stops the run before the first question, not in the middle."""
    try:
        data = path.read_bytes()
        prepare_image(data, max_side_px, max_bytes)
    except (OSError, ImageError) as exc:
        raise EvalVLMError(f"{path}: not a usable photo: {exc}") from None
    return data
