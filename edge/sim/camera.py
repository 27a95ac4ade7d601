"""The simulated robot's camera: a plain picture per object.

The picture depends only on what an object looks like: a real food and its resin replica,
or raw and boiled kiri mochi, give the same image, so vision alone cannot tell them apart,
just as with the real objects.
"""

from __future__ import annotations

import hashlib
import io

from PIL import Image, ImageDraw

from edge.sim.catalogue import DATASETS, ObjectClass, get

IMAGE_SIZE_PX = (320, 240)


def visual_key(name: str) -> str:
    """What the object looks like: the name without replica/cooking qualifiers."""
    get(name)  # refuse unknown names
    for prefix in ("resin_replica_", "raw_", "boiled_"):
        if name.startswith(prefix):
            return name[len(prefix):]
    return name


def _looks(key: str) -> ObjectClass:
    """The object drawn for a visual key: the first in the catalogue with that key, so both
    members of a pair get one size and shape (boiled kiri mochi is 2 mm wider than raw, a
    difference the picture must not give away)."""
    return next(o for objects in DATASETS.values() for o in objects
                if visual_key(o.name) == key)


def render(name: str) -> bytes:
    """A deterministic JPEG of the object on a table."""
    key = visual_key(name)
    obj = _looks(key)
    digest = hashlib.sha256(key.encode()).digest()
    colour = tuple(60 + b % 160 for b in digest[:3])
    img = Image.new("RGB", IMAGE_SIZE_PX, (214, 206, 190))
    draw = ImageDraw.Draw(img)
    draw.rectangle((0, 170, IMAGE_SIZE_PX[0], IMAGE_SIZE_PX[1]), fill=(150, 120, 90))
    half = int(obj.width_m * 2500)
    cx, cy = IMAGE_SIZE_PX[0] // 2, 170 - half
    box = (cx - half, cy - half, cx + half, cy + half)
    if obj.shape == "round":
        draw.ellipse(box, fill=colour, outline=(30, 30, 30), width=2)
    else:
        draw.rounded_rectangle(box, radius=6, fill=colour, outline=(30, 30, 30), width=2)
    draw.text((8, 8), key.replace("_", " "), fill=(20, 20, 20))
    buf = io.BytesIO()
    img.save(buf, format="JPEG", quality=90)
    return buf.getvalue()
