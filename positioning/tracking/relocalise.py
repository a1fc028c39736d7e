"""Relocalisation against the map's keyframes with ORB descriptors.

When tracking is lost away from the target (a blank wall, a covered lens, a fast turn),
the tracks are gone but the map is still good. Each keyframe keeps ORB descriptors of its
map points (computed at the KLT positions, so they describe exactly the tracked points);
a lost frame's ORB features are matched against them (Hamming distance, Lowe's ratio
test), and PnP with RANSAC on the matches gives the pose back. The matched points then
become tracks again under their own ids. ORB is BSD-licensed in OpenCV and binary, so
matching a thousand features against a few thousand descriptors takes milliseconds.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.positioning.camera_model import ahead_mask, project, project_normalised, undistort
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.tracking.features import find_corners, view_at_scale
from cubeloc.positioning.tracking.map import Keyframe, Map
from cubeloc.positioning.tracking.options import TrackerOptions
from cubeloc.positioning.tracking.patch_alignment import PatchAligner
from cubeloc.positioning.tracking.pose_fit import fit_pose, pnp_ransac

ORB_PATCH_PX = 31  # ORB's default patch; keypoints closer than half of it to the edge are dropped


@dataclass(frozen=True)
class Relocalisation:
    T_world_camera: Transform
    point_ids: np.ndarray  # (K,) map points found again (inliers)
    pixels: np.ndarray  # (K, 2) where they are in this image
    matches: int
    covariance: np.ndarray  # (6, 6) ROS order, from the inliers' reprojection errors


@dataclass(frozen=True)
class Refound:
    ids: np.ndarray  # (K,) reference points found again, to follow as tracks
    pixels: np.ndarray  # (K, 2) where
    visible: np.ndarray  # reference points that should have been seen in this view
    found: np.ndarray  # those of them tracked already or found


class Relocaliser:
    def __init__(self, calibration: CameraCalibration, options: TrackerOptions) -> None:
        self.calibration = calibration
        self.options = options
        view = ahead_mask(calibration)  # None: every pixel looks ahead
        # at the features' detect_scale, as find_corners takes it (worked out once)
        self._view_mask = None if view is None else view_at_scale(view, max(1, options.features.detect_scale))
        self._orb = cv2.ORB_create(nfeatures=options.reloc.orb_features, patchSize=ORB_PATCH_PX,
                                   edgeThreshold=ORB_PATCH_PX)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        alignment = options.features.alignment
        # from the identity and a corner up to 1.4 px off, not a warp carried on from the
        # last frame as a track's: more Gauss-Newton steps than a track takes
        self._aligner = None if alignment is None else PatchAligner(
            dataclasses.replace(alignment, iterations=options.reloc.align_iterations))
        self._reference_of: Map | None = None  # the map _reference_arrays are of
        self._reference_arrays: tuple = ()

    def describe(self, image: np.ndarray, keyframe: Keyframe, world_map: Map, ids: np.ndarray,
                 pixels: np.ndarray) -> None:
        """Store on ``keyframe`` the ORB descriptors of its tracks that have map points, and
        the image patch around each (what a match is aligned to)."""
        has = world_map.mapped(ids)
        if not has.any():
            return
        keypoints, descriptors = self._describe(image, pixels[has], np.flatnonzero(has))
        if descriptors is None or not keypoints:
            return
        keyframe.descriptor_ids = np.array([ids[k.class_id] for k in keypoints], dtype=np.int64)
        keyframe.descriptors = descriptors
        if self._aligner is not None:
            at = np.array([k.pt for k in keypoints], dtype=np.float32)
            keyframe.patches = self._aligner.patches(image, at)  # uint8, as the image

    def refind(self, image: np.ndarray, world_map: Map, pose: Transform, tracked: np.ndarray,
               places: list[Keyframe] | None = None) -> Refound:
        """A loaded map's points (the reference, ``world_map.fixed``), or those described
        by the keyframes ``places`` (a place kept, seen again after a loop closed), found
        again in ``image`` near where ``pose`` projects them, to follow as tracks; and which
        of them should have been seen here, and were (for ``Map.retire``).

        Without it a robot booted on a saved map tracks the map's points only while the
        relocalisation's tracks live, then its own, triangulated from a pose a few
        millimetres off, and keeps that error (four 10 s runs of bench boot along the lap:
        RMS 4.7, 7.8, 3.1, 5.6 mm without it, 3.9, 3.2, 2.7, 4.2 with it). A point should
        be seen when it projects into the image in front of the camera, viewed within
        ``refind.max_angle_deg`` of the keyframe that described it and from a distance
        within ``refind.max_scale`` times its (in the room as mapped, 80 % of those
        within 5 deg are found, 53 % at 20-30 deg, 49 % at 1.25-1.5x); one ``tracked``
        already is found. For the others: the corners within ``refind.radius_px`` of the
        projection, the nearest in Hamming distance to its descriptor found if within
        ``refind.max_hamming``, and followed if clearly nearer than the second (Lowe's
        ratio) and claimed by no other point. ~15 ms a keyframe at 1280x1024 (2000
        corners described)."""
        o = self.options
        reference = self._reference(world_map) if places is None else _described(world_map, places)
        alive = world_map.mapped(reference[0])  # not retired
        ids, points, centres, descriptors = (a[alive] for a in reference)
        none = Refound(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0, np.int64))
        if not len(ids):
            return none
        in_camera = pose.inverse().apply(points)
        rays_now, rays_then = points - pose.translation, points - centres
        cosine = np.einsum("ij,ij->i", rays_now, rays_then) / (
            np.linalg.norm(rays_now, axis=1) * np.linalg.norm(rays_then, axis=1) + 1e-12)
        scale = np.linalg.norm(rays_now, axis=1) / np.maximum(np.linalg.norm(rays_then, axis=1), 1e-9)
        visible = (in_camera[:, 2] > 0.1) & (cosine > np.cos(np.radians(o.refind.max_angle_deg))) & \
            (scale < o.refind.max_scale) & (scale > 1.0 / o.refind.max_scale)
        pixels = np.full((len(ids), 2), -1.0)
        pixels[visible] = project(in_camera[visible], self.calibration)
        margin, w, h = ORB_PATCH_PX, self.calibration.width, self.calibration.height
        visible &= (pixels[:, 0] >= margin) & (pixels[:, 0] < w - margin) & (pixels[:, 1] >= margin) & \
            (pixels[:, 1] < h - margin)
        held = np.isin(ids, tracked)
        wanted = visible & ~held
        none = Refound(none.ids, none.pixels, ids[visible], ids[visible & held])
        if not wanted.any():
            return none
        at, found = self._frame_features(image)
        if not len(at):
            return none
        bits = np.unpackbits(found, axis=1)
        claims: dict[int, list[int]] = {}
        present = []  # a corner like it near: there (if not told apart from a neighbour)
        near = cKDTree(at).query_ball_point(pixels[wanted], o.refind.radius_px)
        for row, candidates in zip(np.flatnonzero(wanted), near, strict=True):
            if not candidates:
                continue
            distance = np.count_nonzero(bits[candidates] != np.unpackbits(descriptors[row]), axis=1)
            order = np.argsort(distance)
            best = int(distance[order[0]])
            if best > o.refind.max_hamming:
                continue
            present.append(int(row))
            if len(order) == 1 or best < o.reloc.ratio * distance[order[1]]:
                claims.setdefault(candidates[int(order[0])], []).append(int(row))
        rows = np.array([r[0] for r in claims.values() if len(r) == 1], dtype=np.int64)
        corner = np.array([c for c, r in claims.items() if len(r) == 1], dtype=np.int64)
        return Refound(ids[rows], at[corner].reshape(-1, 2), none.visible,
                       np.concatenate([none.found, ids[np.array(present, dtype=np.int64)]]))

    def _aligned(self, image: np.ndarray, ids: np.ndarray, pixels: np.ndarray, patches: dict[int, np.ndarray]
                 ) -> tuple[np.ndarray, np.ndarray]:
        """``pixels`` of the map points ``ids`` aligned to the patches their keyframes saw
        them in (affine Lucas-Kanade from the matched corner, ``PatchAligner``), and which
        are precise. A corner is found on the ``detect_scale`` grid, up to a pixel from
        where a track put the point; aligned, a match is as precise as a track, and one
        that does not align (another corner like it, a view too different) is not taken.
        A point without a patch (a map file's, or tracks without alignment) is taken at
        its corner, as precise as its map can say."""
        have = np.array([int(t) in patches for t in ids], dtype=bool)
        if self._aligner is None or not have.any():
            return pixels, ~have
        self._aligner.reset()
        self._aligner.add_patches(ids[have], np.array([patches[int(t)] for t in ids[have]], np.float32))
        refined, aligned = self._aligner.refine(np.asarray(image, np.float32), ids, pixels)
        return refined, aligned | ~have

    def _reference(self, world_map: Map) -> tuple[np.ndarray, ...]:
        """The loaded map's described points (``_described``), kept per map: a loaded map's
        points never move."""
        if self._reference_of is not world_map:
            fixed = [kf for kf in world_map.keyframes.values() if kf.kf_id in world_map.fixed]
            self._reference_arrays = _described(world_map, fixed, lambda point_id: world_map.point_birth.get(point_id)
                                                in world_map.fixed)
            self._reference_of = world_map
        return self._reference_arrays

    def _frame_features(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The frame's corners (K, 2) and their descriptors (K, 32), for matching against the
        map: the same corners as the tracks (Shi-Tomasi), described upright (ORB's own FAST
        keypoints land elsewhere and its orientation would not match the keyframes'), dense
        (6 px apart: the greedy spacing of the tracker's own detection would pick a
        different subset of corners in a different view)."""
        o = self.options
        corners = find_corners(image, o.reloc.orb_features, o.features, self._view_mask, min_distance_px=6)
        keypoints, descriptors = self._describe(image, corners, np.arange(len(corners))) if len(corners) else ([], None)
        if descriptors is None or not keypoints:
            return np.zeros((0, 2)), np.zeros((0, 32), np.uint8)
        return np.array([k.pt for k in keypoints], dtype=np.float64), descriptors

    def _describe(self, image: np.ndarray, pixels: np.ndarray, tags: np.ndarray) -> tuple[list, np.ndarray | None]:
        """Upright ORB descriptors (angle 0, full resolution) at the given pixels; each
        keypoint's ``class_id`` is its tag (OpenCV drops keypoints too near the edge)."""
        keypoints = [cv2.KeyPoint(float(x), float(y), ORB_PATCH_PX, 0.0, 0, 0, int(t))
                     for t, (x, y) in zip(tags, pixels, strict=True)]
        return self._orb.compute(image, keypoints)

    def relocalise(self, image: np.ndarray, world_map: Map, thorough: bool = False,
                   among: list[Keyframe] | None = None, excluding: set[int] | None = None) -> Relocalisation | None:
        """The pose of ``image`` in the map, or None when too few matches agree. ``thorough``
        (at boot on a saved map, where nothing else can give a pose): RANSAC with
        ``reloc.boot_iterations`` P3P samples instead of 500 SQPnP ones (bench boot: a view
        15-20 deg from every keyframe has 10-25 % of its matches right; 500 samples found
        none, 10,000 found 16-28 inliers; P3P's samples are 4x cheaper: ~100 ms). ``among``
        matches against those keyframes' points only, less the ``excluding`` ones (a loop
        closure: a place seen long ago, not the points being tracked)."""
        o = self.options
        known: dict[int, np.ndarray] = {}
        patches: dict[int, np.ndarray] = {}
        for kf in world_map.keyframes.values() if among is None else among:  # newest last: its descriptor wins
            for k, (point_id, descriptor) in enumerate(zip(kf.descriptor_ids, kf.descriptors, strict=True)):
                if int(point_id) in world_map.points and (excluding is None or int(point_id) not in excluding):
                    known[int(point_id)] = descriptor
                    if kf.patches is not None:
                        patches[int(point_id)] = kf.patches[k]
                    else:
                        patches.pop(int(point_id), None)
        if len(known) < o.reloc.min_inliers:
            return None
        map_ids = np.array(list(known), dtype=np.int64)
        map_descriptors = np.array(list(known.values()), dtype=np.uint8)
        at, descriptors = self._frame_features(image)
        if len(at) < o.reloc.min_inliers:
            return None
        pairs = self._matcher.knnMatch(descriptors, map_descriptors, k=2)
        best: dict[int, tuple[float, int]] = {}  # map index -> (distance, keypoint index)
        for pair in pairs:
            if len(pair) == 2 and pair[0].distance < o.reloc.ratio * pair[1].distance:
                m = pair[0]
                if m.trainIdx not in best or m.distance < best[m.trainIdx][0]:
                    best[m.trainIdx] = (m.distance, m.queryIdx)
        if len(best) < o.reloc.min_inliers:
            return None
        train = np.array(list(best), dtype=np.int64)
        query = np.array([best[t][1] for t in train], dtype=np.int64)
        pixels = at[query]
        ids = map_ids[train]
        pixels, precise = self._aligned(image, ids, pixels, patches)
        obj = np.array([world_map.points[int(i)] for i in ids])
        xn = undistort(pixels, self.calibration)
        threshold = o.reloc.reproj_px / self.calibration.fx
        iterations, solver = (o.reloc.boot_iterations, cv2.SOLVEPNP_P3P) if thorough else (500, cv2.SOLVEPNP_SQPNP)
        found = pnp_ransac(obj, xn, threshold, iterations, solver)
        if found is None or len(found[2]) < o.reloc.min_inliers:
            return None
        rvec, tvec, inl = found
        # the pose, the tracks followed on and the keyframe made here from the matches as
        # precise as tracks (a corner's pixel, a pixel off, in bundle adjustment beside
        # tracks 0.05 px off: its points cut as outliers, the map then rebuilt on the
        # relocalised poses alone and running away, blank_wall 22 mm -> 2 m RMS)
        inl = inl[precise[inl]]
        if len(inl) < o.reloc.min_inliers:
            return None
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl], xn[inl], np.eye(3), None, rvec.reshape(3, 1), tvec.reshape(3, 1))
        T_camera_world = Transform.from_rvec_tvec(rvec, tvec)
        proj, z = project_normalised(T_camera_world, obj)
        good = (z > 0) & (np.linalg.norm(proj - xn, axis=1) <= threshold) & precise
        pose = T_camera_world.inverse()
        if good.sum() < o.reloc.min_inliers or not np.all(np.isfinite(pose.matrix())):
            return None
        # A wrong relocalisation is worse than none: matches of far points in a narrow view
        # can agree on a pose that is centimetres off (measured: 60 mm on blank_wall, its
        # map then built on it). Refused unless the matches pin the position down.
        err_px = np.linalg.norm(proj[good] - xn[good], axis=1) * self.calibration.fx
        fit = fit_pose(pose, obj[good], xn[good], None, fx=self.calibration.fx,
                       sigma_px=max(float(np.sqrt(np.mean(err_px**2))), o.track_sigma_px), iterations=0)
        if fit is None or np.sqrt(np.max(np.linalg.eigvalsh(fit.covariance[:3, :3]))) > o.reloc.max_position_sigma_m:
            return None
        return Relocalisation(pose, ids[good], pixels[good], len(best), fit.covariance)


def _described(world_map: Map, keyframes: list[Keyframe], keep: Callable[[int], bool] | None = None
               ) -> tuple[np.ndarray, ...]:
    """The points ``keyframes`` described (``keep(point_id)`` true, if given) that are still
    in the map: ids, positions, the describing keyframe's camera centre, descriptors (the
    newest keyframe's of a point seen by several)."""
    known: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for kf in keyframes:  # newest last, so the newest descriptor wins
        for point_id, descriptor in zip(kf.descriptor_ids, kf.descriptors, strict=True):
            if int(point_id) in world_map.points and (keep is None or keep(int(point_id))):
                known[int(point_id)] = (kf.T_world_camera.translation, descriptor)
    ids = np.array(list(known), dtype=np.int64)
    return (ids, np.array([world_map.points[int(i)] for i in ids]).reshape(-1, 3),
            np.array([c for c, _ in known.values()]).reshape(-1, 3),
            np.array([d for _, d in known.values()], dtype=np.uint8).reshape(-1, 32))
