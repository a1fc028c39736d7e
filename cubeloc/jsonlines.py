"""Files of JSON documents, one per line (``cubeloc track --poses``, ``record --odometry``)."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from cubeloc.atomic import atomic_write_text
from cubeloc.errors import InputFileError

T = TypeVar("T")


def read_json_lines(path: str | os.PathLike[str], parse: Callable[[dict], T | None], what: str) -> list[T]:
    """``parse`` of every non-blank line's document, in the file's order (None: left out);
    InputFileError naming the file, the line and what was expected when a line is not JSON
    or ``parse`` raises ValueError, KeyError, TypeError or AttributeError."""
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{path}: cannot read ({exc})") from None
    out = []
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            value = parse(json.loads(line))
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise InputFileError(f"{path}:{number}: not a {what} document ({exc})") from None
        if value is not None:
            out.append(value)
    return out


def write_json_lines(path: str | os.PathLike[str], documents: list[dict]) -> None:
    """The documents, one JSON per line, written atomically (what ``read_json_lines`` reads)."""
    atomic_write_text(Path(path), "".join(json.dumps(doc) + "\n" for doc in documents))
