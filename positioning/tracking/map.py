"""The tracker's map: keyframes with their observations, and 3-D points, in the world frame.

A point's id is the id of the feature track it was triangulated from (one track, one
point), so a keyframe stores its observations by track id and a point's observations
are the keyframes holding its id. Keyframes seen while the target was trusted are
*anchored*: they also hold the target's corners (fixed world points) for bundle
adjustment. The map is internal, mutable state of one tracker; it is never shared
between threads without the tracker's lock.
"""

from __future__ import annotations

import collections
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.tracking.options import TrackerOptions
from cubeloc.positioning.tracking.twoview import baseline_scale_var, triangulate


@dataclass
class Keyframe:
    kf_id: int
    stamp_ns: int
    T_world_camera: Transform
    track_ids: np.ndarray  # (N,) int64: tracks observed here (with or without a point)
    xn: np.ndarray  # (N, 2) their normalised coordinates
    anchored: bool = False
    target_world: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (M, 3) fixed corners
    target_xn: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (M, 2) observed
    # For relocalisation: ORB descriptors of this keyframe's map points
    descriptor_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (K,)
    descriptors: np.ndarray = field(default_factory=lambda: np.zeros((0, 32), np.uint8))  # (K, 32)
    # and the image around each, (K, S, S) uint8 (``PatchAligner.patches``): a match found by
    # its descriptor is aligned to it, to the pixel precision of a track
    patches: np.ndarray | None = None
    position_sigma_m: float = 0.0  # its pose's own (target, PnP or match), not the drift
    drift_m: float = 0.0  # the drift's growth since the target when it was made (Drift.grown_m)
    loop_moved: bool = False  # moved by a loop closure's spread (Map.correct with after_ns): no reference
    # anchored: the target pose's own position covariance (3, 3), how sure its place in the
    # target's frame is (Map.anchored_scale_var)
    anchor_covariance: np.ndarray | None = None

    def __post_init__(self) -> None:
        self._index = {int(t): i for i, t in enumerate(self.track_ids)}

    def observation(self, track_id: int) -> np.ndarray | None:
        i = self._index.get(int(track_id))
        return None if i is None else self.xn[i]

    def add_observations(self, track_ids: np.ndarray, xn: np.ndarray) -> None:
        fresh = np.array([int(t) not in self._index for t in track_ids], dtype=bool)
        if not fresh.any():
            return
        start = len(self.track_ids)
        self.track_ids = np.concatenate([self.track_ids, np.asarray(track_ids, np.int64)[fresh]])
        self.xn = np.concatenate([self.xn, np.asarray(xn, np.float64).reshape(-1, 2)[fresh]])
        for i, t in enumerate(self.track_ids[start:], start=start):
            self._index[int(t)] = i


FIXED_BIRTH = -2


class Map:
    """Keyframes in insertion order and points by track id."""

    def __init__(self) -> None:
        self.keyframes: OrderedDict[int, Keyframe] = OrderedDict()
        self.points: dict[int, np.ndarray] = {}  # track id -> (3,) world position
        self.point_birth: dict[int, int] = {}  # track id -> keyframe it was triangulated at
        self.point_serial: dict[int, int] = {}  # track id -> when it was added (``points_added`` then)
        self.points_added = 0  # points ever added: a background solution knows what came after it
        self.next_kf_id = 0
        # Bumped whenever the map is moved as a whole (correction, reset), so that a bundle
        # adjustment computed on the old map is not applied to the new one.
        self.epoch = 0
        # Keyframe ids a correction must not move (a map loaded from a file: it was made
        # with the cube and is the reference); FIXED_BIRTH is the birth of its points whose
        # keyframe had been culled before it was saved.
        self.fixed: set[int] = set()
        # a loaded point's last chances to be seen (True: it was), and how many were retired
        self.point_history: dict[int, collections.deque] = {}
        self.point_chance_at: dict[int, np.ndarray] = {}  # where each one's last chance was taken
        # points of places kept, found again after a loop closed (Tracker.loop_places): the
        # reference from then on, as a loaded map's points are (moved only by corrections)
        self.place_points: set[int] = set()
        # a loop closed or agreed (Tracker.close_loop): the places kept take part in tracking
        # and are followed (Tracker.loop_places)
        self.places_agree = False
        self.points_retired = 0

    def __len__(self) -> int:
        return len(self.points)

    @property
    def last_keyframe(self) -> Keyframe | None:
        return next(reversed(self.keyframes.values())) if self.keyframes else None

    def add_keyframe(self, stamp_ns: int, T_world_camera: Transform, track_ids: np.ndarray, xn: np.ndarray,
                     target_world: np.ndarray | None = None, target_xn: np.ndarray | None = None) -> Keyframe:
        anchored = target_world is not None and len(target_world) > 0
        kf = Keyframe(
            self.next_kf_id, stamp_ns, T_world_camera, np.asarray(track_ids, np.int64).copy(),
            np.asarray(xn, np.float64).reshape(-1, 2).copy(), anchored,
            np.asarray(target_world, np.float64).reshape(-1, 3) if anchored else np.zeros((0, 3)),
            np.asarray(target_xn, np.float64).reshape(-1, 2) if anchored else np.zeros((0, 2)),
        )
        self.keyframes[kf.kf_id] = kf
        self.next_kf_id += 1
        return kf

    def mapped(self, track_ids: np.ndarray) -> np.ndarray:
        """(N,) bool: which of these tracks have a point in the map."""
        return np.fromiter((int(t) in self.points for t in track_ids), bool, len(track_ids))

    def anchored_scale_var(self) -> float:
        """The variance of the map's relative scale as its anchored keyframes fix it, no
        better than their best pair: two target poses a baseline b apart, each off by its
        own covariance along b, give the scale to (b^T (C_i + C_j) b) / |b|^4. (A fit to all
        of them is surer than its best pair, so this errs on the safe side.) 0 without two
        anchored keyframes with a covariance."""
        anchors = [kf for kf in self.keyframes.values() if kf.anchored and kf.anchor_covariance is not None]
        if len(anchors) < 2:
            return 0.0
        positions = np.array([kf.T_world_camera.translation for kf in anchors])
        covariances = np.array([kf.anchor_covariance for kf in anchors])
        baselines = positions[None, :, :] - positions[:, None, :]  # (n, n, 3): j's position less i's
        variances = baseline_scale_var(baselines, covariances[:, None], covariances[None, :])
        upper = np.triu(np.isfinite(variances), k=1)
        if not upper.any():
            return 0.0
        return float(np.min(variances[upper]))

    def add_point(self, track_id: int, position: np.ndarray, birth_kf: int) -> None:
        self.points[int(track_id)] = np.asarray(position, np.float64).reshape(3).copy()
        self.point_birth[int(track_id)] = birth_kf
        self.points_added += 1
        self.point_serial[int(track_id)] = self.points_added

    def remove_point(self, track_id: int) -> None:
        self.points.pop(int(track_id), None)
        self.point_birth.pop(int(track_id), None)
        self.point_serial.pop(int(track_id), None)
        self.place_points.discard(int(track_id))

    def is_reference(self, track_ids: np.ndarray, loaded_only: bool = False) -> np.ndarray:
        """Which of ``track_ids`` are the reference: a loaded map's points (born in its
        ``fixed`` keyframes) and, unless ``loaded_only``, the ``place_points``."""
        places = set() if loaded_only else self.place_points
        if not self.fixed and not places:
            return np.zeros(len(track_ids), bool)
        return np.fromiter((self.point_birth.get(int(t)) in self.fixed or int(t) in places
                            for t in track_ids), bool, len(track_ids))

    def observers(self, track_id: int) -> list[Keyframe]:
        return [kf for kf in self.keyframes.values() if kf.observation(track_id) is not None]

    def places(self, recent: int, idle: bool = False) -> set[int]:
        """The keyframes the tracker made beyond its newest ``recent`` (a loaded map's do not
        count): places kept for a loop to close on (``Map.thin``). ``idle``: only while no
        loop has closed or agreed (``places_agree``); until then they take no part in
        tracking (no point is triangulated against them, none holds a bundle window), so that
        with loop closure on, a run that closes no loop is the run without it."""
        if idle and self.places_agree:
            return set()
        built = [k for k in self.keyframes if k not in self.fixed]
        return set(built[: max(len(built) - recent, 0)])

    def triangulate(self, kf: Keyframe, fx: float, min_parallax_deg: float, max_reproj_px: float,
                    min_baseline_sigmas: float, recent: int | None = None) -> None:
        """New points for the keyframe's tracks that have none, each against the oldest
        keyframe that saw it (the longest baseline the track offers, of the newest ``recent``
        before ``kf``: idle places kept beyond them take no part; None: of all) whose
        baseline to this one is ``min_baseline_sigmas`` times the two poses' own standard
        deviations (below it the poses' errors, not the parallax, would set the depths and
        so the map's scale), where the two rays meet at ``min_parallax_deg`` or more. A
        track that does not reproject on that pair waits: it is not tried on a shorter
        baseline (tried so, the family's runs went far off: docs/tracker.md, "Tracking,
        keyframes and points")."""
        places = self.places(recent + 1, idle=True) if recent is not None else set()
        pending: dict[int, list[int]] = {}
        for i, t in enumerate(kf.track_ids):
            if int(t) in self.points:
                continue
            for other in self.keyframes.values():
                if other.kf_id == kf.kf_id:
                    break
                if other.kf_id in places or other.observation(int(t)) is None:
                    continue
                baseline = np.linalg.norm(other.T_world_camera.translation - kf.T_world_camera.translation)
                if baseline >= min_baseline_sigmas * np.hypot(other.position_sigma_m, kf.position_sigma_m):
                    pending.setdefault(other.kf_id, []).append(i)
                    break
        for first_id, rows in pending.items():
            first = self.keyframes[first_id]
            ids = kf.track_ids[rows]
            xa = np.array([first.observation(int(t)) for t in ids])
            result = triangulate(first.T_world_camera, kf.T_world_camera, xa, kf.xn[rows], fx, max_reproj_px,
                                 min_parallax_deg)
            for track_id, point in zip(ids[result.good], result.points_world[result.good], strict=True):
                self.add_point(int(track_id), point, kf.kf_id if kf.anchored else first_id)

    def correct(self, correction: Transform, grown_m: float = 0.0, since_m: float = 0.0,
                after_ns: int | None = None) -> None:
        """Move the drifted part of the map by ``correction`` (T_true_drifted): the
        target's return, or a place seen before (a loop closure), says where it really is.

        With ``grown_m`` (the drift's growth since the target, now) each keyframe takes the
        share of the correction that had drifted by the time it was made, ``(drift_m -
        since_m) / (grown_m - since_m)`` (0 where the reference was made, 1 now), and each
        point its birth keyframe's share: the drift is spread along the way as it grew (the
        long lap's keyframes, its 6 mm return corrected so: 0.9 mm RMS off the truth, 3.7 mm
        uncorrected). ``since_m`` is the drift's growth where the reference is (0 for the
        target; a loop keyframe's ``drift_m``), and ``after_ns`` keeps every keyframe made
        before it where it is (the reference and what came before it). Without ``grown_m``,
        all of it everywhere. Anchored and loaded (``fixed``) keyframes stay."""
        drifted = {k: kf for k, kf in self.keyframes.items() if not kf.anchored and k not in self.fixed
                   and (after_ns is None or kf.stamp_ns > after_ns)}
        span = grown_m - since_m
        shares = {k: 1.0 if span <= 0 else float(np.clip((kf.drift_m - since_m) / span, 0.0, 1.0))
                  for k, kf in drifted.items()}
        oldest = min(shares.values(), default=1.0)
        rotvec = correction.rvec()
        moves: dict[float, Transform] = {}

        def share_of(share: float) -> Transform:
            if share not in moves:
                moves[share] = Transform.from_rvec_tvec(share * rotvec, share * correction.translation)
            return moves[share]

        for k, kf in drifted.items():
            kf.T_world_camera = share_of(shares[k]) @ kf.T_world_camera
            kf.loop_moved = kf.loop_moved or (after_ns is not None and shares[k] > 0.0)
            if after_ns is not None:  # corrected onto the reference: drifted since it by what was left
                kf.drift_m = since_m + (1.0 - shares[k]) * max(kf.drift_m - since_m, 0.0)
        # a point whose birth keyframe is gone (culled) takes the share of the first keyframe kept
        # after it (ids grow with time); before the reference, none
        kept = np.array(sorted(drifted), dtype=np.int64)
        first_after = None if after_ns is None else self._first_after(after_ns)
        for track_id, birth in self.point_birth.items():
            if birth in self.fixed or (birth in self.keyframes and birth not in drifted):
                continue
            share = shares.get(birth)
            if share is None:
                later = int(np.searchsorted(kept, birth))
                if after_ns is None:
                    share = oldest
                elif later == len(kept) or (later == 0 and birth < first_after):
                    share = 0.0
                else:
                    share = shares[int(kept[later])]
            if share > 0.0:
                self.points[track_id] = share_of(share).apply(self.points[track_id][None])[0]
        self.epoch += 1

    def _first_after(self, stamp_ns: int) -> int:
        """The id of the first keyframe kept made after ``stamp_ns`` (the next id when none)."""
        return next((k for k, kf in self.keyframes.items() if kf.stamp_ns > stamp_ns), self.next_kf_id)

    def retire(self, visible: np.ndarray, found: np.ndarray, camera_position: np.ndarray,
               options: TrackerOptions) -> int:
        """Count, for a loaded map's points, the chances to be seen (``visible`` from
        ``camera_position``) and those taken (``found``); a point's chance counts only from
        at least ``refind.retire_min_move_m`` from where its last one was (one place seen again
        and again tells nothing new: 20-30 % of the points that should be seen are not
        matched from a given place, room unchanged). A point found in at most
        ``refind.retire_max_found`` of its last ``refind.retire_after_visible`` chances is retired
        (removed): a thing moved away or covered. Returns how many went."""
        found_set = {int(p) for p in found}
        gone = []
        for point_id in (int(p) for p in visible):
            last = self.point_chance_at.get(point_id)
            if last is not None and np.linalg.norm(camera_position - last) < options.refind.retire_min_move_m:
                continue
            self.point_chance_at[point_id] = np.asarray(camera_position, np.float64).copy()
            history = self.point_history.setdefault(point_id, collections.deque(maxlen=options.refind.retire_after_visible))
            history.append(point_id in found_set)
            if len(history) == history.maxlen and sum(history) <= options.refind.retire_max_found:
                gone.append(point_id)
        for point_id in gone:
            self.remove_point(point_id)
            self.point_history.pop(point_id, None)
            self.point_chance_at.pop(point_id, None)
        self.points_retired += len(gone)
        return len(gone)

    def cull(self, max_keyframes: int, live_track_ids: set[int]) -> None:
        """Drop the oldest keyframes beyond ``max_keyframes`` (a loaded map's, ``fixed``,
        stay and do not count) and the points nobody holds: no remaining keyframe observes
        them and no live track follows them."""
        built = [k for k in self.keyframes if k not in self.fixed]
        for kf_id in built[: max(0, len(built) - max_keyframes)]:
            del self.keyframes[kf_id]
        self._drop_unheld(live_track_ids)

    def thin(self, max_keyframes: int, keep_newest: int, live_track_ids: set[int], keep_fixed: bool = False) -> None:
        """Keep ``max_keyframes`` keyframes: the ``keep_newest`` newest (the ones tracking
        and bundle adjustment are working with) and, of the others, those spread widest
        over the area (farthest-point sampling of their positions: where the map is dense
        it loses keyframes, where it is thin it keeps them); then the points nobody holds.
        ``keep_fixed``: a loaded map's keyframes stay and do not count (as ``cull``)."""
        keyframes = [kf for kf in self.keyframes.values() if not (keep_fixed and kf.kf_id in self.fixed)]
        if len(keyframes) <= max_keyframes:
            return
        newest = keyframes[len(keyframes) - min(keep_newest, max_keyframes):] if keep_newest else []
        kept = {kf.kf_id for kf in newest}
        rest = [kf for kf in keyframes if kf.kf_id not in kept]
        positions = np.array([kf.T_world_camera.translation for kf in rest])
        reference = np.array([kf.T_world_camera.translation for kf in newest] or [positions[0]])
        distance = np.min(np.linalg.norm(positions[:, None] - reference[None], axis=2), axis=1)
        while len(kept) < max_keyframes:
            chosen = int(np.argmax(distance))
            kept.add(rest[chosen].kf_id)
            distance = np.minimum(distance, np.linalg.norm(positions - positions[chosen], axis=1))
            distance[chosen] = -1.0
        for kf in keyframes:
            if kf.kf_id not in kept:
                del self.keyframes[kf.kf_id]
        self._drop_unheld(live_track_ids)

    def _drop_unheld(self, live_track_ids: set[int]) -> None:
        if not self.points:
            return
        ids = np.fromiter(self.points.keys(), np.int64, len(self.points))
        held = [np.fromiter(live_track_ids, np.int64, len(live_track_ids))]
        held += [kf.track_ids for kf in self.keyframes.values()]
        for track_id in ids[~np.isin(ids, np.concatenate(held))]:  # one vectorised test, not a set per id
            self.remove_point(int(track_id))
        # keyframe observations of tracks that will never become points cost memory only
        # while the keyframe lives, so they go with it
