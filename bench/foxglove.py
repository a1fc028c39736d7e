"""What the Foxglove viewer costs the daemon: CPU with it off, on with nobody connected,
and on with one client subscribed to every channel, side by side in one run.

The real daemon (bench/e2e.py's ``start_daemon``: capture thread, tracker, Zenoh) runs in
this process on pre-rendered 1280x1024 frames of the cube played at 10 Hz (the paper's
rate; at 30 Hz this machine's two cores are saturated and a cost shows as frames lost); the viewer
client is another process (tests/foxglove_client.py, the protocol as the Foxglove app
speaks it), so its own work is not counted. CPU = this process's CPU time (every thread:
capture, processing, the viewer's thread, the SDK's server threads) per second of wall
time, as a share of one core, over 10 s after a 3 s warm-up. The three modes take turns,
five rounds, each round starting with the next mode; each figure is the median of five.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.common import REPO, markdown_table
from bench.e2e import free_port, render_frames, start_daemon

TITLE = "Foxglove viewer: CPU cost, off / on without a client / on with one client"

RATE_HZ = 10.0  # the paper's rate: the daemon keeps up with room to spare, so CPU shows the cost
RUN_SECONDS = 10.0
WARMUP_S = 3.0
ROUNDS = 5
MODES = ("off", "on, no client", "on, one client")
CLIENT = REPO / "tests" / "foxglove_client.py"


def measure(images, mode: str, workdir: Path) -> dict:
    port = free_port()
    sections = {} if mode == "off" else {"foxglove": {"listen": f"127.0.0.1:{port}"}}
    daemon, stop, thread, camera, _ = start_daemon(images, RATE_HZ, workdir, **sections)
    client = None
    try:
        if mode == "on, one client":
            client = subprocess.Popen([sys.executable, str(CLIENT), str(port), str(WARMUP_S + RUN_SECONDS + 5)],
                                      stdout=subprocess.PIPE, text=True)
            assert client.stdout.readline().strip() == "subscribed"
        time.sleep(WARMUP_S)
        cpu, wall, frames = time.process_time(), time.monotonic(), daemon.stats.frames
        time.sleep(RUN_SECONDS)
        cpu, wall = time.process_time() - cpu, time.monotonic() - wall
        frames = daemon.stats.frames - frames
        viewer = daemon.report().extra.get("foxglove", {})
    finally:
        stop.set()
        thread.join(10.0)
    received = {}
    if client is not None:
        out, _ = client.communicate(timeout=60)
        received = json.loads(out.strip().splitlines()[-1])
    return {"mode": mode, "cpu_share": cpu / wall, "fps": frames / wall, "viewer": viewer, "received": received}


def run() -> str:
    images = render_frames()
    results: dict[str, list[dict]] = {mode: [] for mode in MODES}
    with tempfile.TemporaryDirectory(prefix="cubeloc-bench-foxglove-") as tmp:
        for k in range(ROUNDS):
            for mode in MODES[k % len(MODES):] + MODES[:k % len(MODES)]:  # each mode first in turn
                r = measure(images, mode, Path(tmp))
                print(json.dumps(r), flush=True)
                results[mode].append(r)
    base = statistics.median(r["cpu_share"] for r in results["off"])
    rows = []
    for mode in MODES:
        share = statistics.median(r["cpu_share"] for r in results[mode])
        fps = statistics.median(r["fps"] for r in results[mode])
        last = results[mode][-1]
        images_sent = last["viewer"].get("images", "-")
        received = last["received"]
        per_frame = statistics.median(1000 * r["cpu_share"] / r["fps"] for r in results[mode])
        spread = [100 * r["cpu_share"] for r in results[mode]]
        rows.append([mode, f"{100 * share:.1f} ({min(spread):.1f}-{max(spread):.1f})", f"{100 * (share - base):+.1f}",
                     f"{per_frame:.1f}", f"{fps:.1f}",
                     f"{images_sent}", f"{received.get('/camera/image', '-')} / {received.get('/pose', '-')}",
                     f"{last['viewer'].get('dropped', '-')}"])
    table = markdown_table(["mode", "CPU, % of a core: median of 5 (range)", "more than off, points",
                            "CPU ms per frame processed", "frames/s",
                            "images sent (last run)", "client got images / poses (last run)",
                            "frames the viewer skipped (last run)"], rows)
    return (table + f"\nThe daemon (tracker) on 1280x1024 frames at {RATE_HZ:g} Hz, {RUN_SECONDS:g} s per run "
            f"after {WARMUP_S:g} s; viewer defaults: 640x512 JPEG (quality 80) at most 10 Hz. "
            f"The client subscribes to all 8 channels. Goal: one client at most 5 points of a core more "
            f"than off, nothing without a client.\n")


if __name__ == "__main__":  # pragma: no cover
    print(run())
