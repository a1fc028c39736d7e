"""Where to look for a target's tags in an image: the regions a prior pose predicts, and how
finely the AprilTag library's quad search must decimate to find tags of a given size.
Used by ``TargetObserver`` (observer.py)."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.positioning.camera_model import ahead, project, undistort
from cubeloc.positioning.detection import cells_across, library_decimate
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.target import Target

# A predicted tag region grows by this fraction of the tag's size on each side, plus a
# fixed margin: the camera moves between frames and the prediction is last frame's pose.
REGION_GROWTH = 0.35
REGION_MARGIN_PX = 16
# The completion search after a pose from this frame's own tags needs less room: no motion
# since the pose, and everything outside the predicted quiet zone is painted white anyway.
# The smaller crop is cheaper to search (2 m: 0.70 against 0.88 ms for the missing tag);
# over the range map's 480 views no pose lost and two gained a third face (at 0.1 one
# lost a face: the crop's own margin matters to the decimated search).
COMPLETION_GROWTH = 0.2
# Tags seen more obliquely than this are not predicted: the library decoded a tag at 85 deg
# on the range map (bench range), none beyond.
MAX_PREDICTED_ANGLE_DEG = 87.0


# A predicted tag this large (pixels) is searched with more decimation: its quad is still
# 30 px or more in the decimated image, and a third cheaper to find.
LARGE_TAG_PX = 90.0
LARGE_TAG_DECIMATE = 3.0
# The library's quad search finds a tag whose narrow width is at least this many pixels in
# the decimated image (board renders at 640x480 to 1280x1024, blur 0.3-1 px: all found
# from 13 px, a third lost at 10-13); a search is decimated so that the smallest tag it
# expects keeps twice that, the tags of one target in one view differing in size by up to
# 2x (depth and foreshortening).
MIN_DECIMATED_TAG_PX = 13.0
PAPER_FRAME_PIXELS = 1280 * 1024


def decimate_for(width_px: float, most: float) -> float:
    """The decimation (1 to ``most``, one the library performs) that keeps a tag
    ``width_px`` wide findable with room."""
    return library_decimate(min(most, width_px / (2.0 * MIN_DECIMATED_TAG_PX)))

def finest_empty_decimate(shape: tuple[int, ...], quad_decimate: float) -> float:
    """The decimation of the full-frame pass after an empty coarse one: the library's own
    (``quad_decimate``) on the paper's 1280x1024 frame, and as much finer on a smaller frame
    as keeps the pass's cost (pixels over decimation squared) the same: 1 at 640x480 and
    752x480, where tags 13-26 px wide are otherwise found only beside larger ones."""
    share = shape[0] * shape[1] / PAPER_FRAME_PIXELS
    return library_decimate(quad_decimate * min(1.0, float(np.sqrt(share))))


# Recovery searches this many tag sizes around a lone tag for its neighbours.
NEIGHBOURHOOD_TAG_SIZES = 1.2
# A tag needs a white quiet zone one cell wide; the masked search keeps this much of it.
QUIET_ZONE_KEPT_CELLS = 0.8


def grey_percentile(values: np.ndarray, q: float) -> float:
    """``np.percentile(values, q)`` (linear interpolation) of uint8 grey levels, from their
    histogram: the same value in 44 against 200 us for the 40,000 pixels of a tag region."""
    counts = np.cumsum(np.bincount(values, minlength=256))
    position = q / 100.0 * (len(values) - 1)
    low = int(position)
    below = int(np.searchsorted(counts, low, side="right"))
    above = int(np.searchsorted(counts, min(low + 1, len(values) - 1), side="right"))
    return below + (position - low) * (above - below)


@dataclass(frozen=True)
class TagRegion:
    tag_id: int
    roi: tuple[int, int, int, int]  # x0, y0, x1, y1 pixels
    quiet_zone: np.ndarray  # (4, 2) pixels: the tag and most of its white margin, predicted
    size_px: float = 0.0  # the tag's predicted size (longest side of its pixel box)


def _field_of_view(calibration: CameraCalibration) -> tuple[np.ndarray, np.ndarray]:
    """The smallest and largest normalised (x, y) of the rays through the image's border
    (its corners and the middles of its sides); worked out once per calibration."""
    return _field_of_view_of(calibration.width, calibration.height, calibration.camera_matrix.tobytes(),
                             calibration.distortion.tobytes(), calibration.distortion_model)


@functools.lru_cache(maxsize=8)
def _field_of_view_of(width: int, height: int, k_bytes: bytes, d_bytes: bytes,
                      model: str) -> tuple[np.ndarray, np.ndarray]:
    calibration = CameraCalibration(width, height, np.frombuffer(k_bytes).reshape(3, 3), np.frombuffer(d_bytes), model)
    w, h = width - 1, height - 1
    border = np.array([[0, 0], [w / 2, 0], [w, 0], [w, h / 2], [w, h], [w / 2, h], [0, h], [0, h / 2]], np.float64)
    # a fisheye seeing beyond 90 deg off axis: those rays have no (x, y, 1); they bound nothing
    border = border[ahead(border, calibration)]
    rays = undistort(border, calibration) if len(border) else np.zeros((1, 2))
    low, high = rays.min(axis=0), rays.max(axis=0)
    low.setflags(write=False)
    high.setflags(write=False)
    return low, high


def _facing(target: Target, calibration: CameraCalibration, T_world_camera: Transform, cos_limit: float,
            spread: float, min_depth_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Which tags face the camera at ``T_world_camera`` (the normal within the angle of
    ``cos_limit`` of it), with every corner ``min_depth_m`` or more in front of it and within
    the image's field of view widened by ``spread`` of it on each side; and each tag's
    corners in the camera frame (T, 4, 3)."""
    T_camera_world = T_world_camera.inverse()
    low_n, high_n = _field_of_view(calibration)
    margin = spread * (high_n - low_n)
    tags = target.tags
    centres = np.array([tag.center for tag in tags])
    normals = np.array([tag.normal for tag in tags])
    to_camera = T_world_camera.translation - centres
    keep = np.einsum("ij,ij->i", normals, to_camera) > cos_limit * np.linalg.norm(to_camera, axis=1)
    in_camera = T_camera_world.apply(np.concatenate([tag.corners for tag in tags])).reshape(len(tags), 4, 3)
    keep &= np.all(in_camera[:, :, 2] > min_depth_m, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = in_camera[:, :, :2] / in_camera[:, :, 2:]
    keep &= np.all((xn >= low_n - margin) & (xn <= high_n + margin), axis=(1, 2))
    return keep, in_camera


def tags_in_view(target: Target, calibration: CameraCalibration, T_world_camera: Transform) -> list[int]:
    """The tags wholly in the image at ``T_world_camera`` and facing the camera, however
    obliquely: every corner in front of it, within the field of view, and inside the image."""
    keep, in_camera = _facing(target, calibration, T_world_camera, 0.0, 0.0, 0.0)
    inside = []
    for index in np.flatnonzero(keep):
        pixels = project(in_camera[index], calibration)
        if np.all((pixels >= 0.0) & (pixels <= (calibration.width - 1, calibration.height - 1))):
            inside.append(target.tags[index].tag_id)
    return inside


def predicted_tag_regions(target: Target, calibration: CameraCalibration, T_world_camera: Transform,
                          growth: float = REGION_GROWTH, margin_px: int = REGION_MARGIN_PX) -> list[TagRegion]:
    """Where each tag facing the camera at ``T_world_camera`` should appear, one pixel box
    per tag, enlarged for motion; tags behind the camera or out of the image are left out."""
    # Not seen edge-on or from behind, in front of the camera, and near the field of view:
    # far outside it the distortion polynomial folds points back into the image (measured:
    # a cube 60+ degrees off-axis gave a whole-image box, 18 ms of search per frame for
    # nothing). Kept to a field of view half as wide again as the image's (its border's
    # rays: a fisheye's reach far beyond what its focal length alone says).
    keep, in_camera = _facing(target, calibration, T_world_camera, np.cos(np.radians(MAX_PREDICTED_ANGLE_DEG)),
                              0.25, 0.05)
    tags = target.tags
    chosen = np.flatnonzero(keep)
    if len(chosen) == 0:
        return []
    grow = 1.0 + 2.0 * QUIET_ZONE_KEPT_CELLS / cells_across(target.family, target.border_bits)
    corners = in_camera[chosen]
    centre = corners.mean(axis=1, keepdims=True)
    outline = np.concatenate([corners, centre + grow * (corners - centre)], axis=1)  # (K, 8, 3)
    pixels = project(outline.reshape(-1, 3), calibration).reshape(len(chosen), 8, 2)
    regions = []
    for index, outline_px in zip(chosen, pixels, strict=True):
        quad, quiet_zone = outline_px[:4], outline_px[4:]
        low, high = quad.min(axis=0), quad.max(axis=0)
        pad = (high - low).max() * growth + margin_px
        x0, y0 = np.floor(low - pad).astype(int)
        x1, y1 = np.ceil(high + pad).astype(int) + 1
        x0, y0 = max(int(x0), 0), max(int(y0), 0)
        x1, y1 = min(int(x1), calibration.width), min(int(y1), calibration.height)
        if x1 - x0 >= 16 and y1 - y0 >= 16:
            regions.append(TagRegion(tags[index].tag_id, (x0, y0, x1, y1), quiet_zone, float((high - low).max())))
    return regions
