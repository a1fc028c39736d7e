"""cubeloc: shared core (version, error hierarchy, safe file writes).

The functional packages are top-level: ``drivers`` (cameras), ``fakes`` (synthetic camera),
``calib`` (camera calibration), ``positioning`` (target, detection, pose, tracker) and
``daemon`` (configuration, CLI, the capture -> positioning -> Zenoh loop).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("cubeloc")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"
