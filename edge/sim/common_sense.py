"""What the simulated VLM knows about how things feel: common sense about object *names*.

The paper's claim is that a VLM infers how an object feels from the names of the objects it
feels like ("similar to otedama, kiwi piece": soft) through the common sense it learnt from
people's words. The simulated VLM (:mod:`edge.sim.standin_vlm`) needs that common sense too,
and this table is all of it: for 91 everyday object names, materials and words of feel, how
much a person expects each to give under a gentle push of two fingers, from 0 (does not give
at all: metal, glass, wood, resin) to 1 (gives completely: cotton wool, marshmallow).

The values are written from everyday experience of the *names* and reviewed by hand; they are
deliberately not derived from the simulator (``edge/sim/catalogue.py``'s moduli and relaxation
are physics a VLM never sees), so the stand-in can be wrong where common sense is, and its
accuracy moves only through what reaches it as words: the encoder's neighbours and their
descriptions. Reviewing a value means asking "would a person say so, knowing only the name?"
(a canele has a crust; a dried kiri mochi is hard as a tile; a boiled one is soft; a resin
replica of any food is hard plastic).

Reading a sentence: the text is lower-cased, ``_`` read as a space, and split into items at
commas outside parentheses (one item per reference class in a touch sentence). In an item the
first known phrase by position is its head, longer phrases winning over the shorter ones they
contain ("raw kiri mochi" over "mochi", "rubber eraser" over "rubber"): "piece of raw apple" is
raw apple, "resin replica of macaron" is resin.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass

# How much an object gives under a gentle push, 0 (not at all) .. 1 (completely).
GIVE: Mapping[str, float] = {
    # metals, glass, stone, wood, hard plastics: they do not give
    "stainless steel": 0.0, "steel": 0.0, "aluminium": 0.0, "aluminum": 0.0, "metal": 0.0,
    "iron": 0.0, "glass": 0.0, "marble": 0.0, "stone": 0.0, "ceramic": 0.0, "wood": 0.05,
    "acrylic": 0.05, "resin": 0.05, "plastic": 0.1, "chocolate": 0.1, "soap": 0.15,
    # firm: a little give
    "raw apple": 0.2, "apple": 0.25, "cork": 0.35, "rubber eraser": 0.35, "eraser": 0.35,
    "canele": 0.3, "rubber": 0.45, "macaron": 0.45, "silicone": 0.55, "clay": 0.55,
    "yokan": 0.55, "bean jelly": 0.55,
    # soft-ish foods and toys
    "cheese": 0.6, "gummy": 0.6, "cherry tomato": 0.6, "tomato": 0.65, "grape": 0.65,
    "quail egg": 0.65, "boiled egg": 0.65, "konjac": 0.7, "strawberry": 0.7,
    "otedama": 0.75, "beanbag": 0.75, "bean bag": 0.75, "kiwi": 0.75, "gyoza": 0.75,
    "onigiri": 0.75, "rice ball": 0.75, "banana": 0.8, "dango": 0.8, "dumpling": 0.8,
    "melon pan": 0.8, "tamagoyaki": 0.8, "omelette": 0.8, "sushi": 0.8, "ikura sushi": 0.8,
    # soft
    "bread": 0.85, "tofu": 0.85, "momen tofu": 0.85, "foam": 0.85, "jelly": 0.85,
    "gelatin": 0.9, "sponge": 0.9, "cream puff": 0.9, "mochi": 0.9, "marshmallow": 0.95,
    "cotton": 1.0,
    # a food that is hard or soft depending on how it was prepared
    "raw kiri mochi": 0.05, "dried kiri mochi": 0.05, "boiled kiri mochi": 0.95,
    "raw kabocha squash": 0.1, "raw kabocha": 0.1, "boiled kabocha squash": 0.65,
    "boiled kabocha": 0.65, "kabocha squash": 0.4, "kabocha": 0.4,
    # imitations: a replica of a food is made of resin or vinyl, whatever food it shows
    "resin replica": 0.05, "food replica": 0.05, "food sample": 0.05, "replica": 0.05,
    # words of feel, for a sentence that uses them (the ablation's descriptions)
    "unyielding": 0.0, "rigid": 0.05, "hard": 0.05, "firm": 0.35, "springy": 0.5,
    "bouncy": 0.5, "elastic": 0.5, "chewy": 0.55, "soft": 0.85, "squashy": 0.9,
    "spongy": 0.9, "wobbly": 0.9, "mushy": 0.9, "airy": 0.9, "feather-soft": 1.0,
}

# Words in a name that say the object is an imitation of what the photo shows: a photo of a
# macaron is, to a VLM, first of all a macaron.
IMITATION_WORDS = frozenset({"replica", "imitation", "fake", "sample", "model"})

_SPACES = re.compile(r"\s+")
# Longest first, so a phrase claims its words before the shorter phrases inside it.
_PHRASES = sorted(GIVE, key=lambda p: (-len(p), p))
_PATTERNS = [(p, re.compile(r"(?<![a-z])" + re.escape(p) + r"(?![a-z])")) for p in _PHRASES]


def normalise(text: str) -> str:
    return _SPACES.sub(" ", text.replace("_", " ").lower()).strip()


def items(sentence: str) -> list[str]:
    """The comma-separated items of ``sentence``, commas inside parentheses kept."""
    out, depth, current = [], 0, []
    for ch in sentence:
        depth += (ch == "(") - (ch == ")")
        if ch == "," and depth <= 0:
            out.append("".join(current))
            current = []
        else:
            current.append(ch)
    out.append("".join(current))
    return [normalise(i) for i in out if i.strip()]


@dataclass(frozen=True)
class Known:
    """A phrase the table knows, where it was found and how much it gives."""

    phrase: str
    start: int
    give: float


def known_phrases(text: str) -> list[Known]:
    """Every known phrase in ``text``, by position; longer phrases claim their words first."""
    text = normalise(text)
    taken = [False] * len(text)
    found = []
    for phrase, pattern in _PATTERNS:
        for m in pattern.finditer(text):
            if any(taken[m.start():m.end()]):
                continue
            taken[m.start():m.end()] = [True] * (m.end() - m.start())
            found.append(Known(phrase, m.start(), GIVE[phrase]))
    return sorted(found, key=lambda k: k.start)


def give_of(name: str) -> float | None:
    """How much the object ``name`` (a label or a description) gives, from its first known
    phrase; None when common sense knows none of its words."""
    found = known_phrases(name)
    return found[0].give if found else None


def is_imitation(name: str) -> bool:
    return bool(IMITATION_WORDS & set(re.findall(r"[a-z]+", normalise(name))))
