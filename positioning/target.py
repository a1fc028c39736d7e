"""The target: a rigid set of AprilTags with known 3-D corners, defining the world frame.

A target file (YAML) is either explicit tags, for any rigid arrangement::

    family: tag36h11
    tags:
      - id: 0
        corners: [[x, y, z], [x, y, z], [x, y, z], [x, y, z]]   # TL, TR, BR, BL, metres

or the cube shorthand::

    family: tag36h11
    cube: {side: 0.18, tag_size: 0.144, ids: [0, 1, 2, 3, 4, 5]}

Cube layout (docs/target.md has a picture): the world origin is the cube centre, z up (the
cube stands on its ``-z`` face), and ``ids`` are the tags on the faces
``+x, +y, -x, -y, +z (top), -z (bottom)`` in that order. Side faces are printed upright
(tag "up" = world +z). Unfolded, the four side faces form a strip ``+x, +y, -x, -y`` from
left to right seen from outside, the top face sits above ``+x`` (its "up" is world -x) and
the bottom face below ``+x`` (its "up" is world +x).

or the Kalibr AprilGrid shorthand, Kalibr's own target file read as it is::

    target_type: 'aprilgrid'
    tagCols: 6
    tagRows: 6
    tagSize: 0.088      # metres, the outer black edge of a tag
    tagSpacing: 0.3     # the gap between two tags, as a fraction of tagSize

An AprilGrid has Kalibr's layout and origin: tag ``r * tagCols + c`` at row ``r`` (up the
board, +y) and column ``c`` (+x), the origin at the outer corner of tag 0's black border,
z out of the printed side; its tags are printed upside down in that frame (Kalibr's
generator turns them 180 degrees) and have a two-cell black border, and a black square
of the gap's size touches each tag's four corners. ``border_bits: 2`` states that border
in the other forms (any family, any layout); the default is the usual one cell.

Tag corners are TL, TR, BR, BL of the tag printed upright, on the outer edge of its black
border (interfaces.md); tag size is that outer black edge length.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cubeloc.errors import InputFileError

# Families both the AprilTag library and OpenCV's aruco module know.
KNOWN_FAMILIES = ("tag36h11", "tag25h9", "tag16h5", "tag36h10")
FAMILY_MAX_ID = {"tag36h11": 586, "tag25h9": 34, "tag16h5": 29, "tag36h10": 2319}

# Cube faces in the order of ``cube.ids``: (name, outward normal, tag "up" direction).
CUBE_FACES: tuple[tuple[str, tuple[float, float, float], tuple[float, float, float]], ...] = (
    ("+x", (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    ("+y", (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    ("-x", (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    ("-y", (0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    ("+z", (0.0, 0.0, 1.0), (-1.0, 0.0, 0.0)),
    ("-z", (0.0, 0.0, -1.0), (1.0, 0.0, 0.0)),
)

PLANARITY_TOLERANCE_M = 1e-4
# Sanity bounds on a file's numbers (metres): a target smaller than a millimetre or farther
# than a kilometre from its origin is a unit mistake or junk, and its arithmetic overflows.
MIN_TAG_SIZE_M = 1e-3
MAX_COORDINATE_M = 1e3
SQUARENESS_TOLERANCE = 1e-3  # relative, on edge lengths and diagonals


@dataclass(frozen=True)
class Tag:
    """One tag of a target: its id and 3-D corners (TL, TR, BR, BL) in the world frame."""

    tag_id: int
    corners: np.ndarray  # (4, 3) metres, world frame
    face: str = ""  # cube face name where the target is a cube

    @property
    def size_m(self) -> float:
        return float(np.mean(np.linalg.norm(np.roll(self.corners, -1, axis=0) - self.corners, axis=1)))

    @functools.cached_property
    def normal(self) -> np.ndarray:
        """Outward normal (the side the tag is seen from); cached, positioning asks often."""
        c = self.corners
        n = np.cross(c[1] - c[0], c[3] - c[0])  # right x down ... points into the tag
        return -n / np.linalg.norm(n)

    @functools.cached_property
    def center(self) -> np.ndarray:
        return self.corners.mean(axis=0)


@dataclass(frozen=True)
class CubeSpec:
    side_m: float
    tag_size_m: float
    ids: tuple[int, ...]


@dataclass(frozen=True)
class GridSpec:
    """A Kalibr AprilGrid's parameters (the gap squares are drawn from them)."""

    rows: int
    cols: int
    tag_size_m: float
    spacing: float  # the gap as a fraction of the tag size

    @property
    def gap_m(self) -> float:
        return self.spacing * self.tag_size_m

    def to_kalibr_yaml(self) -> str:
        return (f"target_type: 'aprilgrid'\ntagCols: {self.cols}\ntagRows: {self.rows}\n"
                f"tagSize: {self.tag_size_m:g}\ntagSpacing: {self.spacing:g}\n")


@dataclass(frozen=True)
class Target:
    """A validated target. ``tags`` are in file order; look up by id with ``tag(id)``.

    ``border_bits``: cells of black border around each tag's code (1, or 2 for a Kalibr
    AprilGrid); ``grid``: the AprilGrid the tags were made from, if any."""

    family: str
    tags: tuple[Tag, ...]
    cube: CubeSpec | None = None
    source: str = ""  # the file it came from, for messages
    border_bits: int = 1
    grid: GridSpec | None = None

    @property
    def ids(self) -> tuple[int, ...]:
        return tuple(t.tag_id for t in self.tags)

    def tag(self, tag_id: int) -> Tag:
        for t in self.tags:
            if t.tag_id == tag_id:
                return t
        raise KeyError(tag_id)

    def has(self, tag_id: int) -> bool:
        return any(t.tag_id == tag_id for t in self.tags)

    def corners_of(self, tag_ids: list[int] | tuple[int, ...]) -> np.ndarray:
        """(4N, 3) world corners of the given tags, TL TR BR BL each, in the given order."""
        return np.concatenate([self.tag(i).corners for i in tag_ids]).reshape(-1, 3)

    def to_yaml(self) -> str:
        """The explicit-tags form (always loadable, whatever the target was made from); a
        Kalibr AprilGrid's own file for an AprilGrid, so that its gap squares stay known."""
        if self.grid is not None:
            return self.grid.to_kalibr_yaml()
        doc: dict[str, Any] = {"family": self.family}
        if self.border_bits != 1:
            doc["border_bits"] = self.border_bits
        doc |= {
            "tags": [
                {"id": t.tag_id, "corners": [[round(float(v), 9) for v in c] for c in t.corners]}
                for t in self.tags
            ],
        }
        return yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)


def cube_tag_corners(side_m: float, tag_size_m: float, normal: np.ndarray, up: np.ndarray) -> np.ndarray:
    """TL, TR, BR, BL of a tag centred on a cube face, seen from outside. (4, 3) metres."""
    normal = np.asarray(normal, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    right = np.cross(up, normal)  # camera looking at the face: x right = up x normal
    center = normal * side_m / 2.0
    h = tag_size_m / 2.0
    return np.array(
        [
            center + h * (-right + up),
            center + h * (right + up),
            center + h * (right - up),
            center + h * (-right - up),
        ]
    )


def make_cube(
    side_m: float = 0.18,
    tag_size_m: float = 0.144,
    ids: tuple[int, ...] = (0, 1, 2, 3, 4, 5),
    family: str = "tag36h11",
) -> Target:
    """The cube shorthand as a Target (see the module docstring for the layout)."""
    if len(ids) != 6:
        raise InputFileError(f"cube.ids must list 6 tag ids (+x +y -x -y +z -z), got {len(ids)}")
    if not 0 < tag_size_m <= side_m:
        raise InputFileError(
            f"cube.tag_size {tag_size_m} m must be positive and no larger than cube.side {side_m} m"
        )
    tags = tuple(
        Tag(int(tag_id), cube_tag_corners(side_m, tag_size_m, np.array(n), np.array(u)), name)
        for tag_id, (name, n, u) in zip(ids, CUBE_FACES, strict=True)
    )
    target = Target(family, tags, CubeSpec(side_m, tag_size_m, tuple(int(i) for i in ids)))
    validate_target(target, "cube")
    return target


def make_board(rows: int = 6, cols: int = 6, tag_size_m: float = 0.088, gap_m: float = 0.026,
               first_id: int = 0, family: str = "tag36h11") -> Target:
    """A flat grid of tags (an AprilGrid such as Kalibr's): ``rows`` x ``cols`` tags of
    ``tag_size_m`` with ``gap_m`` between them, ids from ``first_id`` row by row, in the
    plane z = 0 facing +z, its top-left tag's top-left corner at the origin (x right along
    a row, y up the board, rows going down)."""
    pitch = tag_size_m + gap_m
    tags = []
    for row in range(rows):
        for col in range(cols):
            x0, y0 = col * pitch, -row * pitch
            corners = np.array([[x0, y0, 0.0], [x0 + tag_size_m, y0, 0.0], [x0 + tag_size_m, y0 - tag_size_m, 0.0],
                                [x0, y0 - tag_size_m, 0.0]])
            tags.append(Tag(first_id + row * cols + col, corners))
    target = Target(family, tuple(tags))
    validate_target(target, "board")
    return target


def make_aprilgrid(rows: int = 6, cols: int = 6, tag_size_m: float = 0.088, spacing: float = 0.3,
                   family: str = "tag36h11") -> Target:
    """A Kalibr AprilGrid (see the module docstring for the layout): ``rows`` x ``cols`` tags
    of ``tag_size_m`` with ``spacing * tag_size_m`` between them, ids from 0 row by row."""
    if not (isinstance(rows, int) and isinstance(cols, int)) or rows < 1 or cols < 1 or rows * cols > 10000:
        raise InputFileError(f"an AprilGrid needs 1-10000 tags in tagRows x tagCols, got {rows!r} x {cols!r}")
    if not 0 < spacing <= 2:
        raise InputFileError(f"tagSpacing {spacing!r} must be a fraction of tagSize in (0, 2]")
    pitch = tag_size_m * (1.0 + spacing)
    tags = []
    for row in range(rows):
        for col in range(cols):
            x0, y0 = col * pitch, row * pitch
            # TL, TR, BR, BL of the tag as printed: turned 180 degrees in the board's frame
            corners = np.array([[x0 + tag_size_m, y0, 0.0], [x0, y0, 0.0], [x0, y0 + tag_size_m, 0.0],
                                [x0 + tag_size_m, y0 + tag_size_m, 0.0]])
            tags.append(Tag(row * cols + col, corners))
    target = Target(family, tuple(tags), border_bits=2, grid=GridSpec(rows, cols, tag_size_m, spacing))
    validate_target(target, "aprilgrid")
    return target


def _parse_kalibr(doc: dict, where: str) -> Target:
    """A Kalibr target file (``target_type: 'aprilgrid'``) as a Target."""
    kind = doc.get("target_type")
    if kind != "aprilgrid":
        raise InputFileError(f"{where}: a Kalibr target of type {kind!r} has no tags; cubeloc reads 'aprilgrid' "
                             "(a checkerboard serves calibration: cubeloc calibrate --board)")
    keys = {"tagCols", "tagRows", "tagSize", "tagSpacing"}
    missing = keys - set(doc)
    if missing:
        raise InputFileError(f"{where}: the aprilgrid is missing {sorted(missing)}")
    unknown = set(doc) - keys - {"target_type"}
    if unknown:
        raise InputFileError(f"{where}: unknown key(s) {sorted(unknown)}; an aprilgrid has {sorted(keys)}")
    for name in ("tagCols", "tagRows"):
        if isinstance(doc[name], bool) or not isinstance(doc[name], int):
            raise InputFileError(f"{where}: {name} must be a whole number, got {doc[name]!r}")
    try:
        target = make_aprilgrid(doc["tagRows"], doc["tagCols"], _number(doc["tagSize"], "tagSize", where),
                                _number(doc["tagSpacing"], "tagSpacing", where))
    except InputFileError as exc:
        message = str(exc)
        raise InputFileError(message if message.startswith(where) else f"{where}: {message}") from None
    return dataclasses.replace(target, source=where)


def validate_target(target: Target, where: str) -> None:
    """Raise InputFileError naming ``where`` and the first problem found."""
    if target.family not in KNOWN_FAMILIES:
        raise InputFileError(
            f"{where}: unrecognised tag family {target.family!r}; families I know: {', '.join(KNOWN_FAMILIES)}"
        )
    if not target.tags:
        raise InputFileError(f"{where}: the target has no tags")
    if target.border_bits not in (1, 2):
        raise InputFileError(f"{where}: border_bits must be 1 or 2 (cells of black border), got {target.border_bits!r}")
    seen: set[int] = set()
    for tag in target.tags:
        if tag.tag_id in seen:
            raise InputFileError(f"{where}: tag id {tag.tag_id} appears twice")
        seen.add(tag.tag_id)
        if not 0 <= tag.tag_id <= FAMILY_MAX_ID[target.family]:
            raise InputFileError(
                f"{where}: tag id {tag.tag_id} is outside {target.family} (0..{FAMILY_MAX_ID[target.family]})"
            )
        _validate_square(tag, where)


def _validate_square(tag: Tag, where: str) -> None:
    c = tag.corners
    if c.shape != (4, 3) or not np.all(np.isfinite(c)):
        raise InputFileError(f"{where}: tag {tag.tag_id} needs 4 finite corners [x, y, z]")
    edges = np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1)
    size = edges.mean()
    if size <= 0:
        raise InputFileError(f"{where}: tag {tag.tag_id} has zero size")
    if size < MIN_TAG_SIZE_M:
        raise InputFileError(
            f"{where}: tag {tag.tag_id} is {size * 1000:.3g} mm across, below {MIN_TAG_SIZE_M * 1000:g} mm; "
            "sizes and corners are in metres"
        )
    normal = np.cross(c[1] - c[0], c[3] - c[0])
    if not np.linalg.norm(normal) > 0:  # collinear corners: no plane at all
        raise InputFileError(f"{where}: tag {tag.tag_id} corners are collinear, not a square")
    normal /= np.linalg.norm(normal)
    off_plane = np.abs((c - c.mean(axis=0)) @ normal).max()
    if off_plane > PLANARITY_TOLERANCE_M:
        raise InputFileError(
            f"{where}: tag {tag.tag_id} corners are not planar ({off_plane * 1000:.2f} mm off the plane)"
        )
    diagonals = np.linalg.norm(c[2] - c[0]), np.linalg.norm(c[3] - c[1])
    if (np.ptp(edges) / size > SQUARENESS_TOLERANCE
            or abs(diagonals[0] - diagonals[1]) / size > SQUARENESS_TOLERANCE
            or not math.isclose(diagonals[0], size * math.sqrt(2), rel_tol=SQUARENESS_TOLERANCE)):
        raise InputFileError(
            f"{where}: tag {tag.tag_id} corners are not a square (edges {np.round(edges * 1000, 2).tolist()} mm); "
            "corners must be TL, TR, BR, BL of the outer black border"
        )


def _number(value: Any, name: str, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputFileError(f"{where}: {name} must be a finite number (metres), got {value!r}")
    if abs(value) > MAX_COORDINATE_M:
        raise InputFileError(f"{where}: {name} {value!r} is beyond {MAX_COORDINATE_M:g} m; values are in metres")
    return float(value)


def parse_target(doc: Any, where: str) -> Target:
    """Build a Target from a parsed YAML document."""
    if not isinstance(doc, dict):
        raise InputFileError(f"{where}: expected a mapping with 'family' and 'tags' or 'cube'")
    if "target_type" in doc:
        return _parse_kalibr(doc, where)
    unknown = set(doc) - {"family", "tags", "cube", "border_bits"}
    if unknown:
        raise InputFileError(f"{where}: unknown key(s) {sorted(unknown)}; expected family, border_bits, tags or cube")
    border_bits = doc.get("border_bits", 1)
    if isinstance(border_bits, bool) or border_bits not in (1, 2):
        raise InputFileError(f"{where}: border_bits must be 1 or 2 (cells of black border), got {border_bits!r}")
    family = doc.get("family", "tag36h11")
    if not isinstance(family, str):
        raise InputFileError(f"{where}: family must be a string such as 'tag36h11'")
    if ("tags" in doc) == ("cube" in doc):
        raise InputFileError(f"{where}: give exactly one of 'tags' (explicit corners) or 'cube' (shorthand)")
    if "cube" in doc:
        cube = doc["cube"]
        if not isinstance(cube, dict):
            raise InputFileError(f"{where}: cube must be a mapping {{side, tag_size, ids}}")
        missing = {"side", "tag_size", "ids"} - set(cube)
        if missing:
            raise InputFileError(f"{where}: cube is missing {sorted(missing)}")
        extra = set(cube) - {"side", "tag_size", "ids"}
        if extra:
            raise InputFileError(f"{where}: cube: unknown key(s) {sorted(extra)}; expected side, tag_size, ids")
        ids = cube["ids"]
        if not isinstance(ids, list) or not all(isinstance(i, int) and not isinstance(i, bool) for i in ids):
            raise InputFileError(f"{where}: cube.ids must be a list of 6 integers")
        try:
            target = make_cube(
                _number(cube["side"], "cube.side", where),
                _number(cube["tag_size"], "cube.tag_size", where),
                tuple(ids),
                family,
            )
        except InputFileError as exc:
            message = str(exc)
            raise InputFileError(message if message.startswith(where) else f"{where}: {message}") from None
        return Target(target.family, target.tags, target.cube, where, border_bits)
    raw_tags = doc["tags"]
    if not isinstance(raw_tags, list) or not raw_tags:
        raise InputFileError(f"{where}: tags must be a non-empty list")
    tags = []
    for index, raw in enumerate(raw_tags):
        if not isinstance(raw, dict) or "id" not in raw or "corners" not in raw:
            raise InputFileError(f"{where}: tags[{index}] needs 'id' and 'corners'")
        tag_id = raw["id"]
        extra = set(raw) - {"id", "corners"}
        if extra:
            raise InputFileError(f"{where}: tags[{index}]: unknown key(s) {sorted(extra)}; expected id, corners")
        if isinstance(tag_id, bool) or not isinstance(tag_id, int):
            raise InputFileError(f"{where}: tags[{index}].id must be an integer, got {tag_id!r}")
        corners = raw["corners"]
        if not isinstance(corners, list) or len(corners) != 4:
            count = len(corners) if isinstance(corners, list) else "no"
            raise InputFileError(f"{where}: tag {tag_id} needs 4 corners (TL, TR, BR, BL), got {count}")
        points = []
        for corner in corners:
            if not isinstance(corner, list) or len(corner) != 3:
                raise InputFileError(f"{where}: tag {tag_id}: each corner must be [x, y, z]")
            points.append([_number(v, f"tag {tag_id} corner", where) for v in corner])
        tags.append(Tag(tag_id, np.array(points)))
    target = Target(family, tuple(tags), None, where, border_bits)
    validate_target(target, where)
    return target


def load_target(path: str | os.PathLike[str]) -> Target:
    """Read and validate a target file; raise InputFileError with a one-line reason."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputFileError(f"{path}: target file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{path}: cannot read target file ({exc})") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise InputFileError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    except RecursionError:  # PyYAML recurses per nesting level: "[[[[..." overflows the stack
        raise InputFileError(f"{path}: not valid YAML (nested too deeply)") from None
    return parse_target(doc, str(path))


def combine_targets(primary: Target, others: list[tuple[Target, np.ndarray]]) -> Target:
    """One rigid target from several, in ``primary``'s frame: each other target's tags moved
    by its 4x4 ``T_primary_other`` (from their placements in the map). Any tag seen then
    poses the camera in that one frame, and tags of two targets in one view are used
    together. Refused (InputFileError, one line naming both files) where two share a tag
    id or the families differ."""
    tags, owner = list(primary.tags), {t.tag_id: primary.source for t in primary.tags}
    for target, T in others:
        if (target.family, target.border_bits) != (primary.family, primary.border_bits):
            raise InputFileError(f"{target.source}: its tags ({target.family}, border {target.border_bits}) are not "
                                 f"those of {primary.source} ({primary.family}, border {primary.border_bits}): "
                                 "several targets must share one tag family and border")
        clash = sorted(t.tag_id for t in target.tags if t.tag_id in owner)
        if clash:
            raise InputFileError(f"{target.source}: tag id(s) {clash} also in {owner[clash[0]]}: every tag of "
                                 "every target needs its own id")
        rotation, translation = np.asarray(T)[:3, :3], np.asarray(T)[:3, 3]
        for tag in target.tags:
            tags.append(Tag(tag.tag_id, tag.corners @ rotation.T + translation, tag.face))
            owner[tag.tag_id] = target.source
    if not others:
        return primary
    return Target(primary.family, tuple(tags), None, " + ".join([primary.source, *(t.source for t, _ in others)]),
                  primary.border_bits)


def default_cube_yaml() -> str:
    """The default target file: the paper's 18 cm cube with 14.4 cm tag36h11 tags, ids 0-5."""
    return "family: tag36h11\ncube: {side: 0.18, tag_size: 0.144, ids: [0, 1, 2, 3, 4, 5]}\n"
