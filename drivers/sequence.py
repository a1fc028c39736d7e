"""Recorded sequences in the EuRoC camera layout (interfaces.md).

::

    <seq>/mav0/cam0/data.csv          #timestamp [ns],filename   (one row per frame)
    <seq>/mav0/cam0/data/<ns>.png     8-bit mono
    <seq>/groundtruth.tum             optional, T_world_camera per frame

The writer is safe to interrupt at any point: each PNG is written to a temporary name and
renamed into place before its CSV row is appended, so the CSV only ever names frames that
are whole on disk; a reader ignores a last CSV line cut short by a kill.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cubeloc.errors import InputFileError
from cubeloc.images import to_mono8

CSV_HEADER = "#timestamp [ns],filename\n"


def camera_dir(root: str | os.PathLike[str]) -> Path:
    return Path(root) / "mav0" / "cam0"


@dataclass(frozen=True)
class SequenceEntry:
    stamp_ns: int
    path: Path


def read_sequence_index(root: str | os.PathLike[str]) -> list[SequenceEntry]:
    """The frames of a sequence, in file order. Raise InputFileError naming the problem."""
    root = Path(root)
    csv_path = camera_dir(root) / "data.csv"
    if not root.is_dir():
        raise InputFileError(f"{root}: sequence directory not found")
    if not csv_path.is_file():
        raise InputFileError(f"{root}: not a sequence in the EuRoC layout (no mav0/cam0/data.csv)")
    try:
        text = csv_path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{csv_path}: cannot read ({exc})") from None
    lines = text.split("\n")
    if not text.endswith("\n"):
        lines = lines[:-1]  # a last row cut short by a kill: the frame is not trusted
    entries: list[SequenceEntry] = []
    for number, line in enumerate(lines, start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        stamp, sep, filename = line.partition(",")
        try:
            stamp_ns = int(stamp.strip())
        except ValueError:
            raise InputFileError(f"{csv_path}:{number}: timestamp {stamp!r} is not an integer (ns)") from None
        if not sep or not filename.strip():
            raise InputFileError(f"{csv_path}:{number}: expected 'timestamp,filename'")
        entries.append(SequenceEntry(stamp_ns, camera_dir(root) / "data" / filename.strip()))
    if not entries:
        raise InputFileError(f"{csv_path}: the sequence has no frames")
    return entries


def read_image(path: Path) -> np.ndarray:
    """An 8-bit mono image from any image file OpenCV decodes, 8- or 16-bit, grey or colour
    (``to_mono8``); raise InputFileError naming the file when it is missing, not an image,
    or of another type (float)."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: image not found")
    data = np.fromfile(path, dtype=np.uint8)
    if data.size == 0:
        raise InputFileError(f"{path}: empty file, not an image")
    # OpenCV logs its own "[ WARN:0@...] PNG input buffer is incomplete" beside ours: not
    # while decoding here (the error below names the file and says what is wrong)
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    try:
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    finally:
        cv2.utils.logging.setLogLevel(level)
    if image is None:
        raise InputFileError(f"{path}: not an image OpenCV can decode (truncated or corrupt)")
    try:
        return to_mono8(image)
    except ValueError:
        raise InputFileError(f"{path}: expected an 8- or 16-bit image, got {image.dtype}") from None


def read_image_sized(path: Path, width: int, height: int) -> np.ndarray:
    """``read_image``, and an InputFileError naming the file when it is not ``width`` x
    ``height`` (the size a calibration is for)."""
    image = read_image(path)
    if image.shape != (height, width):
        raise InputFileError(
            f"{path}: image is {image.shape[1]}x{image.shape[0]} but the calibration is for {width}x{height}")
    return image


class SequenceWriter:
    """Write frames into a new sequence directory, safe to interrupt at any point."""

    def __init__(self, root: str | os.PathLike[str], *, overwrite: bool = False) -> None:
        self.root = Path(root)
        self.data_dir = camera_dir(self.root) / "data"
        csv_path = camera_dir(self.root) / "data.csv"
        if csv_path.exists() and not overwrite:
            raise InputFileError(f"{self.root}: a sequence is already there (choose another --out)")
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self._csv = open(csv_path, "w", encoding="utf-8")  # noqa: SIM115 - closed in close()
        self._csv.write(CSV_HEADER)
        self._csv.flush()
        self.frames = 0
        self._last_stamp_ns: int | None = None

    def write(self, stamp_ns: int, image: np.ndarray) -> Path:
        if image.dtype != np.uint8 or image.ndim != 2:
            raise ValueError(f"expected a (H, W) uint8 image, got {image.dtype} {image.shape}")
        if self._last_stamp_ns is not None and stamp_ns <= self._last_stamp_ns:
            raise ValueError(f"timestamps must increase: {stamp_ns} after {self._last_stamp_ns}")
        ok, encoded = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise OSError("PNG encoding failed")
        filename = f"{stamp_ns}.png"
        final = self.data_dir / filename
        partial = self.data_dir / f".{filename}.part"
        encoded.tofile(partial)
        os.replace(partial, final)
        self._csv.write(f"{stamp_ns},{filename}\n")
        self._csv.flush()
        self.frames += 1
        self._last_stamp_ns = stamp_ns
        return final

    def close(self) -> None:
        if not self._csv.closed:
            self._csv.flush()
            os.fsync(self._csv.fileno())
            self._csv.close()

    def __enter__(self) -> SequenceWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
