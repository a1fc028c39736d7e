"""Several targets ([[frames.targets]]): each placed in the map, all moved into the first
one's frame as one rigid target (positioning.target.combine_targets); any of them poses
the camera, two in one view are used together, and tag ids may not collide."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cubeloc.calib.camera_info import paper_camera, write_camera_info
from cubeloc.daemon.config import Config
from cubeloc.daemon.preflight import combined_target
from cubeloc.errors import InputFileError
from cubeloc.fakes import render_view
from cubeloc.positioning.geometry import Transform, look_at
from cubeloc.positioning.single_frame import TargetPoseProcessor
from cubeloc.positioning.target import combine_targets, default_cube_yaml, make_cube

# the second cube 1.6 m along the map's x from the first, turned 90 deg
SECOND = Transform(Rotation.from_euler("z", 90, degrees=True).as_matrix(), [1.6, 0.0, 0.0])


def _cubes(tmp_path, second_ids=(6, 7, 8, 9, 10, 11)):
    (tmp_path / "a.yaml").write_text(default_cube_yaml())
    (tmp_path / "b.yaml").write_text(f"family: tag36h11\ncube: {{side: 0.18, tag_size: 0.144, ids: {list(second_ids)}}}\n")
    write_camera_info(tmp_path / "camera.yaml", paper_camera())
    return Config.model_validate({
        "positioning": {"target": tmp_path / "a.yaml", "calibration": tmp_path / "camera.yaml"},
        "frames": {"map_from_target": {"xyz": [3.0, 1.0, 0.0]},  # the first cube somewhere in the map
                   "targets": [{"file": tmp_path / "b.yaml", "xyz": [4.6, 1.0, 0.0], "rpy_deg": [0, 0, 90]}]},
    })


def test_a_second_target_is_moved_into_the_first_ones_frame_by_their_placements(tmp_path):
    target = combined_target(_cubes(tmp_path))
    assert target.ids == (0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11) and target.cube is None
    alone = make_cube(0.18, 0.144, (6, 7, 8, 9, 10, 11))
    for tag_id in (6, 9, 10):
        np.testing.assert_allclose(target.tag(tag_id).corners, SECOND.apply(alone.tag(tag_id).corners), atol=1e-12)
    assert str(tmp_path / "a.yaml") in target.source and str(tmp_path / "b.yaml") in target.source


def test_targets_sharing_a_tag_id_or_a_family_are_refused_naming_both_files(tmp_path):
    with pytest.raises(InputFileError) as caught:
        combined_target(_cubes(tmp_path, second_ids=(6, 7, 8, 9, 10, 5)))
    message = str(caught.value)
    assert "[5]" in message and str(tmp_path / "a.yaml") in message and str(tmp_path / "b.yaml") in message
    other = make_cube(0.18, 0.144, (20, 21, 22, 23, 24, 25), "tag25h9")
    with pytest.raises(InputFileError, match="family"):
        combine_targets(make_cube(0.18, 0.144, (0, 1, 2, 3, 4, 5)), [(other, np.eye(4))])


def test_run_check_refuses_colliding_targets_with_one_line(tmp_path, cli):
    _cubes(tmp_path, second_ids=(6, 7, 8, 9, 10, 0))
    (tmp_path / "c.toml").write_text(
        f'[camera]\nsource = "synthetic:paper"\n[positioning]\ntarget = "{tmp_path / "a.yaml"}"\n'
        f'calibration = "{tmp_path / "camera.yaml"}"\n[[frames.targets]]\nfile = "{tmp_path / "b.yaml"}"\n'
        "xyz = [1.6, 0, 0]\n")
    result = cli("run", "--config", str(tmp_path / "c.toml"), "--check", timeout=60)
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert "tag id(s) [0]" in result.stderr and "b.yaml" in result.stderr and "a.yaml" in result.stderr


def test_either_target_poses_the_camera_and_two_in_view_are_used_together(tmp_path):
    """Renders of both cubes (the second placed as above): a view of both uses tags of both
    (measured: tags 0 3 4 7 8 10, 4 planes, 0.29 mm); a view of the second alone gives the
    camera in the first one's frame (0.19 mm)."""
    target = combined_target(_cubes(tmp_path))
    camera = paper_camera()
    processor = TargetPoseProcessor(target, camera)
    both = look_at(np.array([0.8, -2.4, 1.1]), np.array([0.8, 0.0, 0.0]))
    only_second = look_at(SECOND.apply(np.array([[1.5, -1.3, 0.9]]))[0], SECOND.translation)
    for truth, expect_both, bound_mm in ((both, True, 1.0), (only_second, False, 0.6)):
        processor.reset()
        result = processor.process(render_view(truth, target=target, seed=3), 0, 0)
        assert result.estimate is not None, result.detail
        ids = set(result.estimate.tag_ids)
        assert (bool(ids & {0, 1, 2, 3, 4, 5}) and bool(ids & {6, 7, 8, 9, 10, 11})) == expect_both, ids
        assert ids & {6, 7, 8, 9, 10, 11}
        error_mm = np.linalg.norm(result.estimate.T_world_camera.translation - truth.translation) * 1000
        assert error_mm < bound_mm, (ids, error_mm)


def test_calibrate_target_learns_where_the_second_target_stands_from_images_of_both(tmp_path, cli):
    """Four renders showing both cubes: the block it writes places the second cube within
    1 mm and 0.1 deg of where it is, and goes into a config as it is."""
    import cv2
    import tomllib

    config = _cubes(tmp_path)
    both = combined_target(config)
    for k, (x, y) in enumerate(((0.8, -2.4), (0.2, -2.6), (1.4, -2.5), (0.8, -2.9))):
        view = look_at(np.array([x, y, 1.1]), np.array([0.8, 0.0, 0.0]))
        cv2.imwrite(str(tmp_path / f"view{k}.png"), render_view(view, target=both, seed=k))
    argv = ["calibrate-target", "--place", str(tmp_path / "b.yaml"), "--target", str(tmp_path / "a.yaml"),
            "--calib", str(tmp_path / "camera.yaml"), "--images", str(tmp_path / "view*.png"),
            "--out", str(tmp_path / "b.toml")]
    result = cli(*argv, timeout=120)
    assert result.returncode == 0, result.stderr
    block = tomllib.loads((tmp_path / "b.toml").read_text())["frames"]["targets"][0]
    placed = Transform.from_quaternion(block["xyz"], block["quaternion"])
    assert np.linalg.norm(placed.translation - SECOND.translation) < 0.001, block
    assert np.degrees(placed.rotation_angle_to(SECOND)) < 0.1, block
    # and it reads back as a config: the same twelve tags
    again = Config.model_validate({**config.model_dump(), "frames": {"targets": [block]}})
    assert combined_target(again).ids == both.ids
    # a single image showing both is not enough to trust
    for k in (1, 2, 3):
        (tmp_path / f"view{k}.png").unlink()
    result = cli(*argv, "--force", timeout=120)
    assert result.returncode == 2 and "1 of the 1 images" in result.stderr and result.stderr.count("\n") == 1
