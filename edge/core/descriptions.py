"""What a reference class's description may say: what the object *is*, never how it feels.

The method's claim (docs/method.md, 'Reference database and retrieval') is that a VLM infers
how a pressed object feels from the *names* of the reference objects it feels like, through
its own common sense: "similar to otedama, kiwi piece" tells it "soft" with no tactile label
written by anyone. A description is therefore the object's name made unambiguous for a VLM
("otedama (a small Japanese cloth beanbag filled with beans)", "wood cube"). A description
that says "hard", "springy" or "smooth" hands the VLM the answer and bypasses the mechanism
the paper tests, so building or extending a database refuses one.

The check is a word list (:data:`TACTILE_WORDS`, with their comparative, adverb and noun
forms): words of hardness, softness, elasticity, texture and give. A material or food named
as what the object is made of ("rubber", "sponge", "foam", "jelly") is a name and passes.
"""

from __future__ import annotations

import re

from edge.core.errors import DescriptionError

# Words that say how an object feels under the fingers. Each also matches with the endings
# in _ENDINGS ("softer", "softly", "softness", "springiness").
TACTILE_WORDS: frozenset[str] = frozenset({
    # hardness
    "hard", "soft", "firm", "rigid", "rigidity", "stiff", "solid", "unyielding", "tough",
    "tender",
    # give and elasticity
    "give", "gives", "giving", "yield", "yields", "yielding", "springy", "spring", "springs",
    "bouncy", "elastic", "rubbery", "flexible", "pliable", "supple", "malleable",
    "compressible", "squeezable", "resilient",
    # soft kinds
    "squashy", "squishy", "spongy", "mushy", "wobbly", "jiggly", "airy", "fluffy", "doughy",
    "chewy", "gooey", "sticky", "tacky", "crumbly", "brittle", "crisp", "crispy", "crunchy",
    "fragile", "delicate", "flows", "squash", "squashes", "squashed", "squish", "bounce",
    "bounces",
    # surface and texture
    "smooth", "rough", "slick", "slippery", "grippy", "moist", "juicy", "taut", "dense",
    "grainy", "granular", "texture", "textured",
    # the sense itself
    "feel", "feels", "feeling", "touch", "tactile", "hardness", "softness", "elasticity",
})
_ENDINGS = ("", "er", "est", "ly", "ness", "iness", "ily", "ier", "iest", "s", "ish")
_WORD = re.compile(r"[a-z]+")


def _stems(word: str) -> set[str]:
    """``word`` and what it could be with one of the endings taken off."""
    out = {word}
    for ending in _ENDINGS:
        if ending and word.endswith(ending) and len(word) > len(ending) + 2:
            base = word[: -len(ending)]
            out |= {base, base + "y", base + "e"}
    return out


def tactile_words(text: str) -> list[str]:
    """The words of ``text`` that say how something feels, in order of appearance."""
    return [w for w in _WORD.findall(text.lower()) if _stems(w) & TACTILE_WORDS]


def check_description(text: str, label: str = "") -> str:
    """``text`` stripped, or :class:`DescriptionError` saying which words to drop and why."""
    text = " ".join(str(text).split())
    who = f"description of {label!r}" if label else "description"
    if not text:
        raise DescriptionError(f"{who} is empty: name the object, e.g. 'wood cube'")
    found = tactile_words(text)
    if found:
        words = ", ".join(dict.fromkeys(found))
        raise DescriptionError(
            f"{who} {text!r} says how the object feels ({words}): a description names the "
            "object only, made unambiguous for a VLM (e.g. 'otedama (a small Japanese cloth "
            "beanbag filled with beans)', 'wood cube'); the VLM infers how it feels from the "
            "names of the references a press is similar to. Remove those words.")
    return text
