"""The motion model: how the tracker predicts the next pose, and how sure that prediction is.

``MotionModel`` keeps the last pose (its time stamp and covariance), the last *measured*
pose (not held), and the camera's velocity: a constant-velocity model, per second, as a
live camera's frames come irregularly. Where wheel odometry is the prior
(``odometry.OdometryPrior``), the wheels' motion since the last pose is the prediction
instead. The same model says what a prediction that nothing else measures is worth:

- held on rays (``hold.RayHold``), the velocity's translation dies away
  (``motion.hold_velocity_half_life_s``: a robot that stops to turn on the spot), and a position
  nothing measures is as unsure as a robot that may change its speed (``unmeasured_sigma``);
- with nothing in view, the prediction alone for at most ``motion.max_coast_s`` (``coast``).

The tracker owns one and decides when a pose is a measurement of motion (``update``), a
correction (``relocalised``: where the camera is, not how it moves) or too noisy to say.
"""

from __future__ import annotations

import numpy as np

from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.tracking.odometry import OdometryPrior
from cubeloc.positioning.tracking.options import TrackerOptions
from cubeloc.positioning.tracking.pose_fit import beyond_motion

Held = tuple[Transform, np.ndarray]  # pose and its 6x6 covariance (ROS order)


class MotionModel:
    def __init__(self, options: TrackerOptions) -> None:
        self.options = options
        self.reset()

    def reset(self) -> None:
        self.last: Transform | None = None  # pose of the last frame with one
        self.stamp = 0  # ...its time stamp
        self.covariance: np.ndarray | None = None  # ...and its covariance
        # camera motion per second (rotation vector, translation of T_last_next in the last
        # camera's frame)
        self.velocity: tuple[np.ndarray, np.ndarray] | None = None
        # the covariance (3, 3, world frame, per second squared) of the velocity's translation:
        # what the own covariances of the two poses it was measured between allow
        self.velocity_covariance: np.ndarray | None = None
        self.own: np.ndarray | None = None  # the last pose's own position covariance (3, 3), drift apart
        self.after_relocalisation = False  # the last pose was a correction (relocalised())
        self.measured: tuple[Transform, int] | None = None  # the last pose measured (not held), its stamp

    # ------------------------------------------------------------------ predicting
    def predict(self, stamp_ns: int, odometry: OdometryPrior | None = None) -> Transform | None:
        """The pose at ``stamp_ns``: the wheels' motion from the last pose where
        ``odometry`` is the prior, else the last pose carried on by the velocity (the last
        pose itself when the velocity is unknown or the gap is longer than
        ``motion.max_extrapolation_s``); None before any pose."""
        if self.last is None:
            return None
        carried = None if odometry is None else odometry.prior(self.last, self.stamp, stamp_ns)
        if carried is not None:
            return carried
        dt = (stamp_ns - self.stamp) / 1e9
        if self.velocity is None or not 0.0 < dt <= self.options.motion.max_extrapolation_s:
            return self.last
        return self.extrapolated(self.last, dt)

    def extrapolated(self, pose: Transform, dt: float) -> Transform:
        """``pose`` carried ``dt`` seconds on by the velocity."""
        rotation_per_s, translation_per_s = self.velocity
        return pose @ Transform.from_rvec_tvec(rotation_per_s * dt, translation_per_s * dt)

    # ------------------------------------------------------------------ what a pose tells
    def update(self, pose: Transform, stamp_ns: int, noisy: bool = False, own: np.ndarray | None = None,
               held: bool = False) -> None:
        """Take ``pose`` as the last one and the step to it as the velocity, unless the
        step is a correction or ``noisy`` (then the velocity stays, also for the next step).
        ``own`` is the pose's own covariance (its measurement's, the map's drift apart): a
        velocity measured between two poses is as unsure as their own covariances over the
        step allow. A ``held`` pose followed the prediction, so its step measures nothing
        new: the velocity's covariance stays (docs/tracker.md, "Coasting")."""
        dt = (stamp_ns - self.stamp) / 1e9
        own = None if own is None else np.asarray(own, np.float64)[:3, :3]
        previous, self.own = self.own, own
        if self.last is None or not 0.0 < dt <= self.options.motion.max_extrapolation_s:
            self.velocity = self.velocity_covariance = None
        elif noisy:
            pass
        elif self.after_relocalisation and self.velocity is not None:
            # the step from a relocalised pose measures its correction (its match is some
            # millimetres off), not the camera's motion: the velocity it had stays one
            # more frame (spin_on_axis: 11.6 -> 5.3 mm RMS, blank_wall 25 -> 15 mm)
            pass
        else:
            self.velocity = velocity(self.last, pose, dt)
            if not held:
                self.velocity_covariance = velocity_covariance(previous, own, dt)
        self.after_relocalisation = noisy
        self.last, self.stamp = pose, stamp_ns

    def relocalised(self, pose: Transform, stamp_ns: int, covariance: np.ndarray | None,
                    own: np.ndarray | None = None) -> None:
        """``pose`` was found by matching the frame to the map: a correction of where the
        camera is. The velocity stays: a relocalisation corrects where the camera is, not
        how it moves (spin_on_axis, 4.5 deg a frame: without it the next frame's unguided
        KLT lost 3/4 of the tracks, three relocalisations in a row and then the track);
        unless it cannot have brought the camera here from the last pose measured (PnP
        would refuse this pose against its prediction): lost, the velocity is none and held
        steps make it a standstill, and in a spin every frame after was then found by
        relocalisation alone (narrow lens at 90 deg/s: 30 frames). Lost, the velocity is
        unknown: the step from the last pose measured, within ``motion.max_extrapolation_s`` (the
        relocalisation before this one), is the velocity, as unsure as the two poses' own
        covariances over the step (without it the next frame's KLT searches unguided, and in a
        turn loses most of the tracks the relocalisation gave back: blank_wall, 120 -> 2)."""
        position = None if own is None else np.asarray(own, np.float64)[:3, :3]
        if self.measured is not None:
            before, before_stamp = self.measured
            dt = (stamp_ns - before_stamp) / 1e9
            if 0.0 < dt <= self.options.motion.max_extrapolation_s:
                expected = before if self.velocity is None else self.extrapolated(before, dt)
                if self.velocity is None or beyond_motion(pose, expected, self.options):
                    # lost, the pose before is a relocalisation's, as unsure as its match
                    previous = self.own if self.velocity is None else None
                    self.velocity = velocity(before, pose, dt)
                    self.velocity_covariance = velocity_covariance(previous, position, dt)
        self.own = position
        self.measured = (pose, stamp_ns)
        self.last, self.stamp, self.covariance = pose, stamp_ns, covariance
        self.after_relocalisation = True

    def moved(self, pose: Transform, stamp_ns: int) -> None:
        """The last pose was moved to ``pose`` (a loop closed): it is where the camera was measured."""
        self.last = pose
        self.measured = (pose, stamp_ns)

    def stop(self) -> None:
        """Lost: the velocity is no longer known."""
        self.velocity = self.velocity_covariance = None

    # ------------------------------------------------------------------ unmeasured
    def speed(self, prediction: Transform, stamp_ns: int) -> float:
        """The camera's speed (m/s) that ``prediction`` at ``stamp_ns`` implies from the last pose."""
        step_s = (stamp_ns - self.stamp) / 1e9
        return float(np.linalg.norm(prediction.translation - self.last.translation)) / step_s if step_s > 0 else 0.0

    def faded(self, prediction: Transform, stamp_ns: int) -> np.ndarray:
        """The position the motion model gives when nothing measures the translation: its
        step from the last pose dies away, halving every ``motion.hold_velocity_half_life_s``."""
        decay = 0.5 ** ((stamp_ns - self.stamp) / 1e9 / self.options.motion.hold_velocity_half_life_s)
        return self.last.translation + decay * (prediction.translation - self.last.translation)

    def velocity_sigma(self) -> float:
        """The largest standard deviation of the velocity's translation (m/s), 0 unknown."""
        if self.velocity_covariance is None:
            return 0.0
        return float(np.sqrt(max(np.max(np.linalg.eigvalsh(self.velocity_covariance)), 0.0)))

    def unmeasured_sigma(self, speed_m_s: float, seconds: float) -> float:
        """The standard deviation of a position nothing has measured for ``seconds``: the
        robot may have gone on at the speed it had then (``speed_m_s``, itself as unsure as
        ``velocity_sigma``; the motion model lets that speed die away) or changed it by
        ``motion.coast_accel_m_s2`` (0.5 a t^2), as the coast assumes."""
        o = self.options
        return o.hold.sigma_m + (o.hold.sigma_m_per_s + speed_m_s + self.velocity_sigma()) * seconds \
            + 0.5 * o.motion.coast_accel_m_s2 * seconds * seconds

    def coast(self, prediction: Transform, seconds: float) -> Held | None:
        """Nothing to see (a passer-by filling the view): the prediction for at most
        ``motion.max_coast_s`` since the last measured pose, with the covariance of a robot that
        may have changed its speed by ``motion.coast_accel_m_s2`` and its turn rate by
        ``motion.coast_angular_accel_rad_s2`` meanwhile (0.5 a t^2), at a velocity known to
        ``velocity_covariance``."""
        o = self.options
        if seconds > o.motion.max_coast_s:
            return None
        t = max(seconds, 1e-3)
        covariance = np.zeros((6, 6))
        covariance[:3, :3] = np.eye(3) * (o.hold.sigma_m + 0.5 * o.motion.coast_accel_m_s2 * t * t) ** 2
        if self.velocity_covariance is not None:  # carried on at a velocity this unsure
            covariance[:3, :3] += self.velocity_covariance * t * t
        covariance[3:, 3:] = np.eye(3) * (0.5 * o.motion.coast_angular_accel_rad_s2 * t * t) ** 2
        return prediction, covariance


def velocity_covariance(a: np.ndarray | None, b: np.ndarray | None, dt: float) -> np.ndarray | None:
    """The covariance (3, 3, per second squared) of a velocity measured over ``dt`` seconds
    between two positions with covariances ``a`` and ``b`` (None: not known, left out);
    None when neither is known."""
    both = [c for c in (a, b) if c is not None]
    return sum(both) / dt**2 if both else None


def velocity(a: Transform, b: Transform, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The camera's motion per second from ``a`` to ``b``, ``dt`` seconds apart (rotation vector
    and translation of T_a_b, in a's frame)."""
    step = a.inverse() @ b
    return step.rvec() / dt, step.translation / dt
