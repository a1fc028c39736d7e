"""The corners cache: what detection found in each image of a directory, kept next to them.

As in mrcal, detection is the slow part and solving the part one repeats (another
distortion model, a fixed principal point), so ``corners.yaml`` in an image directory
remembers, per image file, its content hash, size and the board points found (or that
none were). A cache made for another board spec is ignored; an image whose bytes
changed is detected again. The file is written atomically and is plain YAML, so other
tools can read the corners too.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import structlog
import yaml

from cubeloc.atomic import atomic_write_text
from cubeloc.calib.boards import BoardSpec
from cubeloc.calib.detect import Detection

CACHE_NAME = "corners.yaml"
SCHEMA = "cubeloc.corners/1"

log = structlog.get_logger()


@dataclass(frozen=True)
class ImageRecord:
    """One image file and what detection found in it."""

    name: str  # file name inside its directory
    sha256: str
    width: int
    height: int
    detection: Detection | None


def _detection_to_dict(detection: Detection) -> dict:
    return {
        "ids": [int(i) for i in detection.ids],
        # 9 significant digits give back the exact float32 the detector returned
        "points": [[float(f"{u:.9g}"), float(f"{v:.9g}")] for u, v in detection.image_points.astype(np.float32)],
        "edge_width_px": round(float(detection.edge_width_px), 3),
    }


def _detection_from_dict(node: dict, board: BoardSpec) -> Detection:
    ids = np.asarray(node["ids"], dtype=np.int32)
    points = np.asarray(node["points"], dtype=np.float32).reshape(-1, 2)
    if len(ids) != len(points) or (len(ids) and (ids.min() < 0 or ids.max() >= len(board.object_points()))):
        raise ValueError("ids and points do not match the board")
    return Detection(points, board.object_points()[ids], ids, float(node["edge_width_px"]))


def load_cache(directory: str | os.PathLike[str], board: BoardSpec) -> dict[str, ImageRecord]:
    """The cached records of ``directory`` for ``board`` (empty if none or unusable)."""
    path = Path(directory) / CACHE_NAME
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return {}
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        log.warning("corners cache unreadable, detecting again", path=str(path), error=str(exc).splitlines()[0])
        return {}
    if not isinstance(doc, dict) or doc.get("schema") != SCHEMA or doc.get("board") != board.text:
        return {}
    records = {}
    for name, node in (doc.get("images") or {}).items():
        try:
            detection = _detection_from_dict(node["board"], board) if node.get("board") else None
            records[name] = ImageRecord(name, str(node["sha256"]), int(node["width"]), int(node["height"]), detection)
        except (KeyError, TypeError, ValueError):
            continue  # one bad entry: that image is detected again
    return records


def save_cache(directory: str | os.PathLike[str], board: BoardSpec, records: list[ImageRecord]) -> bool:
    """Write ``corners.yaml`` (merging with what is there); False if the directory is read-only."""
    directory = Path(directory)
    merged = load_cache(directory, board)
    merged.update({r.name: r for r in records})
    images = {}
    for name in sorted(merged):
        r = merged[name]
        images[name] = {
            "sha256": r.sha256, "width": r.width, "height": r.height,
            "board": _detection_to_dict(r.detection) if r.detection is not None else None,
        }
    text = yaml.safe_dump({"schema": SCHEMA, "board": board.text, "images": images}, sort_keys=False, default_flow_style=None)
    try:
        atomic_write_text(directory / CACHE_NAME, text)
    except OSError as exc:
        log.warning("cannot write the corners cache", path=str(directory / CACHE_NAME), error=str(exc))
        return False
    return True
