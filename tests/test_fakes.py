"""The synthetic camera's renderer: exact geometry, tag conventions, effects, determinism."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cubeloc.calib.camera_info import CameraCalibration, paper_camera
from cubeloc.fakes import Box, Room, render_view
from cubeloc.fakes.accuracy import measure_tag_corners
from cubeloc.fakes.optics import project, undistort_pixels
from cubeloc.fakes.render import pixel_rays, subpixel_offsets
from cubeloc.positioning.geometry import look_at
from cubeloc.positioning.target import Tag, Target, make_cube

CUBE = make_cube()
PAPER = paper_camera()
PINHOLE = CameraCalibration(PAPER.width, PAPER.height, PAPER.camera_matrix, np.zeros(5))


def detect(image: np.ndarray) -> dict[int, np.ndarray]:
    """tag36h11 detections with OpenCV's aruco: id -> (4, 2) corners."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    corners, ids, _ = cv2.aruco.ArucoDetector(dictionary).detectMarkers(image)
    return {} if ids is None else {int(i): c.reshape(4, 2) for i, c in zip(ids.ravel(), corners, strict=True)}


def three_face_poses(count: int, seed: int) -> list:
    """Cameras above the +x/-y corner of the cube at 0.9-1.7 m, aimed near the cube, so
    tags land anywhere from the centre to the edge of the image."""
    rng = np.random.default_rng(seed)
    poses = []
    for _ in range(count):
        azimuth = np.radians(rng.uniform(-75, -15))
        distance = rng.uniform(0.9, 1.7)
        position = distance * np.array([np.cos(azimuth), np.sin(azimuth), 0.0]) + [0, 0, rng.uniform(0.35, 0.8)]
        poses.append(look_at(position, rng.uniform(-0.2, 0.2, 3)))
    return poses


@pytest.mark.parametrize("calibration", [PAPER, PINHOLE], ids=["distortion", "pinhole"])
def test_tag_corners_land_where_the_projection_says(calibration):
    errors = []
    for pose in three_face_poses(4, seed=11):
        image = render_view(pose, calibration=calibration, noise_sigma=0.0, supersample=5)
        measured = measure_tag_corners(image, pose, calibration, CUBE)
        errors.append(measured.errors_px)
    errors = np.concatenate(errors)
    rms = float(np.sqrt(np.mean(errors**2)))
    print(f"corner error over {errors.size} corners: max {errors.max():.4f} px, RMS {rms:.4f} px")
    assert errors.size >= 32  # most tags were measurable, not skipped
    assert errors.max() < 0.05
    assert rms < 0.025


def test_corner_measurement_sees_a_shifted_camera():
    """The proof can fail: a camera 0.1 px off in cx shows up as a ~0.1 px corner error."""
    pose = three_face_poses(1, seed=4)[0]
    image = render_view(pose, noise_sigma=0.0, supersample=5)
    k = PAPER.camera_matrix.copy()
    k[0, 2] += 0.1
    wrong = CameraCalibration(PAPER.width, PAPER.height, k, PAPER.distortion)
    errors = measure_tag_corners(image, pose, wrong, CUBE).errors_px
    assert np.all(np.abs(errors - 0.1) < 0.04)


def test_subpixel_rays_match_the_exact_inverse_distortion():
    s = 5
    us, vs = np.array([0, 640, 1279, 3]), np.array([0, 512, 1023, 1020])
    x, y = pixel_rays(PAPER, us, vs, s)
    ox, oy = subpixel_offsets(s)
    assert abs(ox.mean()) < 1e-7 and abs(oy.mean()) < 1e-7  # samples centred on the pixel
    assert len(np.unique(ox)) == s * s and len(np.unique(oy)) == s * s  # n-rooks
    positions = np.column_stack([(us[:, None] + ox.ravel()).ravel(), (vs[:, None] + oy.ravel()).ravel()])
    exact = undistort_pixels(positions, PAPER)
    error_px = np.hypot(x.ravel() - exact[:, 0], y.ravel() - exact[:, 1]) * PAPER.fx
    assert error_px.max() < 1e-3


def test_tags_decode_with_the_documented_ids_and_corner_order():
    pose = look_at(np.array([1.3, -1.3, 0.9]), np.zeros(3))
    image = render_view(pose, seed=1)
    found = detect(image)
    assert set(found) == {0, 3, 4}  # +x, -y and top faces
    truth = {i: project(pose.inverse().apply(CUBE.tag(i).corners), PAPER) for i in found}
    for tag_id, corners in found.items():
        # aruco's corners are rough (a few px) but in the same order, TL, TR, BR, BL: any
        # other order would put them a tag's side (~100 px) away
        assert np.abs(corners - truth[tag_id]).max() < 4.0


def test_hidden_and_glare_tags_are_not_readable_the_rest_are():
    pose = look_at(np.array([1.3, -1.3, 0.9]), np.zeros(3))
    assert set(detect(render_view(pose, hidden_tags=(3,), seed=2))) == {0, 4}
    assert set(detect(render_view(pose, hidden_tags=(3, 4), seed=2))) == {0}
    glare = render_view(pose, glare_tag=4, seed=2)
    assert set(detect(glare)) == {0, 3}
    top = project(pose.inverse().apply(CUBE.tag(4).center[None]), PAPER)[0].round().astype(int)
    assert glare[top[1], top[0]] == 255  # over-exposed


def test_same_seed_same_frame_different_seed_different_noise():
    pose = look_at(np.array([1.2, -1.4, 0.8]), np.zeros(3))
    a = render_view(pose, seed=7)
    assert np.array_equal(a, render_view(pose, seed=7))
    b = render_view(pose, seed=8)
    assert not np.array_equal(a, b)
    noise = a.astype(float) - b.astype(float)
    assert 1.5 < noise.std() / np.sqrt(2) < 2.5  # the 2 DN read noise, nothing else changed
    room_b = render_view(pose, seed=7, room=Room(seed=1))
    assert np.mean(np.abs(room_b.astype(float) - a)) > 20  # another room texture


def test_effects_blur_gain_and_noise_change_the_image_as_asked():
    pose = look_at(np.array([1.2, -1.4, 0.8]), np.zeros(3))
    clean = render_view(pose, noise_sigma=0.0).astype(float)
    brighter = render_view(pose, noise_sigma=0.0, exposure_gain=1.5).astype(float)
    unsaturated = (clean > 10) & (brighter < 250)
    assert np.median(brighter[unsaturated] / clean[unsaturated]) == pytest.approx(1.5, abs=0.02)

    def sharpness(image):
        return cv2.Laplacian(image, cv2.CV_64F).var()

    blurred = render_view(pose, noise_sigma=0.0, blur_sigma_px=2.0).astype(float)
    moved = render_view(pose, noise_sigma=0.0, motion_blur_px=9.0).astype(float)
    assert sharpness(blurred) < 0.3 * sharpness(clean)
    assert sharpness(moved) < 0.6 * sharpness(clean)
    # horizontal motion blur smears along x: vertical gradients survive better
    gx, gy = np.abs(np.diff(moved, axis=1)).mean(), np.abs(np.diff(moved, axis=0)).mean()
    assert gx < 0.8 * gy


def test_surfaces_behind_the_camera_are_clipped_not_wrapped():
    """A box beside the camera, reaching 1.5 m behind it: only its part in front is drawn,
    exactly where the clipped face projects; nothing of the part behind wraps round."""
    pose = look_at(np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 1.0]))  # looking along +x
    room = Room(boxes=(Box(center=(0.0, 0.45, 1.0), size=(3.0, 0.3, 1.0), seed=3),))
    drawn = render_view(pose, room=room, noise_sigma=0.0) != render_view(pose, noise_sigma=0.0)
    # the face y = 0.3 in front of the camera (from x = 0.3: nearer is outside the view)
    steps = np.linspace(0, 1, 200)[:, None]
    corners = np.array([[0.3, 0.3, 0.5], [1.5, 0.3, 0.5], [1.5, 0.3, 1.5], [0.3, 0.3, 1.5]])
    outline = np.concatenate([a + steps * (b - a) for a, b in zip(corners, np.roll(corners, -1, axis=0), strict=True)])
    pixels = project(pose.inverse().apply(outline), PAPER)
    expected = np.zeros(drawn.shape, np.uint8)
    cv2.fillPoly(expected, [np.round(pixels * 16).astype(np.int32)], 1, cv2.LINE_8, 4)
    kernel = np.ones((5, 5), np.uint8)
    surely_inside = cv2.erode(expected, kernel).astype(bool)
    surely_outside = ~cv2.dilate(expected, kernel).astype(bool)
    assert surely_inside.sum() > 50_000  # the face fills a good part of the view
    assert drawn[surely_inside].mean() > 0.97  # (a box texel may equal the wall behind)
    assert not drawn[surely_outside].any()


def test_back_faces_are_not_drawn_and_nearer_surfaces_cover_farther():
    # a single tag plate facing -x (right = -y, down = -z), seen from behind: nothing drawn
    corners = np.array([[0.0, 0.1, 0.1], [0.0, -0.1, 0.1], [0.0, -0.1, -0.1], [0.0, 0.1, -0.1]])
    plate = Target("tag36h11", (Tag(7, corners),))
    far_away = Target("tag36h11", (Tag(7, corners + [0.0, 0.0, 2.5]),))  # out of view
    behind = look_at(np.array([1.5, 0.0, 0.2]), np.zeros(3))
    assert np.array_equal(
        render_view(behind, target=plate, noise_sigma=0.0), render_view(behind, target=far_away, noise_sigma=0.0)
    )
    front = look_at(np.array([-1.5, 0.0, 0.2]), np.zeros(3))
    assert set(detect(render_view(front, target=plate, seed=1))) == {7}
    # an obstacle between the camera and the cube hides the -y face
    pose = look_at(np.array([1.3, -1.3, 0.9]), np.zeros(3))
    blocker = Room(boxes=(Box(center=(0.35, -0.45, 0.11), size=(0.12, 0.12, 0.4), seed=1),))
    seen = detect(render_view(pose, room=blocker, seed=1))
    assert 3 not in seen and 0 in seen


def test_camera_outside_the_room_is_refused():
    with pytest.raises(ValueError, match="outside the room"):
        render_view(look_at(np.array([9.0, 0.0, 1.0]), np.zeros(3)))


def test_a_wall_retextured_changes_that_wall_and_no_other():
    """Room(retextured=(3,)): the view of the wall at y = +4 m changes, one of the wall at
    y = -4 m does not (bench boot's room changed in part)."""
    pose_up = look_at(np.array([0.0, 1.0, 1.2]), np.array([0.0, 4.0, 1.2]), up=np.array([0.0, 0.0, 1.0]))
    pose_down = look_at(np.array([0.0, -1.0, 1.2]), np.array([0.0, -4.0, 1.2]), up=np.array([0.0, 0.0, 1.0]))
    changed = Room(retextured=(3,))
    for pose, differs in ((pose_up, True), (pose_down, False)):
        a = render_view(pose, room=True, seed=1, hidden_tags=make_cube().ids, noise_sigma=0.0)
        b = render_view(pose, room=changed, seed=1, hidden_tags=make_cube().ids, noise_sigma=0.0)
        assert bool(np.mean(np.abs(a.astype(int) - b.astype(int))) > 10) is differs


def test_a_response_curve_moves_a_blurred_edge_into_the_black_side():
    """``apply_sensor(response_gamma=0.8)``: a black/white step blurred by 1.5 px is found
    at its mid-level 0.11 of the blur's sigma (0.16 px) into the black side (the white one
    grows), as a real camera's non-linear response moves it; gamma 1 leaves it in place."""
    from scipy.stats import norm

    from cubeloc.fakes.render import apply_sensor

    columns = np.arange(200, dtype=np.float32) - 100.0 + 0.5  # the step at x = 0 (between columns 99 and 100)
    radiance = np.tile(np.where(columns < 0, 30 / 255, 220 / 255).astype(np.float32), (40, 1))

    def crossing(gamma: float) -> float:
        row = apply_sensor(radiance, noise_sigma=0.0, seed=0, blur_sigma_px=1.5, response_gamma=gamma)[20]
        level = (float(row[:40].mean()) + float(row[-40:].mean())) / 2
        i = int(np.argmax(row >= level))
        return float(columns[i - 1] + (level - row[i - 1]) / (float(row[i]) - float(row[i - 1])))

    b, w = (30 / 255) ** 0.8, (220 / 255) ** 0.8
    expected = 1.5 * norm.ppf((((b + w) / 2) ** (1 / 0.8) - 30 / 255) / (190 / 255))  # where the curve puts mid-level
    assert abs(crossing(1.0)) < 0.03
    assert abs(crossing(0.8) - expected) < 0.03 and expected < -0.1  # x < 0 is the black side
