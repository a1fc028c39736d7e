"""One module per ``cubeloc`` verb; see ``daemon.cli``."""

from __future__ import annotations

from pathlib import Path


def check_out(out: Path, force: bool) -> None:
    """InputFileError unless ``out`` may be written: new (or ``force``), in a directory."""
    from cubeloc.errors import InputFileError

    if out.exists() and not force:
        raise InputFileError(f"{out}: already exists; use --force to replace it")
    if not out.parent.is_dir():
        raise InputFileError(f"--out {out}: directory {out.parent} does not exist")
