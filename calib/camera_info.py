"""Camera calibration files in the ROS ``camera_info`` YAML format.

The same format as ROS ``camera_calibration_parsers``, so ROS tools read ours and we read
theirs. Our extra metadata (RMS error, parameter standard deviations, views, board,
serial, date, software version) lives under one extra top-level key, ``calibration:``,
which ROS ignores. Files are written atomically.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cubeloc.atomic import atomic_write_text
from cubeloc.errors import InputFileError

# ROS' distortion models: OpenCV's pinhole (k1 k2 p1 p2 k3; k1..k6 with p1 p2), and
# ``equidistant``, the fisheye (Kannala-Brandt) model of cv2.fisheye (k1 k2 k3 k4)
DISTORTION_LENGTHS = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}
# Sanity bounds on a file's numbers: beyond these the file is junk or a unit mistake, and
# the projection arithmetic downstream overflows or means nothing.
MAX_FOCAL_PER_PIXEL = 100.0  # fx, fy at most 100 x the larger image side (a ~0.6 deg field)
MAX_DISTORTION = 1e4  # |coefficient|; real rational_polynomial ones stay well below


@dataclass(frozen=True)
class CameraCalibration:
    """Intrinsics and distortion of one camera, in OpenCV conventions.

    ``camera_matrix`` is the 3x3 K; ``distortion`` the OpenCV coefficient vector
    (k1 k2 p1 p2 k3 for ``plumb_bob``; k1 k2 p1 p2 k3 k4 k5 k6 for ``rational_polynomial``;
    k1 k2 k3 k4 of ``cv2.fisheye`` for ``equidistant``, where a ray at angle theta from the
    axis lands theta (1 + k1 theta^2 + ... + k4 theta^8) focal lengths from the centre).
    """

    width: int
    height: int
    camera_matrix: np.ndarray  # (3, 3) float64
    distortion: np.ndarray  # (5,), (8,) or (4,) float64
    distortion_model: str = "plumb_bob"
    camera_name: str = "camera"
    metadata: dict[str, Any] = field(default_factory=dict)  # the ``calibration:`` block

    def __post_init__(self) -> None:
        k = np.asarray(self.camera_matrix, dtype=np.float64).reshape(3, 3)
        d = np.asarray(self.distortion, dtype=np.float64).reshape(-1)
        k.setflags(write=False)
        d.setflags(write=False)
        object.__setattr__(self, "camera_matrix", k)
        object.__setattr__(self, "distortion", d)

    @property
    def fx(self) -> float:
        return float(self.camera_matrix[0, 0])

    @property
    def fy(self) -> float:
        return float(self.camera_matrix[1, 1])

    @property
    def cx(self) -> float:
        return float(self.camera_matrix[0, 2])

    @property
    def cy(self) -> float:
        return float(self.camera_matrix[1, 2])

    @property
    def is_fisheye(self) -> bool:
        """The equidistant (fisheye) model: OpenCV's pinhole functions do not apply."""
        return self.distortion_model == "equidistant"

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels, the order OpenCV functions take."""
        return (self.width, self.height)


def paper_camera(width: int = 1280, height: int = 1024) -> CameraCalibration:
    """The paper's camera: Hikvision MV-CA013 (4.8 um pixels) with an 8 mm lens.

    fx = fy = 8 mm / 4.8 um = 1667 px, principal point at the image centre (OpenCV pixel
    centres, so (W-1)/2, (H-1)/2) and mild barrel distortion.
    """
    f = 8.0e-3 / 4.8e-6
    k = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    d = np.array([-0.08, 0.05, 0.0, 0.0, 0.0])
    return CameraCalibration(width, height, k, d, "plumb_bob", "mv-ca013-8mm-nominal")


def _matrix(rows: int, cols: int, data: np.ndarray) -> dict[str, Any]:
    return {"rows": rows, "cols": cols, "data": [float(x) for x in np.asarray(data).reshape(-1)]}


def to_yaml(calibration: CameraCalibration) -> str:
    """The camera_info YAML text (ROS key order, then our ``calibration:`` block)."""
    c = calibration
    projection = np.zeros((3, 4))
    projection[:, :3] = c.camera_matrix
    document: dict[str, Any] = {
        "image_width": int(c.width),
        "image_height": int(c.height),
        "camera_name": c.camera_name,
        "camera_matrix": _matrix(3, 3, c.camera_matrix),
        "distortion_model": c.distortion_model,
        "distortion_coefficients": _matrix(1, len(c.distortion), c.distortion),
        "rectification_matrix": _matrix(3, 3, np.eye(3)),
        "projection_matrix": _matrix(3, 4, projection),
    }
    if c.metadata:
        document["calibration"] = c.metadata
    return yaml.safe_dump(document, sort_keys=False, default_flow_style=None)


def write_camera_info(path: str | os.PathLike[str], calibration: CameraCalibration) -> None:
    """Write atomically: the old file or the new one survives a crash, never half of one."""
    atomic_write_text(path, to_yaml(calibration))


def _read_matrix(doc: dict[str, Any], key: str, path: Path, shape: tuple[int, int] | None) -> np.ndarray:
    node = doc.get(key)
    if not isinstance(node, dict) or "data" not in node:
        raise InputFileError(f"{path}: '{key}' must be a mapping with rows, cols and data")
    try:
        data = np.asarray(node["data"], dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise InputFileError(f"{path}: '{key}.data' must be a list of numbers") from exc
    if shape is not None:
        if data.size != shape[0] * shape[1]:
            raise InputFileError(
                f"{path}: '{key}' has {data.size} numbers, expected {shape[0]}x{shape[1]}"
            )
        data = data.reshape(shape)
    if not np.all(np.isfinite(data)):
        raise InputFileError(f"{path}: '{key}' contains NaN or infinite values")
    return data


def read_camera_info(path: str | os.PathLike[str]) -> CameraCalibration:
    """Read a camera_info YAML (ours or one written by ROS ``camera_calibration``)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputFileError(f"{path}: calibration file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{path}: cannot read calibration file ({exc})") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise InputFileError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    except RecursionError:  # PyYAML recurses per nesting level: "[[[[..." overflows the stack
        raise InputFileError(f"{path}: not valid YAML (nested too deeply)") from None
    if not isinstance(doc, dict):
        raise InputFileError(f"{path}: expected a camera_info YAML mapping")
    for key in ("image_width", "image_height"):
        value = doc.get(key)
        if not isinstance(value, int) or isinstance(value, bool) or not 0 < value < 100_000:
            raise InputFileError(f"{path}: '{key}' must be a positive integer, got {value!r}")
    k = _read_matrix(doc, "camera_matrix", path, (3, 3))
    if not (k[0, 0] > 0 and k[1, 1] > 0 and math.isclose(k[2, 2], 1.0)):
        raise InputFileError(f"{path}: camera_matrix must have fx, fy > 0 and K[2][2] = 1")
    if k[1, 0] != 0 or k[2, 0] != 0 or k[2, 1] != 0:
        raise InputFileError(f"{path}: camera_matrix must be upper triangular [fx s cx; 0 fy cy; 0 0 1]")
    width, height = doc["image_width"], doc["image_height"]
    max_focal = MAX_FOCAL_PER_PIXEL * max(width, height)
    if max(k[0, 0], k[1, 1]) > max_focal:
        raise InputFileError(f"{path}: focal length {max(k[0, 0], k[1, 1]):.6g} px is implausible for a "
                             f"{width}x{height} image (at most {max_focal:g} px)")
    if not (0 <= k[0, 2] < width and 0 <= k[1, 2] < height):
        raise InputFileError(f"{path}: principal point ({k[0, 2]:.6g}, {k[1, 2]:.6g}) px lies outside "
                             f"the {width}x{height} image")
    model = doc.get("distortion_model", "plumb_bob")
    if not isinstance(model, str) or model not in DISTORTION_LENGTHS:
        known = ", ".join(DISTORTION_LENGTHS)
        raise InputFileError(f"{path}: distortion_model {model!r} is not supported (known: {known})")
    d = _read_matrix(doc, "distortion_coefficients", path, None)
    expected = DISTORTION_LENGTHS[model]
    if d.size == 0:
        d = np.zeros(expected)
    if d.size != expected:
        raise InputFileError(
            f"{path}: {model} needs {expected} distortion coefficients, the file has {d.size}"
        )
    if np.abs(d).max() > MAX_DISTORTION:
        raise InputFileError(f"{path}: distortion coefficient {d[np.abs(d).argmax()]:.6g} is implausible "
                             f"(|value| at most {MAX_DISTORTION:g})")
    metadata = doc.get("calibration") or {}
    if not isinstance(metadata, dict):
        raise InputFileError(f"{path}: 'calibration' must be a mapping")
    return CameraCalibration(
        width=doc["image_width"],
        height=doc["image_height"],
        camera_matrix=k,
        distortion=d,
        distortion_model=model,
        camera_name=str(doc.get("camera_name", "camera")),
        metadata=metadata,
    )
