"""``graylight rig import FILE.yaml --out rig.json`` and ``graylight rig export rig.json --out
FILE.yaml``: OpenCV FileStorage stereo calibrations to and from rig.json
(:mod:`shared.formats.opencv_rig`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.cli.args import parse_size


def _import(args: argparse.Namespace) -> int:
    # OpenCV and numpy load here, not at start-up: every other command (and --help) stays without them.
    from shared.formats.opencv_rig import read_opencv_rig
    from shared.formats.rig import save_rig

    cam = parse_size(args.camera_size, "--camera-size", lo=1) if args.camera_size else None
    proj = parse_size(args.projector_size, "--projector-size", lo=1) if args.projector_size else None
    rig = read_opencv_rig(Path(args.file), camera_size=cam, projector_size=proj, units=args.units)
    save_rig(rig, Path(args.out))
    print(
        f"camera {rig.camera.width}x{rig.camera.height} fx {rig.camera.fx:.1f}, projector "
        f"{rig.projector.width}x{rig.projector.height} fx {rig.projector.fx:.1f}, baseline {rig.baseline:.2f} {rig.units}"
    )
    print(f"rig: {args.out}")
    return 0


def _export(args: argparse.Namespace) -> int:
    from shared.formats.opencv_rig import write_opencv_rig  # OpenCV, numpy: loaded only for this command
    from shared.formats.rig import load_rig

    rig = load_rig(Path(args.rig))
    write_opencv_rig(rig, Path(args.out), naming=args.naming)
    print(f"opencv ({args.naming} naming): {args.out}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("rig", help="import or export a rig as an OpenCV stereo calibration")
    sub = p.add_subparsers(dest="rig_command", metavar="ACTION", required=True)
    q = sub.add_parser("import", help="OpenCV FileStorage YAML/XML -> rig.json")
    q.add_argument("file", help="camera_matrix/projector_matrix/R/T or K1/D1/K2/D2/R/T file")
    q.add_argument("--out", required=True, help="rig.json to write")
    q.add_argument("--camera-size", help="camera WxH, when the file has none")
    q.add_argument("--projector-size", help="projector (second device) WxH, when the file has none")
    q.add_argument("--units", help="units of T (default: the file's 'units', else mm)")
    q.set_defaults(func=_import)
    q = sub.add_parser("export", help="rig.json -> OpenCV FileStorage YAML")
    q.add_argument("rig", help="rig.json")
    q.add_argument("--out", required=True, help="YAML (or .xml) file to write")
    q.add_argument(
        "--naming", default="graylight",
        help="key names: graylight (default) or stereo (others are refused with a one-line error)"
    )
    q.set_defaults(func=_export)
