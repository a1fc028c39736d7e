"""The tracker's map on disk: ``cubeloc.map/1`` (docs/map.md), saved and loaded whole.

One file holds what relocalisation and tracking need to start without the cube: the
keyframes (pose, when, whether the cube anchored it, their observations and the ORB
descriptors of their map points) and the 3-D points, metric, in the target's frame. A
NumPy ``.npz`` archive (a ZIP of ``.npy`` arrays, read with ``allow_pickle=False``: no code
in it can run): ``header`` is a JSON document, every other member an array:

==================  =========  ====================================================
member              dtype      what
==================  =========  ====================================================
header              uint8      UTF-8 JSON: schema ``cubeloc.map/1``, created_ns,
                               software, calibration {width, height, model,
                               fingerprint}, target {family, ids, fingerprint},
                               keyframes, points
point_ids           int64 (P)  each point's id (the track it was triangulated from)
points              f8 (P, 3)  its position, metres, target frame
point_births        int64 (P)  the keyframe it was triangulated at (-1: culled since)
kf_ids, kf_stamps   int64 (K)  keyframe id, time stamp (ns)
kf_poses            f8 (K,4,4) T_world_camera of each keyframe
kf_anchored         bool (K)   the cube was trusted in it
kf_sigmas           f8 (K)     its pose's own position standard deviation (m)
obs_offsets         int64(K+1) keyframe k's observations are rows [o[k], o[k+1])
obs_ids, obs_xn     int64, f8  track id and normalised coordinates of each row
desc_offsets        int64(K+1) the same for the ORB descriptors
desc_ids, desc      int64, u1  point id and 32-byte descriptor of each row
==================  =========  ====================================================

The fingerprints are SHA-256 of the camera's intrinsics and distortion (rounded: a
file read back gives the same) and of the target's explicit-tags YAML: a map from
another calibration or another target is refused, with one line.
"""

from __future__ import annotations

import hashlib
import io
import json
import time
import zipfile
from pathlib import Path

import numpy as np

from cubeloc import __version__
from cubeloc.atomic import atomic_open
from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.errors import InputFileError
from cubeloc.positioning.geometry import Transform
from cubeloc.positioning.target import Target
from cubeloc.positioning.tracking.map import FIXED_BIRTH, Keyframe, Map

SCHEMA = "cubeloc.map/1"
ARRAYS = ("point_ids", "points", "point_births", "kf_ids", "kf_stamps", "kf_poses", "kf_anchored", "kf_sigmas", "obs_offsets",
          "obs_ids", "obs_xn", "desc_offsets", "desc_ids", "desc")


def calibration_fingerprint(calibration: CameraCalibration) -> str:
    values = np.concatenate([[calibration.width, calibration.height], calibration.camera_matrix.ravel(),
                             calibration.distortion])
    text = calibration.distortion_model + ":" + ",".join(f"{v:.6g}" for v in values)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def target_fingerprint(target: Target) -> str:
    return hashlib.sha256(target.to_yaml().encode()).hexdigest()[:16]


def _offsets(parts: list[np.ndarray]) -> np.ndarray:
    return np.concatenate([[0], np.cumsum([len(p) for p in parts])]).astype(np.int64)


def save_map(path: Path, world_map: Map, calibration: CameraCalibration, target: Target) -> dict:
    """Write ``world_map`` to ``path`` atomically (the old file stays until the new one is
    complete, also through a kill -9); returns the header written."""
    arrays = map_arrays(world_map, calibration, target)
    write_map(path, arrays)
    return json.loads(bytes(arrays["header"]))


def write_map(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """The arrays of ``map_arrays`` to ``path``, atomically (compressing takes most of it:
    the daemon does it outside the frame loop)."""
    with atomic_open(path, "wb") as handle:
        np.savez_compressed(handle, **arrays)


def map_arrays(world_map: Map, calibration: CameraCalibration, target: Target) -> dict[str, np.ndarray]:
    """A copy of ``world_map`` as the file's arrays (taken where the map is not changing:
    the frame loop's thread)."""
    keyframes = list(world_map.keyframes.values())
    point_ids = np.fromiter(world_map.points, np.int64, len(world_map.points))
    header = {
        "schema": SCHEMA, "created_ns": time.time_ns(), "software": __version__,
        "calibration": {"width": calibration.width, "height": calibration.height,
                        "model": calibration.distortion_model, "fingerprint": calibration_fingerprint(calibration)},
        "target": {"family": target.family, "ids": list(target.ids), "fingerprint": target_fingerprint(target)},
        "keyframes": len(keyframes), "points": len(point_ids),
    }
    arrays = {
        "header": np.frombuffer(json.dumps(header).encode(), np.uint8),
        "point_ids": point_ids,
        "points": np.array([world_map.points[int(i)] for i in point_ids], np.float64).reshape(-1, 3),
        "point_births": np.array([world_map.point_birth.get(int(i), -1) for i in point_ids], np.int64),
        "kf_ids": np.array([kf.kf_id for kf in keyframes], np.int64),
        "kf_stamps": np.array([kf.stamp_ns for kf in keyframes], np.int64),
        "kf_poses": np.array([kf.T_world_camera.matrix() for kf in keyframes], np.float64).reshape(-1, 4, 4),
        "kf_anchored": np.array([kf.anchored for kf in keyframes], bool),
        "kf_sigmas": np.array([kf.position_sigma_m for kf in keyframes], np.float64),
        "obs_offsets": _offsets([kf.track_ids for kf in keyframes]),
        "obs_ids": np.concatenate([kf.track_ids for kf in keyframes] + [np.zeros(0, np.int64)]),
        "obs_xn": np.concatenate([kf.xn for kf in keyframes] + [np.zeros((0, 2))]),
        "desc_offsets": _offsets([kf.descriptor_ids for kf in keyframes]),
        "desc_ids": np.concatenate([kf.descriptor_ids for kf in keyframes] + [np.zeros(0, np.int64)]),
        "desc": np.concatenate([kf.descriptors for kf in keyframes] + [np.zeros((0, 32), np.uint8)]),
    }
    return arrays


def read_header(path: Path) -> dict:
    """The header of a map file; InputFileError (one line naming the file) when it is not one."""
    return _open(path)[0]


def _open(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    path = Path(path)
    try:
        with open(path, "rb") as handle:
            if handle.read(4) != b"PK\x03\x04":  # every .npz is a ZIP archive
                raise InputFileError(f"{path}: not a cubeloc map (not an .npz archive)")
        with np.load(path, allow_pickle=False) as archive:
            if "header" not in archive.files:
                raise InputFileError(f"{path}: not a cubeloc map (no header)")
            header = json.loads(bytes(archive["header"]).decode("utf-8"))
            if not isinstance(header, dict) or header.get("schema") != SCHEMA:
                schema = header.get("schema") if isinstance(header, dict) else None
                raise InputFileError(f"{path}: map format {schema!r}, this cubeloc reads {SCHEMA!r}")
            missing = [name for name in ARRAYS if name not in archive.files]
            if missing:
                raise InputFileError(f"{path}: not a complete {SCHEMA} map (missing {', '.join(missing)})")
            arrays = {name: archive[name] for name in ARRAYS}
    except FileNotFoundError:
        raise InputFileError(f"{path}: map file not found") from None
    except InputFileError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, UnicodeDecodeError, KeyError) as exc:
        raise InputFileError(f"{path}: not a readable cubeloc map ({type(exc).__name__}: {exc})") from None
    return header, arrays


def load_map(path: Path, calibration: CameraCalibration, target: Target) -> tuple[Map, dict]:
    """The map in ``path`` for this camera and target, and its header; InputFileError with
    one line when the file is not a map, is damaged, or was made with another
    calibration or target."""
    header, a = _open(path)
    mine, theirs = calibration_fingerprint(calibration), header.get("calibration", {}).get("fingerprint")
    if mine != theirs:
        raise InputFileError(f"{path}: made with another camera calibration ({theirs}; this one is {mine}): "
                             "map again with this calibration")
    mine, theirs = target_fingerprint(target), header.get("target", {}).get("fingerprint")
    if mine != theirs:
        raise InputFileError(f"{path}: made with another target ({theirs}; this one is {mine})")
    try:
        world_map = _build(a)
    except (ValueError, IndexError, TypeError) as exc:
        raise InputFileError(f"{path}: a damaged {SCHEMA} map ({exc})") from None
    return world_map, header


def _build(a: dict[str, np.ndarray]) -> Map:
    k = len(a["kf_ids"])
    shapes = {"points": (len(a["point_ids"]), 3), "point_births": (len(a["point_ids"]),), "kf_poses": (k, 4, 4), "obs_offsets": (k + 1,),
              "desc_offsets": (k + 1,), "obs_xn": (len(a["obs_ids"]), 2), "desc": (len(a["desc_ids"]), 32)}
    for name, shape in shapes.items():
        if a[name].shape != shape:
            raise ValueError(f"{name} is {a[name].shape}, expected {shape}")
    for name in ("points", "kf_poses", "obs_xn", "kf_sigmas"):
        if not np.all(np.isfinite(a[name])):
            raise ValueError(f"{name} is not finite")
    for name, rows in (("obs_offsets", len(a["obs_ids"])), ("desc_offsets", len(a["desc_ids"]))):
        o = a[name]
        if o[0] != 0 or o[-1] != rows or np.any(np.diff(o) < 0):
            raise ValueError(f"{name} do not cover the rows")
    world_map = Map()
    kf_ids = {int(i) for i in a["kf_ids"]}
    for point_id, position, birth in zip(a["point_ids"], a["points"], a["point_births"], strict=True):
        world_map.add_point(int(point_id), position, int(birth) if int(birth) in kf_ids else FIXED_BIRTH)
    for i in range(k):
        lo, hi = a["obs_offsets"][i], a["obs_offsets"][i + 1]
        dlo, dhi = a["desc_offsets"][i], a["desc_offsets"][i + 1]
        kf = Keyframe(int(a["kf_ids"][i]), int(a["kf_stamps"][i]), Transform.from_matrix(a["kf_poses"][i]),
                      a["obs_ids"][lo:hi].astype(np.int64), a["obs_xn"][lo:hi].astype(np.float64),
                      bool(a["kf_anchored"][i]), descriptor_ids=a["desc_ids"][dlo:dhi].astype(np.int64),
                      descriptors=a["desc"][dlo:dhi].astype(np.uint8), position_sigma_m=float(a["kf_sigmas"][i]))
        world_map.keyframes[kf.kf_id] = kf
    world_map.next_kf_id = int(a["kf_ids"].max()) + 1 if k else 0
    world_map.fixed = kf_ids | {FIXED_BIRTH}  # the reference: corrections move only what is built on it
    return world_map


def map_summary(path: Path) -> dict:
    """What ``cubeloc map info`` prints: the header and the map's extent."""
    header, a = _open(path)
    points, poses = a["points"], a["kf_poses"]
    extent = (np.concatenate([points, poses[:, :3, 3]]) if len(points) or len(poses) else np.zeros((1, 3)))
    return {**header, "anchored_keyframes": int(a["kf_anchored"].sum()), "descriptors": len(a["desc_ids"]),
            "extent_m": {"min": np.round(extent.min(axis=0), 3).tolist(), "max": np.round(extent.max(axis=0), 3).tolist()},
            "age_s": round((time.time_ns() - int(header.get("created_ns", 0))) / 1e9, 1),
            "bytes": Path(path).stat().st_size}


def export_ply(path: Path, out: Path) -> tuple[int, int]:
    """The points and the keyframe positions as an ASCII PLY (points grey, keyframes red
    where the cube anchored them, else blue); returns (points, keyframes)."""
    _, a = _open(path)
    rows = [f"{x:.6f} {y:.6f} {z:.6f} 200 200 200" for x, y, z in a["points"]]
    for pose, anchored in zip(a["kf_poses"], a["kf_anchored"], strict=True):
        x, y, z = pose[:3, 3]
        rows.append(f"{x:.6f} {y:.6f} {z:.6f} " + ("230 40 40" if anchored else "40 80 230"))
    text = io.StringIO()
    text.write("ply\nformat ascii 1.0\ncomment cubeloc map export: points, then keyframe positions\n"
               f"element vertex {len(rows)}\nproperty float x\nproperty float y\nproperty float z\n"
               "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    text.write("".join(row + "\n" for row in rows))
    with atomic_open(out, "w") as handle:
        handle.write(text.getvalue())
    return len(a["points"]), len(a["kf_poses"])


def prune_map(path: Path, out: Path, calibration: CameraCalibration, target: Target, keyframes: int
              ) -> tuple[tuple[int, int], tuple[int, int]]:
    """The map of ``path`` thinned to ``keyframes`` keyframes (``Map.thin``) and saved to
    ``out`` (``cubeloc map prune``): (keyframes, points) before and after."""
    world_map, _ = load_map(path, calibration, target)
    before = (len(world_map.keyframes), len(world_map.points))
    world_map.thin(keyframes, 0, set())
    save_map(out, world_map, calibration, target)
    return before, (len(world_map.keyframes), len(world_map.points))
