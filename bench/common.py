"""Helpers shared by the benchmarks: timing with medians, and the results file."""

from __future__ import annotations

import contextlib
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "docs" / "benchmarks.md"
HEADER = (
    "# Benchmarks\n\n"
    "Written by `make bench` (each section by its own module in `bench/`). Medians over "
    "repeated runs; the machine is shared and noisy, so compare ratios measured side by side.\n"
)


def machine_line() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, NumPy SIMD {_simd()}, Python {platform.python_version()}"


def _simd() -> str:
    """The widest SIMD extension NumPy dispatches its kernels to on this CPU (NumPy's own
    report): the same code rounds differently on another, and the tracker's runs on the
    family follow the rounding (docs/family.md, "Draws")."""
    import numpy as np

    simd = np.show_config(mode="dicts").get("SIMD Extensions", {})
    found = simd.get("found") or simd.get("baseline") or ["unknown"]
    return found[-1]


def without_gtsam(bench: str) -> bool:
    """True, after saying so on stderr, when GTSAM is not installed: the GTSAM benchmarks
    need ``pip install gtsam==4.3.0``, which cubeloc does not depend on."""
    try:
        import gtsam  # noqa: F401
    except ImportError:
        print(f"{bench}: needs GTSAM (pip install gtsam==4.3.0); cubeloc does not depend on it", file=sys.stderr)
        return True
    return False


def median_seconds(fn: Callable[[], object], repeats: int = 7, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` over ``repeats`` runs after ``warmup`` runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def markdown_table(headers: list[str], rows: list[list[object]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def update_section(name: str, title: str, body: str) -> None:
    """Replace (or append) the section ``name`` of docs/benchmarks.md."""
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    text = RESULTS.read_text() if RESULTS.exists() else HEADER
    stamp = time.strftime("%Y-%m-%d", time.gmtime())
    block = (
        f"<!-- bench:{name} -->\n## {title}\n\n{body.rstrip()}\n\n"
        f"_Measured {stamp} on {machine_line()}; reproduce with `make bench` "
        f"(or `.venv/bin/python -m bench {name}`)._\n<!-- /bench:{name} -->\n"
    )
    pattern = re.compile(rf"<!-- bench:{re.escape(name)} -->.*?<!-- /bench:{re.escape(name)} -->\n", re.S)
    text = pattern.sub(lambda _: block, text) if pattern.search(text) else text.rstrip("\n") + "\n\n" + block
    RESULTS.write_text(text)


def package_prefix(tree: Path) -> str:
    """How ``tree`` names its modules: ``"cubeloc."`` in a tree that installs one package
    (``cubeloc.daemon.cli``), ``""`` in one older than that (``daemon.cli``)."""
    pyproject = (tree / "pyproject.toml").read_text(encoding="utf-8")
    return "cubeloc." if '"cubeloc.daemon" = "daemon"' in pyproject else ""


@contextlib.contextmanager
def previous_tree(commit: str, work: Path, given: str | None = None) -> Iterator[Path | None]:
    """A checkout of ``commit`` (``git worktree`` under ``work``, removed afterwards) to run
    the previous code side by side with this tree; ``given``, an existing checkout, is used
    as it is. None when git cannot make one (a tarball without history)."""
    if given:
        yield Path(given)
        return
    tree = work / "previous"
    done = subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", str(tree), commit],
                          capture_output=True, text=True)
    try:
        yield tree if done.returncode == 0 else None
    finally:
        if done.returncode == 0:
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)], capture_output=True)


def baseline_commit(default: str) -> str:
    """The commit a bench runs beside this tree: ``CUBELOC_BENCH_BASELINE_COMMIT`` when set
    (the tree before a change, to measure the change alone), else the bench's ``default``."""
    return os.environ.get("CUBELOC_BENCH_BASELINE_COMMIT") or default


@contextlib.contextmanager
def renders_root(bench: str, variable: str = "CUBELOC_BENCH_SEQUENCES") -> Iterator[tuple[Path, Path]]:
    """(where a bench keeps its renders, a scratch folder): the folder ``variable`` names
    when set (kept for the next run), else the scratch folder, removed afterwards."""
    keep = os.environ.get(variable)
    with tempfile.TemporaryDirectory(prefix=f"cubeloc-bench-{bench}-") as tmp:
        root = Path(keep) if keep else Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        yield root, Path(tmp)
