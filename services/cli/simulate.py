"""``graylight simulate``: write a synthetic capture with ground truth (the virtual rig).

``graylight simulate --scene bunny --out DIR [--size 2048x1536] [--projector 1024x768] [--seed N]
[--colour] [--bits 16] [--response srgb|linear|gamma:G] [--no-rows] [--no-inverses] [--force]`` writes a ``graycode-v1`` capture folder with
``rig.json`` and ``truth.npz`` (see :mod:`shared.sim.simulate`). With ``--views N [--turntable | --orbit]``
it writes a ``graylight-scanset-v1`` scan set of N captures with every view's true pose
(:mod:`shared.sim.scanset`): a turntable set sees what a real one does (backdrop, table, the
turntable's base and plate) and has no ``roi`` unless ``--roi`` asks for the crop.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from services.cli.args import parse_size
from shared.core.errors import InputError

log = logging.getLogger(__name__)


class _SceneHelp(argparse.HelpFormatter):
    """Lists the scene names only when ``simulate --help`` is printed: the scene module loads
    numpy and numba, which every other command (and ``graylight --help``) should not pay for."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.dest == "scene":
            from shared.sim.scenes import SCENES  # slow import (numba), only for this help text

            return f"scene name: {', '.join(SCENES)}"
        return super()._get_help_string(action)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="render a synthetic Gray-code capture with ground truth",
        description="Render a synthetic graycode-v1 capture (images, capture.json, rig.json, truth.npz).",
        formatter_class=_SceneHelp,
    )
    p.add_argument("--scene", required=True, help="scene name")
    p.add_argument("--out", required=True, type=Path, help="output capture folder (must not exist or be empty)")
    p.add_argument("--size", default="2048x1536", help="camera size WxH (default 2048x1536; up to 15 MP and more)")
    p.add_argument("--projector", default="1024x768", help="projector size WxH (default 1024x768)")
    p.add_argument("--seed", type=int, default=0, help="seed of the rig, scene textures and sensor noise")
    p.add_argument("--colour", "--color", action="store_true", help="colour camera (BGR images)")
    p.add_argument("--bits", type=int, choices=(8, 16), default=8, help="bits per sample (8 or 16)")
    p.add_argument("--response", default="srgb",
                   help="camera response curve: srgb (default), linear or gamma:G (recorded in capture.json and truth.npz)")
    p.add_argument("--no-rows", action="store_true", help="capture column patterns only")
    p.add_argument("--no-inverses", action="store_true", help="leave out the inverse patterns")
    p.add_argument("--force", action="store_true", help="replace a non-empty output folder")
    p.add_argument("--views", type=int, default=1,
                   help="N > 1: a graylight-scanset-v1 scan set of N views with their true poses (shared.sim.scanset)")
    motion = p.add_mutually_exclusive_group()
    motion.add_argument("--turntable", dest="motion", action="store_const", const="turntable",
                        help="the object turns on a turntable before a fixed rig (default with --views)")
    motion.add_argument("--orbit", dest="motion", action="store_const", const="orbit",
                        help="the rig moves around the object")
    p.add_argument("--roi", action="store_true",
                   help="scan sets: also write the roi sphere that crops every view to the object (a real capture has none)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from shared.sim.simulate import ImagingParams, simulate_named

    size = parse_size(args.size, "--size", lo=2)
    projector = parse_size(args.projector, "--projector", lo=2)
    imaging = ImagingParams(colour=args.colour, bits=args.bits, rows=not args.no_rows, inverses=not args.no_inverses,
                            response=args.response)
    t0 = time.perf_counter()
    if args.roi and args.views == 1 and not args.motion:
        raise InputError("--roi", "only a scan set (--views N) has a region of interest")
    if args.views != 1 or args.motion:
        from shared.sim.scanset import simulate_scanset

        path = simulate_scanset(args.scene, args.out, views=args.views, mode=args.motion or "turntable", size=size,
                                projector=projector, seed=args.seed, imaging=imaging, overwrite=args.force,
                                roi=args.roi)
        print(f"{path}: scene {args.scene}, {args.views} views ({args.motion or 'turntable'}), camera "
              f"{size[0]}x{size[1]}, projector {projector[0]}x{projector[1]}, truth.npz with the true poses"
              f"{', roi written' if args.roi else ''}")
        return 0
    capture = simulate_named(args.scene, args.out, size=size, projector=projector, seed=args.seed,
                             imaging=imaging, overwrite=args.force)
    log.info("simulated %s in %.1f s", args.scene, time.perf_counter() - t0)
    print(f"{capture.root}: scene {args.scene}, camera {size[0]}x{size[1]}, projector {projector[0]}x{projector[1]}, "
          f"{len(capture.image_paths())} images, rig.json, truth.npz")
    return 0
