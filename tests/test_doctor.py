"""``cubeloc doctor`` against Aravis' fake camera, real files and real Zenoh sessions.

A temporary config names Aravis' built-in fake camera (``aravis:Fake_1``, serial ``1``,
sensor 2048x2048, set to 512x512), a calibration and a target file, and a Zenoh listen
endpoint where a stand-in daemon session holds the ``alive`` token. Then each thing is
broken in turn and the doctor must say FAIL with a fix and exit 1.
"""

from __future__ import annotations

import json
import socket
from pathlib import Path

import numpy as np
import pytest
import structlog
import zenoh
from gv_fake import FAKE_GV_CAMERA, GvFake, gvcp_listening

from cubeloc.calib.camera_info import CameraCalibration, write_camera_info
from cubeloc.daemon.cli import main
from cubeloc.daemon.commands.doctor import FAIL, OK, WARN, packet_size_verdict
from cubeloc.drivers.ownership import CameraLock
from cubeloc.net import free_port
from cubeloc.positioning.target import default_cube_yaml

NAME = "doctortest"
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def keep_logging_config():
    """``main()`` configures structlog onto this test's captured stderr; put it back after."""
    saved = structlog.get_config()
    yield
    structlog.configure(**saved)


@pytest.fixture(autouse=True)
def lock_dir(tmp_path, monkeypatch):
    for variable in [v for v in __import__("os").environ if v.startswith("CUBELOC_")]:
        monkeypatch.delenv(variable)
    monkeypatch.setenv("CUBELOC_LOCK_DIR", str(tmp_path / "locks"))
    (tmp_path / "locks").mkdir()


def write_setup(root, *, port: int, source: str = "aravis:Fake_1", serial: str = "1",
                size: tuple[int, int] = (512, 512), target: str | None = None, connect: str | None = None) -> str:
    k = np.array([[600.0, 0, (size[0] - 1) / 2], [0, 600.0, (size[1] - 1) / 2], [0, 0, 1]])
    write_camera_info(root / "camera.yaml", CameraCalibration(size[0], size[1], k, np.zeros(5),
                                                              metadata={"camera_serial": serial, "rms_px": 0.2}))
    (root / "target.yaml").write_text(target if target is not None else default_cube_yaml())
    zenoh_lines = f'listen = ["tcp/127.0.0.1:{port}"]\n' + (f'connect = ["{connect}"]\n' if connect else "")
    (root / "cubeloc.toml").write_text(
        f'name = "{NAME}"\n[camera]\nsource = "{source}"\nwidth = 512\nheight = 512\n'
        f'[positioning]\ncalibration = "{root / "camera.yaml"}"\ntarget = "{root / "target.yaml"}"\n'
        f"[zenoh]\n{zenoh_lines}multicast_scouting = false\n"
    )
    return str(root / "cubeloc.toml")


def stand_in_daemon(port: int, zenoh_file=None) -> tuple[zenoh.Session, object]:
    """A Zenoh peer listening where the daemon would, and its liveliness token."""
    conf = zenoh.Config.from_file(str(zenoh_file)) if zenoh_file else zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    session = zenoh.open(conf)
    return session, session.liveliness().declare_token(f"cubeloc/{NAME}/alive")


def doctor(capsys, config: str, *extra: str) -> tuple[int, dict[str, list[dict]]]:
    capsys.readouterr()  # whatever the test itself logged
    code = main(["doctor", "--config", config, "--json", "--timeout", "0.5", *extra])
    report = json.loads(capsys.readouterr().out)
    assert report["ok"] == (code == 0)
    by_check: dict[str, list[dict]] = {}
    for check in report["checks"]:
        assert check["level"] in (OK, WARN, FAIL)
        assert check["level"] != FAIL or check["fix"], check  # every failure comes with its fix
        by_check.setdefault(check["check"], []).append(check)
    return code, by_check


def levels(by_check, name: str) -> set[str]:
    return {c["level"] for c in by_check.get(name, [])}


def test_all_well_on_the_fake_camera(tmp_path, capsys):
    port = free_port()
    config = write_setup(tmp_path, port=port)
    daemon, _token = stand_in_daemon(port)
    try:
        code, checks = doctor(capsys, config, "--fake")
    finally:
        daemon.close()
    assert code == 0, checks
    for name in ("config", "aravis", "cameras", "camera", "calibration", "target", "zenoh"):
        assert levels(checks, name) == {OK}, (name, checks.get(name))
    assert "Fake_1" in checks["cameras"][0]["message"]
    assert "serial 1" in checks["calibration"][0]["message"]
    assert f"cubeloc/{NAME}/alive is there" in checks["zenoh"][0]["message"]
    assert levels(checks, "service") <= {OK, WARN}  # WARN where systemd does not run (CI, containers)


def test_every_broken_thing_fails_with_its_fix(tmp_path, capsys):
    port = free_port()
    config = write_setup(tmp_path, port=port, serial="22334455", size=(1280, 1024),
                         target="family: tag36h11\ncube: {side: 0.1, tag_size: 0.2, ids: [0, 1, 2, 3, 4, 5]}\n")
    with socket.socket() as squatter:  # another program on the daemon's port
        squatter.bind(("127.0.0.1", port))
        squatter.listen()
        code, checks = doctor(capsys, config, "--fake")
    assert code == 1
    calibration = " ".join(c["message"] for c in checks["calibration"])
    assert levels(checks, "calibration") == {FAIL}
    assert "1280x1024" in calibration and "512x512" in calibration and "serial 22334455" in calibration
    assert levels(checks, "target") == {FAIL} and "tag_size" in checks["target"][0]["message"]
    assert levels(checks, "zenoh") == {FAIL} and "port is taken" in checks["zenoh"][0]["message"]
    assert levels(checks, "camera") == {OK}  # the camera itself is fine


def run_as_printed(command: str, tmp_path) -> None:
    """Run a suggested command exactly as printed (``cubeloc`` is this checkout's): it
    must exit 0, or, for a live calibration that waits for the board, be running after
    5 s (then it is interrupted, as a technician would) with no other complaint than that."""
    import shlex
    import signal
    import subprocess
    import sys

    words = shlex.split(command)
    assert words[0] == "cubeloc", command
    # Ctrl-C as a technician's terminal delivers it: a suite started in the background
    # (``make test &``) ignores SIGINT, and its children would inherit that and never stop
    process = subprocess.Popen([sys.executable, "-m", "cubeloc.daemon.cli", *words[1:]], cwd=tmp_path, text=True,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        out, err = process.communicate(timeout=5)
        assert process.returncode == 0, (command, err)
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGINT)
        try:
            out, err = process.communicate(timeout=20)
        finally:
            process.kill()  # (a no-op once it has exited) never left running
        # it grabbed until told to stop: its one complaint is that no view was kept
        errors = [line for line in err.splitlines() if "error" in line.lower()]
        assert errors and all("stopped on request" in line for line in errors), (command, err)
        assert words[1] == "calibrate" and "--camera" in words, command  # the one that waits for views


def test_every_suggested_command_runs_as_printed(tmp_path, capsys):
    """Before: ``cubeloc calibrate --board SPEC --camera Fake_1 ...`` (a placeholder and the
    source without its ``aravis:``): it could not run."""
    port = free_port()
    config = write_setup(tmp_path, port=port, serial="22334455", size=(1280, 1024), target="family: [\n")
    code, checks = doctor(capsys, config, "--fake")
    assert code == 1
    commands = {c["command"] for group in checks.values() for c in group if c["command"]}
    assert {"cubeloc generate cube --help"} < commands, commands
    calibrate = next(c for c in commands if c.startswith("cubeloc calibrate"))
    assert "--camera aravis:Fake_1" in calibrate and f"--config {config}" in calibrate and "--force" in calibrate
    for command in sorted(commands):
        run_as_printed(command, tmp_path)


def test_missing_camera_unreachable_router_and_text_output(tmp_path, capsys):
    port, closed = free_port(), free_port()
    config = write_setup(tmp_path, port=port, source="aravis:NO-SUCH-CAMERA", connect=f"tcp/127.0.0.1:{closed}")
    code = main(["doctor", "--config", config, "--fake", "--timeout", "0.5"])
    lines = capsys.readouterr().out.splitlines()
    assert code == 1
    assert all(line.split()[0] in (OK, WARN, FAIL) for line in lines[:-1]) and lines[-1].endswith("warnings")
    camera = next(line for line in lines if line.startswith("FAIL  camera:"))
    assert "aravis:NO-SUCH-CAMERA" in camera and "aravis:Fake_1" in camera  # the fix lists what is there
    router = next(line for line in lines if f"127.0.0.1:{closed} (connect)" in line)
    assert router.startswith("FAIL") and "-- fix:" in router
    listen = next(line for line in lines if f"127.0.0.1:{port} (listen)" in line)
    assert listen.startswith("WARN") and "not running" in listen


def test_a_camera_in_use_is_not_opened(tmp_path, capsys):
    config = write_setup(tmp_path, port=free_port())
    with CameraLock("Aravis-Fake-1"):  # as the running daemon holds it (vendor-model-serial)
        code, checks = doctor(capsys, config, "--fake")
    in_use = [c for c in checks["camera"] if "in use" in c["message"]]
    assert in_use and in_use[0]["level"] == OK and "held by pid" in in_use[0]["message"]


def test_bad_config_is_one_failure_not_a_traceback(tmp_path, capsys):
    config = tmp_path / "bad.toml"
    config.write_bytes(b"[camera]\nwidth = 'wide'\n")
    code, checks = doctor(capsys, str(config))
    assert code == 1 and levels(checks, "config") == {FAIL} and str(config) in checks["config"][0]["message"]
    assert levels(checks, "aravis") == {OK}  # what does not need the config is still checked


@pytest.mark.parametrize(("packet", "interface", "mtu", "level", "words"), [
    (1400, "eth0", 1500, OK, "fit the MTU 1500"),
    (8192, "eth0", 9000, OK, "fit the MTU 9000"),
    (8192, "eth0", 1500, FAIL, "exceed the MTU 1500"),
    (1400, "eth1", 9000, WARN, "jumbo frames"),
    (1400, None, None, WARN, "unknown"),
])
def test_packet_size_against_mtu(packet, interface, mtu, level, words):
    check = packet_size_verdict("cam", packet, interface, mtu)
    assert check.level == level and words in check.message
    assert check.level == OK or check.fix


@pytest.mark.skipif(__import__("shutil").which(FAKE_GV_CAMERA) is None, reason=f"{FAKE_GV_CAMERA} not installed")
def test_gige_packet_size_on_the_gige_vision_fake(tmp_path, capsys):
    if gvcp_listening():
        pytest.skip("127.0.0.1:3956/udp is taken by another test's GigE Vision fake")
    fake = GvFake("GV08").start()
    try:
        code, checks = doctor(capsys, write_setup(tmp_path, port=free_port(), source="aravis:Aravis-Fake-GV08",
                                                  serial="GV08"))
    finally:
        fake.stop()
    gige = checks["gige"][0]
    assert "Aravis-Fake-GV08" in gige["message"] and " lo" in gige["message"] and "MTU 65536" in gige["message"]
    assert levels(checks, "calibration") == {OK}  # serial GV08, 512x512 within the 2048x2048 sensor


def test_zenoh_check_logs_in_with_the_daemons_credentials(tmp_path, capsys):
    """With examples/zenoh-acl.json5 the probe must log in (user and password from the
    file) and must not apply the daemon's access-control rules to itself."""
    (tmp_path / "zenoh-credentials.txt").write_text("cubeloc:daemon-secret\n")
    acl = tmp_path / "zenoh.json5"
    acl.write_text((REPO / "examples" / "zenoh-acl.json5").read_text()
                   .replace("/etc/cubeloc/", f"{tmp_path}/").replace("change-me-daemon-password", "daemon-secret"))
    port = free_port()
    config = write_setup(tmp_path, port=port)
    with open(config, "a") as toml:
        toml.write(f'config_file = "{acl}"\n')
    daemon, _token = stand_in_daemon(port, acl)
    try:
        _, checks = doctor(capsys, config, "--fake")
        acl.write_text(acl.read_text().replace('password: "daemon-secret"', 'password: "wrong"'))
        _, refused = doctor(capsys, config, "--fake")
    finally:
        daemon.close()
    assert levels(checks, "zenoh") == {OK} and "alive is there" in checks["zenoh"][0]["message"]
    assert levels(refused, "zenoh") == {FAIL}  # a wrong password in the file: the fix names the credentials
    assert "credentials" in refused["zenoh"][0]["fix"]


@pytest.mark.parametrize(("budget", "buffers", "level", "words"), [
    ("16", 8, OK, "usbfs_memory_mb 16 MB holds 8 buffers x 1.25 MB"),   # the kernel's default, our default
    ("16", 16, FAIL, "needs 16 buffers x 1.25 MB (1280x1024 Mono8) = 20.0 MB"),
    ("0", 64, OK, "0 (no limit)"),
    ("1000", 64, OK, "holds 64 buffers"),
])
def test_usbfs_budget_against_the_stream_on_a_fake_sysfs(tmp_path, budget, buffers, level, words):
    from cubeloc.daemon.commands.doctor_checks import USBFS_PARAMETER, check_usbfs
    from cubeloc.daemon.config import Config

    parameter = tmp_path / USBFS_PARAMETER
    parameter.parent.mkdir(parents=True)
    parameter.write_text(budget + "\n")
    config = Config.model_validate({"camera": {"stream_buffers": buffers}})
    check = check_usbfs(config, sysfs=tmp_path)
    assert check.level == level and words in check.message, check
    if level == FAIL:  # the fix both ways: at once, and for good
        assert f"echo 1000 | sudo tee {parameter}" in check.fix and "usbcore.usbfs_memory_mb=1000" in check.fix
        assert "options usbcore usbfs_memory_mb=1000" in check.fix
    assert check_usbfs(config, sysfs=tmp_path / "elsewhere").level == OK  # no usbcore: nothing to check


def test_the_stream_settings_reach_aravis():
    """camera.stream_buffers, usb_mode and usb_bandwidth_mbps from the config to the
    backend: the buffers in flight on the fake camera's stream (a USB3 camera is not at
    hand here: the USB mode and bandwidth are applied only to one)."""
    from cubeloc.daemon.cameras import make_camera
    from cubeloc.daemon.config import Config
    from cubeloc.drivers.aravis_camera import AravisCamera

    config = Config.model_validate({"camera": {"source": "aravis:Fake_1", "width": 512, "height": 512,
                                               "stream_buffers": 3, "usb_mode": "sync"}})
    settings = config.camera.settings()
    assert (settings.stream_buffers, settings.usb_mode, settings.usb_bandwidth_mbps) == (3, "sync", None)
    camera = make_camera(config.camera.source, settings)
    assert isinstance(camera, AravisCamera)
    with camera:
        assert camera._stream.get_n_buffers() == (3, 0)
        assert camera.read_settings().stream_buffers == 3
    with pytest.raises(Exception, match="usb_mode"):
        Config.model_validate({"camera": {"usb_mode": "turbo"}})
