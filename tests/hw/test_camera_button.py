import asyncio
import shlex
import sys
import time

import pytest

from edge.core.errors import DeviceError, DeviceTimeoutError
from edge.hw.button import _PolledButton
from edge.hw.camera import CommandCamera, HttpCamera
from edge.sim.robot import SimRobot
from tests.support.fakes import FakeCamera
from tests.support.waits import wait_until

WRITE_JPEG = ("import sys; from PIL import Image; "
              "Image.new('RGB', (64, 48), 'red').save(sys.argv[1], 'JPEG')")


def py(code: str) -> str:
    return f"{shlex.quote(sys.executable)} -c {shlex.quote(code)}"


@pytest.mark.asyncio
async def test_command_camera_reads_the_file_it_writes():
    image = await CommandCamera(py(WRITE_JPEG) + " {out}").capture()
    assert image[:3] == b"\xff\xd8\xff"


@pytest.mark.asyncio
async def test_command_camera_failures_are_clear():
    with pytest.raises(DeviceError, match="must contain"):
        CommandCamera("fswebcam still.jpg")
    with pytest.raises(DeviceError, match="exit 3"):
        await CommandCamera(py("import sys; sys.stderr.write('no camera'); sys.exit(3)")
                            + " {out}").capture()
    with pytest.raises(DeviceError, match="wrote no file"):
        await CommandCamera(py("pass") + " {out}").capture()
    with pytest.raises(DeviceError, match="cannot start"):
        await CommandCamera("/nonexistent/camera {out}").capture()
    t = time.monotonic()
    with pytest.raises(DeviceTimeoutError):
        await CommandCamera(py("import time; time.sleep(10)") + " {out}", 0.3).capture()
    assert time.monotonic() - t < 5


@pytest.mark.asyncio
async def test_http_camera_on_the_simulated_robot():
    async with SimRobot("macaron") as robot:
        image = await HttpCamera(f"{robot.control_url}/camera.jpg").capture()
        assert image[:3] == b"\xff\xd8\xff"
        with pytest.raises(DeviceError, match="HTTP 404"):
            await HttpCamera(f"{robot.control_url}/nope.jpg").capture()


@pytest.mark.asyncio
async def test_polled_button_debounces_and_reports_presses():
    levels = iter([False] * 3 + [True, False, True] + [True] * 10 + [False] * 10 + [True] * 10
                  + [False] * 1000)
    reads = 0

    def read():
        nonlocal reads
        reads += 1
        return next(levels)

    button = _PolledButton(read, "test")
    presses = []

    async def collect():
        async for t in button.presses():
            presses.append(t)

    task = asyncio.create_task(collect())
    # Until the last press and release have been read, however late a loaded host polls;
    # then a moment for any press still on its way to the loop.
    await wait_until(lambda: reads > 46, 10.0, "the levels read")
    await asyncio.sleep(0.1)
    task.cancel()
    await button.close()
    # The bounce right after the first press is ignored: two clean presses.
    assert len(presses) == 2


@pytest.mark.asyncio
async def test_fake_camera_counts_captures():
    camera = FakeCamera(b"\xff\xd8\xff")
    assert await camera.capture() == b"\xff\xd8\xff" and camera.captures == 1
