"""The whole emulated robot: the world, the ``xela_server`` emulator on loopback and the
Dynamixel bus emulator on a pseudo-terminal, plus a small control API: ``GET``/``POST
/object`` (what the table holds, place another object), ``GET /camera.jpg`` (a picture),
``POST /fault`` (switch one of the emulators' faults, :data:`FAULTS`) and ``GET /motors``
(each motor as the emulator holds it); documented with examples in ``docs/reliability.md``.
The runtime connects to it with the real drivers; only the device addresses in its
configuration differ from the real robot's. With a ``replay``, the XELA emulator serves that
real recording instead of the physics' frames (the arm and gripper are still emulated).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import replace
from typing import Any

from aiohttp import web

from edge.core.config import Config
from edge.core.layout import PadLayout
from edge.sim import camera as sim_camera
from edge.sim.catalogue import get
from edge.sim.world import SimWorld, raw_from_width, robot_motors, robot_pads
from edge.sim.xela_replay import Replay
from edge.sim.xela_server import Fault, XelaServerEmulator

log = logging.getLogger(__name__)

# POST /fault's switches: the fault's name -> its fields (name -> type and default; None:
# required). What each does: docs/reliability.md, "The emulated robot's control API".
_MOTOR = (int, None)
FAULTS: dict[str, dict[str, tuple[type, Any]]] = {
    "motor_silent": {"motor": _MOTOR, "on": (bool, True)},
    "crc_errors": {"motor": _MOTOR, "count": (int, 1)},
    "hardware_error": {"motor": _MOTOR, "bits": (int, None)},
    "serial_error": {},
    "unplug": {},
    "plug": {},
    "sensor": {"mode": (str, None)},
}


class SimRobot:
    def __init__(self, object_name: str = "stainless_cube", seed: int = 0, *,
                 xela_port: int = 0, control_port: int = 0, rate_hz: float = 125.0,
                 dialect: str = "1.8", reply_latency_s: float = 0.0,
                 initial_width_m: float | None = None, cfg: Config | None = None,
                 replay: Replay | None = None, replay_loop: bool = True,
                 calibrated: bool = False) -> None:
        get(object_name)
        bus, sensor = (cfg or Config()).bus, (cfg or Config()).sensor
        # The pads of the configured layout ([sensor] pads, taxels, rows), as xela_server
        # reports them.
        pads = replace(robot_pads(seed, PadLayout.of(sensor)),
                       gain=(cfg or Config()).sim.pad_gain)
        self.world = SimWorld(object_name, seed, gripper_id=bus.gripper_id, skin_draw=pads)
        poses = (cfg or Config()).poses
        positions = {mid: float(v) for mid, v in zip(bus.joint_ids, poses["rest"], strict=True)}
        # The gripper starts open, where the runtime opens it before a press.
        width = (cfg or Config()).press.open_width_m if initial_width_m is None else initial_width_m
        positions[bus.gripper_id] = raw_from_width(width)
        self.dxl = robot_motors(self.world, bus.joint_ids, positions,
                                reply_latency_s=reply_latency_s)
        self.xela = XelaServerEmulator(self.world, port=xela_port, rate_hz=rate_hz,
                                       dialect=dialect,  # type: ignore[arg-type]
                                       replay=replay, loop=replay_loop,
                                       calibrated=calibrated, sensors=sensor.pads,
                                       taxels=sensor.taxels_per_pad, model=sensor.model)
        self._control_port = control_port
        self._runner: web.AppRunner | None = None
        self.control_url = ""

    async def start(self) -> SimRobot:
        self.dxl.start()
        await self.xela.start()
        app = web.Application()
        app.add_routes([web.get("/object", self._get_object), web.post("/object", self._place),
                        web.get("/camera.jpg", self._camera), web.post("/fault", self._fault),
                        web.get("/motors", self._motors)])
        self._runner = web.AppRunner(app, access_log=None)
        await self._runner.setup()
        site = web.TCPSite(self._runner, "127.0.0.1", self._control_port)
        await site.start()
        port = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]
        self.control_url = f"http://127.0.0.1:{port}"
        log.info("emulated robot: xela %s, bus %s, control %s", self.xela.url, self.dxl.port,
                 self.control_url)
        return self

    async def stop(self) -> None:
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        await self.xela.stop(keep_port=False)
        self.dxl.stop()

    async def __aenter__(self) -> SimRobot:
        return await self.start()

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    def runtime_config(self, cfg: Config) -> Config:
        """``cfg`` pointed at this robot: only the device addresses change."""
        return replace(
            cfg,
            sensor=replace(cfg.sensor, url=self.xela.url),
            bus=replace(cfg.bus, port=self.dxl.port),
            camera=replace(cfg.camera, kind="http", url=f"{self.control_url}/camera.jpg"),
        )

    async def _get_object(self, request: web.Request) -> web.Response:
        return web.json_response({"object": self.world.object_name,
                                  "peak_force_n": self.world.peak_force_n,
                                  "force_n": self.world.force_n,
                                  "gap_m": self.world.gap_m,
                                  "placements": self.world.placements})

    async def _place(self, request: web.Request) -> web.Response:
        try:
            body = await request.json()
            name = body["name"]
            self.world.place(name)
        except (ValueError, KeyError, TypeError) as exc:
            return web.json_response({"error": f"send {{\"name\": OBJECT}}: {exc}"}, status=400)
        return web.json_response({"object": name})

    def apply_fault(self, request: Mapping[str, Any]) -> dict[str, Any]:
        """Switch one fault: ``{"fault": NAME, FIELD: VALUE...}`` (see :data:`FAULTS`).
        Returns the fault with every field as applied; ValueError naming what is wrong."""
        name = request.get("fault")
        if name not in FAULTS:
            raise ValueError(f"unknown fault {name!r}; one of: {', '.join(FAULTS)}")
        fields = FAULTS[name]
        unknown = sorted(set(request) - {"fault", *fields})
        if unknown:
            raise ValueError(f"{name} takes no {', '.join(unknown)}; its fields: "
                             f"{', '.join(fields) or 'none'}")
        args = {key: _field(request, key, *spec) for key, spec in fields.items()}
        dxl = self.dxl
        if "motor" in args and args["motor"] not in dxl.ids:
            raise ValueError(f"motor: {args['motor']} is not on the bus (motors "
                             f"{', '.join(map(str, dxl.ids))})")
        if name == "motor_silent":
            dxl.set_missing(args["motor"], args["on"])
        elif name == "crc_errors":
            if args["count"] < -1:
                raise ValueError(f"count: {args['count']}; -1 (every packet), 0 (none) or more")
            dxl.corrupt_crc(args["motor"], args["count"])
        elif name == "hardware_error":
            if not 0 <= args["bits"] <= 0xFF:
                raise ValueError(f"bits: {args['bits']} is not a byte (0..255)")
            dxl.set_hardware_error(args["motor"], args["bits"])
        elif name == "serial_error":
            dxl.serial_error_once()
        elif name == "unplug":
            dxl.unplug()
        elif name == "plug":
            dxl.plug()
        else:
            try:
                self.xela.fault = Fault(args["mode"])
            except ValueError:
                raise ValueError(f"mode: {args['mode']!r}; one of: "
                                 f"{', '.join(f.value for f in Fault)}") from None
        applied = {"fault": name, **args}
        log.info("emulated fault switched: %s", applied)
        return applied

    def motors(self) -> dict[str, Any]:
        """Each motor as the emulator holds it, and whether the bus adapter is plugged in."""
        dxl = self.dxl
        return {"plugged": dxl.plugged, "motors": [
            {"id": i, "position": round(dxl.true_position(i), 1),
             "torque": bool(dxl.get_register(i, "Torque Enable")),
             "hardware_error": dxl.get_register(i, "Hardware Error Status"),
             "bus_watchdog": dxl.get_register(i, "Bus Watchdog"),
             "silent": dxl.missing(i)} for i in dxl.ids]}

    async def _fault(self, request: web.Request) -> web.Response:
        try:
            body = await request.json()
        except ValueError:
            body = None
        if not isinstance(body, dict):
            return web.json_response({"error": 'send a JSON object {"fault": NAME, ...}; '
                                      f"faults: {', '.join(FAULTS)}"}, status=400)
        try:
            return web.json_response(self.apply_fault(body))
        except ValueError as exc:
            return web.json_response({"error": str(exc)}, status=400)

    async def _motors(self, request: web.Request) -> web.Response:
        return web.json_response(self.motors())

    async def _camera(self, request: web.Request) -> web.Response:
        import asyncio

        data = await asyncio.to_thread(sim_camera.render, self.world.object_name)
        return web.Response(body=data, content_type="image/jpeg")


_TYPE_NAMES = {int: "an integer", bool: "true or false", str: "a string"}


def _field(request: Mapping[str, Any], key: str, kind: type, default: Any) -> Any:
    """``request[key]``, of type ``kind`` (``default`` where absent; None: required);
    ValueError naming the field when missing or of another type."""
    if key not in request:
        if default is None:
            raise ValueError(f"{key}: missing ({_TYPE_NAMES[kind]})")
        return default
    value = request[key]
    # (A JSON true is no motor ID, though bool is an int to Python.)
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise ValueError(f"{key}: {value!r} is not {_TYPE_NAMES[kind]}")
    return value
