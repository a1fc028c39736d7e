"""Malformed target, calibration and config files through the real CLI (issue 8, bad input).

Every case must end in exit code 2 and one line on stderr that names the file at fault,
with no traceback and no numpy warning. Most cases run the CLI entry point in this
process (``daemon.cli.main``, the function ``cubeloc`` calls: a stray exception fails the
test); a few run ``cubeloc`` in a fresh interpreter to show the same from the outside.
Hypothesis then mutates valid documents into junk and feeds them to the loaders.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import structlog
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cubeloc.calib.camera_info import paper_camera, read_camera_info, to_yaml, write_camera_info
from cubeloc.daemon.cli import main
from cubeloc.daemon.config import load_config
from cubeloc.errors import ConfigError, InputFileError
from cubeloc.positioning.target import default_cube_yaml, parse_target

CALIB = to_yaml(paper_camera())
CUBE = "family: tag36h11\ncube: {side: 0.18, tag_size: 0.144, ids: [0, 1, 2, 3, 4, 5]}\n"
SQUARE = "[[0, 0, 0], [0.1, 0, 0], [0.1, 0, -0.1], [0, 0, -0.1]]"

# Junk that is wrong for any of the three files.
ANY_FILE = {
    "empty": b"",
    "binary junk": bytes(range(256)) * 8,
    "non-UTF-8": "name: caf\u00e9\n".encode("latin-1"),
    "NUL bytes": b"\x00\x00\x00\x00",
    "nested too deeply": b"[" * 1_000,
    "a list": b"[1, 2, 3]\n",
}

BAD_TARGETS = {
    **ANY_FILE,
    "wrong type: family": b"family: [1]\n" + CUBE.split("\n")[1].encode(),
    "wrong type: side": CUBE.replace("0.18", '"big"').encode(),
    "wrong type: ids": CUBE.replace("[0, 1, 2, 3, 4, 5]", '"012345"').encode(),
    "wrong type: tags": b"family: tag36h11\ntags: {a: 1}\n",
    "missing key: cube.ids": b"cube: {side: 0.18, tag_size: 0.144}\n",
    "missing key: corners": b"tags: [{id: 0}]\n",
    "NaN side": CUBE.replace("0.18", ".nan").encode(),
    "infinite corner": f"tags: [{{id: 0, corners: {SQUARE.replace('0.1,', '.inf,', 1)}}}]\n".encode(),
    "huge side": CUBE.replace("0.18", "1.0e+300").replace("0.144", "1.0e+299").encode(),
    "huge corner": f"tags: [{{id: 0, corners: {SQUARE.replace('0.1', '1.0e+200')}}}]\n".encode(),
    "huge tag id": CUBE.replace("5]", "99999999999999999999999]").encode(),
    "tiny cube": CUBE.replace("0.18", "1.0e-12").replace("0.144", "1.0e-13").encode(),
    "collinear corners": b"tags: [{id: 0, corners: [[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]]}]\n",
    "duplicate id": f"tags: [{{id: 3, corners: {SQUARE}}}, {{id: 3, corners: {SQUARE}}}]\n".encode(),
    "unknown key at the top": (CUBE + "size_mm: 180\n").encode(),
    "unknown key in cube": CUBE.replace("ids:", "tag_size_mm: 144, ids:").encode(),
    "unknown key in a tag": f"tags: [{{id: 0, corners: {SQUARE}, size: 0.1}}]\n".encode(),
}

BAD_CALIBRATIONS = {
    **ANY_FILE,
    "wrong type: image_width": CALIB.replace("image_width: 1280", "image_width: '1280'").encode(),
    "wrong type: distortion_model": CALIB.replace("distortion_model: plumb_bob", "distortion_model: [a]").encode(),
    "wrong type: data": CALIB.replace("data: [1666", "data: [x, 1666", 1).encode(),
    "missing key: camera_matrix": b"image_width: 1280\nimage_height: 1024\n",
    "missing key: distortion": "\n".join(
        line for line in CALIB.splitlines() if not line.startswith("distortion_coefficients")).encode(),
    "NaN fx": CALIB.replace("data: [1666.6666666666667", "data: [.nan", 1).encode(),
    "huge width": CALIB.replace("image_width: 1280", "image_width: 99999999999999999999999").encode(),
    "huge fx": CALIB.replace("data: [1666.6666666666667", "data: [1.0e+308", 1).encode(),
    "huge distortion": CALIB.replace("data: [-0.08", "data: [1.0e+300").encode(),
    "principal point far outside": CALIB.replace("639.5", "-1.0e+9", 1).encode(),
    "too few coefficients": CALIB.replace("data: [-0.08, 0.05, 0.0, 0.0, 0.0]", "data: [-0.08]").encode(),
}

BAD_CONFIGS = {
    # (an empty file is a valid config: all defaults)
    **{k: v for k, v in ANY_FILE.items() if k not in ("a list", "empty")},
    "not TOML": b"this is not = = toml\n",
    "wrong type: width": b"[camera]\nwidth = 'wide'\n",
    "wrong type: section": b"camera = 3\n",
    "unknown key": b"[camera]\nwidht = 1280\n",
    "NaN": b"[positioning]\nmax_reproj_rms_px = nan\n",
    "infinity": b"[camera]\nframe_timeout_s = inf\n",
    "huge number": b"[camera]\nwidth = 99999999999999999999999999\n",
    "bad name": b'name = "robot/7"\n',
    "bad endpoint": b'[zenoh]\nconnect = ["10.0.0.1:7447"]\n',
    "duplicate key": b'name = "a"\nname = "b"\n',
}


@pytest.fixture(autouse=True)
def keep_logging_config():
    """``main()`` configures structlog onto this test's captured stderr; put it back after."""
    saved = structlog.get_config()
    yield
    structlog.configure(**saved)


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    """Valid files (and a tiny sequence) so that only the file under test is wrong."""
    root = tmp_path_factory.mktemp("good")
    write_camera_info(root / "camera.yaml", paper_camera())
    (root / "target.yaml").write_text(default_cube_yaml())
    cv2.imwrite(str(root / "image.png"), np.zeros((1024, 1280), np.uint8))
    cam = root / "seq" / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    cv2.imwrite(str(cam / "data" / "1000.png"), np.zeros((1024, 1280), np.uint8))
    (cam / "data.csv").write_text("#timestamp [ns],filename\n1000,1000.png\n")
    return root


def run_main(capsys, *argv: str) -> tuple[int, str, str]:
    """``cubeloc ARGV`` in this process; numpy warnings count as failures."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_naming(code: int, out: str, err: str, verb: str, path: Path) -> None:
    assert code == 2, (code, out, err)
    assert out == ""
    assert err.endswith("\n") and err.count("\n") == 1, err
    assert err.startswith(f"cubeloc {verb}: error: ") and str(path) in err, err
    assert "Traceback" not in err


def _write(tmp_path: Path, name: str, data: bytes | None, suffix: str) -> Path:
    """The bad file; ``None`` means a directory where the file should be."""
    path = tmp_path / f"bad{suffix}"
    if data is None:
        path.mkdir()
    else:
        path.write_bytes(data)
    return path


@pytest.mark.parametrize("case", [*BAD_TARGETS, "a directory"])
def test_bad_target_file(tmp_path, capsys, good, case):
    path = _write(tmp_path, case, BAD_TARGETS.get(case), ".yaml")
    for verb, argv in (
        ("pose", ["pose", "--target", str(path), "--calib", str(good / "camera.yaml"), str(good / "image.png")]),
        ("track", ["track", "--target", str(path), "--calib", str(good / "camera.yaml"),
                   "--sequence", str(good / "seq"), "--out", str(tmp_path / "out.tum")]),
    ):
        assert_one_line_naming(*run_main(capsys, *argv), verb, path)
    assert not (tmp_path / "out.tum").exists()


@pytest.mark.parametrize("case", [*BAD_CALIBRATIONS, "a directory"])
def test_bad_calibration_file(tmp_path, capsys, good, case):
    path = _write(tmp_path, case, BAD_CALIBRATIONS.get(case), ".yaml")
    for verb, argv in (
        ("pose", ["pose", "--target", str(good / "target.yaml"), "--calib", str(path), str(good / "image.png")]),
        ("track", ["track", "--target", str(good / "target.yaml"), "--calib", str(path),
                   "--sequence", str(good / "seq"), "--out", str(tmp_path / "out.tum")]),
    ):
        assert_one_line_naming(*run_main(capsys, *argv), verb, path)


@pytest.mark.parametrize("case", [*BAD_CONFIGS, "a directory"])
def test_bad_config_file(tmp_path, capsys, good, monkeypatch, case):
    for variable in [v for v in os.environ if v.startswith("CUBELOC_")]:
        monkeypatch.delenv(variable)
    path = _write(tmp_path, case, BAD_CONFIGS.get(case), ".toml")
    assert_one_line_naming(*run_main(capsys, "run", "--config", str(path), "--check"), "run", path)


@pytest.mark.parametrize("key", ["calibration", "target"])
def test_config_naming_a_bad_file(tmp_path, capsys, good, key):
    """The config is fine but a file it names is junk: the line names that file."""
    junk = tmp_path / "junk.yaml"
    junk.write_bytes(bytes(range(256)))
    files = {"calibration": good / "camera.yaml", "target": good / "target.yaml", key: junk}
    config = tmp_path / "cubeloc.toml"
    config.write_text(f'name = "t"\n[camera]\nsource = "synthetic:static?seconds=1"\n[positioning]\n'
                      f'calibration = "{files["calibration"]}"\ntarget = "{files["target"]}"\n')
    assert_one_line_naming(*run_main(capsys, "run", "--config", str(config), "--check"), "run", junk)


@pytest.mark.parametrize("case", ["missing", "not a sequence"])
def test_run_check_refuses_a_replay_source_that_run_would_refuse(tmp_path, capsys, good, case):
    """``--check`` checks what ``run`` checks: a replay directory that is missing, or that
    is not a sequence, is one line naming it and exit 2 (before: --check passed it)."""
    directory = tmp_path / "recorded"
    if case == "not a sequence":
        directory.mkdir()
        (directory / "notes.txt").write_text("not frames\n")
    config = tmp_path / "cubeloc.toml"
    config.write_text(f'name = "t"\n[camera]\nsource = "replay:{directory}"\n[positioning]\n'
                      f'calibration = "{good / "camera.yaml"}"\ntarget = "{good / "target.yaml"}"\n')
    for argv in (["run", "--config", str(config), "--check"], ["run", "--config", str(config)]):
        assert_one_line_naming(*run_main(capsys, *argv), "run", directory)


def test_bad_files_from_outside(tmp_path, good):
    """The same, as a user sees it: a fresh ``cubeloc`` process per verb (run side by side)."""
    junk = tmp_path / "junk.bin"
    junk.write_bytes(bytes(range(256)) * 4)
    nan_calib = tmp_path / "nan.yaml"
    nan_calib.write_bytes(BAD_CALIBRATIONS["NaN fx"])
    cases = (
        ("pose", ["pose", "--target", str(junk), "--calib", str(good / "camera.yaml"), str(good / "image.png")], junk),
        ("track", ["track", "--target", str(good / "target.yaml"), "--calib", str(nan_calib),
                   "--sequence", str(good / "seq"), "--out", str(tmp_path / "o.tum")], nan_calib),
        ("run", ["run", "--config", str(junk), "--check"], junk),
    )
    processes = [subprocess.Popen([sys.executable, "-m", "cubeloc.daemon.cli", *argv], stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True, env={"PATH": "/usr/bin:/bin"},
                                  cwd=Path(__file__).resolve().parents[1]) for _, argv, _ in cases]
    for (verb, _, named), process in zip(cases, processes, strict=True):
        out, err = process.communicate(timeout=120)
        assert_one_line_naming(process.returncode, out, err, verb, named)


# -- Hypothesis: valid documents mutated into junk -------------------------------------------
JUNK_SCALARS = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-(10**30), max_value=10**30),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8),
)
JUNK = st.recursive(JUNK_SCALARS, lambda inner: st.lists(inner, max_size=4)
                    | st.dictionaries(st.text(max_size=6), inner, max_size=4), max_leaves=12)


def _paths(node, prefix=()):
    """Every path into a nested dict/list document."""
    yield prefix
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _paths(value, (*prefix, key))
    elif isinstance(node, list):
        for index, value in enumerate(node):
            yield from _paths(value, (*prefix, index))


def _mutate(doc, path, value):
    if not path:
        return value
    copy = dict(doc) if isinstance(doc, dict) else list(doc)
    copy[path[0]] = _mutate(copy[path[0]], path[1:], value)
    return copy


def _mutations(document):
    paths = list(_paths(document))
    return st.tuples(st.sampled_from(paths), JUNK).map(lambda pv: _mutate(document, *pv))


TARGET_DOCS = [yaml.safe_load(CUBE), yaml.safe_load(f"family: tag36h11\ntags: [{{id: 0, corners: {SQUARE}}}]\n")]


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.sampled_from(TARGET_DOCS).flatmap(_mutations))
def test_fuzz_target_document(doc):
    """Whatever junk replaces a value, the result is a valid target or an InputFileError."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            target = parse_target(doc, "fuzz.yaml")
        except InputFileError as exc:
            assert str(exc).startswith("fuzz.yaml") and "\n" not in str(exc)
            return
    for tag in target.tags:
        assert np.all(np.isfinite(tag.corners)) and tag.size_m >= 1e-3


@settings(max_examples=120, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.just(yaml.safe_load(CALIB)).flatmap(_mutations))
def test_fuzz_calibration_document(tmp_path, doc):
    path = tmp_path / "fuzz.yaml"
    try:
        path.write_text(yaml.safe_dump(doc, allow_unicode=True))
    except (yaml.YAMLError, UnicodeEncodeError):  # surrogates PyYAML cannot write
        return
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            calibration = read_camera_info(path)
        except InputFileError as exc:
            assert str(exc).startswith(str(path)) and "\n" not in str(exc)
            return
    assert np.all(np.isfinite(calibration.camera_matrix)) and np.all(np.isfinite(calibration.distortion))
    assert 0 <= calibration.cx < calibration.width and 0 <= calibration.cy < calibration.height


CONFIG_VALUES = st.one_of(
    st.integers(min_value=-(2**63), max_value=2**63 - 1), st.floats(), st.booleans(),
    st.text(alphabet=st.characters(blacklist_categories=("Cs",)), max_size=10),
    st.lists(st.text(max_size=5), max_size=3),
)
CONFIG_FIELDS = [("", "name"), ("camera", "width"), ("camera", "exposure_us"), ("camera", "trigger"),
                 ("camera", "frame_timeout_s"), ("positioning", "max_reproj_rms_px"), ("zenoh", "connect"),
                 ("zenoh", "mode"), ("daemon", "timeout_streak"), ("logging", "level")]


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "nan" if math.isnan(value) else ("inf" if value == math.inf else "-inf" if value == -math.inf else repr(value))
    if isinstance(value, str):
        return '"' + value.encode("unicode_escape").decode("ascii").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return str(value)


@settings(max_examples=120, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.sampled_from(CONFIG_FIELDS), CONFIG_VALUES)
def test_fuzz_config_value(tmp_path, field, value):
    section, key = field
    text = f"{key} = {_toml_value(value)}\n"
    path = tmp_path / "fuzz.toml"
    path.write_text(f"[{section}]\n{text}" if section else text)
    try:
        config = load_config(path, environ={})
    except ConfigError as exc:
        assert str(exc).startswith(f"config {path}") and "\n" not in str(exc)
        return
    assert config.model_dump() is not None


def _sequence_with_a_truncated_frame(root: Path) -> Path:
    """Four frames; the third's PNG cut in half (a disk filled up while recording)."""
    from cubeloc.drivers.sequence import SequenceWriter

    with SequenceWriter(root / "seq") as writer:
        for k in range(4):
            writer.write(1000 + k, np.full((1024, 1280), 40 * k, np.uint8))
    third = sorted((root / "seq" / "mav0" / "cam0" / "data").iterdir())[2]
    third.write_bytes(third.read_bytes()[: third.stat().st_size // 2])
    return third


def test_a_truncated_frame_in_a_replay_is_dropped_and_counted_or_with_strict_stops(tmp_path, good):
    """As a camera's bad frame: dropped, counted, one warning naming it, and not OpenCV's
    own "[ WARN:0@...]" line beside it; ``cubeloc track --strict`` stops there, exit 2."""
    import subprocess
    import sys

    from cubeloc.drivers.base import CameraSettings, EndOfStream
    from cubeloc.drivers.replay import open_replay_source

    third = _sequence_with_a_truncated_frame(tmp_path)
    camera = open_replay_source(str(tmp_path / "seq"), CameraSettings())
    camera.start()
    stamps = []
    with pytest.raises(EndOfStream):
        while True:
            stamps.append(camera.next_frame(1.0).stamp_ns)
    assert stamps == [1000, 1001, 1003] and camera.stats.incomplete == 1 and camera.stats.delivered == 3

    argv = [sys.executable, "-m", "cubeloc.daemon.cli", "track", "--target", str(good / "target.yaml"),
            "--calib", str(good / "camera.yaml"), "--sequence", str(tmp_path / "seq"), "--out", str(tmp_path / "o.tum")]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "4 frames" in done.stdout and "dropped 1" in done.stdout
    assert str(third) in done.stderr and "WARN:" not in done.stderr and "Traceback" not in done.stderr
    strict = subprocess.run([*argv, "--strict"], capture_output=True, text=True, timeout=120)
    assert strict.returncode == 2 and strict.stderr.count("\n") == 1 and str(third) in strict.stderr, strict.stderr
    assert "WARN:" not in strict.stderr


def test_track_odometry_replay_drops_and_counts_bad_samples_and_refuses_a_broken_file(tmp_path, capsys, good):
    """``cubeloc track --odometry``: a NaN, a non-unit quaternion and an out-of-order sample
    are dropped and counted in the summary; a line that is not a document is exit 2, one
    line naming the file and the line."""
    rows = [{"stamp_ns": 900, "position": [0, 0, 0], "orientation": [0, 0, 0, 1]},
            {"stamp_ns": 950, "position": [float("nan"), 0, 0], "orientation": [0, 0, 0, 1]},
            {"stamp_ns": 960, "position": [0, 0, 0], "orientation": [0, 0, 0.5, 0.5]},
            {"stamp_ns": 800, "position": [0, 0, 0], "orientation": [0, 0, 0, 1]},
            {"stamp_ns": 990, "position": [0.01, 0, 0], "orientation": [0, 0, 0, 1]}]
    odometry = tmp_path / "odom.jsonl"
    odometry.write_text("".join(json.dumps(r) + "\n" for r in rows))
    argv = ["track", "--target", str(good / "target.yaml"), "--calib", str(good / "camera.yaml"),
            "--sequence", str(good / "seq"), "--out", str(tmp_path / "out.tum"), "--odometry", str(odometry)]
    code, out, err = run_main(capsys, *argv)
    assert code == 0, err
    assert "odometry samples 2" in out and "odometry dropped (nan) 1" in out, out
    assert "odometry dropped (not_unit) 1" in out and "odometry dropped (out_of_order) 1" in out, out
    odometry.write_text(json.dumps(rows[0]) + "\n{\"stamp_ns\": 1000\n")
    code, out, err = run_main(capsys, *argv)
    assert code == 2 and err.count("\n") == 1 and f"{odometry}:2" in err and "Traceback" not in err, err
