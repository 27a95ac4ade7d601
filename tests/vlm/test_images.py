"""Images: validation, decompression bombs, shrink and re-encode."""

import io
import struct
import time
import zlib

import numpy as np
import pytest
from PIL import Image

from edge.core.errors import EdgeError, ImageError
from edge.vlm.images import data_url, prepare_image
from tests.vlm.helpers import image_bytes


def _png_header_only(width: int, height: int) -> bytes:
    """A tiny PNG whose header claims ``width`` x ``height`` (a decompression bomb)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    idat = zlib.compress(b"\x00" * 64)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(
        b"IEND", b"")


def _open(data: bytes) -> Image.Image:
    img = Image.open(io.BytesIO(data))
    img.load()
    return img


def test_small_jpeg_and_png_pass_unchanged():
    for fmt, mime in (("JPEG", "image/jpeg"), ("PNG", "image/png")):
        data = image_bytes(320, 240, fmt)
        out = prepare_image(data, max_side_px=1024, max_bytes=1_000_000)
        assert out.data == data and out.mime == mime and not out.reencoded
        assert (out.width, out.height) == (320, 240)
        assert out.info()["sha256"] == out.sha256 and "data" not in out.info()


def test_large_image_is_shrunk_to_max_side():
    data = image_bytes(4000, 3000, noise=True)
    started = time.perf_counter()
    out = prepare_image(data, max_side_px=1024, max_bytes=1_000_000)
    took = time.perf_counter() - started
    print(f"\nprepare_image 4000x3000 noisy JPEG {len(data)} B -> {out.width}x{out.height} "
          f"{len(out.data)} B in {took * 1e3:.0f} ms")
    assert out.reencoded and out.mime == "image/jpeg"
    assert (out.width, out.height) == (1024, 768)
    img = _open(out.data)
    assert img.format == "JPEG" and img.size == (1024, 768)
    assert (out.source_width, out.source_height, out.source_bytes) == (4000, 3000, len(data))


def test_too_many_bytes_is_reencoded_under_the_limit():
    data = image_bytes(800, 800, "PNG", noise=True)  # ~2 MB of noise
    out = prepare_image(data, max_side_px=1024, max_bytes=100_000)
    assert len(out.data) <= 100_000 and out.reencoded
    assert _open(out.data).format == "JPEG"


def test_transparency_and_16_bit_are_flattened_to_rgb():
    rgba = image_bytes(2000, 100, "PNG", mode="RGBA")
    out = prepare_image(rgba, max_side_px=500, max_bytes=1_000_000)
    assert _open(out.data).mode == "RGB" and out.width == 500
    grey16 = Image.fromarray((np.arange(600 * 600).reshape(600, 600) % 65536).astype(np.uint16))
    buf = io.BytesIO()
    grey16.save(buf, "PNG")
    out = prepare_image(buf.getvalue(), max_side_px=300, max_bytes=1_000_000)
    img = _open(out.data)
    assert img.mode == "RGB" and img.size == (300, 300)
    assert len(set(np.asarray(img).ravel().tolist())) > 16  # scaled, not clipped to white


@pytest.mark.parametrize(
    ("data", "needle"),
    [
        (b"", "empty"),
        (b"this is a text file, not a photo", "not a JPEG or PNG"),
        (b"GIF89a" + b"\x00" * 64, "not a JPEG or PNG"),
        (image_bytes(64, 64, "BMP"), "not a JPEG or PNG"),
        (image_bytes(640, 480, noise=True)[:2000], "corrupt or truncated"),
        (_png_header_only(100_000, 100_000), "decompression bomb"),
        ("a string", "must be bytes"),
    ],
)
def test_bad_images_are_refused_clearly(data, needle):
    with pytest.raises(ImageError, match=needle) as err:
        prepare_image(data)
    assert isinstance(err.value, EdgeError) and isinstance(err.value, ValueError)


def test_oversized_input_is_refused_before_decoding():
    with pytest.raises(ImageError, match="more than the 1000 allowed"):
        prepare_image(image_bytes(320, 240, noise=True), max_input_bytes=1000)


def test_data_url():
    assert data_url(b"\xff\xd8\xff", "image/jpeg") == "data:image/jpeg;base64,/9j/"
