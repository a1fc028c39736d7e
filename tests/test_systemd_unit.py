"""The systemd unit and the default config shipped in systemd/."""

from __future__ import annotations

import configparser
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from cubeloc.daemon.config import Config, load_config

REPO = Path(__file__).resolve().parents[1]
UNIT = REPO / "systemd" / "cubeloc.service"


def _unit_for_this_machine(tmp_path: Path, text: str | None = None) -> Path:
    """The unit with ExecStart pointing at this checkout's cubeloc (verify checks it exists)."""
    text = text if text is not None else UNIT.read_text()
    cubeloc = Path(sys.executable).with_name("cubeloc")
    path = tmp_path / "cubeloc.service"
    path.write_text(text.replace("/opt/cubeloc/.venv/bin/cubeloc", str(cubeloc)))
    return path


def _verify(path: Path) -> subprocess.CompletedProcess:
    return subprocess.run(["systemd-analyze", "verify", str(path)], capture_output=True, text=True, timeout=60)


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_unit_passes_systemd_analyze_verify(tmp_path):
    result = _verify(_unit_for_this_machine(tmp_path))
    assert result.returncode == 0 and result.stderr.strip() == "", result.stderr
    # systemd-analyze only warns (exit 0) on an unknown key: the empty stderr above is the check.
    broken = _verify(_unit_for_this_machine(tmp_path, UNIT.read_text().replace("WatchdogSec=", "WatchdogSecs=")))
    assert "WatchdogSecs" in broken.stderr


def test_unit_has_what_the_daemon_relies_on():
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str
    unit.read_string(UNIT.read_text())
    service = unit["Service"]
    assert service["Type"] == "notify" and service["NotifyAccess"] == "main"
    assert service["Restart"] == "on-failure" and float(service["RestartSec"]) > 0
    assert "PYTHONUNBUFFERED=1" in service["Environment"]
    # ProtectSystem=strict: numba's compiled kernels need a writable cache of their own
    assert f"NUMBA_CACHE_DIR=/var/cache/{service['CacheDirectory']}/" in service["Environment"]
    assert service["User"] == "cubeloc" and service["DeviceAllow"].startswith("char-usb_device")
    assert "PrivateNetwork" not in service  # GigE cameras and Zenoh need the host network
    assert "--config /etc/cubeloc/cubeloc.toml" in service["ExecStart"]
    assert int(service["WatchdogSec"]) > 1.0 + 5.0  # above the loop's stall limit (frame timeout + 5 s)


def test_default_config_is_valid_and_states_the_defaults():
    shipped = load_config(REPO / "systemd" / "cubeloc.toml", environ={})
    # The file documents the built-in defaults: they must not drift apart.
    assert shipped == Config.model_validate({"name": shipped.name})
