"""Tag detection: real photographs with reference corners, corner order, ROI, lifecycle."""

from __future__ import annotations

import re
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import real_photographs

from cubeloc.positioning.detection import LIBRARY_TO_UPRIGHT, DetectorOptions, TagDetector

REPO = Path(__file__).resolve().parents[1]


def reference_detections(path):
    """[(id, (4, 2) corners)] in the C library's order and (0.5, 0.5) pixel convention."""
    rows = []
    for line in path.read_text().splitlines():
        numbers = [float(x) for x in re.findall(r"-?\d+(?:\.\d+)?", line)]
        rows.append((int(numbers[0]), np.array(numbers[1:9]).reshape(4, 2)))
    return rows


def test_real_photos_match_the_reference_corners_after_the_convention_change():
    # The reference was made with quad_decimate 1 and no edge refinement.
    detector = TagDetector("tag36h11", DetectorOptions(quad_decimate=1.0, refine_edges=False, max_hamming=2,
                                                       min_decision_margin=0.0))
    matched = total = 0
    for photo in sorted(real_photographs("apriltag-real").glob("*.jpg")):
        image = cv2.imread(str(photo), cv2.IMREAD_GRAYSCALE)
        found = detector.detect(image)
        for tag_id, library_corners in reference_detections(photo.with_suffix(".txt")):
            total += 1
            expected = library_corners[LIBRARY_TO_UPRIGHT] - 0.5  # our order, OpenCV pixels
            errors = [np.abs(d.corners - expected).max() for d in found if d.tag_id == tag_id]
            matched += bool(errors) and min(errors) <= 0.1
    assert total == 47
    assert matched >= 46


def marker_scene(tag_id: int, rotations: int) -> tuple[np.ndarray, np.ndarray]:
    """An upright cv2.aruco marker on white, rotated by 90 deg steps, and its TL TR BR BL
    outer corners in OpenCV pixels (pixel edges sit at half-integers)."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    marker = cv2.aruco.generateImageMarker(dictionary, tag_id, 160)
    image = np.full((300, 300), 255, np.uint8)
    image[60:220, 80:240] = marker
    corners = np.array([[79.5, 59.5], [239.5, 59.5], [239.5, 219.5], [79.5, 219.5]])
    for _ in range(rotations):  # np.rot90 turns counter-clockwise: (x, y) -> (y, W-1-x)
        image = np.rot90(image)
        corners = np.column_stack([corners[:, 1], 299 - corners[:, 0]])
    return np.ascontiguousarray(image), corners


@pytest.mark.parametrize("rotations", [0, 1, 2, 3])
def test_corner_order_is_tl_tr_br_bl_as_printed(rotations):
    detector = TagDetector()
    for tag_id in (0, 5, 17):
        image, expected = marker_scene(tag_id, rotations)
        (found,) = detector.detect(image)
        assert found.tag_id == tag_id
        # Same order and within a fraction of a pixel: the (0.5, 0.5) shift is gone.
        assert np.abs(found.corners - expected).max() < 0.3
        # Handedness: TL -> TR -> BR turns clockwise on screen (y down), as printed.
        (e1x, e1y), (e2x, e2y) = np.diff(found.corners[:3], axis=0)
        assert e1x * e2y - e1y * e2x > 0


def test_region_search_returns_full_image_pixels():
    detector = TagDetector()
    image, _ = marker_scene(9, 0)
    full = detector.detect(image)[0]
    inside = detector.detect(image, roi=(50, 30, 270, 250))[0]
    assert np.abs(full.corners - inside.corners).max() < 0.05
    assert detector.detect(image, roi=(0, 0, 60, 60)) == []
    assert detector.detect(image, roi=(-20, -20, 2000, 2000))[0].tag_id == 9


def test_a_blurred_search_leaves_the_callers_image_as_it_was():
    """Undecimated with a blur (or a sharpening), the AprilTag library works on the buffer
    it is given in place; the detector hands it a copy, so the same image searched again,
    or by the next stage, is the camera's."""
    detector = TagDetector()
    image, _ = marker_scene(4, 0)
    image = cv2.add(image, np.random.default_rng(0).integers(0, 30, image.shape, dtype=np.uint8))
    before = image.copy()
    for decimate, sigma in ((1.0, 0.8), (1.0, -0.8), (2.0, 0.8)):
        assert [d.tag_id for d in detector.detect(image, None, decimate, sigma)] == [4]
        assert np.array_equal(image, before), (decimate, sigma)
    assert [d.tag_id for d in detector.detect(image, (40, 20, 280, 260), 1.0, 0.8)] == [4]  # (a crop is a copy)
    assert np.array_equal(image, before)


def test_rejects_images_it_cannot_read():
    detector = TagDetector()
    with pytest.raises(ValueError, match="uint8"):
        detector.detect(np.zeros((10, 10), np.uint16))
    with pytest.raises(ValueError, match="family"):
        TagDetector("tag99h1")


def test_many_detectors_created_and_collected_do_not_crash():
    # A binding was seen to segfault when a detector was collected while a second one was
    # alive; run the lifecycle in a child so a crash fails this test instead of pytest.
    script = textwrap.dedent(
        """
        import gc
        import numpy as np
        from cubeloc.positioning.detection import TagDetector
        import cv2
        dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
        image = np.full((300, 300), 255, np.uint8)
        image[60:220, 80:240] = cv2.aruco.generateImageMarker(dictionary, 3, 160)
        keeper = TagDetector()
        for _ in range(30):
            first = TagDetector()
            second = TagDetector()
            assert first.detect(image)[0].tag_id == 3
            del first
            gc.collect()
            assert second.detect(image)[0].tag_id == 3
            second.close()
            del second
        assert keeper.detect(image)[0].tag_id == 3
        print("survived")
        """
    )
    result = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "survived" in result.stdout
