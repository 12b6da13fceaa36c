"""``graylight tiles`` and ``graylight preview``: the render stages, in-process, with their
progress on stderr (a bar on a terminal, plain lines otherwise)."""

from __future__ import annotations

import argparse
import atexit
import gc
import os
import sys
from pathlib import Path

from services.cli.args import parse_size
from shared.core.errors import InputError
from shared.render.options import PREVIEW_DEFAULTS, PreviewOptions


def _tiles(args: argparse.Namespace) -> int:
    if args.workers is not None and args.workers < 1:
        raise InputError("--workers", f"must be at least 1, got {args.workers}")
    # The build calls no BLAS, and OpenBLAS's threads (numpy's; scipy's, loaded for numba's
    # BLAS check) spin for a while once started: 0.05-0.08 s of CPU. Only effective before
    # numpy loads, as in the ``graylight`` process, where the stage import below loads it.
    if "numpy" not in sys.modules:
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    # The garbage collector would walk the objects numba's import and start-up leave (none of
    # them garbage) over and over: 0.1 s of CPU of the 2 M-point build, which itself makes few
    # reference cycles, so it runs without collections. At exit the interpreter collects in
    # full while it tears the modules down, 0.3 s more; frozen, those objects are only freed.
    atexit.register(gc.freeze)
    collecting = gc.isenabled()
    gc.disable()
    try:
        from services.cli.progress import progress_bar
        from shared.render.stages import tiles_stage

        with progress_bar("tiles") as progress:  # a bar on a terminal, plain lines in a log
            report = tiles_stage(Path(args.cloud), Path(args.out), workers=args.workers,
                                 estimate_normals=args.estimate_normals, node_codec=args.node_codec,
                                 progress=progress)  # fmt: skip
    finally:
        if collecting:
            gc.enable()
    print(
        f"{report['points']} points in {report['nodes']} nodes, {report['depth']} levels deep, "
        f"{report['bytes'] / 1e6:.1f} MB, in {report['seconds']:.1f} s ({report['points_per_second'] / 1e6:.2f} M points/s)"
    )
    print(f"tiles: {report['tiles']}")
    return 0


def _preview(args: argparse.Namespace) -> int:
    from services.cli.progress import progress_bar
    from shared.render.camera_path import NAMED_PATHS, parse_camera_doc, read_path_file
    from shared.render.stages import preview_stage

    camera = None
    if args.path not in NAMED_PATHS:  # a local keyframe file: the user names their own files
        camera = parse_camera_doc(read_path_file(args.path), args.path)
    options = PreviewOptions(path=args.path if camera is None else "auto", size=parse_size(args.size, "--size"),
                             seconds=args.seconds, fps=args.fps, camera=camera, camera_where=args.path)
    with progress_bar("preview") as progress:  # frames rendered
        merge = Path(args.merge) if args.merge else None
        report = preview_stage(Path(args.tiles), Path(args.out), options.checked("--"), renderer=args.renderer,
                               progress=progress, merge_dir=merge,
                               derivatives_dir=Path(args.derivatives) if args.derivatives else merge)  # fmt: skip
    print(
        f"{report['frames']} frames {report['width']}x{report['height']} at {report['fps']} fps "
        f"({report['renderer']} renderer, {report['render_fps']:.1f} frames/s) in {report['elapsed_seconds']:.1f} s"
    )
    print(f"video:  {report['video']}")
    print(f"poster: {report['poster']}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("tiles", help="build Potree 2.0 level-of-detail tiles from a cloud PLY")
    p.add_argument("cloud", help="cloud PLY (x, y, z; colour, normal, size when present)")
    p.add_argument("--out", required=True, help="output folder (replaced atomically)")
    p.add_argument("--workers", type=int, default=None, help="threads building chunks (default: the CPUs this process may use)")
    p.add_argument(
        "--estimate-normals",
        action="store_true",
        help="give a cloud without normals unit normals from its neighbourhoods (facing the origin)",
    )
    p.add_argument(
        "--node-codec",
        choices=("plain", "octree"),
        default="plain",
        help="how octree.bin stores nodes: plain (Potree's DEFAULT, any Potree viewer opens it) or octree "
        "(octree-coded, lossless, several times smaller; Graylight's viewer and preview read it)",
    )
    p.set_defaults(func=_tiles)

    p = subparsers.add_parser("preview", help="render a flythrough MP4 and poster PNG of tiles")
    p.add_argument("tiles", help="tiles folder written by 'graylight tiles'")
    p.add_argument("--out", required=True, help="output MP4 (the poster is written beside it as .png)")
    w, h = PREVIEW_DEFAULTS.size
    p.add_argument("--path", default=PREVIEW_DEFAULTS.path, help=f"auto, arc, orbit, dolly or a JSON keyframe file (default {PREVIEW_DEFAULTS.path}: an arc on the scanner's side for one view, an orbit for a merged model)")
    p.add_argument("--size", default=f"{w}x{h}", help=f"WIDTHxHEIGHT (default {w}x{h})")
    p.add_argument("--seconds", type=float, default=PREVIEW_DEFAULTS.seconds, help=f"duration (default {PREVIEW_DEFAULTS.seconds:g})")
    p.add_argument("--fps", type=float, default=PREVIEW_DEFAULTS.fps, help=f"frames per second (default {PREVIEW_DEFAULTS.fps:g})")
    p.add_argument(
        "--renderer",
        choices=["auto", "cpu", "gl"],
        default="auto",
        help="auto: OpenGL on a hardware GPU, else the CPU rasteriser (default)",
    )
    p.add_argument("--merge", default=None, help="the merge these tiles are of: orbit its turntable axis "
                   "(registration.json), kept up, and draw its textured derivative (mesh_<level>.glb) if it has one")
    p.add_argument("--derivatives", default=None, help="folder of the textured derivatives (default: the --merge folder)")
    p.set_defaults(func=_preview)
