"""cubeloc: the one installed package, and its shared core (version, error hierarchy, safe
file writes).

Its subpackages live in folders of their own at the top of the repository (pyproject.toml
maps each): ``cubeloc.drivers`` (cameras, drivers/), ``cubeloc.fakes`` (synthetic camera,
fakes/), ``cubeloc.calib`` (camera calibration, calib/), ``cubeloc.positioning`` (target,
detection, pose, tracker, positioning/) and ``cubeloc.daemon`` (configuration, CLI, the
capture -> positioning -> Zenoh loop, daemon/).
"""

from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

# In a source tree the subpackages are the folders beside this one: found here, they are this
# tree's own, also for a second checkout run with PYTHONPATH=<tree> beside an editable
# install of another (the benchmarks' side-by-side runs). An installed wheel has them inside.
_TREE = Path(__file__).resolve().parent.parent
if not (Path(__file__).parent / "positioning").is_dir() and (_TREE / "positioning" / "__init__.py").is_file():
    __path__.append(str(_TREE))

try:
    __version__ = version("cubeloc")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"
