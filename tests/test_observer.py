"""The one target observer: both modes see the target the same way, and its search finds
what the library finds. Rendered, seeded."""

from __future__ import annotations

import numpy as np
import pytest

from cubeloc.calib.camera_info import paper_camera
from cubeloc.fakes import render_view
from cubeloc.positioning.detection import TagDetector
from cubeloc.positioning.geometry import look_at
from cubeloc.positioning.observer import TargetObserver
from cubeloc.positioning.range_map import camera_on_sphere
from cubeloc.positioning.single_frame import TargetPoseProcessor
from cubeloc.positioning.target import make_cube
from cubeloc.positioning.target_pose import unique_target_detections
from cubeloc.positioning.tracking import TrackingProcessor

CUBE = make_cube()
CAMERA = paper_camera()


def test_tracker_target_poses_are_those_of_cubeloc_pose_on_static_frames():
    """30 frames from one place at 1.9 m (noise differs): the tracker's target poses have
    the spread and bias of ``cubeloc pose`` within 10 % (measured: identical, 0.047 mm RMSE
    per axis, where the tracker's own corners-only search gave 0.117 mm)."""
    direction = np.array([1.0, 0.9, 0.8]) / np.linalg.norm([1.0, 0.9, 0.8])
    truth = look_at(direction * 1.9, np.zeros(3))
    frames = [render_view(truth, seed=s) for s in range(30)]
    spread, bias = {}, {}
    for name, processor in (("pose", TargetPoseProcessor(CUBE, CAMERA)), ("track", TrackingProcessor(CUBE, CAMERA))):
        positions = []
        for i, frame in enumerate(frames):
            result = processor.process(frame, i * 100_000_000, i)
            assert result.estimate is not None and result.estimate.state.value == "target", result
            positions.append(result.estimate.T_world_camera.translation)
        positions = np.array(positions)
        spread[name] = float(np.sqrt(np.mean((positions - positions.mean(axis=0)) ** 2)))
        bias[name] = float(np.linalg.norm(positions.mean(axis=0) - truth.translation))
        if hasattr(processor, "close"):
            processor.close()
    assert spread["track"] <= 1.1 * spread["pose"] and bias["track"] <= 1.1 * bias["pose"] + 1e-5, (spread, bias)
    assert spread["pose"] < 0.0001  # 0.1 mm: edge-aligned (the corners alone give about 0.12)


@pytest.mark.parametrize("azimuth", [210.0, 300.0])
def test_the_search_finds_every_tag_the_library_finds_at_decimate_2(azimuth):
    """From 60 deg up at 1 m a side face is seen at up to 85 deg from its normal; the
    library at decimate 2 still decodes it, and so must the observer (decimate 3 first,
    then the regions its pose predicts)."""
    detector = TagDetector(CUBE.family)
    processor = TargetPoseProcessor(CUBE, CAMERA)
    for k, offset in enumerate((-9.0, -3.0, 3.0, 9.0)):
        image = render_view(camera_on_sphere(azimuth + offset, 60.0, 1.0), seed=40 + k)
        library = {d.tag_id for d in unique_target_detections(detector.detect(image, None, 2.0), CUBE)}
        processor.reset()
        seen = set(processor.process(image, 0, 0).tags_seen)
        assert library <= seen, (azimuth + offset, library, seen)


def test_the_masked_search_paints_the_quiet_zone_grey_level_numpy_would_give():
    """The masked search's white level (the 90th percentile of the region's pixels) comes
    from a histogram of the grey levels: it must equal numpy's linear percentile, on
    uniform, constant, two-level and tiny sets of pixels."""
    from cubeloc.positioning.tag_search import grey_percentile

    rng = np.random.default_rng(16)
    samples = [rng.integers(0, 256, int(n)).astype(np.uint8) for n in rng.integers(1, 5000, 300)]
    samples += [np.full(17, 200, np.uint8), np.array([0, 255], np.uint8), np.array([7], np.uint8),
                np.where(rng.random(999) < 0.8, 20, 240).astype(np.uint8)]
    for values in samples:
        for q in (10.0, 50.0, 90.0):
            assert grey_percentile(values, q) == pytest.approx(np.percentile(values, q), abs=1e-9)


def _full_frame_passes(observer: TargetObserver) -> list[float]:
    """Records the decimation of every full-frame library run ``observer`` makes."""
    passes: list[float] = []
    detect = observer._detector.detect

    def recorded(image, roi=None, decimate=None, sigma=None):
        if roi is None and image.shape == (CAMERA.height, CAMERA.width):  # not a masked crop
            passes.append(decimate)
        return detect(image, roi, decimate, sigma)

    observer._detector.detect = recorded
    return passes


def test_a_far_cube_is_searched_finer_only_where_its_pose_leaves_a_tag_in_view_unused():
    """At 4 m every tag is small for the coarse pass (decimate 3). Three faces on, the
    coarse pass and the completion search give every tag in view: no finer full-frame pass
    runs (each is a whole library run: 49 ms at decimate 1 against 6 ms at 3), and the pose
    is as good (measured 0.15-0.5 mm off). Seen from low on one face, the coarse pass finds
    one tag of three; the finer passes find the others, and the pose uses all three."""
    for k, azimuth in enumerate((45.0, 135.0, 225.0)):
        truth = camera_on_sphere(azimuth, 33.0, 4.0)
        observer = TargetObserver(CUBE, CAMERA)
        passes = _full_frame_passes(observer)
        image = render_view(truth, seed=k)
        observer.observe(image, None, 0, full_search=True)  # the first also checks the tags' size
        passes.clear()
        observation = observer.observe(image, None, 1, full_search=True)
        assert observation.pose is not None and len(observation.pose.tag_ids) == 3, observation.detail
        assert passes == [3.0], passes
        assert np.linalg.norm(observation.pose.T_world_camera.translation - truth.translation) < 0.001
    position = np.array([0.650, -3.702, 1.368])
    truth = look_at(position, position + 4.0 * np.array([-0.1349, 0.9520, -0.2748]))
    observer = TargetObserver(CUBE, CAMERA)
    passes = _full_frame_passes(observer)
    observation = observer.observe(render_view(truth, seed=1), None, 0, full_search=True)
    assert passes[0] == 3.0 and min(passes) < 3.0, passes
    assert observation.pose is not None and observation.pose.tag_ids == (0, 3, 4), observation.detail
    assert np.linalg.norm(observation.pose.T_world_camera.translation - truth.translation) < 0.003
