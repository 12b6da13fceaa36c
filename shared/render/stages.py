"""Render stages as the job service and the CLI run them: tiles from a cloud, a preview video
from tiles.

``tiles_stage(cloud_ply, out_dir)`` builds Potree 2.0 tiles (:mod:`shared.render.octree`);
``preview_stage(tiles_dir, out_path, ...)`` renders an MP4 and a poster PNG
(:mod:`shared.render.preview`). Both return a JSON-able report and write their outputs atomically
(a temporary folder or file renamed when complete), so a failure leaves no finished-looking
artifact. Bad input raises :class:`shared.core.errors.InputError`.

For fan-out under the job service, the tile build splits into
:func:`shared.render.octree.plan_tiles` (one task), :func:`shared.render.octree.build_chunk` (one task a
chunk, independent) and :func:`shared.render.octree.merge_tiles` (one task).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from shared.render.octree import build_tiles
from shared.render.options import PREVIEW_DEFAULTS, PreviewOptions


def tiles_stage(
    cloud_ply: Path, out_dir: Path, *, workers: int | None = None, estimate_normals: bool = False,
    node_codec: str = "plain", progress: Callable[[float], None] | None = None,
) -> dict:  # fmt: skip
    """Build tiles of ``cloud_ply`` into ``out_dir`` (``estimate_normals`` for a cloud without
    normals; ``node_codec`` "plain" or "octree", see :func:`shared.render.octree.plan_tiles`);
    ``progress`` gets the fraction done (chunks laid out, nodes written); returns points, nodes,
    depth, bytes, chunks, seconds, points_per_second and the output folder."""
    report = build_tiles(Path(cloud_ply), Path(out_dir), workers=workers, estimate_normals=estimate_normals,
                         node_codec=node_codec, progress=progress)  # fmt: skip
    report["tiles"] = str(out_dir)
    return report


def preview_stage(
    tiles_dir: Path,
    out_path: Path,
    options: PreviewOptions = PREVIEW_DEFAULTS,
    *,
    renderer: str = "auto",
    progress: Callable[[float], None] | None = None,
    merge_dir: Path | None = None,
    derivatives_dir: Path | None = None,
) -> dict:
    """Render a preview flythrough of ``tiles_dir`` to ``out_path`` (MP4) plus a poster PNG.

    A merged model (``merge_dir``, its ``registration.json``) turns around its turntable axis,
    kept up; with its textured derivatives (``derivatives_dir`` holding ``mesh_<level>.glb``)
    the preview draws the one that suits the frame size as triangles
    (:mod:`shared.render.mesh_preview`) rather than the tiles' points.

    ``options``: path, size, seconds and fps (:class:`~shared.render.options.PreviewOptions`);
    ``renderer``: "auto" (OpenGL on a hardware GPU, else the CPU rasteriser), "cpu" or "gl";
    ``progress`` is called with the fraction of frames written.
    """
    # Imported here: the preview's OpenCV, shading and rasteriser modules cost a tile build
    # (``graylight tiles``, a tiles task) half a second of start-up it does not need.
    from shared.render.mesh_preview import pick_derivative, turntable_up
    from shared.render.preview import render_preview

    up = turntable_up(Path(merge_dir) / "registration.json") if merge_dir is not None else None
    mesh = pick_derivative(Path(derivatives_dir), *options.size) if derivatives_dir is not None else None
    return render_preview(
        Path(tiles_dir), Path(out_path), path=options.path, size=options.size, seconds=options.seconds,
        fps=options.fps, renderer=renderer, camera=options.camera, camera_where=options.camera_where,
        progress=progress, mesh=mesh, up=up,
    )  # fmt: skip
