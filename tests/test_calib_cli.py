"""``cubeloc calibrate`` as a technician runs it: from images, live from a (replayed)
camera, and with the usual mistakes. Real files in tmp_path, the real CLI in a subprocess."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest
import yaml

from cubeloc.calib.boards import parse_board
from cubeloc.calib.camera_info import read_camera_info
from cubeloc.fakes.board_views import (
    synthetic_board_camera,
    write_board_images,
    write_board_sequence,
)
from tests.conftest import REPO, run_cli

CHARUCO = "charuco:11x8:0.030:0.022:DICT_5X5_100"
CAMERA = synthetic_board_camera(640, 512)


@pytest.fixture(scope="module")
def charuco_images(tmp_path_factory):
    """12 ChArUco views, the last one heavily blurred (rendered once for the module)."""
    directory = tmp_path_factory.mktemp("charuco")
    write_board_images(directory, parse_board(CHARUCO), CAMERA, count=12, seed=4, corrupt=1)
    return directory


def _copy_images(source, destination):
    destination.mkdir()
    for path in sorted(source.glob("*.png")):
        shutil.copy(path, destination / path.name)
    return destination


def _no_traceback(result):
    assert "Traceback" not in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr


def test_images_solve_writes_calibration_report_and_corners_cache(charuco_images, tmp_path):
    images = _copy_images(charuco_images, tmp_path / "imgs")
    out = tmp_path / "cam.yaml"
    result = run_cli("calibrate", "--images", f"{images}/*.png", "--board", CHARUCO, "--out", str(out))
    assert result.returncode == 0, result.stderr
    calibration = read_camera_info(out)
    assert calibration.size == (640, 512)
    assert abs(calibration.fx / CAMERA.fx - 1) < 0.003
    meta = calibration.metadata
    assert meta["board"] == parse_board(CHARUCO).text
    assert meta["views"] >= 10 and meta["corners"] > 300 and 0 < meta["rms_px"] < 0.5
    assert set(meta["std"]) == {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"}
    assert meta["software"].startswith("cubeloc ")
    assert meta["verdict"].split(":")[0] in ("good", "usable")
    named = {e["view"] for e in meta["dropped"]} | {e["image"] for e in meta["skipped"]}
    assert "img_11.png" in named  # the blurred view is named
    assert "verdict:" in result.stdout and "img_11.png" in result.stdout
    assert (tmp_path / "cam.report.png").stat().st_size > 1000
    cache = yaml.safe_load((images / "corners.yaml").read_text())
    assert cache["board"] == parse_board(CHARUCO).text and len(cache["images"]) == 12

    # an existing output is not replaced without --force, and stays as it was
    before = out.read_bytes()
    again = run_cli("calibrate", "--images", f"{images}/*.png", "--board", CHARUCO, "--out", str(out))
    assert again.returncode == 2 and "--force" in again.stderr
    _no_traceback(again)
    assert out.read_bytes() == before

    # --force, another model: re-solved from the cache (images unchanged, cache unchanged)
    cache_before = (images / "corners.yaml").read_bytes()
    forced = run_cli(
        "calibrate", "--images", f"{images}/*.png", "--board", CHARUCO, "--out", str(out),
        "--force", "--model", "rational_polynomial", "--fix-aspect-ratio",
    )
    assert forced.returncode == 0, forced.stderr
    rational = read_camera_info(out)
    assert rational.distortion_model == "rational_polynomial" and len(rational.distortion) == 8
    assert rational.fx == pytest.approx(rational.fy, rel=1e-9)
    assert (images / "corners.yaml").read_bytes() == cache_before


def test_no_board_in_any_image_names_the_off_by_one(tmp_path):
    # a 9x6 chessboard (inner corners), described by its squares: 10x7
    write_board_images(tmp_path / "imgs", parse_board("chessboard:9x6:0.025"), CAMERA, count=6, seed=5)
    out = tmp_path / "cam.yaml"
    result = run_cli("calibrate", "--images", str(tmp_path / "imgs"), "--board", "chessboard:10x7:0.025", "--out", str(out))
    assert result.returncode == 2
    _no_traceback(result)
    assert "0 of 6 images show a 10x7 chessboard" in result.stderr
    assert "chessboard:9x6:0.025" in result.stderr and "inner corners" in result.stderr
    assert not out.exists() and not (tmp_path / "cam.report.png").exists()


def test_bad_image_sets_fail_with_one_line(charuco_images, tmp_path):
    import cv2

    out = tmp_path / "cam.yaml"
    # mixed sizes
    mixed = _copy_images(charuco_images, tmp_path / "mixed")
    cv2.imwrite(str(mixed / "img_99.png"), np.zeros((480, 640), np.uint8))
    result = run_cli("calibrate", "--images", f"{mixed}/*.png", "--board", CHARUCO, "--out", str(out))
    assert result.returncode == 2 and "640x480" in result.stderr and "640x512" in result.stderr
    _no_traceback(result)
    # an unreadable image
    broken = _copy_images(charuco_images, tmp_path / "broken")
    (broken / "img_05.png").write_bytes(b"not a png at all")
    result = run_cli("calibrate", "--images", f"{broken}/*.png", "--board", CHARUCO, "--out", str(out))
    assert result.returncode == 2 and "img_05.png" in result.stderr
    _no_traceback(result)
    # too few views
    few = tmp_path / "few"
    few.mkdir()
    for name in ("img_00.png", "img_01.png", "img_02.png"):
        shutil.copy(charuco_images / name, few / name)
    result = run_cli("calibrate", "--images", str(few), "--board", CHARUCO, "--out", str(out))
    assert result.returncode == 2 and "at least 5" in result.stderr
    _no_traceback(result)
    # a glob matching nothing, and a bad board spec
    result = run_cli("calibrate", "--images", f"{tmp_path}/nothing/*.png", "--board", CHARUCO, "--out", str(out))
    assert result.returncode == 2 and "no image files match" in result.stderr
    result = run_cli("calibrate", "--images", str(few), "--board", "chessboard:9x6:25", "--out", str(out))
    assert result.returncode == 2 and "metres" in result.stderr
    assert not out.exists()


def test_live_capture_from_a_replayed_camera_saves_views_that_re_solve(tmp_path):
    sequence = tmp_path / "seq"
    frames = write_board_sequence(sequence, parse_board(CHARUCO), CAMERA, count=14, seed=6)
    out = tmp_path / "live.yaml"
    result = run_cli("calibrate", "--camera", f"replay:{sequence}", "--board", CHARUCO, "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert "end of the recorded source" in result.stdout
    assert "X [" in result.stdout and "skew [" in result.stdout  # the coverage display
    views = sorted((tmp_path / "live.views").glob("view_*.png"))
    # each view was held for two frames, and blank frames came between: only new views count
    assert 10 <= len(views) <= 14 < frames
    live = read_camera_info(out)
    assert abs(live.fx / CAMERA.fx - 1) < 0.003
    assert live.metadata["views"] + len(live.metadata["dropped"]) + len(live.metadata["skipped"]) == len(views)

    resolved_out = tmp_path / "again.yaml"
    again = run_cli("calibrate", "--images", f"{tmp_path}/live.views/*.png", "--board", CHARUCO, "--out", str(resolved_out))
    assert again.returncode == 0, again.stderr
    resolved = read_camera_info(resolved_out)
    # the same corners (from the saved cache) give the same calibration; to 1e-5 px, not
    # bit for bit: OpenCV's solver sums in threads (CI measured cx 3.6e-7 px apart, and a
    # loaded 2-core machine k2 1.9e-8 apart, 2.7e-6 of its value)
    np.testing.assert_allclose(resolved.camera_matrix, live.camera_matrix, rtol=0, atol=1e-5)
    np.testing.assert_allclose(resolved.distortion, live.distortion, rtol=1e-5, atol=1e-7)

    # a second capture to the same output needs --force (checked before the camera opens)
    refused = run_cli("calibrate", "--camera", f"replay:{sequence}", "--board", CHARUCO, "--out", str(out))
    assert refused.returncode == 2 and "--force" in refused.stderr


def test_live_capture_with_too_few_views_writes_nothing(tmp_path):
    sequence = tmp_path / "seq"
    write_board_sequence(sequence, parse_board(CHARUCO), CAMERA, count=3, seed=7)
    out = tmp_path / "live.yaml"
    result = run_cli("calibrate", "--camera", f"replay:{sequence}", "--board", CHARUCO, "--out", str(out))
    assert result.returncode == 2 and "only 3 views" in result.stderr and "nothing written" in result.stderr
    assert not out.exists() and not (tmp_path / "live.views").exists()


def test_sigterm_during_live_capture_saves_what_it_has(tmp_path):
    sequence = tmp_path / "seq"
    write_board_sequence(sequence, parse_board(CHARUCO), CAMERA, count=20, seed=6, repeats=1, blank_every=0)
    out = tmp_path / "live.yaml"
    process = subprocess.Popen(
        [sys.executable, "-m", "cubeloc.daemon.cli", "calibrate", "--camera", f"replay:{sequence}@pace",
         "--board", CHARUCO, "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
    )
    try:
        accepted = 0
        for line in process.stdout:  # one line per accepted view (not a terminal)
            accepted += line.startswith("views")
            if accepted >= 7:
                process.send_signal(signal.SIGTERM)
                break
        stdout, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0, stderr
    assert "stopped on request" in stdout
    calibration = read_camera_info(out)
    assert 7 <= calibration.metadata["views"] + len(calibration.metadata["dropped"]) < 20


def test_camera_owned_by_another_process_says_how_to_proceed(tmp_path):
    from cubeloc.drivers.ownership import CameraLock

    env = {**os.environ, "CUBELOC_LOCK_DIR": str(tmp_path / "locks")}
    os.environ["CUBELOC_LOCK_DIR"] = env["CUBELOC_LOCK_DIR"]
    try:
        with CameraLock("Aravis-Fake-1"):  # the lock name: vendor-model-serial
            result = run_cli("calibrate", "--camera", "aravis:Fake_1", "--out", str(tmp_path / "c.yaml"), env=env)
    finally:
        del os.environ["CUBELOC_LOCK_DIR"]
    assert result.returncode == 2
    _no_traceback(result)
    assert "systemctl stop cubeloc" in result.stderr and "Aravis-Fake-1" in result.stderr


def test_help_spells_out_what_board_sizes_count():
    from cubeloc.daemon.cli import build_parser

    parser = build_parser()
    calibrate = parser._subparsers._group_actions[0].choices["calibrate"]
    text = calibrate.format_help()
    assert "INNER CORNERS" in text and "SQUARES" in text and "chessboard:9x6:0.025" in text
    assert "--fix-principal-point" in text and "rational_polynomial" in text
