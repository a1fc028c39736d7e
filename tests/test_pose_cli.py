"""``cubeloc pose`` and ``cubeloc generate cube`` as a user runs them: real files, a fresh
interpreter, one JSON line per image, one error line and exit 2 for bad input."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from PIL import Image

from cubeloc.calib.camera_info import paper_camera, write_camera_info
from cubeloc.fakes import render_view
from cubeloc.positioning.detection import TagDetector
from cubeloc.positioning.range_map import camera_on_sphere
from cubeloc.positioning.target import default_cube_yaml


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A target file, a calibration, a three-face image, a one-face image, and the truth."""
    root = tmp_path_factory.mktemp("pose")
    (root / "cube.yaml").write_text(default_cube_yaml())
    write_camera_info(root / "camera.yaml", paper_camera())
    truth = camera_on_sphere(40.0, 30.0, 1.8)
    cv2.imwrite(str(root / "three.png"), render_view(truth, seed=11))
    cv2.imwrite(str(root / "one.png"), render_view(camera_on_sphere(0.0, 0.0, 1.5), seed=12))
    return root, truth


def test_pose_prints_one_json_line_per_image(cli, scene):
    root, truth = scene
    result = cli("pose", "--target", str(root / "cube.yaml"), "--calib", str(root / "camera.yaml"),
                 str(root / "three.png"), str(root / "one.png"))
    assert result.returncode == 0, result.stderr
    lines = [json.loads(line) for line in result.stdout.splitlines()]
    assert [line["image"] for line in lines] == [str(root / "three.png"), str(root / "one.png")]
    good, one = lines
    assert good["ok"] is True and good["planes"] == 3 and good["tags"] == [0, 1, 4]
    assert np.linalg.norm(np.array(good["position"]) - truth.translation) < 2e-3
    q = np.array(good["orientation"])
    assert abs(np.linalg.norm(q) - 1) < 1e-6 and q[3] >= 0
    assert np.allclose(q, truth.quaternion(), atol=1e-3)
    assert good["reproj_rms_px"] < 0.5 and len(good["covariance"]) == 36
    assert one == {"image": str(root / "one.png"), "ok": False, "reason": "one_face",
                   "detail": one["detail"], "tags_seen": [0]}


@pytest.mark.parametrize(("bits", "aligned"), [(12, "low"), (12, "high"), (16, "high")])
def test_a_16_bit_image_gives_the_pose_its_8_bit_original_gives(cli, scene, bits, aligned):
    """Mono12 in the low bits of its container (a camera's), in the high bits (TUM-VI's
    PNGs) and Mono16: each scaled to the bits it uses, so the pose is the 8-bit one's."""
    root, truth = scene
    eight = cv2.imread(str(root / "three.png"), cv2.IMREAD_GRAYSCALE).astype(np.uint16)
    deep = eight << (bits - 8) | (eight >> (16 - bits) if bits > 8 else 0)  # 255 -> all bits set
    if aligned == "high":
        deep = deep << (16 - bits)
    path = root / f"three_{bits}_{aligned}.png"
    cv2.imwrite(str(path), deep.astype(np.uint16))
    result = cli("pose", "--target", str(root / "cube.yaml"), "--calib", str(root / "camera.yaml"),
                 str(root / "three.png"), str(path))
    assert result.returncode == 0, result.stderr
    original, converted = (json.loads(line) for line in result.stdout.splitlines())
    assert converted["ok"] and converted["tags"] == original["tags"]
    assert np.allclose(converted["position"], original["position"], atol=1e-6)


def _bad_inputs(root):
    (root / "empty.png").write_bytes(b"")
    (root / "text.png").write_text("hello, not a picture\n")
    cv2.imwrite(str(root / "float.tiff"), np.zeros((1024, 1280), np.float32))
    cv2.imwrite(str(root / "small.png"), np.zeros((480, 640), np.uint8))
    (root / "bad_target.yaml").write_text("family: tag36h11\ncube: {side: 0.10, tag_size: 0.144, ids: [0, 1, 2, 3, 4, 5]}\n")
    (root / "dup_target.yaml").write_text(
        "family: tag36h11\ntags:\n"
        "  - {id: 3, corners: [[0, 0, 0], [1, 0, 0], [1, -1, 0], [0, -1, 0]]}\n"
        "  - {id: 3, corners: [[2, 0, 0], [3, 0, 0], [3, -1, 0], [2, -1, 0]]}\n"
    )


@pytest.mark.parametrize(
    ("target", "image", "message"),
    [
        ("cube.yaml", "empty.png", "empty.png: empty file"),
        ("cube.yaml", "text.png", "text.png: not an image"),
        ("cube.yaml", "float.tiff", "float.tiff: expected an 8- or 16-bit image, got float32"),
        ("cube.yaml", "small.png", "small.png: image is 640x480 but the calibration is for 1280x1024"),
        ("cube.yaml", "missing.png", "missing.png: image not found"),
        ("bad_target.yaml", "three.png", "bad_target.yaml: cube.tag_size 0.144 m must be positive and no larger"),
        ("dup_target.yaml", "three.png", "dup_target.yaml: tag id 3 appears twice"),
    ],
)
def test_bad_input_is_one_line_and_exit_2_with_nothing_printed(cli, scene, target, image, message):
    root, _ = scene
    _bad_inputs(root)
    # The good image first: nothing may be printed for it when a later file is bad.
    result = cli("pose", "--target", str(root / target), "--calib", str(root / "camera.yaml"),
                 str(root / "three.png"), str(root / image))
    assert result.returncode == 2
    assert result.stdout == ""
    assert message in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr


def test_generate_cube_writes_faces_that_decode_to_the_right_ids(cli, tmp_path):
    target = tmp_path / "cube.yaml"
    target.write_text("family: tag36h11\ncube: {side: 0.18, tag_size: 0.144, ids: [7, 8, 9, 10, 11, 12]}\n")
    out = tmp_path / "print"
    result = cli("generate", "cube", "--target", str(target), "--out", str(out), "--dpi", "150")
    assert result.returncode == 0, result.stderr
    assert "cube.pdf" in result.stdout and "150 dpi" in result.stdout
    pdf = (out / "cube.pdf").read_bytes()
    assert pdf.startswith(b"%PDF") and pdf.count(b"/Type /Page\n") + pdf.count(b"/Type /Page ") >= 6
    assert b"/MediaBox [ 0 0 595.2 841.92 ]" in pdf  # A4 at true scale, in points
    detector = TagDetector()
    for index, tag_id in enumerate([7, 8, 9, 10, 11, 12]):
        face = Image.open(out / f"face_{index}_id{tag_id}.png")
        assert face.info["dpi"][0] == pytest.approx(150, abs=0.05)
        assert face.size == (round(180 / 25.4 * 150), round(180 / 25.4 * 150))  # 180 mm at 150 dpi
        pixels = np.array(face)
        (found,) = detector.detect(pixels)
        assert found.tag_id == tag_id
        # Tag edge: the outer black border is 144 mm = 850.4 px at 150 dpi.
        edge_px = np.linalg.norm(found.corners[1] - found.corners[0])
        assert edge_px == pytest.approx(144 / 25.4 * 150, abs=2.0)
        assert found.corners[0][0] < found.corners[1][0] and found.corners[0][1] < found.corners[3][1]  # upright
    assert (out / "cube_layout.png").is_file() and (out / "target.yaml").read_text() == target.read_text()


def test_generate_refuses_explicit_targets_and_bad_dpi(cli, tmp_path):
    target = tmp_path / "tags.yaml"
    target.write_text("family: tag36h11\ntags:\n  - {id: 1, corners: [[0, 0, 0], [1, 0, 0], [1, -1, 0], [0, -1, 0]]}\n")
    result = cli("generate", "cube", "--target", str(target), "--out", str(tmp_path / "o"))
    assert result.returncode == 2 and "not the 'cube:' shorthand" in result.stderr
    assert not (tmp_path / "o").exists()
    cube = tmp_path / "cube.yaml"
    cube.write_text(default_cube_yaml())
    result = cli("generate", "cube", "--target", str(cube), "--out", str(tmp_path / "o"), "--dpi", "5")
    assert result.returncode == 2 and "--dpi 5" in result.stderr


def test_a_reader_that_stops_early_gets_no_traceback(scene):
    """``cubeloc pose ... | head -1`` and ``cubeloc doctor --json | head``: the pipe closes
    before cubeloc is done; it stops quietly (before: a BrokenPipeError traceback)."""
    import subprocess
    import sys

    root, _ = scene
    images = [str(root / "three.png")] * 40
    for argv in (["pose", "--target", str(root / "cube.yaml"), "--calib", str(root / "camera.yaml"), *images],
                 ["doctor", "--json", "--timeout", "0.2"]):
        done = subprocess.run(f"{sys.executable} -m cubeloc.daemon.cli {' '.join(argv)} | head -c 1", shell=True,
                              capture_output=True, text=True, timeout=300)
        assert len(done.stdout) == 1, (argv[0], done.stdout)
        assert "Traceback" not in done.stderr and "BrokenPipe" not in done.stderr, (argv[0], done.stderr[-2000:])
