"""What a calibration is worth: a verdict with its reasons, a text report and a PNG.

The verdict looks beyond the RMS (after mrcal): a low RMS from views that never tilt
the board still leaves the focal length loose, which the standard deviations show.
The PNG has three panels drawn with OpenCV: residual arrows where they occur in the
image (with the 3 x 3 coverage cells), all residuals as a scatter, and per-view RMS.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calib.solve import Solution

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
            for name, value in zip(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"), d, strict=False)
        ),
        "per-view RMS px: " + ", ".join(f"{v.name} {v.rms_px:.2f}" for v in solution.views),
    ]
    lines += [f"dropped {v.name}: {v.reason}" for v in solution.dropped]
    lines += [f"skipped {name}: {reason}" for name, reason in skipped]
    lines.append(f"verdict: {verdict.text}")
    return lines


def _draw_text(canvas: np.ndarray, text: str, origin: tuple[int, int], scale: float = 0.45, color=(40, 40, 40)) -> None:
    cv2.putText(canvas, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, color, 1, cv2.LINE_AA)


def render_report(solution: Solution, panel_width: int = 640) -> np.ndarray:
    """A BGR image: residual arrows over the image frame, residual scatter, per-view RMS."""
    width, height = solution.image_size
    scale = panel_width / width
    panel_height = int(round(height * scale))
    top = 40
    canvas = np.full((panel_height + top + 30, panel_width * 2 + 30, 3), 255, np.uint8)
    all_residuals = np.concatenate([v.residuals for v in solution.views])
    magnitudes = np.linalg.norm(all_residuals, axis=1)
    reach = max(float(np.percentile(magnitudes, 99)), 1e-3)
    arrow_gain = 25.0 / reach  # the 99th percentile residual draws 25 px long

    # panel 1: where the points are, their residuals, and the 3 x 3 coverage cells
    x0, y0 = 10, top
    cv2.rectangle(canvas, (x0, y0), (x0 + panel_width, y0 + panel_height), (0, 0, 0), 1)
    for i in (1, 2):
        cv2.line(canvas, (x0 + panel_width * i // 3, y0), (x0 + panel_width * i // 3, y0 + panel_height), (200, 200, 200), 1)
        cv2.line(canvas, (x0, y0 + panel_height * i // 3), (x0 + panel_width, y0 + panel_height * i // 3), (200, 200, 200), 1)
    for view in solution.views:
        for (u, v), (du, dv) in zip(view.image_points, view.residuals, strict=True):
            start = (int(x0 + u * scale), int(y0 + v * scale))
            end = (int(start[0] + du * arrow_gain), int(start[1] + dv * arrow_gain))
            cv2.circle(canvas, start, 1, (150, 150, 150), -1)
            cv2.line(canvas, start, end, (30, 30, 200), 1, cv2.LINE_AA)
    _draw_text(canvas, f"residuals x{arrow_gain:.0f} over the image ({width}x{height}); RMS {solution.rms_px:.3f} px", (x0, 25))

    # panel 2 (upper half): scatter of all residuals; (lower half): per-view RMS bars
    x1 = x0 + panel_width + 10
    half = panel_height // 2 - 10
    centre = (x1 + panel_width // 2, y0 + half // 2)
    scatter_gain = (half / 2 - 5) / (1.2 * reach)
    cv2.rectangle(canvas, (x1, y0), (x1 + panel_width, y0 + half), (0, 0, 0), 1)
    cv2.circle(canvas, centre, int(solution.rms_px * scatter_gain), (0, 160, 0), 1, cv2.LINE_AA)
    for du, dv in all_residuals:
        cv2.circle(canvas, (int(centre[0] + du * scatter_gain), int(centre[1] + dv * scatter_gain)), 1, (200, 80, 30), -1)
    _draw_text(canvas, f"residual scatter, +/-{1.2 * reach:.2f} px; green: RMS", (x1 + 5, y0 + 15))
    bars_top = y0 + half + 20
    bars_height = panel_height - half - 20
    cv2.rectangle(canvas, (x1, bars_top), (x1 + panel_width, bars_top + bars_height), (0, 0, 0), 1)
    entries = [(v.name, v.rms_px, False) for v in solution.views] + [(v.name, v.rms_px, True) for v in solution.dropped]
    top_value = max(e[1] for e in entries) * 1.1
    bar_width = max(1, (panel_width - 10) // len(entries))
    for i, (_, value, dropped) in enumerate(entries):
        bar = int(value / top_value * (bars_height - 20))
        left = x1 + 5 + i * bar_width
        color = (40, 40, 220) if dropped else (160, 110, 40)
        cv2.rectangle(canvas, (left, bars_top + bars_height - bar), (left + bar_width - 2, bars_top + bars_height), color, -1)
    _draw_text(canvas, f"per-view RMS (max {top_value / 1.1:.2f} px); red: dropped", (x1 + 5, bars_top + 15))
    return canvas
