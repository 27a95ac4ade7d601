"""The device contracts: importable without any hardware library."""

from __future__ import annotations

import subprocess
import sys

HARDWARE_LIBRARIES = ("dynamixel_sdk", "serial", "aiohttp", "cv2", "gpiod")


def test_contracts_import_no_sdk_network_or_serial_library():
    # A fresh interpreter: this test process has long since imported the drivers.
    code = (
        "import sys\n"
        "import edge.hw.contracts\n"
        f"libs = {HARDWARE_LIBRARIES!r}\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in libs))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", f"edge.hw.contracts loaded {out.stdout.strip()}"
