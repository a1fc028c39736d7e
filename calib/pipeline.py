"""From image files (or live detections) to a calibration with its report.

``detect_images`` reads each file once, reuses the corners cache where the bytes are
unchanged, and refuses a set that mixes image sizes or holds unreadable files.
``calibrate_views`` turns detections into views (skipping blurred ones, and naming
them), solves, judges, and returns a ``CameraCalibration`` whose ``calibration:`` block
carries the report, ready for ``write_camera_info``.
"""

from __future__ import annotations

import datetime
import hashlib
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

import cubeloc
from cubeloc.calib.boards import BoardSpec
from cubeloc.calib.camera_info import CameraCalibration
from cubeloc.calib.corners_cache import ImageRecord, load_cache, save_cache
from cubeloc.calib.detect import Detection, detect_board, diagnose_missing_board
from cubeloc.calib.report import Verdict, judge
from cubeloc.calib.solve import CalibrationError, Solution, SolveOptions, View, solve
from cubeloc.errors import InputFileError
from cubeloc.images import to_mono8


@dataclass(frozen=True)
class ImageDetection:
    path: Path
    size: tuple[int, int]  # (width, height)
    detection: Detection | None


@dataclass(frozen=True)
class CalibrationRun:
    calibration: CameraCalibration  # with the ``calibration:`` metadata block
    solution: Solution
    verdict: Verdict
    skipped: tuple[tuple[str, str], ...]  # (image name, why it was not used)


def _decode(path: Path, data: bytes) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    if image is None:
        raise InputFileError(f"{path}: not an image OpenCV can read (remove it from the set or re-export it)")
    try:
        return to_mono8(image)  # 8- or 16-bit, grey or colour
    except ValueError:
        raise InputFileError(f"{path}: expected an 8- or 16-bit image, got {image.dtype}") from None


def detect_images(paths: list[Path], board: BoardSpec, *, use_cache: bool = True) -> list[ImageDetection]:
    """Detect ``board`` in every image, through the corners cache of each directory."""
    by_directory: dict[Path, list[Path]] = defaultdict(list)
    for path in paths:
        by_directory[path.parent].append(path)
    results: dict[Path, ImageDetection] = {}
    first_size: tuple[tuple[int, int], Path] | None = None
    for directory, members in by_directory.items():
        cached = load_cache(directory, board) if use_cache else {}
        fresh: list[ImageRecord] = []
        for path in members:
            try:
                data = path.read_bytes()
            except OSError as exc:
                raise InputFileError(f"{path}: cannot read image ({exc.strerror or exc})") from None
            digest = hashlib.sha256(data).hexdigest()
            record = cached.get(path.name)
            if record is None or record.sha256 != digest:
                image = _decode(path, data)
                record = ImageRecord(path.name, digest, image.shape[1], image.shape[0], detect_board(image, board))
                fresh.append(record)
            size = (record.width, record.height)
            if first_size is None:
                first_size = (size, path)
            elif size != first_size[0]:
                w, h = first_size[0]
                raise InputFileError(
                    f"{path}: {size[0]}x{size[1]} while {first_size[1].name} is {w}x{h}; "
                    "calibrate one camera at one resolution at a time"
                )
            results[path] = ImageDetection(path, size, record.detection)
        if fresh and use_cache:
            save_cache(directory, board, fresh)
    return [results[p] for p in paths]


def no_board_message(detections: list[ImageDetection], board: BoardSpec) -> str:
    """'0 of 25 images show a 9x6 chessboard; check ...' with the off-by-one hint."""
    message = f"0 of {len(detections)} images show {board.description}"
    sample = [d.path for d in detections[:4]]
    images = [_decode(p, p.read_bytes()) for p in sample if p.is_file()]
    hint = diagnose_missing_board([i for i in images if i is not None], board)
    if hint:
        return f"{message}; {hint}"
    advice = {
        "chessboard": "check the board size: it counts inner corners (where four squares meet)",
        "charuco": "check the board size (it counts squares), the dictionary and that the markers are in view",
        "circles": "check the grid size (it counts circles) and that the whole grid is in view",
        "acircles": "check the grid size (circles per row x rows) and that the whole grid is in view",
        "aprilgrid": "check that the tags are tag36h11 with a two-cell black border and black squares between them",
    }[board.kind]
    return f"{message}; {advice}"


def views_from_detections(detections: list[ImageDetection], board: BoardSpec) -> tuple[list[View], list[tuple[str, str]]]:
    """Usable views and the (name, reason) of every image left out."""
    if not detections:
        raise CalibrationError("no images to calibrate from")
    if all(d.detection is None for d in detections):
        raise CalibrationError(no_board_message(detections, board))
    views: list[View] = []
    skipped: list[tuple[str, str]] = []
    for item in detections:
        name = item.path.name
        if item.detection is None:
            skipped.append((name, f"{board.description} not found"))
        elif not item.detection.is_sharp:
            skipped.append((name, f"blurred (edges {item.detection.edge_width_px:.1f} px wide)"))
        else:
            views.append(View(name, item.detection.image_points, item.detection.object_points))
    return views, skipped


def _sig(value: float, digits: int = 6) -> float:
    return float(f"{value:.{digits}g}")


def calibrate_views(
    views: list[View],
    image_size: tuple[int, int],
    board: BoardSpec,
    options: SolveOptions | None = None,
    *,
    skipped: list[tuple[str, str]] = (),
    camera_name: str = "camera",
    camera_serial: str = "",
    now: datetime.datetime | None = None,
) -> CalibrationRun:
    """Solve, judge, and package the result with its ``calibration:`` metadata block."""
    options = options or SolveOptions()
    if len(views) < 5:
        total = len(views) + len(skipped)
        raise CalibrationError(
            f"only {len(views)} of {total} images give a usable view of {board.description}; "
            "at least 5 are needed (20 or more is better)"
        )
    solution = solve(views, image_size, options)
    verdict = judge(solution)
    now = now or datetime.datetime.now(datetime.timezone.utc)
    metadata = {
        "rms_px": _sig(solution.rms_px, 4),
        "std": {name: _sig(value, 3) for name, value in solution.std.items()},
        "views": len(solution.views),
        "corners": solution.points,
        "board": board.text,
        "camera_serial": camera_serial,
        "date": now.replace(microsecond=0).isoformat(),
        "software": f"cubeloc {cubeloc.__version__}",
        "fix_principal_point": options.fix_principal_point,
        "fix_aspect_ratio": options.fix_aspect_ratio,
        "verdict": verdict.text,
        "per_view_rms_px": {v.name: _sig(v.rms_px, 3) for v in solution.views},
        "dropped": [{"view": v.name, "rms_px": _sig(v.rms_px, 3), "reason": v.reason} for v in solution.dropped],
        "skipped": [{"image": name, "reason": reason} for name, reason in skipped],
    }
    calibration = CameraCalibration(
        width=image_size[0], height=image_size[1], camera_matrix=solution.camera_matrix,
        distortion=solution.distortion, distortion_model=solution.model,
        camera_name=camera_name, metadata=metadata,
    )
    return CalibrationRun(calibration, solution, verdict, tuple(skipped))


def capture_views(camera, board: BoardSpec, min_views: int, max_views: int, stop, on_frame=None,
                  source: str = "the camera", max_timeouts: int = 10) -> tuple[list[tuple], str]:
    """Views of ``board`` from a started ``camera`` (the camera protocol), each frame kept
    when it is sharp and adds coverage (``calib.coverage.CoverageTracker``), until coverage
    is good enough, the source ends, ``max_timeouts`` frame timeouts in a row, ``stop`` (a
    threading.Event) is set or Ctrl-C. ``on_frame(stamp_ns, image, detection, offer,
    tracker)`` sees every frame searched. Returns ([(name, image, detection)] of the kept
    views, why capture ended)."""
    from cubeloc.calib.coverage import CoverageTracker
    from cubeloc.drivers.base import EndOfStream, FrameTimeout, StreamBroken

    accepted: list[tuple] = []
    tracker: CoverageTracker | None = None
    timeouts = 0
    try:
        while not stop.is_set():
            try:
                frame = camera.next_frame(timeout_s=1.0)
            except FrameTimeout:
                timeouts += 1
                if timeouts >= max_timeouts:
                    return accepted, f"no frames from {source} for {max_timeouts} s"
                continue
            except EndOfStream:
                return accepted, "end of the recorded source"
            except StreamBroken as exc:
                return accepted, f"camera stream broke ({exc})"
            timeouts = 0
            image = frame.image
            if tracker is None:
                size = (image.shape[1], image.shape[0])
                tracker = CoverageTracker(board, size, min_views=min_views, max_views=max_views)
            detection = detect_board(image, board)
            offer = tracker.offer(detection)
            if offer.accepted:
                accepted.append((f"view_{len(accepted):03d}.png", image.copy(), detection))
            if on_frame is not None:
                on_frame(frame.stamp_ns, image, detection, offer, tracker)
            if tracker.done:
                return accepted, "coverage good enough"
    except KeyboardInterrupt:
        pass
    return accepted, "stopped on request"


def write_views(views_dir: Path, board: BoardSpec, accepted: list[tuple]) -> None:
    """The kept views ([(name, image, detection)]) as PNGs and their corners
    (``corners.yaml``) in ``views_dir``, a folder that appears whole or not at all (it
    replaces one already there)."""
    import os
    import shutil
    import tempfile

    staging = Path(tempfile.mkdtemp(prefix=f".{views_dir.name}.", dir=views_dir.parent))
    try:
        records = []
        for name, image, detection in accepted:
            ok, png = cv2.imencode(".png", image)
            if not ok:
                raise OSError(f"cannot encode {name}")
            data = png.tobytes()
            (staging / name).write_bytes(data)
            records.append(ImageRecord(name, hashlib.sha256(data).hexdigest(), image.shape[1], image.shape[0], detection))
        save_cache(staging, board, records)
        if views_dir.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{views_dir.name}.old.", dir=views_dir.parent))
            os.replace(views_dir, old / "views")
            os.replace(staging, views_dir)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(staging, views_dir)
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
