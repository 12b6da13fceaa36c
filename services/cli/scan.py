"""``graylight scan``, ``graylight patterns`` and ``graylight import-sequence``.

* ``scan CAPTURE --out OUT [--rig FILE]``: the whole single-view scan in-process
  (:func:`shared.scan.pipeline.scan`) with a progress bar on stderr; prints where the results are.
* ``patterns --projector WxH --out DIR [--no-rows]``: the Gray-code pattern images to show on a
  projector, plus a ``capture.json`` template naming the camera images to take of them.
* ``import-sequence DIR --projector WxH [--white N --black M]``: writes ``DIR/capture.json``
  for frames numbered in OpenCV ``GrayCodePattern`` order.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from services.cli.args import parse_size
from shared.core.errors import InputError

# OpenCV and the capture modules load inside the commands that use them, so other commands
# (``graylight tiles`` ...) start without them.


def _projector_size(text: str) -> tuple[int, int]:
    from shared.formats.capture import MAX_PROJECTOR_SIDE

    return parse_size(text, "--projector", lo=2, hi=MAX_PROJECTOR_SIDE)


def _cmd_scan(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from shared.scan.pipeline import scan

    console = Console(stderr=True)
    with Progress(
        TextColumn("[bold]scanning[/bold]"),
        BarColumn(),
        TextColumn("{task.percentage:>3.0f}%"),
        TimeElapsedColumn(),
        console=console,
        transient=not console.is_terminal,
    ) as bar:
        task = bar.add_task("scan", total=1.0)
        report = scan(Path(args.capture), Path(args.out), rig=Path(args.rig) if args.rig else None,
                      progress=lambda f: bar.update(task, completed=f))
    files = report["files"]
    print(f"{report['points']} points ({100 * report['points_share_of_lit']:.1f} % of lit pixels) "
          f"in {report['seconds']['total']:.1f} s")
    print(f"point cloud: {files['cloud']}")
    print(f"range image: {files['range']}")
    print(f"report:      {files['report']}")
    return 0


def _write_png_atomic(path: Path, image) -> None:
    import cv2

    from shared.core.files import atomic_file

    with atomic_file(path, suffix=".png") as tmp:
        if not cv2.imwrite(str(tmp), image):
            raise OSError(f"could not write {path}")


def _cmd_patterns(args: argparse.Namespace) -> int:
    from shared.formats.capture import write_capture
    from shared.scan.graycode import capture_for_names, pattern_sequence

    w, h = _projector_size(args.projector)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    seq = pattern_sequence(w, h, rows=not args.no_rows)
    for name, _axis, _bit, _inv, image in seq:
        _write_png_atomic(out / name, image)
    capture = capture_for_names(out, w, h, rows=not args.no_rows)
    path = write_capture(capture)
    print(f"{len(seq)} pattern images for a {w}x{h} projector in {out}")
    print(f"capture template: {path} (photograph each pattern and save the photo under the same name)")
    return 0


def _cmd_import(args: argparse.Namespace) -> int:
    from shared.formats.capture import code_bits, numbered_frames, opencv_order_capture, write_capture

    w, h = _projector_size(args.projector)
    folder = Path(args.dir)
    frames = numbered_frames(folder)
    needed = 2 * (code_bits(w) + code_bits(h)) + 2
    if len(frames) != needed:
        raise InputError(
            folder,
            f"{len(frames)} frames, but a {w}x{h} projector in OpenCV order needs exactly {needed} "
            f"({2 * code_bits(w)} column and {2 * code_bits(h)} row patterns with inverses, white, black)",
        )
    for name, idx in (("--white", args.white), ("--black", args.black)):
        if idx is not None and not 0 <= idx < len(frames):
            raise InputError(name, f"frame index {idx} is outside 0..{len(frames) - 1}")
    capture = opencv_order_capture(folder, frames, w, h, white_index=args.white, black_index=args.black)
    path = write_capture(capture)
    print(f"capture description for {len(frames)} frames: {path}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("scan", help="decode and triangulate a capture into a coloured point cloud")
    p.add_argument("capture", help="capture folder (with capture.json)")
    p.add_argument("--out", required=True, help="output folder for cloud.ply, range.npz and report.json")
    p.add_argument("--rig", help="rig.json to use instead of the capture's own")
    p.set_defaults(func=_cmd_scan)

    p = subparsers.add_parser("patterns", help="write Gray-code pattern images and a capture.json template")
    p.add_argument("--projector", required=True, help="projector size WIDTHxHEIGHT, e.g. 1024x768")
    p.add_argument("--out", required=True, help="folder for the pattern images")
    p.add_argument("--no-rows", action="store_true", help="column patterns only")
    p.set_defaults(func=_cmd_patterns)

    p = subparsers.add_parser(
        "import-sequence", help="write capture.json for frames numbered in OpenCV GrayCodePattern order"
    )
    p.add_argument("dir", help="folder of numbered frames (patterns with inverses, then white, then black)")
    p.add_argument("--projector", required=True, help="projector size WIDTHxHEIGHT, e.g. 1024x768")
    p.add_argument("--white", type=int, help="index of the all-white frame (default: after the patterns)")
    p.add_argument("--black", type=int, help="index of the all-black frame (default: after white)")
    p.set_defaults(func=_cmd_import)


__all__ = ["register"]

if __name__ == "__main__":  # pragma: no cover
    from services.cli.main import main

    sys.exit(main())
