"""The single-frame target pose as a ``FrameProcessor``: image in, pose (or reason) out.

A ``TargetObserver`` (observer.py) does the work; this keeps the last pose, from which
the observer predicts where the target will be in the next frame: the steady state
searches those regions only, and the full frame runs when they give fewer faces than
before.
"""

from __future__ import annotations

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.positioning.detection import DetectorOptions
from cubeloc.positioning.estimator import FrameResult, FrameView, PoseEstimate, PoseState
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.observer import TargetObserver, image_problem
from cubeloc.positioning.target import Target
from cubeloc.positioning.target_pose import PoseOptions


class TargetPoseProcessor:
    """The camera pose from the target alone, frame by frame (``state = target``).

    ``last_search`` says which of the observer's searches ran on the last frame.
    """

    def __init__(self, target: Target, calibration: CameraCalibration, options: PoseOptions | None = None,
                 detector_options: DetectorOptions | None = None, edge_refinement: bool = True,
                 full_frame_decimate: float = 3.0, edge_alignment: bool = True) -> None:
        self.target = target
        self.calibration = calibration
        self.observer = TargetObserver(target, calibration, options, detector_options, edge_refinement,
                                       full_frame_decimate, edge_alignment)
        self._last_pose: Transform | None = None

    @property
    def last_search(self) -> str:
        return self.observer.last_search

    def reset(self) -> None:
        self.observer.reset()
        self._last_pose = None

    def process(self, image, stamp_ns: int, seq: int) -> FrameResult:
        problem = image_problem(image, self.calibration)
        if problem is not None:
            return FrameResult(None, "bad_image", problem)
        observation = self.observer.observe(image, self._last_pose, seq)
        pose = observation.pose
        if pose is None:
            self._last_pose = None
            return FrameResult(None, observation.refusal.value, observation.detail, observation.seen,
                               FrameView(observation.outlines))
        self._last_pose = pose.T_world_camera
        estimate = PoseEstimate(pose.T_world_camera, PoseState.TARGET, pose.planes, pose.tag_ids,
                                pose.reproj_rms_px, pose.covariance)
        return FrameResult(estimate, "ok", "", observation.seen, FrameView(observation.outlines))
