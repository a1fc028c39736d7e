"""The effective range (the paper's Fig. 8), cubeloc against a corners-only baseline on the
same frames, and the detection recall of the full-frame search.

Views: the 18 cm cube from 1-5 m, elevations 0-60 deg, every azimuth (12 per circle, each
jittered by up to 10 deg), aimed at a point up to 0.15 m x distance off the cube's centre
(so the cube lands off-centre, where the distortion is), one frame each (noise sigma 2),
through two lenses: the paper's camera (fx 1667 px, k1 -0.08) and another (fx 1400 px,
principal point off-centre, k1 -0.22, k2 0.09, tangential terms). All seeded.

Per view:

- **baseline**: plain AprilTag 3 at decimate 2 (the library's own corners) + EPnP + LM on
  every corner of the target's tags found, one face or more: what anyone would write;
- **cubeloc**: ``cubeloc pose`` (``TargetPoseProcessor``, fresh per view) of this tree,
  and of commit ``PREVIOUS_COMMIT`` (before the one target observer), run on the same
  frames from its own checkout;
- **recall**: the target's tags found by the library over the full frame at decimate 1
  (the reference), 2 and 3, and by cubeloc's search (its ``tags_seen``).

``python -m bench range`` writes the summary here and docs/range/ (range.md, the map).
``CUBELOC_BENCH_RANGE=DIR`` keeps the rendered frames for later runs.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench.common import REPO, markdown_table, package_prefix, previous_tree

TITLE = "Effective range: cubeloc and a corners-only baseline on the same frames"
PREVIOUS_COMMIT = "d45d303"
DISTANCES = (1.0, 2.0, 3.0, 4.0, 5.0)
ELEVATIONS = (0.0, 20.0, 40.0, 60.0)
AZIMUTHS = tuple(range(0, 360, 30))
JUSTIFIED_MM = 5.0  # a refusal is justified where the baseline's own pose is this far off
DOCS = REPO / "docs" / "range"

# Evaluates ``cubeloc pose`` of whichever tree is first on sys.path over the frames of an
# index; one JSON line per view. Only the API both trees share.
_EVALUATE = r"""
import importlib, json, sys
import cv2, numpy as np
cv2.setNumThreads(1)
prefix = sys.argv[2]  # how the tree names its modules (bench.common.package_prefix)
read_camera_info = importlib.import_module(prefix + "calib.camera_info").read_camera_info
TargetPoseProcessor = importlib.import_module(prefix + "positioning.single_frame").TargetPoseProcessor
make_cube = importlib.import_module(prefix + "positioning.target").make_cube
index = json.load(open(sys.argv[1]))
processors = {}
for view in index:
    lens = view["lens"]
    if lens not in processors:
        processors[lens] = TargetPoseProcessor(make_cube(), read_camera_info(view["calibration"]))
    processor = processors[lens]
    processor.reset()
    image = cv2.imread(view["image"], cv2.IMREAD_GRAYSCALE)
    result = processor.process(image, 0, 0)
    truth = np.array(view["T_world_camera"])[:3, 3]
    e = result.estimate
    out = {"status": result.status, "seen": list(result.tags_seen), "planes": e.planes if e else 0,
           "error_mm": float(np.linalg.norm(e.T_world_camera.translation - truth)) * 1000 if e else None,
           "sigma_mm": (float(np.sqrt(max(np.linalg.eigvalsh(e.covariance[:3, :3])))) * 1000
                        if e is not None and e.covariance is not None else None)}
    print(json.dumps(out), flush=True)
"""


def other_lens():
    """A second camera, unlike the paper's: other focal length, off-centre principal
    point, stronger barrel distortion with tangential terms."""
    from cubeloc.calib.camera_info import CameraCalibration

    k = np.array([[1400.0, 0.0, 655.3], [0.0, 1398.0, 497.8], [0.0, 0.0, 1.0]])
    d = np.array([-0.22, 0.09, 0.0008, -0.0006, -0.015])
    return CameraCalibration(1280, 1024, k, d, "plumb_bob", "bench-other-lens")


def views() -> list[dict]:
    from cubeloc.positioning.geometry import look_at

    rng = np.random.default_rng(16)
    out = []
    for lens in ("paper", "other"):
        for distance in DISTANCES:
            for elevation in ELEVATIONS:
                for azimuth in AZIMUTHS:
                    az = np.radians(azimuth + rng.uniform(-10, 10))
                    el = np.radians(elevation)
                    direction = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
                    aim = rng.uniform(-1, 1, 3) * 0.15 * distance / np.sqrt(3)
                    T = look_at(direction * distance, aim)
                    out.append({"lens": lens, "distance_m": distance, "elevation_deg": elevation,
                                "azimuth_deg": float(azimuth), "T_world_camera": T.matrix().tolist(),
                                "seed": len(out)})
    return out


def render_all(root: Path) -> list[dict]:
    """Render every view once into ``root`` (PNG), with an index; existing frames are kept."""
    import cv2

    from cubeloc.calib.camera_info import paper_camera, write_camera_info
    from cubeloc.fakes import Room, render_view
    from cubeloc.positioning.geometry import Transform

    root.mkdir(parents=True, exist_ok=True)
    lenses = {"paper": paper_camera(), "other": other_lens()}
    files = {}
    for name, calibration in lenses.items():
        files[name] = root / f"{name}.yaml"
        write_camera_info(files[name], calibration)
    # The default room is 10 m x 8 m x 3 m: too small for a camera 5 m out and 4 m up.
    room = Room(x_range=(-7.0, 7.0), y_range=(-7.0, 7.0), z_range=(-0.09, 6.0))
    index = []
    for view in views():
        path = root / f"{view['seed']:04d}.png"
        if not path.is_file():
            T = Transform.from_matrix(np.array(view["T_world_camera"]))
            image = render_view(T, calibration=lenses[view["lens"]], seed=view["seed"], room=room)
            cv2.imwrite(str(path), image)
        index.append({**view, "image": str(path), "calibration": str(files[view["lens"]])})
    (root / "index.json").write_text(json.dumps(index))
    return index


def baseline_pose(image: np.ndarray, calibration, detector, target) -> tuple[np.ndarray | None, int, set[int]]:
    """Plain AprilTag 3 (the detector's decimation, its own corners) + EPnP + LM on all the
    target's corners found: (camera position or None, planes, tag ids)."""
    import cv2

    from cubeloc.positioning.target_pose import count_planes, unique_target_detections

    ours = unique_target_detections(detector.detect(image), target)
    ids = tuple(d.tag_id for d in ours)
    if not ours:
        return None, 0, set()
    points = target.corners_of(ids)
    pixels = np.concatenate([d.corners for d in ours]).astype(np.float64)
    k, d = calibration.camera_matrix, calibration.distortion
    ok, rvec, tvec = cv2.solvePnP(points, pixels, k, d, flags=cv2.SOLVEPNP_EPNP)
    if not ok:
        return None, count_planes(target, ids), set(ids)
    rvec, tvec = cv2.solvePnPRefineLM(points, pixels, k, d, rvec.reshape(3, 1).copy(), tvec.reshape(3, 1).copy())
    rotation = cv2.Rodrigues(rvec)[0]
    position = -rotation.T @ tvec.reshape(3)
    return (position if np.all(np.isfinite(position)) else None), count_planes(target, ids), set(ids)


def _library_side(index: list[dict]) -> list[dict]:
    """The baseline's pose and the library's tags at decimate 1, 2 and 3, per view."""
    import cv2

    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.positioning.detection import DetectorOptions, TagDetector
    from cubeloc.positioning.target import make_cube
    from cubeloc.positioning.target_pose import unique_target_detections

    cube = make_cube()
    detector = TagDetector(cube.family, DetectorOptions())  # decimate 2, the paper's
    calibrations = {}
    out = []
    for view in index:
        if view["calibration"] not in calibrations:
            calibrations[view["calibration"]] = read_camera_info(view["calibration"])
        calibration = calibrations[view["calibration"]]
        image = cv2.imread(view["image"], cv2.IMREAD_GRAYSCALE)
        truth = np.array(view["T_world_camera"])[:3, 3]
        position, planes, _ = baseline_pose(image, calibration, detector, cube)
        tags = {str(k): sorted(d.tag_id for d in unique_target_detections(detector.detect(image, None, float(k)),
                                                                         cube)) for k in (1, 2, 3)}
        out.append({"baseline_mm": None if position is None else float(np.linalg.norm(position - truth)) * 1000,
                    "baseline_planes": planes, "tags": tags})
    return out


def _cubeloc_side(tree: Path, index_file: Path) -> list[dict]:
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", _EVALUATE, str(index_file), package_prefix(tree)], cwd=tree, env=env,
                          capture_output=True, text=True, check=True)
    return [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]


def evaluate(root: Path) -> list[dict]:
    """Every view with the baseline, the recall, and cubeloc new and previous."""
    index = render_all(root)
    index_file = root / "index.json"
    cached = root / "library.json"  # the library's side depends on the frames only
    if cached.is_file():
        library = json.loads(cached.read_text())
    else:
        library = _library_side(index)
        cached.write_text(json.dumps(library))
    new = _cubeloc_side(REPO, index_file)
    with tempfile.TemporaryDirectory(prefix="cubeloc-bench-range-") as tmp, \
            previous_tree(PREVIOUS_COMMIT, Path(tmp)) as tree:
        previous = _cubeloc_side(tree, index_file) if tree is not None else [None] * len(index)
    return [{**view, **lib, "new": n, "previous": p}
            for view, lib, n, p in zip(index, library, new, previous, strict=True)]


def _median(values: list[float]) -> str:
    return f"{np.median(values):.2f}" if values else "-"


def success_table(rows: list[dict]) -> str:
    """Per lens and distance: views, poses (baseline, previous, new), refusals the baseline's
    own error justifies, and median errors over the views where both have a pose."""
    table = []
    for lens in ("paper", "other"):
        for distance in DISTANCES:
            at = [r for r in rows if r["lens"] == lens and r["distance_m"] == distance]
            base = [r for r in at if r["baseline_mm"] is not None]
            new = [r for r in at if r["new"]["error_mm"] is not None]
            prev = [r for r in at if r["previous"] and r["previous"]["error_mm"] is not None]
            unjustified = [r for r in base if r["new"]["error_mm"] is None and r["baseline_mm"] <= JUSTIFIED_MM]
            both = [r for r in at if r["baseline_mm"] is not None and r["new"]["error_mm"] is not None]
            two = [r for r in at if r["baseline_planes"] == 2]
            table.append([lens, f"{distance:g}", len(at), len(base), len(prev), len(new), len(unjustified),
                          f"{sum(r['new']['error_mm'] is not None for r in two)}/{len(two)}",
                          _median([r["baseline_mm"] for r in both]), _median([r["new"]["error_mm"] for r in both]),
                          f"{max((r['new']['error_mm'] for r in new), default=0):.1f}"])
    return markdown_table(["lens", "distance m", "views", "baseline poses", "previous poses", "new poses",
                           "refused where the baseline is within 5 mm", "two-face views posed (new)",
                           "median error baseline mm", "median error new mm", "max error new mm"], table)


def recall_table(rows: list[dict]) -> str:
    """Share of the tags the library finds at decimate 1 that each search finds too."""
    table = []
    for lens in ("paper", "other"):
        for distance in DISTANCES:
            at = [r for r in rows if r["lens"] == lens and r["distance_m"] == distance]
            reference = sum(len(r["tags"]["1"]) for r in at)
            cells = [lens, f"{distance:g}", reference]
            for found in (lambda r: r["tags"]["2"], lambda r: r["tags"]["3"], lambda r: r["new"]["seen"]):
                hit = sum(len(set(found(r)) & set(r["tags"]["1"])) for r in at)
                cells.append(f"{100 * hit / max(reference, 1):.1f} %")
            missed = sum(len(set(r["tags"]["2"]) - set(r["new"]["seen"])) for r in at)
            cells.append(missed)
            table.append(cells)
    return markdown_table(["lens", "distance m", "tags at decimate 1", "decimate 2", "decimate 3",
                           "cubeloc's search", "found at decimate 2, not by cubeloc"], table)


def azimuth_table(rows: list[dict]) -> str:
    """Per distance and azimuth (both lenses, every elevation): poses new/baseline of the
    views, and the median errors new/baseline where both have one (mm)."""
    table = []
    for distance in DISTANCES:
        cells = [f"{distance:g}"]
        for azimuth in AZIMUTHS:
            at = [r for r in rows if r["distance_m"] == distance and r["azimuth_deg"] == azimuth]
            new = sum(r["new"]["error_mm"] is not None for r in at)
            base = sum(r["baseline_mm"] is not None for r in at)
            both = [r for r in at if r["baseline_mm"] is not None and r["new"]["error_mm"] is not None]
            cells.append(f"{new}/{base}: {_median([r['new']['error_mm'] for r in both])}/"
                         f"{_median([r['baseline_mm'] for r in both])}")
        table.append(cells)
    return markdown_table(["distance m \\ azimuth deg", *[str(a) for a in AZIMUTHS]], table)


def run() -> str:
    keep = os.environ.get("CUBELOC_BENCH_RANGE")
    with tempfile.TemporaryDirectory(prefix="cubeloc-bench-frames-") as tmp:
        rows = evaluate(Path(keep) if keep else Path(tmp))
    DOCS.mkdir(parents=True, exist_ok=True)
    text = (f"{len(rows)} views (two lenses x {len(DISTANCES)} distances x {len(ELEVATIONS)} elevations x "
            f"{len(AZIMUTHS)} azimuths), one frame each. Previous: commit {PREVIOUS_COMMIT}.\n\n"
            + success_table(rows) + "\nDetection recall (the target's tags):\n\n" + recall_table(rows))
    (DOCS / "range.md").write_text(
        "# Effective range of the single-frame pose (the paper's Fig. 8)\n\n" + (__doc__ or "").split("\n\n", 1)[1]
        + "\n" + text + "\nPer distance and azimuth, both lenses and every elevation together: poses "
        "new/baseline, then median error new/baseline (mm) over the views where both have a pose:\n\n"
        + azimuth_table(rows))
    return text


if __name__ == "__main__":
    print(run())
