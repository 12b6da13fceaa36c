"""Rendering: Potree 2.0 level-of-detail tiles (out-of-core, parallel), the CPU point
rasteriser, camera paths and preview flythrough videos, and the render stages.

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
        "render_preview": "preview",
        "load_scene": "preview",
        "tiles_stage": "stages",
        "preview_stage": "stages",
    },
)
