"""The whole emulated robot: the world, the ``xela_server`` emulator on loopback and the
Dynamixel bus emulator on a pseudo-terminal, plus a small control endpoint (place an object,
take a picture). The runtime connects to it with the real drivers; only the device addresses
in its configuration differ from the real robot's. With a ``replay``, the XELA emulator serves
that real recording instead of the physics' frames (the arm and gripper are still emulated).
"""

from __future__ import annotations

import logging
from dataclasses import replace

from aiohttp import web

from edge.core.config import Config
from edge.core.layout import PadLayout
from edge.sim import camera as sim_camera
from edge.sim.catalogue import get
from edge.sim.world import SimWorld, raw_from_width, robot_motors, robot_pads
from edge.sim.xela_replay import Replay
from edge.sim.xela_server import XelaServerEmulator

log = logging.getLogger(__name__)


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
                        web.get("/camera.jpg", self._camera)])
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

    async def _camera(self, request: web.Request) -> web.Response:
        import asyncio

        data = await asyncio.to_thread(sim_camera.render, self.world.object_name)
        return web.Response(body=data, content_type="image/jpeg")
