"""Rendering: Potree 2.0 level-of-detail tiles (out-of-core, parallel), the CPU point
rasteriser, camera paths and preview flythrough videos, the render stages, and the cloud
exports (LAZ, COPC, E57, PLY) that build on the tiles' octree.

Names resolve lazily: the numba kernels load on first use."""

from shared.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "TilePlan": "octree",
        "plan_tiles": "octree",
        "build_chunk": "octree",
        "merge_tiles": "octree",
        "build_tiles": "octree",
        "morton_codes": "octree",
        "PreviewOptions": "options",
        "PREVIEW_DEFAULTS": "options",
        "Camera": "raster",
        "Rasterizer": "raster",
        "GLRasterizer": "raster",
        "NodeTable": "raster",
        "select_nodes": "raster",
        "CameraPose": "camera_path",
        "make_path": "camera_path",
        "orbit_path": "camera_path",
        "dolly_path": "camera_path",
        "load_path_file": "camera_path",
        "parse_camera_doc": "camera_path",
        "read_path_file": "camera_path",
        "KeyframePath": "camera_path",
        "arc_path": "camera_path",
        "is_single_view": "camera_path",
        "export_cloud": "export",
        "render_preview": "preview",
        "load_scene": "preview",
        "tiles_stage": "stages",
        "preview_stage": "stages",
    },
)
