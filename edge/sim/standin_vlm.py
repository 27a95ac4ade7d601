"""The simulated VLM: a stand-in that knows only what a VLM would know.

For tests, the evaluation harness and ``make run`` with no endpoint configured, this answers
the robot's question the way the paper describes a VLM answering it, from two kinds of
knowledge and nothing else:

- **Eyes.** It compares the photo with how each candidate looks (the simulated camera's
  picture of that name, :func:`edge.sim.camera.render`): like a camera, it sees the kind of
  food, never whether it is real, so a food and its replica, or raw and boiled mochi, all look
  the same to it. A photo it cannot match (a real photo) leaves every candidate in play.
- **Common sense about names** (:mod:`edge.sim.common_sense`): how much an object called so
  gives under a gentle push. It reads the touch sentence's reference names, averages their
  give (the nearest reference weighs most), and compares it with what it expects of each
  candidate the photo allows ("a resin replica of macaron": hard; "boiled kiri mochi": soft).

It never reads the simulator's physics (stiffness, relaxation, ...) or the label of the pressed
object: all it gets is the request (prompt, photo, candidates), as a real VLM
(``tests/vlm/test_standin_vlm.py`` checks both, by what this module imports and by giving
the simulator altered physics). Its behaviour follows the paper's observations: by sight
alone it takes a replica for the real food (a photo of a macaron is a macaron) and answers the
first of look-alike candidates otherwise; touch names it knows to be soft or hard move it to
the candidate whose expected give is nearest, when that is clearly nearer than its sight's
answer (``touch_margin``). So the whole chain (press -> embedding -> names -> common sense ->
label) is exercised, and its accuracy moves when the encoder, the database or the
descriptions change.

Two profiles, chosen by the request's ``model`` (one endpoint serves both, as a real server
serves two models): ``simulated-vlm`` weighs touch with sight (margin 0.05), and
``simulated-vlm-vision-led``, which, like the paper's LLaVA, hardly uses the touch text: it
keeps its sight's answer unless touch points elsewhere by more than 0.8 on the 0..1 scale.

Serve it: ``vt-edge sim vlm --port 8011`` (or ``python -m edge.sim.standin_vlm``); it prints
and logs "simulated VLM" on every line, and answers the strict JSON the robot asks for; asked
for a reason (``vlm.ask_reason``), it says what it saw and felt (:func:`say_why`).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import functools
import hashlib
import io
import logging
import signal
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from edge.sim import common_sense
from edge.sim.fake_vlm import FakeRequest, FakeVLM, plain_reason

log = logging.getLogger(__name__)

TITLE = "simulated VLM"
FINGERPRINT = "vtzero-simulated-vlm"
# The photo is compared with each candidate's picture at this size (grey levels 0..255).
THUMB_PX = (40, 30)
# A candidate "looks like" the photo when its picture is within this mean grey-level
# difference of the best match, and the best match itself is within MATCH_LIMIT (else the
# photo shows none of them). Measured on the simulated camera's pictures: re-encoding a
# JPEG at quality 60 moves a thumbnail by 0.7; two different kinds of food differ by 2.9 or
# more.
SAME_LOOK_TOLERANCE = 1.5
MATCH_LIMIT = 1.5
# Weight of the i-th nearest reference in the touch sentence (0-based): nearest weighs most.
RANK_WEIGHT_DECAY = 1.0


@functools.cache
def knowledge_digest() -> str:
    """A digest of what the stand-in knows and how it decides (this module and its common
    sense table): answers cached under another digest are another model's answers."""
    here = Path(__file__).resolve().parent
    data = b"".join((here / name).read_bytes() for name in ("standin_vlm.py",
                                                              "common_sense.py"))
    return hashlib.sha256(data).hexdigest()


@dataclass(frozen=True)
class Profile:
    """One simulated model: its name and how clear touch must be to override sight."""

    model: str
    title: str
    # How much nearer (0..1 give scale) touch must put another candidate than sight's answer.
    touch_margin: float


DEFAULT = Profile("simulated-vlm", f"{TITLE} (weighs sight and touch)", 0.05)
VISION_LED = Profile("simulated-vlm-vision-led",
                     f"{TITLE}, vision-led (hardly uses touch, like the paper's LLaVA)", 0.8)
PROFILES: dict[str, Profile] = {p.model: p for p in (DEFAULT, VISION_LED)}


@dataclass(frozen=True)
class Decision:
    """An answer and why: what the stand-in saw, felt and picked."""

    label: str
    seen: tuple[str, ...]  # candidates the photo allows
    sight: str  # sight's answer among them
    touch_give: float | None  # the touch sentence's give, None if it named nothing known
    reason: str


@functools.lru_cache(maxsize=512)
def _thumb_of_name(name: str) -> np.ndarray | None:
    from edge.sim.camera import render  # what a candidate looks like

    try:
        return _thumb(render(name))
    except KeyError:
        return None  # a name the camera never drew: the stand-in does not know its look


@functools.lru_cache(maxsize=64)
def _thumb(image: bytes) -> np.ndarray | None:
    try:
        with Image.open(io.BytesIO(image)) as img:
            small = img.convert("L").resize(THUMB_PX, Image.Resampling.BILINEAR)
            return np.asarray(small, dtype=np.float32)
    except (UnidentifiedImageError, OSError, ValueError):
        return None


def seen_candidates(image: bytes | None, candidates: Sequence[str]) -> list[str]:
    """The candidates the photo could show, in candidate order (all without a usable
    photo or when it matches none)."""
    photo = _thumb(image) if image else None
    if photo is None:
        return list(candidates)
    dist = {}
    for c in candidates:
        look = _thumb_of_name(c)
        if look is not None:
            dist[c] = float(np.mean(np.abs(look - photo)))
    if not dist or min(dist.values()) > MATCH_LIMIT:
        return list(candidates)
    best = min(dist.values())
    return [c for c in candidates if c in dist and dist[c] <= best + SAME_LOOK_TOLERANCE]


def sight_answer(seen: Sequence[str]) -> str:
    """What sight alone answers: the first candidate that is not named an imitation (a
    photo of a macaron is a macaron), else the first."""
    return next((c for c in seen if not common_sense.is_imitation(c)), seen[0])


def touch_give(description: str) -> float | None:
    """The give the touch sentence suggests: its items' give, nearest reference first,
    weights 1, 1/2, 1/3, ...; None when it names nothing common sense knows."""
    total = weight = 0.0
    for rank, item in enumerate(common_sense.items(description)):
        give = common_sense.give_of(item)
        if give is None:
            continue
        w = 1.0 / (1.0 + RANK_WEIGHT_DECAY * rank)
        total += w * give
        weight += w
    return total / weight if weight else None


def decide(profile: Profile, image: bytes | None, description: str,
           candidates: Sequence[str]) -> Decision:
    """The stand-in's answer to one question."""
    if not candidates:
        raise ValueError("no candidates")
    seen = seen_candidates(image, candidates)
    sight = sight_answer(seen)
    felt = touch_give(description) if description.strip() else None
    if felt is None:
        why = "no touch sentence" if not description.strip() else "touch names nothing known"
        return Decision(sight, tuple(seen), sight, None, f"sight only ({why})")
    expected = {c: common_sense.give_of(c) for c in seen}
    gap = {c: abs(g - felt) for c, g in expected.items() if g is not None}
    if not gap:
        return Decision(sight, tuple(seen), sight, felt, "sight (no candidate's feel known)")
    best = min(gap, key=lambda c: (gap[c], seen.index(c)))
    if sight not in gap or gap[sight] - gap[best] > profile.touch_margin:
        return Decision(best, tuple(seen), sight, felt,
                        f"touch suggests give {felt:.2f}, nearest {best} ({expected[best]})")
    return Decision(sight, tuple(seen), sight, felt,
                    f"sight kept (touch {felt:.2f} not clearly nearer another)")


def say_why(d: Decision, candidates: Sequence[str]) -> str:
    """The decision's reason in a sentence, as the answer's ``reason``: what the photo
    allowed, then what touch did."""
    if len(d.seen) == len(candidates):
        sight = f"The photo leaves all {len(candidates)} candidates open"
    elif len(d.seen) == 1:
        sight = f"The photo shows {d.seen[0]}"
    else:
        sight = f"The photo could show {', '.join(d.seen)}"
    return f"{sight}; {d.reason}."


class StandIn:
    """The chooser for :class:`edge.sim.fake_vlm.FakeVLM`: the request's model picks the
    profile (an unknown model gets the default one); :meth:`explain` gives its reason."""

    def __call__(self, req: FakeRequest) -> str:
        return self._decide(req).label

    def explain(self, req: FakeRequest, label: str) -> str:
        """Why it answers ``label`` (decided again: the same request decides the same)."""
        d = self._decide(req)
        return say_why(d, req.candidates) if d.label == label else plain_reason(req, label)

    @staticmethod
    def _decide(req: FakeRequest) -> Decision:
        profile = PROFILES.get((req.body or {}).get("model", DEFAULT.model), DEFAULT)
        image = req.images[0] if req.images else None
        d = decide(profile, image, req.description, req.candidates)
        log.debug("%s %s: %s (%s)", TITLE, profile.model, d.label, d.reason)
        return d


def server(host: str = "127.0.0.1", port: int = 0) -> FakeVLM:
    """The stand-in behind the strict OpenAI-compatible fake server (both profiles)."""
    standin = StandIn()
    return FakeVLM(host=host, port=port, model=tuple(PROFILES), choose=standin,
                   explain=standin.explain, title=TITLE, fingerprint=FINGERPRINT)


async def serve(host: str, port: int, ready=print) -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError):
            loop.add_signal_handler(sig, stop.set)
    async with server(host, port) as fake:
        ready(f"{TITLE} at {fake.base_url} (models {', '.join(PROFILES)}; no real model: "
              "common sense about object names, edge/sim/common_sense.py)")
        await stop.wait()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m edge.sim.standin_vlm",
        description="The simulated VLM on loopback (OpenAI-compatible; no real model).")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8011, help="0: any free port")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format=f"{TITLE}: %(levelname)s %(message)s")
    asyncio.run(serve(args.host, args.port, lambda line: print(line, flush=True)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
