"""``graylight calibrate``: a projector-camera rig, or a camera alone, from board captures.

* ``calibrate SESSION_DIR --out rig.json [--export-opencv FILE.yaml] [--report FILE] [--plot FILE] [--k3]``:
  a session folder (``board.json`` + one ``graycode-v1`` capture per board pose) to ``rig.json``,
  with a report JSON (per-pose reprojection errors of both devices; default ``<out>-report.json``
  beside the rig) and a PNG plot of the residuals (default ``<out>-residuals.png``).
* ``calibrate --camera-only IMAGES... --board board.json --out camera.json [--export-opencv FILE]``:
  the camera's intrinsics and distortion from photos of a board.

OpenCV's five-parameter distortion model is fitted with k3 held at 0 unless ``--k3`` is given.

Bad input ends with a one-line error naming the file or field, and nothing written.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from shared.core.errors import InputError
from shared.core.files import write_json_atomic


def _sibling(out: Path, suffix: str) -> Path:
    return out.with_name(f"{out.stem}{suffix}")


def _progress_bar():  # type: ignore[no-untyped-def]
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    console = Console(stderr=True)
    return Progress(
        TextColumn("[bold]calibrating[/bold] {task.description}"),
        BarColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=not console.is_terminal,
    )


def _cmd_calibrate(args: argparse.Namespace) -> int:

    out = Path(args.out)
    if out.suffix.lower() != ".json":
        raise InputError("--out", f"must name a .json file, got {args.out!r}")
    if args.camera_only:
        return _camera_only(args, out)
    if len(args.inputs) != 1:
        raise InputError("SESSION_DIR", f"give exactly one session folder (or use --camera-only), got {len(args.inputs)}")
    if args.board:
        raise InputError("--board", "only with --camera-only: a session folder carries its own board.json")
    from shared.calib.session import run_session, write_outputs
    from shared.scan.albedo import parse_response

    response = parse_response(args.camera_response)

    with _progress_bar() as bar:
        task = bar.add_task("", total=1.0)

        def progress(done: int, total: int, message: str) -> None:
            bar.update(task, completed=done / max(total, 1), description=message)

        result = run_session(Path(args.inputs[0]), progress=progress, k3=args.k3, camera_response=response)
    report = write_outputs(
        result,
        rig_path=out,
        report_path=Path(args.report) if args.report else _sibling(out, "-report.json"),
        yaml_path=Path(args.export_opencv) if args.export_opencv else None,
        plot_path=Path(args.plot) if args.plot else _sibling(out, "-residuals.png"),
    )
    rms = report["rms_px"]
    used = [p for p in report["poses"] if p["used"]]
    print(
        f"rig from {len(used)} of {len(report['poses'])} poses: reprojection RMS camera {rms['camera']:.3f} px, "
        f"projector {rms['projector']:.3f} px; baseline {report['baseline']:.1f} {report['units']}"
    )
    for p in report["poses"]:
        if not p["used"]:
            print(f"  skipped {p['name']}: {p['reason']}")
    for key, path in report["outputs"].items():
        print(f"{key + ':':12s} {path}")
    return 0


def _camera_only(args: argparse.Namespace, out: Path) -> int:
    from shared.calib.board import load_board
    from shared.calib.session import calibrate_camera_images, write_opencv_yaml

    if not args.board:
        raise InputError("--board", "--camera-only needs --board board.json")
    board = load_board(args.board)
    paths = [Path(p) for p in args.inputs]
    result = calibrate_camera_images(paths, board, k3=args.k3)
    doc = result.to_json()
    if args.export_opencv:
        write_opencv_yaml(Path(args.export_opencv), camera=result.calibration.device, extra={"rms": result.calibration.rms})
        doc["opencv_yaml"] = str(args.export_opencv)
    write_json_atomic(out, doc)
    used = sum(1 for i in doc["images"] if i["used"])
    print(f"camera from {used} of {len(paths)} images: reprojection RMS {doc['rms_px']:.3f} px")
    for i in doc["images"]:
        if not i["used"]:
            print(f"  skipped {i['name']}: {i.get('reason')}")
    print(f"camera: {out}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="calibrate a projector-camera rig from a session folder (or a camera from board photos)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("inputs", nargs="+", metavar="SESSION_DIR|IMAGES",
                   help="a session folder (board.json + one capture per pose), or images with --camera-only")
    p.add_argument("--out", required=True, help="rig.json to write (camera.json with --camera-only)")
    p.add_argument("--camera-only", action="store_true", help="calibrate only a camera from photos of a board")
    p.add_argument("--board", help="board.json (with --camera-only)")
    p.add_argument("--export-opencv", metavar="FILE.yaml", help="also write the numbers as an OpenCV FileStorage YAML")
    p.add_argument("--k3", action="store_true",
                   help="also estimate the third radial distortion coefficient (wide-angle lenses; needs poses that "
                        "reach the image corners; held at 0 by default)")  # fmt: skip
    p.add_argument("--camera-response", default="srgb", metavar="srgb|linear|gamma:G|FILE",
                   help="the camera's response from stored value to light (default srgb, what cameras write to 8-bit "
                        "files; linear for raw machine-vision output; FILE: {\"response\": [256 numbers]}); patterns "
                        "without inverses are read against the midpoint of linear light, and the rig records it")
    p.add_argument("--report", help="report JSON (default: <out>-report.json)")
    p.add_argument("--plot", help="residual plot PNG (default: <out>-residuals.png)")
    p.set_defaults(func=_cmd_calibrate)
