"""Web derivatives of a merged model: levels with face and texture budgets (Smithsonian Voyager's
by default), UV atlases, baked base colour / normal / occlusion maps and Draco-compressed GLB files.

Names resolve lazily: numba, xatlas and Open3D load only when used."""

from shared.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "Level": "levels",
        "LEVELS": "levels",
        "DEFAULT_LEVELS": "levels",
        "parse_levels": "levels",
        "BakeParams": "bake",
        "ColourSource": "bake",
        "Maps": "bake",
        "UVMesh": "bake",
        "bake_maps": "bake",
        "unwrap": "bake",
        "vertex_normals": "bake",
        "write_textured_glb": "gltf",
        "encode_jpeg": "gltf",
        "PhotoParams": "photo",
        "PhotoSource": "photo",
        "load_photo_source": "photo",
        "make_derivatives": "pipeline",
        "load_master": "pipeline",
        "simplify_to": "pipeline",
    },
)
