"""The simulated world: one object between the gripper's fingers, shared by the emulators.

The Dynamixel emulator's motion loop reports the gripper position through :meth:`load`
(which advances the contact physics and returns the load current the motor feels); the
XELA emulator reads raw frames through :meth:`frame`. Both run in different threads, so the
state is guarded by a lock. Time is the host's monotonic clock, or the virtual clock of the
dataset recorder (``clock``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from edge.core.layout import XR1944, PadLayout
from edge.sim.catalogue import ObjectClass, get
from edge.sim.contact import Contact, ObjectInstance
from edge.sim.dxl_emulator import DxlEmulator
from edge.sim.skin import Skin, SkinDraw, pad_size_m

# Gripper geometry (docs/hardware.md, 'Gripper width'): width in metres from the raw position.
WIDTH_PER_RAW_M = 1.7626621790e-5
WIDTH_OFFSET_M = 0.036099321
# Current-to-force of the gripper: Goal Current 200 (~538 mA) squeezes ~10 N per finger.
FORCE_PER_MA_N = 10.0 / (200 * 2.69)
PHYSICS_DT_S = 0.0005


# The ROBOTIS "width" is the gripper joint value (-0.010 closed .. 0.019 open); both fingers
# move by it, so the gap between the pads is twice its distance from the closed end.
CLOSED_WIDTH_M = -0.010


def width_from_raw(raw: float) -> float:
    return raw * WIDTH_PER_RAW_M - WIDTH_OFFSET_M


def raw_from_width(width_m: float) -> float:
    return (width_m + WIDTH_OFFSET_M) / WIDTH_PER_RAW_M


def gap_from_raw(raw: float) -> float:
    return max(2.0 * (width_from_raw(raw) - CLOSED_WIDTH_M), 0.0)


# The random stream of a robot's pads, apart from the world's own draws.
_PADS_STREAM = 0x7AD5
# The stream of the pieces a person puts back between presses (see SimWorld.load), apart
# from the first placement's and the pads' noise draws.
_PLACEMENTS_STREAM = 0x91AC
# A gripper open this far past the object after touching it has let go of it...
RELEASE_CLEARANCE_M = 0.5e-3
# ...and one closing this much from its widest gap since starts the next press: on a new
# placement of the object (a fresh piece), as a person puts it back between presses, not on
# the piece the last press left (dented, where it lay).
RECLOSE_M = 1e-3


def robot_pads(seed: int, layout: PadLayout = XR1944) -> SkinDraw:
    """The pads (of ``layout``) of the simulated robot of ``seed``: the daemon's emulated
    robot (``[sim] seed``) and the dataset recorder of the same seed press with the same
    pads, as references collected on a robot are recognised by that robot."""
    return SkinDraw.draw(np.random.default_rng(np.random.SeedSequence([seed, _PADS_STREAM])),
                         layout)


def robot_motors(world: SimWorld, joint_ids: tuple[int, ...], positions: dict[int, float],
                 **emulator_kw: Any) -> DxlEmulator:
    """The arm's motors, coupled to ``world`` both ways: the gripper feels the object through
    the world's load hook, and the world brings the gripper's motion up to a frame's time
    before the pads are read. ``positions``: raw positions at power-up."""
    gripper_id = world.gripper_id
    dxl = DxlEmulator((*joint_ids, gripper_id), load=world.load, initial_positions=positions,
                      **emulator_kw)
    world.sync = lambda: dxl.true_position(gripper_id)
    return dxl


class SimWorld:
    """Holds the object, advances the contact physics and renders tactile frames."""

    def __init__(self, object_name: str, seed: int | np.random.Generator = 0,
                 gripper_id: int = 15, *, skin_draw: SkinDraw | None = None,
                 layout: PadLayout = XR1944,
                 clock: Callable[[], float] = time.monotonic,
                 pads_age_s: float = 0.0) -> None:
        """``layout``: the pads drawn when ``skin_draw`` gives none. ``pads_age_s``: how
        long the pads have been powered when the world starts (their drift has levelled off
        that far: a robot that is already up)."""
        self._lock = threading.Lock()
        self._rng = np.random.default_rng(seed)
        # Spawned, not drawn, from a given generator: the world's own draws (and so every
        # recorded dataset of a seed) stay what they were before pieces were put back.
        self._placements = np.random.default_rng(
            np.random.SeedSequence([seed, _PLACEMENTS_STREAM]) if isinstance(seed, int)
            else self._rng.bit_generator.seed_seq.spawn(1)[0])
        if skin_draw is None:
            skin_draw = (robot_pads(seed, layout) if isinstance(seed, int)
                         else SkinDraw.draw(self._rng, layout))
        self._skin_draw = skin_draw
        self.gripper_id = gripper_id
        # Brings the gripper's motion up to now before the pads are read (the motor model
        # steps on its own thread, in batches): set by robot_motors. Called without the
        # world's lock, which the motors' load hook takes.
        self.sync: Callable[[], object] = lambda: None
        self._t = clock()
        # The pads' drift runs on their own time since power-up (Skin.frame's t_s).
        self._t0 = self._t - pads_age_s
        self._gap = 0.07
        # The contact force behind the last rendered frame (what the pads felt), for benches.
        self.frame_force_n = 0.0
        # Pieces placed so far (by place() and put back between presses).
        self.placements = 0
        self.place(object_name)

    def place(self, object_name: str) -> None:
        """Put a new draw of ``object_name`` between the fingers (a new press)."""
        cls = get(object_name)
        with self._lock:
            self._place(cls, self._rng)

    def _place(self, cls: ObjectClass, rng: np.random.Generator) -> None:
        # Called with the lock held.
        inst = ObjectInstance.draw(cls, rng, pad_size_m(self._skin_draw.layout))
        self.object_name = cls.name
        self.instance = inst
        self._contact = Contact(inst)
        self._skin = Skin(inst, rng, self._skin_draw)
        self.peak_force_n = 0.0
        # When the object first pushed on the pads (the world's clock), for benches.
        self.t_contact: float | None = None
        # The widest gap since the gripper let go of this piece; None while it has not.
        self._released_gap: float | None = None
        self.placements += 1

    def _follow_gripper(self, gap: float) -> None:
        # Called with the lock held. What the last press left stays until the next one
        # starts closing: a bench reads the last press's peak force after it opened.
        if self._released_gap is None:
            if (self.t_contact is not None and self._contact.force == 0.0
                    and gap > self.instance.width_m + RELEASE_CLEARANCE_M):
                self._released_gap = gap
        elif gap > self._released_gap:
            self._released_gap = gap
        elif gap < self._released_gap - RECLOSE_M:
            self._place(self.instance.cls, self._placements)

    def _advance(self, t: float) -> None:
        # Called with the lock held: step the physics up to t at a fixed step.
        while self._t + PHYSICS_DT_S <= t:
            self._contact.step(self._gap, PHYSICS_DT_S)
            self._t += PHYSICS_DT_S
            force = self._contact.force
            if force > self.peak_force_n:
                self.peak_force_n = force
                if self.t_contact is None:
                    self.t_contact = self._t
        if self._t < t - 1.0:
            self._t = t  # a long pause (process stopped): do not replay it step by step

    def load(self, motor_id: int, position_raw: float, t: float) -> float:
        """The Dynamixel emulator's hook: load current in mA resisting the gripper closing,
        at the motion model's time ``t`` (the physics first catches up to it)."""
        if motor_id != self.gripper_id:
            return 0.0
        with self._lock:
            self._advance(t)
            self._gap = gap_from_raw(position_raw)
            self._follow_gripper(self._gap)
            return self._contact.force / FORCE_PER_MA_N

    def frame(self, t: float) -> np.ndarray:
        """The XELA emulator's source: raw counts (C,) uint16 at monotonic time ``t``."""
        self.sync()
        with self._lock:
            self._advance(t)
            self.frame_force_n = self._contact.force
            return self._skin.frame(t - self._t0, self._contact.force,
                                    self._contact.contact_radius())

    def frame_newtons(self) -> np.ndarray:
        """The taxel forces (N, (C,)) behind the last frame, as a calibrated sensor reports
        them (the XELA emulator's ``calibrated``)."""
        with self._lock:
            return self._skin.forces(self.frame_force_n, self._contact.contact_radius())

    @property
    def force_n(self) -> float:
        with self._lock:
            return self._contact.force

    @property
    def gap_m(self) -> float:
        with self._lock:
            return self._gap
