"""Does the tracker hold on to a live camera? (open problem of issue 7, README "Known problem")

The tracker on the real-time synthetic camera the way the daemon runs it, without the rest
of the daemon: frames captured in a thread, only the newest kept, bundle adjustment in its
background thread. Prints the count of each state and the sequence of states (tar = target,
tra = tracking, rel = relocalised, los = lost). On the shared 2-core machine, 2 of 5 runs
lost the map about a second after the cube left the view.

    .venv/bin/python scripts/tracker-live-check.py ["synthetic:paper?seconds=20&fps=10&seed=1&realtime=1"]
"""

from __future__ import annotations

import collections
import contextlib
import queue
import sys
import threading

from daemon.config import Config
from drivers.base import FrameTimeout
from drivers.registry import make_camera
from positioning.tracking import ProcessorOptions, TrackingProcessor

DEFAULT_SOURCE = "synthetic:paper?seconds=20&fps=10&seed=1&realtime=1"


def main(source: str) -> None:
    camera = make_camera(source, Config().camera.settings())
    camera.open()
    camera.start()
    newest: queue.Queue = queue.Queue(maxsize=1)
    ended = threading.Event()

    def capture() -> None:
        try:
            while True:
                try:
                    frame = camera.next_frame(0.25)  # the daemon's poll period
                except FrameTimeout:
                    continue
                with contextlib.suppress(queue.Empty):
                    newest.get_nowait()  # drop the older frame, as the daemon's slot does
                newest.put(frame)
        except Exception:  # EndOfStream: the trajectory is over
            ended.set()

    threading.Thread(target=capture, daemon=True).start()
    processor = TrackingProcessor(camera.target, camera.calibration, ProcessorOptions())
    states: list[str] = []
    while not (ended.is_set() and newest.empty()):
        try:
            frame = newest.get(timeout=0.5)
        except queue.Empty:
            continue
        result = processor.process(frame.image, frame.stamp_ns, frame.frame_id)
        states.append(result.estimate.state.value if result.estimate else result.status)
    processor.close()
    print(dict(collections.Counter(states)))
    print(" ".join(state[:3] for state in states))


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else DEFAULT_SOURCE)
