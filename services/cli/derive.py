"""``graylight derivatives MERGE_DIR [--out DIR] [--levels SPEC] [--colour albedo|shaded]``.

The textured web derivatives of a merged model (:func:`shared.derive.pipeline.make_derivatives`):
per level a Draco GLB with base colour, normal and occlusion maps and a bridged-texel mask, and
``derivatives.json``. Prints one line per level beside its budget. Bad input (no master mesh,
nonsense budgets, a mesh too small to unwrap) ends with a one-line error and exit status 1;
nothing is left half-written.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def _cmd_derivatives(args: argparse.Namespace) -> int:
    # The bake's BLAS calls are small products ((n, 3) by (3, 3)) that OpenBLAS's threads make
    # slower, not faster, on a loaded machine: one thread took the photograph bake of a million
    # texels of the 12-view 2048x1536 bunny from 18.3 s of CPU to 10.6 s (29 s to 16 s wall).
    # Only effective before numpy loads, as in the ``graylight`` process.
    if "numpy" not in sys.modules:
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from shared.derive.pipeline import make_derivatives

    report = make_derivatives(Path(args.merge_dir), Path(args.out) if args.out else None, levels=args.levels,
                              colour=args.colour, scanset=Path(args.scanset) if args.scanset else None)
    for w in report["warnings"]:
        print(f"warning: {w}")
    for lv in report["levels"]:
        bound = "" if lv["max_bytes"] is None else (
            f" (budget {lv['max_bytes'] / 1000:.0f} kB: {'within' if lv['within_max_bytes'] else 'OVER'})")
        print(f"{lv['level']:<8} {lv['faces']:>8} faces (budget {lv['faces_budget']}), {lv['texture_px']} px maps, "
              f"{lv['bytes'] / 1000:.0f} kB{bound}, {lv['seconds']['total']:.1f} s  {lv['file']}")
    print(f"colour: {report['colour_baked']}; {report['seconds']:.1f} s in all")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("derivatives", help="textured web derivatives (GLB levels) of a merged model",
                              description="Make Voyager-style derivative levels (textured, Draco GLB) from a merge's "
                                          "mesh.ply and merged.ply.")
    p.add_argument("merge_dir", help="a graylight merge output folder (mesh.ply, merged.ply)")
    p.add_argument("--out", help="output folder (default: the merge folder)")
    p.add_argument("--levels", help="levels: names (thumb,low,medium,high,highest) or NAME:FACES:PX, comma-separated "
                                    "(default: thumb,low,medium,high)")
    p.add_argument("--colour", choices=("photo", "albedo", "shaded"), default="photo",
                   help="photo (default): the albedo from the views' photographs at their resolution (the cloud's "
                        "where no view sees a texel); albedo: the fused cloud's albedo; shaded: the white-frame colour")
    p.add_argument("--scanset", help="the scan set whose photographs are baked (default: the one the merge's "
                                     "report.json names)")
    p.set_defaults(func=_cmd_derivatives)


__all__ = ["register"]
