"""``cubeloc map info|export|prune MAP``: a saved map (cubeloc.map/1, docs/map.md).

``info`` prints what the file holds (keyframes, points, extent, age, the calibration and
target it was made with; ``--json`` for scripts); ``export --out MAP.ply`` writes its
points and keyframe positions as a PLY for any point-cloud viewer; ``prune --keyframes N
--out SMALLER.map`` keeps N keyframes spread over the mapped area (farthest-point
sampling of their positions) and the points they observe.
"""

from __future__ import annotations

import json
from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser("map", help="look into, export or shrink a saved map (cubeloc track --save-map)",
                                   description="A saved map: info, export to PLY, prune to fewer keyframes.")
    verbs = parser.add_subparsers(dest="map_verb", required=True, metavar="info|export|prune")
    info = verbs.add_parser("info", help="what the map holds")
    info.add_argument("map", metavar="MAP")
    info.add_argument("--json", action="store_true", help="one JSON document")
    export = verbs.add_parser("export", help="points and keyframe positions as PLY")
    export.add_argument("map", metavar="MAP")
    export.add_argument("--out", required=True, metavar="OUT.ply")
    prune = verbs.add_parser("prune", help="keep N keyframes spread over the area and the points they see")
    prune.add_argument("map", metavar="MAP")
    prune.add_argument("--keyframes", type=int, required=True, metavar="N")
    prune.add_argument("--out", required=True, metavar="OUT.map")
    prune.add_argument("--calib", required=True, metavar="FILE", help="the camera_info the map was made with")
    prune.add_argument("--target", required=True, metavar="FILE", help="the target the map was made with")
    parser.set_defaults(func=run)


def run(args) -> int:
    from cubeloc.errors import InputFileError
    from cubeloc.positioning.tracking.map_file import export_ply, map_summary

    if args.map_verb == "info":
        summary = map_summary(Path(args.map))
        if args.json:
            print(json.dumps(summary))
            return 0
        c, t, e = summary["calibration"], summary["target"], summary["extent_m"]
        print(f"{args.map}: {summary['schema']}, {summary['bytes'] / 1e6:.1f} MB, made {summary['age_s'] / 3600:.1f} h ago "
              f"by cubeloc {summary['software']}")
        print(f"  {summary['keyframes']} keyframes ({summary['anchored_keyframes']} anchored by the target), "
              f"{summary['points']} points, {summary['descriptors']} descriptors")
        print(f"  extent x {e['min'][0]:+.2f}..{e['max'][0]:+.2f} m, y {e['min'][1]:+.2f}..{e['max'][1]:+.2f} m, "
              f"z {e['min'][2]:+.2f}..{e['max'][2]:+.2f} m (target frame)")
        print(f"  camera {c['width']}x{c['height']} {c['model']} (calibration {c['fingerprint']}), "
              f"target {t['family']} ids {t['ids']} ({t['fingerprint']})")
        return 0
    if args.map_verb == "export":
        out = Path(args.out)
        if not out.parent.is_dir():
            raise InputFileError(f"{out}: the directory {out.parent} does not exist")
        points, keyframes = export_ply(Path(args.map), out)
        print(f"wrote {points} points and {keyframes} keyframe positions to {out}")
        return 0
    return _prune(args)


def _prune(args) -> int:
    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.errors import InputFileError
    from cubeloc.positioning.target import load_target
    from cubeloc.positioning.tracking.map_file import prune_map

    if args.keyframes < 2:
        raise InputFileError(f"--keyframes {args.keyframes}: at least 2")
    out = Path(args.out)
    if not out.parent.is_dir():
        raise InputFileError(f"{out}: the directory {out.parent} does not exist")
    before, after = prune_map(Path(args.map), out, read_camera_info(args.calib), load_target(args.target),
                              args.keyframes)
    print(f"{before[0]} keyframes, {before[1]} points -> {after[0]} keyframes, {after[1]} points in {out}")
    return 0
