"""``graylight merge SCANSET --out OUT [--drop-unregistered] [--keep-support]``: the whole multi-view merge in-process.

Registers the views of a ``graylight-scanset-v1`` scan set, fuses them and meshes the result
(:func:`shared.merge.pipeline.merge_scanset`) with a progress bar on stderr (plain lines when
stderr is not a terminal), then prints where the results are, what was removed as static or
support, the object's sphere, and every view's fit. Bad input ends with a one-line error naming the view or
field and exit status 1; nothing is left half-written in OUT.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _cmd_merge(args: argparse.Namespace) -> int:
    from services.cli.progress import progress_bar
    from shared.merge.isolate import IsolationParams
    from shared.merge.pipeline import merge_scanset

    with progress_bar("merging") as progress:  # a bar on a terminal, plain lines in a log
        report = merge_scanset(Path(args.scanset), Path(args.out), drop_unregistered=args.drop_unregistered,
                               isolation=IsolationParams(keep_support=args.keep_support), progress=progress)
    files = report["files"]
    reg = report["registration"]
    print(f"{report['registered_views']} of {report['views']} views registered ({report['method']}), "
          f"worst fit RMS {reg['worst_rms_mm']:.3f} mm; {report['points']['merged']} merged points, "
          f"{report['mesh']['faces']} faces, in {report['seconds']['total']:.1f} s")
    if report["dropped_views"]:
        print(f"left out (registered to nothing or failed the checks): {', '.join(report['dropped_views'])}")
    _print_quality(report["quality"])
    loop = reg.get("loop_closure")
    if loop:
        print(f"loop closure (pairwise fits chained around the loop): {loop['chained_pairwise_deg']:.3f} deg, "
              f"{loop['chained_pairwise_mm']:.3f} mm")
    axis = reg.get("turntable_axis")
    if axis:
        d = axis["direction"]
        print(f"rotation axis: direction ({d[0]:.5f}, {d[1]:.5f}, {d[2]:.5f}) through "
              f"({', '.join(f'{v:.2f}' for v in axis['point_mm'])}) mm")
    for key in ("merged", "registration", "mesh_ply", "mesh_glb", "report"):
        print(f"{key + ':':<13} {files[key]}")
    return 0


def _print_quality(q: dict) -> None:
    """What was removed before the registration, the object's sphere, and every view's figures."""
    removed = q["removed"]
    if removed.get("fixed_rig"):
        n = removed["samples"]
        print(f"fixed rig: {removed['static']} of {n} samples static ({100 * removed['static'] / n:.1f} %), "
              f"{removed['support_removed']} on or under the support plane, {removed['clutter_removed']} clutter; "
              f"object {removed['object_samples']} samples")
        plane = removed.get("support_plane")
        if plane:
            nx, ny, nz = plane["normal"]
            disc = plane.get("disc")
            radius = f", plate disc radius {disc['radius_mm']:.1f} mm" if disc else ""
            kept = " (kept in the cloud)" if removed.get("support_kept") else " (left out; --keep-support keeps it)"
            print(f"support plane: normal ({nx:.4f}, {ny:.4f}, {nz:.4f}){radius}{kept}")
    obj = removed.get("object")
    if obj:
        c = obj["center"]
        how = "given roi" if obj["source"] == "roi" else "found; set \"roi\" in scanset.json to change it"
        print(f"object sphere: center [{c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f}] mm, radius {obj['radius']:.1f} mm ({how})")
    print(f"{'view':<16} {'RMS mm':>8} {'overlap':>8} {'inliers':>8} {'free sp.':>8}  flags")
    for v in q["views"]:
        if not v["registered"]:
            print(f"{v['name']:<16} {'-':>8} {'-':>8} {'-':>8} {'-':>8}  left out {' '.join(v['flags'])}")
            continue
        free = v.get("free_space_share")
        free_txt = f"{100 * free:7.2f}%" if free is not None else f"{'-':>8}"
        print(f"{v['name']:<16} {v['rms_mm']:8.3f} {100 * v['overlap']:7.1f}% {100 * v['inlier_share']:7.1f}% "
              f"{free_txt}  {' '.join(v['flags']) or 'ok'}")
    free_doc = q.get("free_space")
    if free_doc:
        print(f"free space: share of each view's pairs' samples lying where the other view saw through; worst "
              f"{free_doc['worst_view']} {100 * free_doc['worst_share']:.2f} % (bound {100 * free_doc['bound_share']:.2f} %)")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("merge", help="register, fuse and mesh the views of a scan set",
                              description="Merge a graylight-scanset-v1 scan set into one cloud and meshes.")
    p.add_argument("scanset", help="scan set folder (with scanset.json)")
    p.add_argument("--out", required=True, help="output folder (merged.ply, registration.json, mesh.*, report.json)")
    p.add_argument("--drop-unregistered", action="store_true",
                   help="leave out, with a warning, views that register to nothing or fail the registration's checks "
                        "(default: an error)")
    p.add_argument("--keep-support", action="store_true",
                   help="keep the turntable's plate (the support plane's disc under the object) in the merged cloud "
                        "(default: left out with the static geometry)")
    p.set_defaults(func=_cmd_merge)


__all__ = ["register"]

if __name__ == "__main__":  # pragma: no cover
    from services.cli.main import main

    sys.exit(main())
