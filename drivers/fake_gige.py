"""Aravis' GigE Vision fake camera on 127.0.0.1 (real GVCP/GVSP packets over loopback), run
as a process that tests and benchmarks can stop and restart (to pull the plug).

Needs ``arv-fake-gv-camera-0.8`` (Debian: aravis-tools). Only one fake can own
127.0.0.1:3956/udp at a time, so ``start`` waits for the port to be free.
"""

from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

GVCP_PORT = 3956
FAKE_GV_CAMERA = "arv-fake-gv-camera-0.8"


def gvcp_listening() -> bool:
    """Is something bound to 127.0.0.1:3956/udp? (/proc/net/udp: little-endian hex address)."""
    wanted = f"0100007F:{GVCP_PORT:04X}"
    try:
        lines = Path("/proc/net/udp").read_text().splitlines()[1:]
    except OSError:
        return False
    return any(line.split()[1] == wanted for line in lines if len(line.split()) > 1)


class GvFake:
    def __init__(self, serial: str = "GV01") -> None:
        if shutil.which(FAKE_GV_CAMERA) is None:
            raise RuntimeError(f"{FAKE_GV_CAMERA} not found: apt-get install aravis-tools")
        self.serial = serial
        self.process: subprocess.Popen | None = None

    @property
    def device_id(self) -> str:
        return f"Aravis-Fake-{self.serial}"

    def start(self) -> GvFake:
        # Wait for the port: a previous fake still closing, or another test run's fake
        # (only one GigE Vision fake can own 127.0.0.1:3956 at a time).
        deadline = time.monotonic() + 90
        while gvcp_listening():
            if time.monotonic() > deadline:
                raise RuntimeError("127.0.0.1:3956/udp is taken by another process")
            time.sleep(0.05)
        self.process = subprocess.Popen([FAKE_GV_CAMERA, "-i", "127.0.0.1", "-s", self.serial],
                                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 10
        while not gvcp_listening():
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"{FAKE_GV_CAMERA} did not start (exit {self.process.poll()})")
            time.sleep(0.02)
        return self

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=10)
        self.process = None
