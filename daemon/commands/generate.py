"""``cubeloc generate (cube|board) ...``: printable targets at true physical scale.

Each kind of printable is a sub-verb with its own ``register_*`` and ``run_*`` below;
adding one (the calibration board) is a parser and a function, with its implementation
imported inside the function so ``cubeloc --help`` stays fast.

``cube --target FILE --out DIR`` writes, for the cube the target file describes:
``cube.pdf`` (one page per face at true scale, plus the unfolded net when the cube fits
on A3), ``face_<n>_id<id>.png`` (each face at ``--dpi``, with that DPI in the file),
``cube_layout.png`` (which tag goes where) and ``target.yaml`` (the target file used).

``aprilgrid`` prints (or writes with ``--out``) a Kalibr AprilGrid target file, which
cubeloc reads as a target and Kalibr as its calibration target; print the board itself
with Kalibr's ``kalibr_create_target_pdf``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from cubeloc.daemon.commands import check_out
from cubeloc.errors import InputFileError


def register(subparsers) -> None:
    parser = subparsers.add_parser("generate", help="printable targets at true physical scale (cube, board), "
                                   "target files (aprilgrid)")
    kinds = parser.add_subparsers(dest="kind", metavar="KIND", required=True)
    register_cube(kinds)
    register_board(kinds)
    register_aprilgrid(kinds)


def register_cube(kinds) -> None:
    parser = kinds.add_parser(
        "cube", help="the faces of a target cube: PDF at true scale and PNG per face",
        description="Printable faces of the cube a target file describes (its 'cube:' shorthand).",
    )
    parser.add_argument("--target", required=True, metavar="FILE", help="target YAML with the cube shorthand")
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory (created if missing)")
    parser.add_argument("--dpi", type=float, default=300.0, help="resolution of the PNGs and the PDF (default 300)")
    parser.set_defaults(func=run_cube)


def _output_directory(out: str) -> Path:
    directory = Path(out)
    if directory.exists() and not directory.is_dir():
        raise InputFileError(f"--out {directory}: exists and is not a directory")
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputFileError(f"--out {directory}: cannot create the directory ({exc.strerror})") from None
    return directory


def run_cube(args) -> int:
    from cubeloc.atomic import atomic_write_bytes, atomic_write_text
    from cubeloc.positioning import printable
    from cubeloc.positioning.target import load_target

    if not 72 <= args.dpi <= 2400:
        raise InputFileError(f"--dpi {args.dpi:g}: choose a printer resolution between 72 and 2400")
    target = load_target(args.target)
    if target.cube is None:
        raise InputFileError(
            f"{args.target}: lists explicit tags, not the 'cube:' shorthand; "
            "cubeloc generate cube prints cubes (cube: {side, tag_size, ids})"
        )
    directory = _output_directory(args.out)
    printed = printable.cube_files(target, args.dpi)  # everything in memory first: no half set of files
    for name, data in printed.files.items():
        atomic_write_bytes(directory / name, data)
    atomic_write_text(directory / "target.yaml", Path(args.target).read_text(encoding="utf-8"))
    cube = target.cube
    net_note = ", then the unfolded net on A3 landscape" if printed.with_net else ""
    print(
        f"wrote {directory}/cube.pdf ({printed.faces} face pages on {printed.page_name}{net_note}, "
        f"{args.dpi:g} dpi), {printed.faces} face PNGs, cube_layout.png, target.yaml: "
        f"cube {cube.side_m * 1000:.1f} mm, tags {cube.tag_size_m * 1000:.1f} mm (outer black border); "
        "print at 100 % (actual size) and check the 100 mm bar",
        file=sys.stdout,
    )
    return 0


def register_board(kinds) -> None:
    from cubeloc.calib.boards import BOARD_HELP, DEFAULT_BOARD

    parser = kinds.add_parser(
        "board", help="a calibration board for `cubeloc calibrate`: PDF (or PNG) at true scale",
        description="A calibration board on the smallest A page that holds it, at true scale, "
        "with its --board spec and a 100 mm check bar printed under it.",
    )
    parser.add_argument("--board", default=DEFAULT_BOARD, metavar="SPEC", help=BOARD_HELP + f" (default {DEFAULT_BOARD})")
    parser.add_argument("--out", required=True, metavar="FILE", help="output .pdf (true scale) or .png")
    parser.add_argument("--dpi", type=float, default=600.0, help="printer resolution (default 600)")
    parser.add_argument("--force", action="store_true", help="replace an existing file")
    parser.set_defaults(func=run_board)


def run_board(args) -> int:
    from cubeloc.atomic import atomic_write_bytes
    from cubeloc.calib.boards import parse_board
    from cubeloc.calib.printable_board import board_sheet, sheet_bytes

    out = Path(args.out)
    file_format = out.suffix.lower().lstrip(".")
    if file_format not in ("pdf", "png"):
        raise InputFileError(f"--out {out}: give a .pdf (true scale) or a .png file name")
    if not 72 <= args.dpi <= 2400:
        raise InputFileError(f"--dpi {args.dpi:g}: choose a printer resolution between 72 and 2400")
    check_out(out, args.force)
    board = parse_board(args.board)
    sheet = board_sheet(board, args.dpi)
    atomic_write_bytes(out, sheet_bytes(sheet, file_format))
    width_m, height_m = board.extent_m
    print(
        f"wrote {out}: {board.description} ({width_m * 1000:.0f} x {height_m * 1000:.0f} mm) on {sheet.page}, "
        f"{args.dpi:g} dpi; print at 100 % (actual size), check the 100 mm bar, then "
        f"cubeloc calibrate --board {board.text} ..."
    )
    return 0


def register_aprilgrid(kinds) -> None:
    parser = kinds.add_parser(
        "aprilgrid", help="a Kalibr AprilGrid target file (cubeloc --target, Kalibr's target.yaml)",
        description="Kalibr's AprilGrid target file: tag36h11 tags with a two-cell border, ids row by row from "
        "the bottom-left, a black square in each gap corner. Print the board with kalibr_create_target_pdf.",
    )
    parser.add_argument("--cols", type=int, default=6, help="tags across (default 6)")
    parser.add_argument("--rows", type=int, default=6, help="tags down (default 6)")
    parser.add_argument("--tag-size", type=float, default=0.088, metavar="M", help="tag edge in metres (default 0.088)")
    parser.add_argument("--spacing", type=float, default=0.3, metavar="FRACTION",
                        help="gap between tags as a fraction of the tag edge (default 0.3)")
    parser.add_argument("--out", metavar="FILE", help="write the file here instead of printing it")
    parser.add_argument("--force", action="store_true", help="replace an existing file")
    parser.set_defaults(func=run_aprilgrid)


def run_aprilgrid(args) -> int:
    from cubeloc.atomic import atomic_write_bytes
    from cubeloc.positioning.target import make_aprilgrid

    if not 0.001 <= args.tag_size <= 10:
        raise InputFileError(f"--tag-size {args.tag_size:g}: give the tag edge in metres (0.001-10)")
    grid = make_aprilgrid(args.rows, args.cols, args.tag_size, args.spacing).grid
    text = grid.to_kalibr_yaml()
    if args.out is None:
        sys.stdout.write(text)
        return 0
    out = Path(args.out)
    check_out(out, args.force)
    atomic_write_bytes(out, text.encode())
    print(f"wrote {out}: a {grid.cols}x{grid.rows} AprilGrid of {grid.tag_size_m * 1000:g} mm tags, "
          f"gaps {grid.gap_m * 1000:g} mm; use it as cubeloc --target and as Kalibr's --target")
    return 0
