"""Aravis' GigE Vision fake camera on 127.0.0.1 (real GVCP/GVSP packets over loopback), run
as a process that tests and benchmarks can stop and restart (to pull the plug).

Needs ``arv-fake-gv-camera-0.8`` (Debian: aravis-tools). Only one fake can own
127.0.0.1:3956/udp at a time, so ``start`` waits for the port to be free; it returns once
Aravis' broadcast discovery lists the fake, so that a client that looks it up by name finds
it even when a busy machine is slow to start the fake's main loop.
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
        self._wait_discoverable(deadline_s=30.0)
        return self

    def _wait_discoverable(self, deadline_s: float) -> None:
        """Bound to its port is not yet answering: each discovery waits out Aravis' own
        reply window (1 s), and this repeats it until the fake answers or the deadline."""
        from cubeloc.drivers.aravis_camera import list_aravis_devices

        deadline = time.monotonic() + deadline_s
        while not any(d.serial == self.serial for d in list_aravis_devices()):
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"{FAKE_GV_CAMERA} -s {self.serial} is not answering GigE Vision "
                                   f"discovery after {deadline_s:.0f} s (exit {self.process.poll()})")

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=10)
        self.process = None
