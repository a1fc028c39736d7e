"""``cubeloc calibrate --camera SOURCE --foxglove HOST:PORT``: the live calibration in Foxglove.

A technician follows it from a laptop (the Foxglove app, ``ws://HOST:PORT``; an SSH tunnel
to ``127.0.0.1:PORT`` keeps it on the robot). Channels:

- ``/camera/image`` ``foxglove.CompressedImage``: the live image (daemon/viewer.py's ImageOut);
- ``/calibration/annotations`` ``foxglove.ImageAnnotations`` on it: the board's points found
  (green: the view was kept, yellow: seen but not kept, e.g. too like a kept one, red:
  blurred), the 3 x 3 cells (filled once a kept view reaches them), a bar per coverage score
  (X, Y, size, skew: calib/coverage.py) and the next hint;
- ``/calibration/hint`` ``foxglove.Log``: the terminal's status line, each time it changes.
"""

from __future__ import annotations

import foxglove
import numpy as np
from foxglove import channels as fc
from foxglove import messages as fm

from cubeloc.calib.coverage import CoverageTracker, Offer
from cubeloc.calib.detect import Detection
from cubeloc.daemon.config import FoxgloveConfig
from cubeloc.daemon.viewer import GREEN, RED, YELLOW, ImageOut, label, rgba, serve, timestamp

CELL_FILL = (0.1, 0.85, 0.2, 0.18)
BAR_WIDTH, BAR_HEIGHT, BAR_GAP = 120.0, 12.0, 22.0  # pixels of the shown image


class CalibrationView:
    def __init__(self, listen: str, config: FoxgloveConfig | None = None) -> None:
        self.config = (config or FoxgloveConfig()).model_copy(update={"listen": listen})
        self.context = foxglove.Context()
        self.picture = ImageOut(self.context, self.config, "camera")
        self.annotations = fc.ImageAnnotationsChannel("/calibration/annotations", context=self.context)
        self.hint = fc.LogChannel("/calibration/hint", context=self.context)
        self.server = serve(self.context, listen, "cubeloc calibrate")
        self._period_ns = int(1e9 / self.config.image_max_hz)
        self._last_ns: int | None = None
        self._last_line = ""

    def show(self, stamp_ns: int, image: np.ndarray, detection: Detection | None, offer: Offer,
             tracker: CoverageTracker) -> None:
        """This frame, if the rate allows (a kept view is always shown)."""
        line = tracker.status_line()
        if line != self._last_line and self.hint.has_sinks():
            self._last_line = line
            self.hint.log(fm.Log(timestamp=timestamp(stamp_ns), level=fm.LogLevel.Info, message=line,
                                 name="cubeloc/calibrate"))
        if not offer.accepted and self._last_ns is not None and 0 <= stamp_ns - self._last_ns < self._period_ns:
            return
        self._last_ns = stamp_ns
        self.picture.publish(stamp_ns, image, None)
        if self.annotations.has_sinks():
            self.annotations.log(self._annotations(stamp_ns, detection, offer, tracker))

    def _annotations(self, stamp_ns: int, detection: Detection | None, offer: Offer,
                     tracker: CoverageTracker) -> fm.ImageAnnotations:
        stamp, points, texts = timestamp(stamp_ns), [], []
        width, height = self.picture.size
        covered = tracker.covered_cells
        for row in range(3):
            for col in range(3):
                x0, x1, y0, y1 = col * width / 3, (col + 1) * width / 3, row * height / 3, (row + 1) * height / 3
                corners = [fm.Point2(x=x, y=y) for x, y in ((x0, y0), (x1, y0), (x1, y1), (x0, y1))]
                points.append(fm.PointsAnnotation(
                    timestamp=stamp, type=fm.PointsAnnotationType.LineLoop, points=corners, thickness=1.0,
                    outline_color=rgba((1.0, 1.0, 1.0, 0.35)),
                    fill_color=rgba(CELL_FILL if (row, col) in covered else (0.0, 0.0, 0.0, 0.0))))
        if detection is not None:
            colour = GREEN if offer.accepted else (RED if not detection.is_sharp else YELLOW)
            points.append(fm.PointsAnnotation(timestamp=stamp, type=fm.PointsAnnotationType.Points,
                                              points=self.picture.px(detection.image_points), thickness=4.0,
                                              outline_color=rgba(colour)))
        for k, (name, value) in enumerate(tracker.progress().items()):
            x0, y0 = 10.0, height - 10.0 - (4 - k) * BAR_GAP
            frame = [(x0, y0), (x0 + BAR_WIDTH, y0), (x0 + BAR_WIDTH, y0 + BAR_HEIGHT), (x0, y0 + BAR_HEIGHT)]
            filled = [(x0, y0), (x0 + BAR_WIDTH * value, y0), (x0 + BAR_WIDTH * value, y0 + BAR_HEIGHT),
                      (x0, y0 + BAR_HEIGHT)]
            done = GREEN if value >= 1.0 else YELLOW
            points.append(fm.PointsAnnotation(timestamp=stamp, type=fm.PointsAnnotationType.LineLoop, thickness=1.0,
                                              points=[fm.Point2(x=x, y=y) for x, y in filled],
                                              outline_color=rgba(done), fill_color=rgba(done)))
            points.append(fm.PointsAnnotation(timestamp=stamp, type=fm.PointsAnnotationType.LineLoop, thickness=1.0,
                                              points=[fm.Point2(x=x, y=y) for x, y in frame],
                                              outline_color=rgba((1.0, 1.0, 1.0, 1.0))))
            texts.append(label(stamp, fm.Point2(x=x0 + BAR_WIDTH + 6.0, y=y0 + BAR_HEIGHT - 1.0),
                               f"{name} {100 * value:.0f} %", size=12.0))
        todo = tracker.missing()
        hint = "; ".join(todo[:3]) if todo else "coverage good: finishing"
        texts.append(label(stamp, fm.Point2(x=8.0, y=20.0), f"views {len(tracker.scores)}: {hint}", size=16.0))
        texts.append(label(stamp, fm.Point2(x=8.0, y=42.0), ("+ " if offer.accepted else "- ") + offer.reason,
                           GREEN if offer.accepted else YELLOW, size=13.0))
        return fm.ImageAnnotations(points=points, texts=texts)

    def close(self) -> None:
        self.server.stop()
