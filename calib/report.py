"""What a calibration is worth: a verdict with its reasons, a text report and a PNG.

The verdict looks beyond the RMS (after mrcal): a low RMS from views that never tilt
the board still leaves the focal length loose, which the standard deviations show.
The PNG has three panels drawn with matplotlib, axes labelled: residual arrows where they
occur in the image (with the 3 x 3 coverage cells), all residuals as a scatter, and
per-view RMS.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import cv2
import numpy as np

from cubeloc.calib.solve import Solution, parameter_names

# thresholds of the verdict; "good" must pass all of them
GOOD_RMS_PX, POOR_RMS_PX = 0.5, 1.0
GOOD_FOCAL_REL, POOR_FOCAL_REL = 0.003, 0.01  # relative std dev of fx, fy
GOOD_CENTRE_PX, POOR_CENTRE_PX = 2.0, 6.0  # std dev of cx, cy
GOOD_VIEWS = 10


@dataclass(frozen=True)
class Verdict:
    grade: str  # "good", "usable" or "poor"
    reasons: tuple[str, ...]  # empty for "good"

    @property
    def text(self) -> str:
        return self.grade + (": " + "; ".join(self.reasons) if self.reasons else "")


def judge(solution: Solution) -> Verdict:
    """Grade a solution and say what to add or check to make it better."""
    reasons: list[tuple[int, str]] = []  # (severity 1 usable / 2 poor, reason)
    if solution.rms_px > GOOD_RMS_PX:
        severity = 2 if solution.rms_px > POOR_RMS_PX else 1
        reasons.append((severity, f"RMS {solution.rms_px:.2f} px is high - check the board is flat and its spec sizes, and focus"))
    k = solution.camera_matrix
    for name, value in (("fx", k[0, 0]), ("fy", k[1, 1])):
        relative = solution.std.get(name, 0.0) / value
        if relative > GOOD_FOCAL_REL:
            severity = 2 if relative > POOR_FOCAL_REL else 1
            reasons.append((severity, f"{name} uncertain to {100 * relative:.1f}% - add tilted views"))
    centre = max(solution.std.get("cx", 0.0), solution.std.get("cy", 0.0))
    if centre > GOOD_CENTRE_PX:
        severity = 2 if centre > POOR_CENTRE_PX else 1
        reasons.append((severity, f"principal point uncertain to {centre:.1f} px - add views near the image corners, tilted"))
    if len(solution.views) < GOOD_VIEWS:
        reasons.append((1, f"only {len(solution.views)} views - {GOOD_VIEWS} or more give reliable uncertainties"))
    if not reasons:
        return Verdict("good", ())
    grade = "poor" if max(s for s, _ in reasons) == 2 else "usable"
    return Verdict(grade, tuple(r for _, r in sorted(reasons, key=lambda sr: -sr[0])))


def format_report(solution: Solution, verdict: Verdict, skipped: list[tuple[str, str]] = ()) -> list[str]:
    """The report as lines of text (the CLI prints them; tests read them)."""
    k, d = solution.camera_matrix, solution.distortion
    std = solution.std
    lines = [
        f"views {len(solution.views)}, corners {solution.points}, model {solution.model}, RMS {solution.rms_px:.3f} px",
        f"fx {k[0, 0]:.2f} +/- {std.get('fx', 0):.2f}   fy {k[1, 1]:.2f} +/- {std.get('fy', 0):.2f}   "
        f"cx {k[0, 2]:.2f} +/- {std.get('cx', 0):.2f}   cy {k[1, 2]:.2f} +/- {std.get('cy', 0):.2f}",
        "distortion " + "  ".join(
            f"{name} {value:+.5f} +/- {std.get(name, 0):.5f}"
            for name, value in zip(parameter_names(solution.model)[4:], d, strict=False)
        ),
        "per-view RMS px: " + ", ".join(f"{v.name} {v.rms_px:.2f}" for v in solution.views),
    ]
    lines += [f"dropped {v.name}: {v.reason}" for v in solution.dropped]
    lines += [f"skipped {name}: {reason}" for name, reason in skipped]
    lines.append(f"verdict: {verdict.text}")
    return lines


def render_report(solution: Solution) -> np.ndarray:
    """A BGR image (matplotlib, labelled axes): the residuals as arrows where they occur in
    the image with the 3 x 3 coverage cells; all residuals as a scatter with the RMS circle;
    the RMS of each view (dropped views in red)."""
    import matplotlib

    matplotlib.use("Agg")  # no display on a robot or in CI
    from matplotlib.figure import Figure

    width, height = solution.image_size
    all_points = np.concatenate([v.image_points for v in solution.views])
    all_residuals = np.concatenate([v.residuals for v in solution.views])
    reach = max(float(np.percentile(np.linalg.norm(all_residuals, axis=1), 99)), 1e-3)
    figure = Figure(figsize=(13, 5), dpi=100, layout="constrained")
    image_axes, scatter, bars = figure.subplots(1, 3, width_ratios=(1.6, 1, 1.2))
    # the 99th percentile residual draws 4 % of the image width long
    gain = 0.04 * width / reach
    image_axes.quiver(all_points[:, 0], all_points[:, 1], all_residuals[:, 0] * gain, all_residuals[:, 1] * gain,
                      angles="xy", scale_units="xy", scale=1, color="tab:red", width=0.002)
    image_axes.scatter(all_points[:, 0], all_points[:, 1], s=1, color="0.6")
    for i in (1, 2):
        image_axes.axvline(width * i / 3, color="0.8", linewidth=0.8)
        image_axes.axhline(height * i / 3, color="0.8", linewidth=0.8)
    image_axes.set_xlim(0, width)
    image_axes.set_ylim(height, 0)  # image rows go down
    image_axes.set_aspect("equal")
    image_axes.set_xlabel("x (px)")
    image_axes.set_ylabel("y (px)")
    image_axes.set_title(f"residuals x{gain:.0f} over the image ({width}x{height}), 3x3 cells")
    limit = 1.2 * reach
    scatter.scatter(all_residuals[:, 0], all_residuals[:, 1], s=2, color="tab:blue", alpha=0.5)
    circle = np.linspace(0, 2 * np.pi, 100)
    scatter.plot(solution.rms_px * np.cos(circle), solution.rms_px * np.sin(circle), color="tab:green",
                 label=f"RMS {solution.rms_px:.3f} px")
    scatter.set_xlim(-limit, limit)
    scatter.set_ylim(limit, -limit)
    scatter.set_aspect("equal")
    scatter.set_xlabel("residual x (px)")
    scatter.set_ylabel("residual y (px)")
    scatter.set_title("every residual")
    scatter.legend(loc="upper right", fontsize=8)
    scatter.grid(True, alpha=0.3)
    entries = [(v.name, v.rms_px, False) for v in solution.views] + [(v.name, v.rms_px, True) for v in solution.dropped]
    bars.bar(range(len(entries)), [e[1] for e in entries],
             color=["tab:red" if dropped else "tab:blue" for _, _, dropped in entries])
    bars.set_xlabel("view (in order; red: dropped)")
    bars.set_ylabel("RMS (px)")
    bars.set_title("per-view RMS")
    bars.grid(True, axis="y", alpha=0.3)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    return cv2.imdecode(np.frombuffer(buffer.getvalue(), np.uint8), cv2.IMREAD_COLOR)
