"""Meshes -> collision geometry -> MJCF and assets.

```python
from scene_export import CollisionOptions, SceneObjectSpec, TableSpec, convex_decomposition, export_scene

collision = convex_decomposition(mesh.vertices_m, mesh.faces, CollisionOptions())
scene = export_scene([SceneObjectSpec(name="bowl", visual=mesh, collision=collision, world_from_object=pose)],
                     TableSpec(), cameras=[], out_dir="out/scene")
```
"""

from typing import TYPE_CHECKING

from image2sim_common.headless_gl import choose_headless_gl
from image2sim_common.lazy import lazy_attributes
from image2sim_common.outdir import register_record_files
from scene_export.errors import (
    CompileError,
    DecompositionError,
    DuplicateNameError,
    InvalidMeshError,
    InvalidSceneSpecError,
    OutputExistsError,
    SceneExportError,
)

choose_headless_gl()  # before mujoco is imported
register_record_files("scene.json")

# name -> module that defines it; resolved on first attribute access (PEP 562), so that importing `scene_export`
# (its errors, say) loads neither MuJoCo, trimesh nor CoACD.
_LAZY = {
    "CoacdOptions": "scene_export._collision",
    "CollisionGeometry": "scene_export._collision",
    "CollisionOptions": "scene_export._collision",
    "convex_decomposition": "scene_export._collision",
    "default_cache_dir": "scene_export._collision",
    "single_hull": "scene_export._collision",
    "CameraSpec": "scene_export._mjcf",
    "ExportedScene": "scene_export._mjcf",
    "ExportOptions": "scene_export._mjcf",
    "SceneObjectSpec": "scene_export._mjcf",
    "SettleMotion": "scene_export._mjcf",
    "TableSpec": "scene_export._mjcf",
    "export_scene": "scene_export._mjcf",
    "mjcf_name": "scene_export._mjcf",
    "render_view": "scene_export._mjcf",
    "settle_test": "scene_export._mjcf",
    "write_preview": "scene_export._mjcf",
}

__getattr__ = lazy_attributes(__name__, _LAZY)


if TYPE_CHECKING:  # what the lazy names are, for type checkers and editors
    from scene_export._collision import (
        CoacdOptions,
        CollisionGeometry,
        CollisionOptions,
        convex_decomposition,
        default_cache_dir,
        single_hull,
    )
    from scene_export._mjcf import (
        CameraSpec,
        ExportedScene,
        ExportOptions,
        SceneObjectSpec,
        SettleMotion,
        TableSpec,
        export_scene,
        mjcf_name,
        render_view,
        settle_test,
        write_preview,
    )

__all__ = [
    "CameraSpec",
    "CoacdOptions",
    "CollisionGeometry",
    "CollisionOptions",
    "CompileError",
    "DecompositionError",
    "DuplicateNameError",
    "ExportOptions",
    "ExportedScene",
    "InvalidMeshError",
    "InvalidSceneSpecError",
    "OutputExistsError",
    "SceneExportError",
    "SceneObjectSpec",
    "SettleMotion",
    "TableSpec",
    "convex_decomposition",
    "default_cache_dir",
    "export_scene",
    "mjcf_name",
    "render_view",
    "settle_test",
    "single_hull",
    "write_preview",
]
