"""A rendered or recorded sequence replayed through the tracker in this process: every
frame in order, bundle adjustment in the frame loop (``ProcessorOptions.in_frame_loop``),
so the same frames give the same poses. What tests, benchmarks and traces replay;
``cubeloc track`` is the command, with the daemon's options and its outputs."""

from __future__ import annotations

from pathlib import Path

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.drivers.sequence import read_image, read_sequence_index
from cubeloc.positioning.estimator import FrameResult
from cubeloc.positioning.evaluation import RunScore, score_estimates
from cubeloc.positioning.target import Target, make_cube
from cubeloc.positioning.tracking.processor import ProcessorOptions, TrackingProcessor
from cubeloc.positioning.trajectory_io import read_tum


def track_results(sequence: Path, calibration: CameraCalibration, target: Target | None = None) -> list[FrameResult]:
    """The tracker's ``FrameResult`` for each frame of ``sequence``, with the target's
    model (the cube's when None) and nothing else known."""
    processor = TrackingProcessor(target or make_cube(), calibration, ProcessorOptions.in_frame_loop())
    try:
        return [processor.process(read_image(e.path), e.stamp_ns, i)
                for i, e in enumerate(read_sequence_index(sequence))]
    finally:
        processor.close()


def track_in_process(sequence: Path, calibration: CameraCalibration, target: Target | None = None) -> RunScore:
    """``track_results`` scored against the sequence's ground truth (``groundtruth.tum``)."""
    results = track_results(sequence, calibration, target)
    return score_estimates(read_tum(sequence / "groundtruth.tum"), [r.estimate for r in results])
