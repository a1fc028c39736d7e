"""Is the target pose's covariance honest when every edge is biased? ``cubeloc pose`` on
the range map's views of the cube (``bench.range.views``: 1-5 m, elevations 0-60 deg,
every azimuth, the paper's lens and another), rendered twice:

- **biased**: a defocus of 0 or 0.8 px, then a response curve ``255 (I / 255) ** gamma``
  with gamma 0.8 or 1.25 (drawn per view, seeded). A blurred edge through a gamma other
  than 1 is found off its true place (below 1 the white side grows), every edge of the
  image alike: a bias the profiles' own noise does not show, as a real camera's response,
  ink spread and a lens model's residual give. Its size is measured on each view: the
  median offset of the edge profiles from the edges projected with the *true* pose
  (0.03-0.1 px, the trusted-pose issue's range);
- **linear**: the same views with gamma 1 and the same defocus.

Per view: the position error against the truth, the claimed standard deviation, and the
NEES (3 dof: honest poses have a median of 2.37 and 99.7 % within 14.16). The goal: at least
97 % of two- and three-face poses inside their 99.7 % ellipsoid on the biased renders, and
the median NEES within 1.5 times its expected value (1.58-3.55).

``python -m bench target_nees`` (docs/benchmarks.md); ``CUBELOC_BENCH_NEES_VIEWS=N`` takes
every view whose index is a multiple of 480 / N (a quick look).
"""

from __future__ import annotations

import os

import numpy as np

from bench.common import markdown_table
from cubeloc.positioning.evaluation import CHI2_3DOF_997

TITLE = "Target covariance under a systematic edge bias (range map views)"
GAMMAS = (0.8, 1.25)
BLURS_PX = (0.0, 0.8)
EXPECTED_MEDIAN_NEES = 2.37  # of a chi-square with 3 degrees of freedom


def edge_shift_px(image: np.ndarray, truth, calibration, tag_ids: tuple[int, ...]) -> float | None:
    """The median offset (pixels, towards the white side) of the image's edge profiles from
    the cube's edges projected with the true pose: the bias every edge shares."""
    from cubeloc.positioning.edge_alignment import edge_model, measure_edges
    from cubeloc.positioning.target import make_cube

    if not tag_ids:
        return None
    T_camera_world = truth.inverse()
    measured = measure_edges(image, edge_model(make_cube(), tuple(tag_ids), 4), T_camera_world.rotation,
                        T_camera_world.translation, calibration)
    return None if measured is None else float(np.median(measured[0]))


def measure(views: list[dict]) -> list[dict]:
    """One row per view and rendering: condition, planes, error and claimed sigma (mm), NEES
    (None: no pose), the measured edge shift (px)."""
    from bench.range import other_lens
    from cubeloc.calib.camera_info import paper_camera
    from cubeloc.fakes import Room, render_view
    from cubeloc.positioning.geometry import Transform
    from cubeloc.positioning.single_frame import TargetPoseProcessor
    from cubeloc.positioning.target import make_cube

    lenses = {"paper": paper_camera(), "other": other_lens()}
    room = Room(x_range=(-7.0, 7.0), y_range=(-7.0, 7.0), z_range=(-0.09, 6.0))  # as bench.range's
    rows = []
    for view in views:
        rng = np.random.default_rng(view["seed"])
        gamma, blur = float(rng.choice(GAMMAS)), float(rng.choice(BLURS_PX))
        truth = Transform.from_matrix(np.array(view["T_world_camera"]))
        calibration = lenses[view["lens"]]
        for condition, g in (("biased", gamma), ("linear", 1.0)):
            image = render_view(truth, calibration=calibration, seed=view["seed"], room=room, blur_sigma_px=blur,
                                response_gamma=g)
            result = TargetPoseProcessor(make_cube(), calibration).process(image, 1, 0)
            row = {"condition": condition, "gamma": g, "blur": blur, "distance_m": view["distance_m"],
                   "planes": 0, "nees": None}
            estimate = result.estimate
            if estimate is not None and estimate.covariance is not None:
                error = estimate.T_world_camera.translation - truth.translation
                covariance = estimate.covariance[:3, :3]
                row.update(planes=estimate.planes, error_mm=1000 * float(np.linalg.norm(error)),
                           sigma_mm=1000 * float(np.sqrt(np.trace(covariance))),
                           nees=float(error @ np.linalg.solve(covariance, error)),
                           shift_px=edge_shift_px(image, truth, calibration, estimate.tag_ids))
            rows.append(row)
    return rows


def summary(rows: list[dict]) -> str:
    header = ["renders", "faces", "poses", "NEES median", "inside 99.7 %", "error median mm",
              "claimed sigma median mm", "edge shift px (median, 10-90 %)"]
    table = []
    for condition in ("biased", "linear"):
        for planes in (2, 3):
            chosen = [r for r in rows if r["condition"] == condition and r["planes"] == planes]
            if not chosen:
                continue
            nees = np.array([r["nees"] for r in chosen])
            shifts = np.abs([r["shift_px"] for r in chosen if r["shift_px"] is not None])
            table.append([condition, str(planes), str(len(chosen)), f"{np.median(nees):.2f}",
                          f"{100 * np.mean(nees <= CHI2_3DOF_997):.1f} %",
                          f"{np.median([r['error_mm'] for r in chosen]):.2f}",
                          f"{np.median([r['sigma_mm'] for r in chosen]):.2f}",
                          f"{np.median(shifts):.3f} ({np.percentile(shifts, 10):.3f}-{np.percentile(shifts, 90):.3f})"])
    return markdown_table(header, table)


def run() -> str:
    from bench.range import views

    every = views()
    wanted = int(os.environ.get("CUBELOC_BENCH_NEES_VIEWS", len(every)))
    chosen = every[:: max(len(every) // max(wanted, 1), 1)]
    body = summary(measure(chosen))
    return (f"{len(chosen)} views of the range map, each rendered biased (gamma 0.8 or 1.25, defocus 0 or 0.8 px) "
            f"and linear (gamma 1, the same defocus); NEES of the position (3 dof), goal: at least 97 % inside "
            f"99.7 % ({CHI2_3DOF_997}) and the median within 1.5 times {EXPECTED_MEDIAN_NEES} on the biased renders. "
            f"`python -m bench target_nees`.\n\n{body}\n")


if __name__ == "__main__":
    print(run())
