"""Cameras other than the paper's, for checking that nothing is tuned to its lens: 640
pixels wide (each is cheap to render and track), the cube's model and nothing else
shared with it.

=========  =============================================================================
``wide``    640x512, f 450 px (HFOV 71 deg), strong barrel distortion (k1 -0.25, k2 0.08)
``narrow``  640x512, f 1250 px (HFOV 29 deg), mild barrel (k1 -0.03)
``vga``     640x480, f 600 px (HFOV 56 deg), principal point 11 px right and 8 px up of
            the centre, barrel and a little tangential distortion
``fisheye`` 640x480, f 280 px (HFOV 131 deg, 82 deg off-axis in the corners): a small
            fisheye camera (the T265 or TUM-VI class), the equidistant (Kannala-Brandt)
            model with TUM-VI cam0's coefficients
``fisheye_hd`` the same lens's field on a 1280x1024 sensor (f 560 px, 84 deg off-axis in
            the corners): the paper's camera body with a fisheye lens
=========  =============================================================================

``paper_half`` is the paper's camera at 640x512 (f 833 px, HFOV 42 deg): the tracker
tests' camera, for side-by-side rows; ``OTHER_LENSES`` are the five above. ``euroc`` is
the EuRoC MAV dataset's cam0 (752x480, f 458 px, its published plumb_bob calibration),
whose real AprilGrid frame is in ``../shared/data/aprilgrid-real``.
"""

from __future__ import annotations

import numpy as np

from cubeloc.calib.camera_info import CameraCalibration, paper_camera

_PAPER = paper_camera()  # paper_half is it at 640x512

# name: (width, height, f px, principal point, distortion (plumb_bob, or equidistant when
# it has 4 coefficients), what it stands for)
LENSES: dict[str, tuple[int, int, float, tuple[float, float], tuple[float, ...], str]] = {
    "wide": (640, 512, 450.0, (319.5, 255.5), (-0.25, 0.08, 0.0, 0.0, 0.0), "HFOV 71 deg, strong barrel"),
    "narrow": (640, 512, 1250.0, (319.5, 255.5), (-0.03, 0.0, 0.0, 0.0, 0.0), "HFOV 29 deg"),
    "vga": (640, 480, 600.0, (331.0, 247.0), (-0.12, 0.03, 0.001, -0.0005, 0.0), "HFOV 56 deg, centre off"),
    "euroc": (752, 480, 458.654, (367.215, 248.375), (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0),
              "EuRoC MAV cam0, HFOV 79 deg"),
    "fisheye": (640, 480, 280.0, (322.5, 238.0), (0.0034823894, 0.0007150348, -0.0020532361, 0.0002029069),
                "HFOV 131 deg, fisheye"),
    "fisheye_hd": (1280, 1024, 560.0, (641.5, 510.0), (0.0034823894, 0.0007150348, -0.0020532361, 0.0002029069),
                   "HFOV 131 deg, fisheye, 1.3 MP"),
    "paper_half": (640, 512, _PAPER.camera_matrix[0, 0] / 2.0, (319.5, 255.5), tuple(_PAPER.distortion),
                   "the paper's camera at half resolution"),
}
OTHER_LENSES = ("wide", "narrow", "vga", "fisheye", "fisheye_hd")


def lens_calibration(name: str) -> CameraCalibration:
    """The calibration of lens ``name`` (one of ``LENSES``)."""
    width, height, f, (cx, cy), distortion, _ = LENSES[name]
    k = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    model = "equidistant" if len(distortion) == 4 else "plumb_bob"
    return CameraCalibration(width, height, k, np.array(distortion), model, name)
