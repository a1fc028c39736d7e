"""Grab throughput from Aravis' GigE Vision fake camera over loopback, 1280x1024 Mono8.

The fake runs as its own process (``arv-fake-gv-camera-0.8``) sending real GVSP packets
to 127.0.0.1; the backend receives them (Aravis' stream thread), copies each frame once
into numpy and hands it over (the capture thread, here the main thread). Per run: frames
per second delivered, % of one core used by the capture thread (``time.thread_time`` over
wall time) and by the whole cubeloc process (Aravis' receive thread included), and frames
lost. Medians over runs.
"""

from __future__ import annotations

import os
import statistics
import time
from pathlib import Path

from bench.common import markdown_table

TITLE = "Grab throughput, Aravis GigE Vision fake camera 1280x1024 Mono8"
RUNS = 5
RUN_SECONDS = 3.0
RATES_HZ = (30.0, 1000.0)  # a typical camera rate, and as fast as the fake can go


def process_cpu_seconds(pid: int) -> float:
    """User + system CPU time of another process (the fake camera), from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def grab_run(camera, seconds: float, fake_pid: int) -> dict[str, float]:
    camera.next_frame(2.0)  # warm: the first frame pays for buffer set-up
    before = (camera.stats.delivered, camera.stats.frame_id_gaps, camera.stats.incomplete)
    fake0 = process_cpu_seconds(fake_pid)
    wall0, thread0, process0 = time.perf_counter(), time.thread_time(), time.process_time()
    while time.perf_counter() - wall0 < seconds:
        camera.next_frame(2.0)
    wall = time.perf_counter() - wall0
    thread, process = time.thread_time() - thread0, time.process_time() - process0
    fake = process_cpu_seconds(fake_pid) - fake0
    frames = camera.stats.delivered - before[0]
    lost = (camera.stats.frame_id_gaps - before[1]) + (camera.stats.incomplete - before[2])
    return {"fps": frames / wall, "thread_cpu": 100 * thread / wall,
            "process_cpu": 100 * process / wall, "fake_cpu": 100 * fake / wall, "lost": 100 * lost / max(frames + lost, 1)}


def run() -> str:
    import logging

    import structlog

    from cubeloc.drivers.aravis_camera import AravisCamera
    from cubeloc.drivers.base import CameraSettings
    from cubeloc.drivers.fake_gige import GvFake

    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    fake = GvFake("BENCH1").start()
    rows = []
    try:
        for rate in RATES_HZ:
            # Short exposure: the fake, like a real camera, cannot run faster than 1/exposure.
            settings = CameraSettings(width=1280, height=1024, frame_rate_hz=rate, exposure_us=1000.0)
            with AravisCamera(fake.device_id, settings) as camera:
                camera.start()
                runs = [grab_run(camera, RUN_SECONDS, fake.process.pid) for _ in range(RUNS)]
                camera.stop()
            med = {key: statistics.median(r[key] for r in runs) for key in runs[0]}
            rows.append([f"{rate:g}", f"{med['fps']:.1f}", f"{med['thread_cpu']:.1f}",
                         f"{med['process_cpu']:.1f}", f"{med['fake_cpu']:.0f}", f"{med['lost']:.1f}"])
    finally:
        fake.stop()
    table = markdown_table(
        ["requested frame rate (Hz)", "frames/s delivered", "capture thread CPU (% of a core)",
         "cubeloc process CPU (% of a core)", "fake camera CPU (% of a core)", "frames lost (%)"],
        rows)
    return table + (
        f"\nMedians over {RUNS} runs of {RUN_SECONDS:g} s each. The fake camera is a separate "
        "process on the same 2 cores (its image generation and packet sending compete with the "
        "receiver), so the highest rate shows the fake's limit as much as ours. The capture "
        "thread's share is the one copy of 1.3 MB per frame plus Python overhead; the process "
        "share adds Aravis' GVSP receive thread.\n")
