"""Images for the VLM: validate, shrink, re-encode, data URL.

:func:`prepare_image` accepts JPEG or PNG bytes (a camera still, an upload), refuses anything
else, truncated files and decompression bombs with :class:`ImageError`, and returns the bytes
to send: unchanged when the image is within ``max_side_px`` and ``max_bytes``, otherwise
shrunk and re-encoded as JPEG. It is CPU work (tens of ms for a camera frame): call it off the
event loop, e.g. ``await asyncio.to_thread(prepare_image, ...)``.
"""

from __future__ import annotations

import base64
import functools
import hashlib
import io
import logging
from dataclasses import dataclass

from PIL import Image, ImageOps, UnidentifiedImageError

from edge.core.errors import ImageError

log = logging.getLogger(__name__)

FORMATS = {"JPEG": "image/jpeg", "PNG": "image/png"}

# Refuse before decoding: a 50 MP still is far more than any camera here sends, and a
# few-KB PNG can declare 100k x 100k pixels (a decompression bomb).
DEFAULT_MAX_PIXELS = 50_000_000
DEFAULT_MAX_INPUT_BYTES = 50_000_000
# JPEG qualities tried in turn, then the side shrinks by _SHRINK_STEP, until under max_bytes.
_QUALITIES = (90, 80, 70, 55, 40)
_SHRINK_STEP = 0.75
_MIN_SIDE_PX = 32




@dataclass(frozen=True)
class PreparedImage:
    """The image as it will be sent, and where it came from."""

    data: bytes
    mime: str
    width: int
    height: int
    source_format: str
    source_bytes: int
    source_width: int
    source_height: int
    reencoded: bool

    @functools.cached_property
    def sha256(self) -> str:
        return hashlib.sha256(self.data).hexdigest()

    def info(self) -> dict[str, object]:
        """A JSON-able summary for storage (no pixel data)."""
        return {
            "mime": self.mime, "bytes": len(self.data), "sha256": self.sha256,
            "width": self.width, "height": self.height, "reencoded": self.reencoded,
            "source_format": self.source_format, "source_bytes": self.source_bytes,
            "source_width": self.source_width, "source_height": self.source_height,
        }

    def __repr__(self) -> str:  # never dump the bytes
        return (f"PreparedImage({self.mime}, {len(self.data)} bytes, "
                f"{self.width}x{self.height}, reencoded={self.reencoded})")


def data_url(data: bytes, mime: str) -> str:
    """``data:<mime>;base64,<...>``: the form OpenAI, vLLM, Ollama and llama.cpp accept."""
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


def prepare_image(
    data: bytes,
    max_side_px: int = 1024,
    max_bytes: int = 1_000_000,
    *,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    max_input_bytes: int = DEFAULT_MAX_INPUT_BYTES,
) -> PreparedImage:
    """Validate ``data`` (JPEG/PNG) and bring it within ``max_side_px`` and ``max_bytes``."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise ImageError(f"image must be bytes, got {type(data).__name__}")
    data = bytes(data)
    if not data:
        raise ImageError("image is empty (0 bytes)")
    if len(data) > max_input_bytes:
        raise ImageError(f"image is {len(data)} bytes, more than the {max_input_bytes} allowed")
    img, (width, height) = _open(data, max_pixels, max_side_px)
    fmt = img.format or "?"
    if max(width, height) <= max_side_px and len(data) <= max_bytes:
        return PreparedImage(data, FORMATS[fmt], width, height, fmt, len(data), width, height,
                             reencoded=False)
    out, (w, h) = _reencode(img, max_side_px, max_bytes)
    log.debug("image %s %dx%d %d B -> JPEG %dx%d %d B", fmt, width, height, len(data), w, h,
              len(out))
    return PreparedImage(out, "image/jpeg", w, h, fmt, len(data), width, height,
                         reencoded=True)


# An image ready to send: as it is sent, and its data URL (ASCII bytes).
VLMImage = tuple[PreparedImage, bytes]


def prepare_for_vlm(data: bytes, max_side_px: int, max_bytes: int) -> VLMImage:
    """:func:`prepare_image`, and the result's data URL as ASCII bytes: the CPU work of
    sending an image, done in one call where the caller runs CPU work."""
    prepared = prepare_image(data, max_side_px, max_bytes)
    _ = prepared.sha256  # hashed here too
    return prepared, data_url(prepared.data, prepared.mime).encode("ascii")


def check_image(data: bytes, max_pixels: int = DEFAULT_MAX_PIXELS) -> tuple[str, int, int]:
    """(format, width, height) of a decodable JPEG/PNG, else :class:`ImageError`.

    Decodes the pixels (a large JPEG at a reduced scale): CPU work, call it off the loop.
    """
    img, (width, height) = _open(bytes(data), max_pixels, 1024)
    return img.format or "?", width, height


def _open(data: bytes, max_pixels: int, max_side_px: int) -> tuple[Image.Image, tuple]:
    try:
        img = Image.open(io.BytesIO(data), formats=list(FORMATS))
    except UnidentifiedImageError:
        raise ImageError(
            f"not a JPEG or PNG image ({len(data)} bytes starting {data[:8]!r})"
        ) from None
    except Image.DecompressionBombError as exc:
        raise ImageError(f"image refused as a decompression bomb: {exc}") from None
    except (OSError, ValueError, SyntaxError) as exc:
        raise ImageError(f"image header cannot be read: {exc}") from None
    # Checked on the header, before any pixel is decoded. (Pillow's own check, global and
    # higher, only warns below twice its limit.)
    width, height = img.size
    if width < 1 or height < 1 or width * height > max_pixels:
        raise ImageError(
            f"image of {width}x{height} pixels refused: more than {max_pixels} pixels "
            "(decompression bomb?)"
        )
    if img.format == "JPEG" and max(width, height) > max_side_px:
        # Decode a large JPEG at 1/2, 1/4 or 1/8 scale (still >= max_side_px): much faster.
        img.draft(img.mode, (max_side_px, max_side_px))
    try:
        img.load()
    except Image.DecompressionBombError as exc:
        raise ImageError(f"image refused as a decompression bomb: {exc}") from None
    except (OSError, ValueError, SyntaxError, EOFError) as exc:
        raise ImageError(f"image data is corrupt or truncated: {exc}") from None
    return img, (width, height)


def _reencode(img: Image.Image, max_side_px: int, max_bytes: int) -> tuple[bytes, tuple]:
    img = ImageOps.exif_transpose(img)
    img = _to_rgb(img)
    side = max_side_px
    while True:
        if max(img.size) > side:
            img.thumbnail((side, side), Image.Resampling.LANCZOS)
        for quality in _QUALITIES:
            buf = io.BytesIO()
            img.save(buf, format="JPEG", quality=quality, optimize=True)
            if buf.tell() <= max_bytes:
                return buf.getvalue(), img.size
        side = int(max(img.size) * _SHRINK_STEP)
        if side < _MIN_SIDE_PX:
            raise ImageError(f"image cannot be brought under {max_bytes} bytes as a JPEG")


def _to_rgb(img: Image.Image) -> Image.Image:
    if img.mode == "RGB":
        return img
    if img.mode in ("RGBA", "LA", "PA") or (img.mode == "P" and "transparency" in img.info):
        rgba = img.convert("RGBA")
        background = Image.new("RGB", rgba.size, (255, 255, 255))
        background.paste(rgba, mask=rgba.getchannel("A"))
        return background
    if img.mode in ("I;16", "I;16B", "I;16L", "I"):
        # 16-bit grey: scale to 8 bits rather than clip.
        return img.convert("I").point(lambda v: v / 256).convert("L").convert("RGB")
    return img.convert("RGB")
