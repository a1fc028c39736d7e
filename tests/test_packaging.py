"""cubeloc installs one top-level package, ``cubeloc``: the folders daemon/, drivers/, calib/,
fakes/ and positioning/ are its subpackages (pyproject.toml maps them), so nothing else lands
in site-packages (``daemon`` is python-daemon's import name)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]
FOLDERS = ("daemon", "drivers", "calib", "fakes", "positioning")


def _setuptools() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]


def _packages_on_disk() -> set[str]:
    names = set()
    for folder in ("cubeloc", *FOLDERS):
        for init in (REPO / folder).rglob("__init__.py"):
            parts = init.parent.relative_to(REPO).parts
            names.add(".".join(parts if folder == "cubeloc" else ("cubeloc", *parts)))
    return names


def test_every_folder_is_a_subpackage_of_cubeloc_in_the_wheel():
    setuptools = _setuptools()
    assert set(setuptools["packages"]) == _packages_on_disk()
    assert setuptools["package-dir"] == {f"cubeloc.{folder}": folder for folder in FOLDERS}


def test_importing_every_module_loads_nothing_outside_cubeloc():
    # Run from the repository's root, where a stray ``import positioning`` (or a "module:function"
    # string naming one) would succeed and load a second copy of the module beside cubeloc's.
    script = (
        "import importlib, pkgutil, sys\n"
        "import cubeloc\n"
        "names = ['cubeloc.' + f for f in sys.argv[1:]]\n"
        "for name in names:\n"
        "    package = importlib.import_module(name)\n"
        "    for info in pkgutil.walk_packages(package.__path__, name + '.'):\n"
        "        if not info.name.endswith('__main__'):\n"
        "            importlib.import_module(info.name)\n"
        "from cubeloc.drivers.registry import BACKENDS\n"
        "import cubeloc.daemon.cameras\n"
        "for factory in BACKENDS.values():\n"
        "    getattr(importlib.import_module(factory.split(':')[0]), factory.split(':')[1])\n"
        "print(sorted({m.split('.')[0] for m in sys.modules} & set(sys.argv[1:])))\n"
    )
    done = subprocess.run([sys.executable, "-c", script, *FOLDERS], cwd=REPO, capture_output=True,
                          text=True, timeout=240)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "[]"
