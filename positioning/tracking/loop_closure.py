"""Loop closure (a mixin of ``tracker.Tracker``, whose state it shares): when the view comes
back to a place mapped long ago, matches against its keyframes say how far the map has
drifted since, and the map being tracked is moved onto it; from then on the places kept are
followed where they are in view, held as the reference (docs/tracker.md, "Loop closure").
Off by default (``TrackerOptions.loop.enabled``).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import structlog

from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.tracking.map import Keyframe
from cubeloc.positioning.tracking.types import TrackedFrame

log = structlog.get_logger()

CHI2_3DOF_99 = 11.34  # chi-square, 3 degrees of freedom: 99 % and 99.9 % quantiles
CHI2_3DOF_999 = 16.27


class LoopClosure:
    def loop_keyframes(self, frame: TrackedFrame) -> list[Keyframe]:
        """Keyframes this frame may close a loop with, the oldest first (the map as first
        made, before any loop closure moved it): made
        ``loop.min_age_s`` or more before it and not in bundle adjustment's window, neither
        anchored (the target holds those) nor loaded, within ``loop.radius_m`` and
        ``loop.max_angle_deg`` of its pose, and with at most ``loop.max_shared`` of their
        points tracked now (a place left and seen again, not the place being tracked), not
        moved by an earlier loop closure (``Keyframe.loop_moved``: its pose is then that
        correction's guess), and whose drift is at most ``loop.max_drift_share`` of this
        frame's. None unless ``frame``'s pose came from the map and made a keyframe, nor
        while it tracks ``reloc.min_reference_points`` points of the places kept (held by
        them, the map has not drifted from them), nor within ``loop.min_age_s`` of a
        relocalisation (the pose was put on the map's keyframes then: it has drifted no more
        since than a keyframe that young, which is no candidate, would say)."""
        o = self.options
        pose = frame.pose
        if pose is None or frame.keyframe is None or self.holding or frame.target is not None:
            return []
        if self.map.is_reference(frame.tracks.ids).sum() >= o.reloc.min_reference_points:
            return []  # held by the places kept already (loop_places): nothing drifted to correct
        if (frame.stamp_ns - self.relocalised_ns) / 1e9 < o.loop.min_age_s:
            return []  # found in the map's keyframes since: what a loop could correct, it has
        keyframes = list(self.map.keyframes.values())[: -self.options.bundle.window_keyframes]
        live = frame.tracks.ids
        axis = pose.rotation[:, 2]
        near = []
        for kf in keyframes:
            if kf.anchored or kf.kf_id in self.map.fixed or kf.loop_moved or not len(kf.descriptor_ids):
                continue
            if (frame.stamp_ns - kf.stamp_ns) / 1e9 < o.loop.min_age_s:
                continue
            distance = float(np.linalg.norm(kf.T_world_camera.translation - pose.translation))
            angle = np.degrees(np.arccos(np.clip(kf.T_world_camera.rotation[:, 2] @ axis, -1.0, 1.0)))
            if distance > o.loop.radius_m or angle > o.loop.max_angle_deg:
                continue
            if np.isin(kf.descriptor_ids, live).mean() > o.loop.max_shared:
                continue
            drift = kf.drift_m if kf.stamp_ns > self._target_stamp else 0.0
            if drift > o.loop.max_drift_share * self._drift.grown_m:
                continue  # about as sure as this frame: little to correct, and its own error to take on
            near.append((kf.kf_id, kf))
        near.sort(key=lambda pair: pair[0])  # the oldest first
        return [kf for _, kf in near[: o.loop.keyframes]]

    def loop_places(self, frame: TrackedFrame) -> list[Keyframe]:
        """The places kept whose points this keyframe looks for again, to follow as tracks
        (``Relocaliser.refind``): once a loop has closed or agreed, every keyframe outside
        bundle adjustment's window made ``loop.min_age_s`` or more before ``frame`` (anchored
        ones too; not a loaded map's, which has its own search). Following them, the map
        tracked is the one first made where it is in view, and its own drift stops growing
        there, as when a saved map is loaded; before a loop has closed the two disagree by
        the drift, and following both would split it between them. [] unless ``frame`` made
        a keyframe."""
        if not self.map.places_agree or frame.keyframe is None or frame.pose is None:
            return []
        o = self.options
        keyframes = list(self.map.keyframes.values())[: -o.bundle.window_keyframes]
        return [kf for kf in keyframes if kf.kf_id not in self.map.fixed and len(kf.descriptor_ids)
                and (frame.stamp_ns - kf.stamp_ns) / 1e9 >= o.loop.min_age_s]

    def close_loop(self, frame: TrackedFrame, pose: Transform, covariance: np.ndarray, reference: Keyframe
                   ) -> tuple[str, TrackedFrame]:
        """``frame``, tracked on the map, was found again in ``reference`` (one of
        ``loop.keyframes``) at ``pose`` with the match's ``covariance``: one piece of
        evidence of how far the map has drifted since the reference (the offset between
        the two poses, its position and its rotation about the camera). A match that puts
        the camera further than this frame's own covariance, drift included, allows
        (chi-square 99.9 %, 3 dof) is the match's error: ``"refused"``. The map is moved
        once ``loop.matches`` pieces within ``loop.window_s`` agree with their median
        (99.9 %) and the median is beyond its noise (99 %): the map made since the surest
        of their references (the least drift) is moved onto it, the drift spread along the
        way (``Map.correct``, as for the target's return): ``"closed"``; the median within
        its noise: ``"agrees"`` (nothing to move); else ``"pending"``.
        One match is not enough: from another viewpoint the old points' own errors put it
        3-25 mm off (the laps scenario, where the drift it corrects is 8 mm). Returns the
        outcome and the frame (at its new pose when the loop closed)."""
        current, stamp_ns = frame.pose, frame.stamp_ns
        if current is None or self.motion.stamp != stamp_ns or self.motion.covariance is None:
            return "refused", frame
        offset = pose.translation - current.translation
        match = np.asarray(covariance)[:3, :3]
        allowed = np.asarray(self.motion.covariance)[:3, :3] + match
        if offset @ np.linalg.solve(allowed, offset) > CHI2_3DOF_999:
            self.loops_refused += 1
            log.debug("tracker.loop_refused", offset_m=float(np.linalg.norm(offset)))
            return "refused", frame
        o = self.options
        turn = pose.rotation @ current.rotation.T
        evidence = [e for e in self._loop_evidence if (stamp_ns - e[0]) / 1e9 <= o.loop.window_s]
        evidence.append((stamp_ns, offset, np.linalg.inv(match), Transform(turn, np.zeros(3)).rvec(), reference))
        # the evidence is of one drift: offsets measured since agree once the first closes
        self._loop_evidence = evidence
        if len(evidence) < o.loop.matches:
            return "pending", frame
        information = sum(e[2] for e in evidence)
        mean = np.median([e[1] for e in evidence], axis=0)  # robust: one match in several is far off
        if any((e[1] - mean) @ e[2] @ (e[1] - mean) > CHI2_3DOF_999 for e in evidence):
            self._loop_evidence = evidence[1:]  # the oldest goes: the rest may agree without it
            return "pending", frame
        self._loop_evidence = []
        # the matches' own scatter, where it is wider than they claim (the old points' errors
        # seen from another viewpoint are not in a match's covariance)
        offsets = np.array([e[1] for e in evidence])
        scatter = np.cov(offsets.T) / len(evidence)
        self.map.places_agree = True
        if mean @ np.linalg.solve(np.linalg.inv(information) + scatter, mean) <= CHI2_3DOF_99:
            return "agrees", frame
        rotation = Transform.from_rvec_tvec(np.median([e[3] for e in evidence], axis=0), np.zeros(3)).rotation
        centre = current.translation
        correction = Transform(rotation, centre + mean - rotation @ centre)
        surest = min((e[4] for e in evidence), key=lambda kf: kf.drift_m if kf.stamp_ns > self._target_stamp else 0.0)
        within = surest.stamp_ns > self._target_stamp  # the reference made since the target
        since = surest.drift_m if within else 0.0
        self.map.correct(correction, self._drift.grown_m, since, max(surest.stamp_ns, self._target_stamp))
        self._drift.rewind(since)
        self._drift.relocalised(np.linalg.inv(information))
        self.loops_closed += 1
        log.debug("tracker.loop_closed", offset_m=float(np.linalg.norm(mean)), reference=surest.kf_id)
        pose = correction @ current
        self.last_closure = (stamp_ns, current, pose)
        self.motion.moved(pose, stamp_ns)
        matched = np.zeros((6, 6))
        matched[:3, :3] = np.linalg.inv(information)  # the matches place it (their orientation: not weighed)
        self._hold.rebase(pose, frame.tracks.ids, frame.xn, matched)
        return "closed", replace(frame, pose=pose)
