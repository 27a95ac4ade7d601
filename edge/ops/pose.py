"""Arm poses: teach them by hand, check them by moving there slowly.

``vt-edge pose teach NAME``: torque off on the arm, the user moves it by hand, Enter stores
the present joint positions as the named pose in the config file (the rest of the file,
comments included, is kept). Torque off lets a raised arm fall, so the user is asked to
support it first; connecting to the bus turns torque off already (the motors are
configured with torque off), so the warning comes before the connection.

``vt-edge pose goto NAME``: torque on, a slow move to the pose (``GOTO_MOVE_TIME_S``) so a
wrong pose shows before it hits anything, the arm holds it until Enter, then goes back to
``rest`` as slowly and torque goes off there, as the daemon leaves it.
"""

from __future__ import annotations

from pathlib import Path

from edge.core import tomledit
from edge.core.config import Config
from edge.core.errors import EdgeError
from edge.core.prompt import Prompt, ask, read_line

# A taught pose is checked at a walking pace: several times the daemon's move time.
GOTO_MOVE_TIME_S = 4.0
# Beyond the move itself, how long the joints may take to settle within tolerance.
GOTO_SETTLE_S = 3.0
SUPPORT_PROMPT = ("support the arm: its torque goes off and a raised arm drops; "
                  "Enter to turn torque off ")


def _check_name(name: str) -> None:
    if not name.replace("_", "").isalnum():
        raise EdgeError(f"pose name {name!r}: use letters, digits and underscores")


async def teach_pose(cfg: Config, config_path: str | Path, name: str,
                     prompt: Prompt = read_line, bus=None) -> tuple[int, ...]:
    """Store the arm's present joint positions as pose ``name`` in ``config_path``."""
    from edge.hw.dynamixel import DynamixelBus

    _check_name(name)
    await ask(prompt, SUPPORT_PROMPT)
    own = bus is None
    bus = bus or DynamixelBus(cfg.bus)
    try:
        if own:
            await bus.connect()
        await bus.set_torque(False)
        await ask(prompt, f"move the arm to the '{name}' pose by hand, then press Enter ")
        state = await bus.read_state()
        joints = tuple(int(state.motors[i].position) for i in cfg.bus.joint_ids)
    finally:
        if own:
            await bus.close()
    # Poses not in the file yet are written with their current values, so the file stays a
    # complete, loadable configuration.
    poses = {k: list(v) for k, v in cfg.poses.items()}
    poses[name] = list(joints)
    tomledit.update(config_path, config_path, {"poses": poses})
    print(f"pose {name} = {list(joints)} saved in {config_path}")
    return joints


async def goto_pose(cfg: Config, name: str, prompt: Prompt = read_line,
                    move_time_s: float = GOTO_MOVE_TIME_S) -> tuple[int, ...]:
    """Move to pose ``name`` over ``move_time_s``, hold it until Enter, then return to
    ``rest`` and turn torque off; returns the joints reached."""
    from edge.hw.arm import DynamixelArm
    from edge.hw.dynamixel import DynamixelBus

    _check_name(name)
    if name not in cfg.poses:
        raise EdgeError(f"pose {name!r} is not in [poses] (known: {', '.join(cfg.poses)}); "
                        f"teach it with `vt-edge pose teach {name}`")
    await ask(prompt, f"the arm moves to '{name}' over {move_time_s:g} s: clear its path and "
                      "support it (connecting turns torque off for a moment); Enter to start ")
    bus = DynamixelBus(cfg.bus)
    arm = DynamixelArm(bus, cfg.poses, move_time_s=move_time_s)
    timeout_s = move_time_s + GOTO_SETTLE_S
    await bus.connect()
    try:
        await bus.set_torque(True)
        await arm.move_to(name, timeout_s)
        joints = tuple(int(j) for j in await arm.joints())
        print(f"at pose {name}: joints {list(joints)} (taught {list(cfg.poses[name])})")
        await ask(prompt, f"holding '{name}'; Enter to go back to rest and turn torque off ")
    finally:
        # Back to rest as slowly as it came (every way out, Ctrl-C included), torque off.
        await bus.close(safe_pose=lambda: arm.move_to("rest", timeout_s))
    return joints
