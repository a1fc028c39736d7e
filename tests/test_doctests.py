"""The usage examples in docstrings (``>>>``) run, so that they stay true: every module of
the installed packages that has one is found and its examples run here."""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# the folders of the installed package ``cubeloc``: cubeloc/ itself, and the five that
# pyproject.toml maps to cubeloc.daemon, cubeloc.drivers, ...
PACKAGES = ("cubeloc", "daemon", "drivers", "calib", "positioning", "fakes")


def _modules_with_examples() -> list[str]:
    names = []
    for package in PACKAGES:
        for path in sorted((REPO / package).rglob("*.py")):
            if ">>>" in path.read_text(encoding="utf-8"):
                parts = path.relative_to(REPO).with_suffix("").parts
                parts = parts if package == "cubeloc" else ("cubeloc", *parts)
                names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


MODULES = _modules_with_examples()


def test_the_modules_with_examples_are_found():
    assert "cubeloc.positioning.tracking.pose_fit" in MODULES and "cubeloc.positioning.evaluation" in MODULES


@pytest.mark.parametrize("name", MODULES)
def test_a_modules_examples_run(name: str):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS, verbose=False)
    assert result.attempted > 0 and result.failed == 0, f"{name}: {result.failed} of {result.attempted} failed"
