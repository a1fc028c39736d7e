"""cubeloc: the one installed package, and its shared core (version, error hierarchy, safe
file writes).

Its subpackages live in folders of their own at the top of the repository (pyproject.toml
maps each): ``cubeloc.drivers`` (cameras, drivers/), ``cubeloc.fakes`` (synthetic camera,
fakes/), ``cubeloc.calib`` (camera calibration, calib/), ``cubeloc.positioning`` (target,
detection, pose, tracker, positioning/) and ``cubeloc.daemon`` (configuration, CLI, the
capture -> positioning -> Zenoh loop, daemon/).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("cubeloc")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"
