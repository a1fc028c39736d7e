"""Every tunable of the tracker, in frozen dataclasses passed explicitly: ``TrackerOptions``
holds one group per concern (features, init, bundle, pnp, keyframes, triangulation, loop,
anchor, motion, hold, drift, reloc, refind), each field with its rule and units.

Defaults suit the paper's camera (1280x1024, fx 1667 px) in a room a few metres across.
Pixel thresholds are in pixels of the full-resolution image.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


@dataclass(frozen=True)
class AlignmentOptions:
    """Each track re-aligned to the patch it was born on (patch_alignment.py)."""

    radius_px: int = 10  # the template is (2r+1)^2 pixels, as KLT's 21 x 21 window
    # Gauss-Newton steps per frame from where KLT ended: the warp carries on from the last
    # frame, so little is left to do
    iterations: int = 2
    min_correlation: float = 0.9  # normalised cross-correlation of the aligned patch
    max_shift_px: float = 2.0  # from where KLT ended
    scale_range: tuple[float, float] = (0.6, 1.6)  # singular values of the warp's linear part


@dataclass(frozen=True)
class FeatureOptions:
    """Shi-Tomasi corners tracked with pyramidal Lucas-Kanade (KLT)."""

    max_features: int = 300  # tracks kept alive; new corners fill up to this at keyframes
    min_distance_px: int = 24  # between corners, so they spread over the image
    quality_level: float = 0.01  # relative to the strongest corner (Shi-Tomasi)
    block_size: int = 7
    detect_scale: int = 2  # corners are found on a 1/2-size image (4x less work), then refined
    window_px: int = 21  # KLT window at each pyramid level
    pyramid_levels: int = 3
    max_fb_error_px: float = 0.5  # forward-backward check: track back and compare
    fb_check_levels: int = 0  # pyramid levels of the backward pass (it starts at the answer)
    target_margin_px: int = 20  # no corners within this of the target's image outline
    border_px: int = 16  # no corners this close to the image edge
    # None: KLT alone (its tracks slide off their corners as the patch deforms)
    alignment: AlignmentOptions | None = field(default_factory=AlignmentOptions)


@dataclass(frozen=True)
class InitOptions:
    """Algorithms 1 and 2 of the paper: a reference frame A, a second frame B."""

    min_features: int = 80  # N_min: corners on the reference frame
    min_points: int = 60  # N_min: triangulated points for the map to count as initialised
    min_planes: int = 2  # target faces a pose needs to be trusted for initialisation
    min_parallax_deg: float = 1.0  # median rotation-compensated parallax A<->B
    max_reproj_px: float = 1.5  # a triangulated point must reproject within this in A and B
    min_point_parallax_deg: float = 0.5  # a single point's own parallax
    # Before a map exists, a target pose this sure may start it (reference A and frame B):
    # Algorithm 2's baseline makes its error small against the depths. Keyframes after it
    # anchor only from the stricter ``AnchorOptions.max_position_std_m``, since an anchor bends the
    # map to itself. (Measured behind a wide lens: docs/notes/2026-12-05-tracker-options.md.)
    max_position_std_m: float = 0.010
    # The pair's baseline as its two target poses measure it (their position covariances
    # along it) is known to this relative standard deviation at least: the scale the map
    # begins with (its anchors refine it). Two poses a centimetre apart, each 40 mm unsure,
    # begin no map, whatever "parallax" their rotations' noise makes.
    max_scale_std: float = 0.5


@dataclass(frozen=True)
class FloorOptions:
    """The floor a robot drives on (floor.py), and how bundle adjustment holds a window to it
    once the target has left (bundle.build_problem)."""

    # Off by default: on the family it takes some seeds' error down 5-35x and moves others
    # the other way, and costs the `laps` scenario (docs/tracker.md, "The floor")
    enabled: bool = False
    # Found from the target poses that anchored keyframes: at least this many, the middle 80 %
    # of their heights within this (a wheeled robot on a flat floor: ~1 mm; carried by hand:
    # centimetres)
    min_target_poses: int = 10
    max_height_spread_m: float = 0.01
    # The floor's layer of points: the lowest one holding at least min_points and min_share
    # of the points below the camera, this thick per metre of its depth under the camera (a
    # map's height error grows with depth as its scale and depth errors do: ~1 %, with margin)
    layer_thickness: float = 0.03
    min_points: int = 20
    min_share: float = 0.25
    min_camera_height_m: float = 0.05  # points less far below the camera are not the floor
    # a track's two rays (the first and the last frame the target posed) meet at this or more:
    # its depth then ~1 % sure at the tracks' ~0.3 px over a few hundred pixels of focal length
    min_parallax_deg: float = 2.0
    # A window's points are held to the floor when near it (within this share of the camera's
    # height above it, however far the window's scale has walked) and in the window's own floor
    # layer, as thick as layer_thickness (floor.on_the_floor)
    band: float = 0.1
    # The priors' weights, in pixels of reprojection error: a track's noise is ~0.3 px
    # (TrackerOptions.track_sigma_px), so 100 px/m holds a floor point to ~3 mm (the floor's
    # flatness and a point's own error) and 300 px/m a keyframe's height to ~1 mm
    floor_px_per_m: float = 100.0
    camera_px_per_m: float = 300.0
    # The older keyframes sharing the window's points (held fixed without a floor) move in
    # height with it, and are held where they are otherwise: this many pixels per millimetre
    # along the floor and per milliradian of turn (~0.3 mm, 0.3 mrad). Fixed, the heights
    # they carry from earlier windows would hold every later window at the same scale.
    older_px_per_mm: float = 1.0


@dataclass(frozen=True)
class BundleOptions:
    """Sliding-window bundle adjustment (bundle.py)."""

    window_keyframes: int = 6
    # The newest anchored keyframes that share points with the window join it (free, with
    # the target's corners), so that after the target has left the view the first keyframes
    # without it are adjusted together with keyframes the target holds, and a solution that
    # lands frames late (the worker thread on a live camera) costs little.
    anchored_keyframes: int = 3
    # "schur": our Levenberg-Marquardt on the Schur complement (schur_lm.py); "scipy":
    # SciPy's least_squares (trf, LSMR), the reference: as accurate applied at once, far
    # worse applied frames late, and ~20x slower live (python -m bench tracker).
    solver: Literal["schur", "scipy"] = "schur"
    # Levenberg damping floor of "schur", px^2 per m^2 or rad^2 (schur_lm.py): a step along
    # what no observation constrains costs this much, so the window cannot slide there (a
    # turn on the camera's own axis leaves the points' scale about it unobserved). It is
    # below what any observed direction carries.
    min_damping: float = 1.0
    max_iterations: int = 10  # residual evaluations per robust round (SciPy max_nfev)
    robust_rounds: int = 2  # reweighting rounds (Huber weights from the last residuals)
    huber_px: float = 1.5
    max_residual_px: float = 2.0  # points erring more than this after BA are dropped...
    min_residual_px: float = 0.5  # ...or more than 3 robust sigmas of all, but never below this
    background: bool = True  # run in a worker thread (the daemon); False: in the frame loop
    # The target's corners fit to ~0.08 px, KLT tracks to ~0.3 px over their life: weights in
    # inverse proportion of those sigmas keep the anchors in charge.
    target_weight: float = 8.0
    floor: FloorOptions = field(default_factory=FloorOptions)


@dataclass(frozen=True)
class PnpOptions:
    """The pose of a frame from the map points it tracks (RANSAC PnP, then a robust refinement)."""

    reproj_px: float = 2.0  # RANSAC inlier threshold
    min_reproj_px: float = 0.5  # the robust refinement threshold never goes below this
    iterations: int = 60
    min_inliers: int = 20  # fewer inliers: the frame has no pose (lost)


@dataclass(frozen=True)
class KeyframeOptions:
    """When a frame becomes a keyframe, and how many the map keeps."""

    baseline_ratio: float = 0.05  # baseline / median depth since the last keyframe
    # the same while the target is trusted: anchored keyframes are what holds the map in
    # the target frame, so take more of them
    anchored_baseline_ratio: float = 0.015
    tracked_ratio: float = 0.8  # map points still tracked / at the last keyframe
    min_points: int = 150  # fewer tracked map points: make a keyframe now
    starving_points: int = 100  # fewer still: a keyframe on every frame (not every other)
    # older keyframes and the points only they saw are culled (but LoopOptions.kept_keyframes
    # of them, with loop closure)
    max_kept: int = 40


@dataclass(frozen=True)
class TriangulationOptions:
    """New map points from a track's keyframes."""

    # a point's parallax before it is triangulated: low enough that a camera walking forwards
    # and turning keeps its map stocked; bundle adjustment then refines the depths with more views
    min_parallax_deg: float = 0.7
    # ...and while the map runs short (fewer than starving_points map points tracked: a
    # turn, driving straight at a wall): a point of 0.3 deg has a depth some 2 % off where
    # 0.7 deg gives 1 %, but no point at all loses the map; taken more often they cost accuracy
    starving_parallax_deg: float = 0.3
    starving_points: int = 40
    max_reproj_px: float = 2.0
    # Two keyframes triangulate only when their baseline is at least this many times the
    # combined standard deviation of their poses (each pose's own fit: target, PnP or
    # relocalisation match), else against an older keyframe of the track that passes: below
    # it the poses' errors, not the parallax, would set the depths and so the map's scale
    min_baseline_sigmas: float = 1.0


@dataclass(frozen=True)
class LoopOptions:
    """Loop closure (Tracker.loop_keyframes / close_loop): a keyframe tracked on the map is
    matched against keyframes made min_age_s ago or more, within radius_m, looking within
    max_angle_deg of the same way, sharing at most max_shared of their points with the live
    tracks (the oldest ``keyframes``)."""

    # off by default: on the randomized family it moved the runs both ways and the poses
    # after a closure claimed far too little (docs/tracker.md, "Loop closure")
    enabled: bool = False
    min_age_s: float = 10.0
    radius_m: float = 1.0
    max_angle_deg: float = 30.0
    max_shared: float = 0.2
    keyframes: int = 3
    max_drift_share: float = 0.5  # ...whose drift (Drift.grown_m) is at most this share of this frame's
    matches: int = 4  # ...and the map moved when this many matches within window_s agree
    window_s: float = 5.0
    # with loop closure, these keyframes beyond KeyframeOptions.max_kept, spread widest over
    # the area (Map.thin), are kept
    kept_keyframes: int = 60


@dataclass(frozen=True)
class AnchorOptions:
    """The target's poses: which anchor keyframes, and when one corrects the map."""

    max_reproj_px: float = 0.25  # a target pose fitting worse (a grazing face) anchors no keyframe
    max_position_std_m: float = 0.005  # ...nor one whose covariance says it is this uncertain
    # A camera that has never given a pose within both bounds above (a small lens, a far
    # target) is held instead to this times the surest pose and the best fit it has given
    best_ratio: float = 2.0
    jump_m: float = 0.01  # a target pose this far from the tracker's: a visible jump
    jump_deg: float = 1.0
    fuse_with_map: bool = False  # target visible: one pose from its corners and the map points


@dataclass(frozen=True)
class MotionOptions:
    """The motion model's prediction, the gate on a tracked pose, and coasting."""

    max_m: float = 0.5  # a tracker pose further than this from the prediction is refused
    # ...or turned further than this from it: the prediction is off by the change of turn
    # rate within one frame, and 5 deg a frame is 50 deg/s at 10 fps (a pose further off is a
    # PnP on drifted points, not a turn)
    max_deg: float = 5.0
    max_extrapolation_s: float = 0.5  # the motion model predicts no further ahead than this
    max_coast_s: float = 0.5  # with too few rays to hold on, the motion model alone for this long
    coast_accel_m_s2: float = 1.0  # ...for a robot that may change its speed by this meanwhile
    coast_angular_accel_rad_s2: float = 2.0  # ...and its turn rate by this
    # the motion model's translation, unmeasured while held, halves in this time (a robot
    # that stops to turn on the spot, or drives on past a blank wall)
    hold_velocity_half_life_s: float = 0.2


@dataclass(frozen=True)
class HoldOptions:
    """Too few map points in view (a turn on the spot): the pose held on rays (pose_fit.py),
    or bridged by the wheels when lost."""

    min_rays: int = 30  # tracks without a point, agreeing with one orientation
    min_ray_fraction: float = 0.6  # ...and that share of them (fewer: parallax or movers)
    min_points: int = 8  # map points that agree, for them to hold the position too
    sigma_m: float = 0.01  # the held position's standard deviation at once...
    sigma_m_per_s: float = 0.05  # ...growing by this per second held
    max_s: float = 20.0  # longer than this on rays alone: lost
    # lost, the wheels alone carry the last pose on for at most this long (odometry.bridge);
    # past it the odometry's drift is the pose, and the frame is lost
    max_bridge_s: float = 20.0
    max_rotation_sigma_deg: float = 0.5
    default_depth_m: float = 3.0  # the rays' prior depth when no map point is in view


@dataclass(frozen=True)
class DriftOptions:
    """The map's drift since the target was last trusted, added to a tracking pose's
    covariance (standard deviations); the position's grows per metre of path by the
    relative scale error bundle adjustment measures (hold.Drift.scale_measured)."""

    floor_m: float = 0.002  # never claimed better (the map agrees with the target to 1-2 mm)
    per_m: float = 0.003  # position, per metre of path, at the least
    m_per_rad: float = 0.002  # position, per radian turned
    rad_per_m: float = 0.001  # orientation, per metre of path
    rad_per_rad: float = 0.002  # orientation, per radian turned


@dataclass(frozen=True)
class RelocOptions:
    """Relocalisation against keyframes (ORB), and at boot on a saved map."""

    orb_features: int = 2000  # corners described in a lost frame
    min_inliers: int = 20  # RANSAC inliers at 2 px: chance agreement of 20 is negligible
    ratio: float = 0.8  # Lowe's ratio test on Hamming distances
    reproj_px: float = 3.0  # RANSAC inlier threshold (a map seen anew is less exact than tracks)
    # Gauss-Newton steps aligning a match to its keyframe's patch (relocalise.py): from the
    # identity warp and a corner up to 1.4 px off, where a track carries its warp on
    align_iterations: int = 10
    max_position_sigma_m: float = 0.01  # a relocalisation less sure than this is refused
    boot_iterations: int = 10_000  # RANSAC samples at boot on a saved map (relocalise.py)
    min_reference_points: int = 30  # a loaded map's points in view that give the pose alone (pose_fit.pose_from_map)


@dataclass(frozen=True)
class RefindOptions:
    """A loaded map's points found again at every keyframe (Relocaliser.refind), and retired
    when no longer there (Map.retire)."""

    enabled: bool = True
    radius_px: float = 10.0
    max_hamming: int = 60  # of 256 bits
    max_angle_deg: float = 30.0  # between the view now and the describing keyframe's
    max_scale: float = 1.5  # distance now against the describing keyframe's, either way
    # a loaded point found in at most retire_max_found of its last retire_after_visible
    # chances to be seen (keyframes, one per place retire_min_move_m apart) retires
    retire_after_visible: int = 10
    retire_max_found: int = 1
    retire_min_move_m: float = 0.1  # between two chances of one point


@dataclass(frozen=True)
class TrackerOptions:
    """The tracker's options, by concern."""

    features: FeatureOptions = field(default_factory=FeatureOptions)
    init: InitOptions = field(default_factory=InitOptions)
    bundle: BundleOptions = field(default_factory=BundleOptions)
    pnp: PnpOptions = field(default_factory=PnpOptions)
    keyframes: KeyframeOptions = field(default_factory=KeyframeOptions)
    triangulation: TriangulationOptions = field(default_factory=TriangulationOptions)
    loop: LoopOptions = field(default_factory=LoopOptions)
    anchor: AnchorOptions = field(default_factory=AnchorOptions)
    motion: MotionOptions = field(default_factory=MotionOptions)
    hold: HoldOptions = field(default_factory=HoldOptions)
    drift: DriftOptions = field(default_factory=DriftOptions)
    reloc: RelocOptions = field(default_factory=RelocOptions)
    refind: RefindOptions = field(default_factory=RefindOptions)
    track_sigma_px: float = 0.3  # a track's noise floor for covariances (KLT + alignment)
