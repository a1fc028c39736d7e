"""The systemd unit's hardening, its documentation, and what the camera needs (issue 8).

``systemd-analyze verify`` (and ``security --offline``) when systemd is installed; the
unit is parsed in any case, so the checks that matter run everywhere.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
UNIT = REPO / "systemd" / "cubeloc.service"
README = REPO / "systemd" / "README.md"
UDEV_RULE = REPO / "systemd" / "99-cubeloc-cameras.rules"

# Directives of [Service] that are sandboxing/hardening (systemd.exec(5) "Security",
# "Sandboxing", "System Call Filtering", "Capabilities", "Credentials").
HARDENING = re.compile(
    r"^(User|Group|UMask|DevicePolicy|DeviceAllow|NoNewPrivileges|CapabilityBoundingSet|AmbientCapabilities"
    r"|Protect\w+|Private\w+|ReadWritePaths|ReadOnlyPaths|InaccessiblePaths|StateDirectory|CacheDirectory|ConfigurationDirectory"
    r"|Restrict\w+|LockPersonality|RemoveIPC|SystemCall\w+|MemoryDenyWriteExecute|IPAddress\w+|ProcSubset"
    r"|KeyringMode|DynamicUser|SupplementaryGroups)$"
)
# Options that would take the camera or the network away from the daemon.
CAMERA_BREAKERS = ("PrivateDevices", "PrivateNetwork", "PrivateUsers", "IPAddressDeny", "DynamicUser")


def service_section() -> dict[str, list[str]]:
    """[Service] as {directive: [values]} (a directive may repeat)."""
    section, out = None, {}
    for raw in UNIT.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = line
            continue
        if section == "[Service]":
            key, _, value = line.partition("=")
            out.setdefault(key.strip(), []).append(value.strip())
    return out


def documented_options() -> set[str]:
    """Directives named in the first column of the README's hardening table."""
    text = README.read_text()
    table = text[text.index("## Hardening"):]
    names = set()
    for line in table.splitlines():
        if line.startswith("| `"):
            first = line.split("|")[1]
            names.update(re.findall(r"`(\w+)=", first))
    return names


def test_every_hardening_option_is_documented_and_every_documented_one_is_set():
    service = service_section()
    in_unit = {key for key in service if HARDENING.match(key)}
    assert len(in_unit) >= 25
    documented = documented_options()
    assert in_unit - documented == set(), "hardening options missing from systemd/README.md"
    assert documented - in_unit == set(), "systemd/README.md documents options the unit lacks"


def test_the_camera_and_the_network_stay_reachable():
    service = service_section()
    single = {key: values[-1] for key, values in service.items()}
    for breaker in CAMERA_BREAKERS:
        assert breaker not in service, f"{breaker}= would cut the daemon off its camera or network"
    assert single["User"] == "cubeloc" and single["Group"] == "cubeloc"
    assert single["CapabilityBoundingSet"] == "" and single["NoNewPrivileges"] == "yes"
    assert single["DevicePolicy"] == "closed"
    assert "char-usb_device rw" in service["DeviceAllow"]  # /dev/bus/usb/BBB/DDD, read-write
    families = set(single["RestrictAddressFamilies"].split())
    assert {"AF_INET", "AF_INET6", "AF_NETLINK", "AF_UNIX"} <= families  # GigE + Zenoh, hot-plug, journal
    assert single["ProtectSystem"] == "strict" and "/run/lock" in single["ReadWritePaths"]
    # The udev rule hands USB3 Vision cameras to the service's group, read-write.
    rules = [line for line in UDEV_RULE.read_text().splitlines() if line and not line.startswith("#")]
    camera_rules = [line for line in rules if "GROUP=" in line]
    assert len(camera_rules) >= 2
    for line in camera_rules:
        assert f'GROUP="{single["Group"]}"' in line and 'MODE="0660"' in line


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_analyze_verify_and_exposure(tmp_path):
    unit = tmp_path / "cubeloc.service"
    unit.write_text(UNIT.read_text().replace("/opt/cubeloc/.venv/bin/cubeloc", str(Path(sys.executable).with_name("cubeloc"))))
    verify = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert verify.returncode == 0 and verify.stderr.strip() == "", verify.stderr
    security = subprocess.run(["systemd-analyze", "security", "--offline=true", str(unit)],
                              capture_output=True, text=True, timeout=60)
    if "--offline" in security.stderr or "unrecognized option" in security.stderr:
        pytest.skip("this systemd-analyze has no 'security --offline' (systemd < 250)")
    match = re.search(r"Overall exposure level for \S+: (\d+\.\d+)", security.stdout)
    assert match, security.stdout[-500:] + security.stderr[-500:]
    assert float(match.group(1)) <= 3.5  # "OK"; an unhardened service scores 9.6
