"""The soak: the daemon on pre-rendered synthetic frames at the camera's full rate, for long.

``run_soak`` runs the real ``Daemon`` (capture
thread, the configured frame processor, real Zenoh on loopback, status thread) in this
process on a ``fakes.faulty.CyclingCamera``: frames rendered once and played back and
forth at ``--fps``, so rendering is not the bottleneck. The cable is pulled every
``--unplug-every`` seconds (the reconnect path must not leak either). A subscriber in a
second Zenoh session checks every pose against the ground truth.

Sampled every ``--sample`` seconds: the process' RSS (/proc/self/status VmRSS), threads
(/proc/self/task), open file descriptors (/proc/self/fd), frames processed. Checks, after
a warm-up (a tenth of the run, at most 3 minutes):

* RSS: the largest sample after the warm-up is < 5 % above the sample at its end;
* threads and fds: at the end no more than at the end of the warm-up (+1 for Zenoh's
  lazily started workers);
* no slow-down (runs of 5 minutes or more after the warm-up): the process' CPU time per
  frame processed in the last quarter <= 115 % of the first quarter's (a growing map or list would show here). CPU time, not the frame
  rate, because the rate on a shared machine follows the other users' load; the rate per
  quarter is reported alongside (the newest-frame slot drops what the processor cannot
  take);
* poses: none off the ground truth by more than 2 cm or 1 degree, stamps strictly
  increasing, and the daemon ends with exit code 0.

``make soak`` (``python -m bench.soak --minutes 30``, bench/soak.py) runs it for 30
minutes and writes docs/soak.md; tests/test_soak_short.py for 12 seconds.
"""

from __future__ import annotations

import json
import math
import os
import resource
import statistics
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cubeloc.net import free_port
from cubeloc.positioning.geometry import quaternion_angle_deg

WRONG_POSITION_M = 0.02
WRONG_ANGLE_DEG = 1.0
RSS_GROWTH_LIMIT = 0.05
SLOWDOWN_MIN_S = 300.0  # the slow-down check needs quarters of at least a minute or so


@dataclass
class Sample:
    t_s: float
    rss_kb: int
    threads: int
    fds: int
    frames: int
    poses: int
    cpu_s: float = 0.0  # user + system CPU time of the whole process so far


@dataclass
class SoakResult:
    seconds: float
    fps: float
    warmup_s: float
    samples: list[Sample]
    frames_delivered: int = 0
    poses_received: int = 0
    wrong_poses: int = 0
    non_increasing_stamps: int = 0
    max_position_error_m: float = 0.0
    max_angle_error_deg: float = 0.0
    reconnects: int = 0
    unplugs: int = 0
    exit_code: int | None = None
    processor: str = ""
    checks: dict[str, tuple[bool, str]] = field(default_factory=dict)
    info: dict[str, str] = field(default_factory=dict)  # figures reported, not checked

    @property
    def ok(self) -> bool:
        return all(ok for ok, _ in self.checks.values())


def _proc_status_kb(key: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"/proc/self/status has no {key}")


def process_sample(t_s: float, frames: int, poses: int) -> Sample:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return Sample(t_s, _proc_status_kb("VmRSS"), len(os.listdir("/proc/self/task")),
                  len(os.listdir("/proc/self/fd")), frames, poses, usage.ru_utime + usage.ru_stime)


class PoseChecker:
    """A subscriber's view: every pose compared with the camera's ground truth."""

    def __init__(self, port: int, name: str, camera) -> None:
        import zenoh

        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        self._camera = camera
        self._lock = threading.Lock()
        self.received = self.wrong = self.non_increasing = 0
        self.max_position_error_m = self.max_angle_error_deg = 0.0
        self.last_stamp_ns = 0
        self.session = zenoh.open(conf)
        self.session.declare_subscriber(f"cubeloc/{name}/pose", self._on_pose)

    def _on_pose(self, sample) -> None:
        pose = json.loads(sample.payload.to_bytes())
        truth = self._camera.ground_truth(pose["stamp_ns"])
        with self._lock:
            self.received += 1
            if pose["stamp_ns"] <= self.last_stamp_ns:
                self.non_increasing += 1
            self.last_stamp_ns = max(self.last_stamp_ns, pose["stamp_ns"])
            if truth is None:  # a stamp the camera never delivered: wrong by definition
                self.wrong += 1
                return
            position_error = float(np.linalg.norm(np.array(pose["position"]) - truth.translation))
            angle_error = quaternion_angle_deg(pose["orientation"], truth.quaternion())
            self.max_position_error_m = max(self.max_position_error_m, position_error)
            self.max_angle_error_deg = max(self.max_angle_error_deg, angle_error)
            if position_error > WRONG_POSITION_M or angle_error > WRONG_ANGLE_DEG:
                self.wrong += 1

    def close(self) -> None:
        self.session.close()


def run_soak(
    seconds: float,
    *,
    fps: float = 10.0,
    images: int = 24,
    sample_s: float = 10.0,
    warmup_s: float | None = None,
    unplug_every_s: float | None = 300.0,
    room: bool = True,
    progress=None,
) -> SoakResult:
    """Run the daemon for ``seconds`` and check it (see the module docstring)."""
    from cubeloc.daemon.preflight import prepare_on_loopback
    from cubeloc.daemon.sdnotify import SystemdNotifier
    from cubeloc.daemon.service import Daemon
    from cubeloc.fakes.faulty import CyclingCamera, Fault, FaultyCamera, orbit_frames

    warmup_s = min(180.0, seconds / 10) if warmup_s is None else warmup_s
    frames, poses = orbit_frames(images, room=room)
    cycling = CyclingCamera(frames, poses, fps=fps, name="soak")
    faults = {}
    if unplug_every_s:
        every = max(1, int(round(unplug_every_s * fps)))
        faults = {k: Fault("unplug", seconds=0.3) for k in range(every, int(seconds * fps) + 1, every)}
    camera = FaultyCamera(cycling, faults)
    port = free_port()
    name = "soak"
    with tempfile.TemporaryDirectory(prefix="cubeloc-soak-") as tmp:
        height, width = frames[0].shape
        prepared = prepare_on_loopback(Path(tmp), port, name, camera={"width": width, "height": height},
                                       logging={"level": "warning"})
        stop = threading.Event()
        daemon = Daemon(prepared, stop, camera_factory=camera, notifier=SystemdNotifier({}))
        result_processor = type(daemon.processor).__name__
        outcome: dict[str, object] = {}

        def run() -> None:
            try:
                outcome["code"] = daemon.run()
            except BaseException as exc:  # reported as a failed check
                outcome["error"] = exc

        thread = threading.Thread(target=run, name="soak-daemon", daemon=True)
        checker = None
        samples: list[Sample] = []
        result = SoakResult(seconds=seconds, fps=fps, warmup_s=warmup_s, samples=samples,
                            processor=result_processor)
        try:
            thread.start()
            if not daemon.serving.wait(60):
                raise RuntimeError("the daemon did not start within 60 s")
            checker = PoseChecker(port, name, cycling)
            started = time.monotonic()
            samples.append(process_sample(0.0, daemon.stats.frames, daemon.stats.poses))
            next_sample = started + sample_s
            while (now := time.monotonic()) < started + seconds and thread.is_alive():
                time.sleep(max(0.0, min(next_sample, started + seconds) - now))
                if time.monotonic() >= next_sample:
                    samples.append(process_sample(time.monotonic() - started, daemon.stats.frames, daemon.stats.poses))
                    next_sample += sample_s
                    if progress is not None:
                        progress(samples[-1])
            if time.monotonic() - started - samples[-1].t_s > sample_s / 2:  # no sliver of a window
                samples.append(process_sample(time.monotonic() - started, daemon.stats.frames, daemon.stats.poses))
            result.reconnects = daemon.capture.status().reconnects
        finally:
            stop.set()
            thread.join(10.0)
            if checker is not None:
                time.sleep(0.3)  # the last poses in flight
                checker.close()
        result.frames_delivered = cycling.stats.delivered
        result.unplugs = sum(1 for entry in camera.log if entry[:2] == ("fault", "unplug"))
        result.exit_code = outcome.get("code") if not thread.is_alive() else None
        if checker is not None:
            result.poses_received = checker.received
            result.wrong_poses = checker.wrong
            result.non_increasing_stamps = checker.non_increasing
            result.max_position_error_m = checker.max_position_error_m
            result.max_angle_error_deg = checker.max_angle_error_deg
        evaluate(result, outcome.get("error"))
        return result


def evaluate(result: SoakResult, error: BaseException | None = None) -> None:
    samples = result.samples
    checks = result.checks
    after = [s for s in samples if s.t_s >= result.warmup_s]
    checks["daemon ran to the end, exit 0"] = (
        result.exit_code == 0 and error is None,
        f"exit code {result.exit_code}" + (f", {type(error).__name__}: {error}" if error else ""))
    if len(after) < 3:
        checks["enough samples after warm-up"] = (False, f"{len(after)} samples after {result.warmup_s:.0f} s")
        return
    warm, end = after[0], after[-1]
    peak = max(s.rss_kb for s in after)
    growth = (peak - warm.rss_kb) / warm.rss_kb
    checks["RSS growth < 5 %"] = (growth < RSS_GROWTH_LIMIT,
                                  f"{warm.rss_kb / 1024:.1f} MiB after warm-up, peak {peak / 1024:.1f} MiB, "
                                  f"end {end.rss_kb / 1024:.1f} MiB ({100 * growth:+.2f} %)")
    checks["no thread leak"] = (end.threads <= warm.threads + 1, f"{warm.threads} -> {end.threads}")
    checks["no fd leak"] = (end.fds <= warm.fds + 1, f"{warm.fds} -> {end.fds}")
    quarter = max(2, len(after) // 4)
    head, tail = after[:quarter], after[-quarter:]
    cpu_first, cpu_last = cpu_ms_per_frame(head), cpu_ms_per_frame(tail)
    cpu_text = f"{cpu_first:.1f} ms of CPU per frame in the first quarter, {cpu_last:.1f} in the last"
    if end.t_s - warm.t_s >= SLOWDOWN_MIN_S:
        checks["no slow-down (CPU per frame)"] = (cpu_last <= 1.15 * cpu_first, cpu_text)
    else:  # quarters of seconds: a tracker's bundle adjustment more or less decides it
        result.info["CPU per frame"] = cpu_text
    rates = window_rates(after)
    result.info["frame rate"] = (
        f"{rate(head):.2f} fps in the first quarter, {rate(tail):.2f} in the last, min window "
        f"{min(rates):.2f}, mean {statistics.fmean(rates):.2f} (camera {result.fps:g}; shared 2-core machine)")
    checks["no wrong pose"] = (
        result.poses_received > 0 and result.wrong_poses == 0 and result.non_increasing_stamps == 0,
        f"{result.poses_received} poses, {result.wrong_poses} off the truth, "
        f"{result.non_increasing_stamps} stamps not increasing; max error "
        f"{1000 * result.max_position_error_m:.2f} mm, {result.max_angle_error_deg:.3f} deg")
    if result.unplugs:
        checks["recovers from every unplug"] = (result.reconnects >= result.unplugs,
                                                f"{result.unplugs} unplugs, {result.reconnects} reconnects")


def cpu_ms_per_frame(samples: list[Sample]) -> float:
    frames = samples[-1].frames - samples[0].frames
    return 1000 * (samples[-1].cpu_s - samples[0].cpu_s) / frames if frames > 0 else math.inf


def rate(samples: list[Sample]) -> float:
    span = samples[-1].t_s - samples[0].t_s
    return (samples[-1].frames - samples[0].frames) / span if span > 0 else 0.0


def window_rates(samples: list[Sample]) -> list[float]:
    return [(b.frames - a.frames) / (b.t_s - a.t_s) for a, b in zip(samples, samples[1:], strict=False) if b.t_s > a.t_s]
