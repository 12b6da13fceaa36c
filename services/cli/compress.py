"""``graylight compress`` and ``graylight decompress``: range images and clouds in the Graylight container.

* ``compress INPUT --out FILE [--max-error E | --quantum Q]``: INPUT is a scan's output folder
  (its ``range.npz``), a ``range.npz`` or a PLY cloud; a range image is coded lossless at the
  quantum (default 0.02 mm) or within the error bound, a cloud on a grid of the quantum (or
  of twice the error bound).
* ``decompress FILE --out OUT``: a ``range.npz`` exactly as a scan writes it, or a PLY in the
  cloud contract (OUT a file, or a folder that receives ``range.npz`` / ``cloud.ply``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

# The codecs (numba kernels) load inside the commands, so other commands start without them.


def _cmd_compress(args: argparse.Namespace) -> int:
    from shared.compress.files import compress_file

    s = compress_file(Path(args.input), Path(args.out), quantum=args.quantum, max_error=args.max_error,
                      effort=args.effort)
    per = s.get("bits_per_valid_sample", s.get("bits_per_point"))
    unit = "bits per valid sample" if s["kind"] == "range" else "bits per point"
    how = f"within {s['max_error']:g}" if s["mode"] == "bounded" else f"lossless at quantum {s['quantum']:g}"
    print(f"{s['kind']} {how}: {s['bytes']} bytes, {per:.3f} {unit}, {s['ratio']:.1f}x smaller, {s['seconds']:.2f} s")
    print(f"compressed: {s['output']}")
    return 0


def _cmd_decompress(args: argparse.Namespace) -> int:
    from shared.compress.files import decompress_file

    s = decompress_file(Path(args.file), Path(args.out))
    what = "valid samples" if s["kind"] == "range" else "points"
    print(f"{s['kind']}: {s['count']} {what} in {s['seconds']:.2f} s")
    print(f"decompressed: {s['output']}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("compress", help="compress a range image or a point cloud (.glr / .glo)")
    p.add_argument("input", help="a scan's output folder, a range.npz or a PLY cloud")
    p.add_argument("--out", required=True, help="the compressed file to write")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--max-error", type=float, metavar="E", help="every sample (coordinate) within E, in the data's units")
    mode.add_argument("--quantum", type=float, metavar="Q", help="lossless to the nearest multiple of Q (default 0.02 mm)")
    p.add_argument("--effort", type=int, choices=(1, 2), default=1,
                   help="range images: 2 also tries JPEG-XL's weighted predictor (up to 2 %% smaller lossless, "
                        "about 2.5x slower to code, bands that take it about 2x slower to decode)")
    p.set_defaults(func=_cmd_compress)

    p = subparsers.add_parser("decompress", help="decompress a .glr / .glo file to range.npz or PLY")
    p.add_argument("file", help="the compressed file")
    p.add_argument("--out", required=True, help="range.npz or .ply to write (or a folder for it)")
    p.set_defaults(func=_cmd_decompress)


__all__ = ["register"]

if __name__ == "__main__":  # pragma: no cover
    from services.cli.main import main

    sys.exit(main())
