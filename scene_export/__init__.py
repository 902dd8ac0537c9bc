"""Meshes -> collision geometry -> MJCF and assets.

```python
from scene_export import CollisionOptions, SceneObjectSpec, TableSpec, convex_decomposition, export_scene

collision = convex_decomposition(mesh.vertices_m, mesh.faces, CollisionOptions())
scene = export_scene([SceneObjectSpec(name="bowl", visual=mesh, collision=collision, world_from_object=pose)],
                     TableSpec(), cameras=[], out_dir="out/scene")
```
"""

import os as _os

# Headless machines have no display for MuJoCo's default GLFW backend: render on the CPU with OSMesa unless the
# user chose a backend (MUJOCO_GL=egl for a GPU). Must happen before mujoco is imported.
if "MUJOCO_GL" not in _os.environ and not _os.environ.get("DISPLAY"):
    _os.environ["MUJOCO_GL"] = "osmesa"
    _os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")


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
from scene_export.errors import (
    CompileError,
    DecompositionError,
    DuplicateNameError,
    InvalidMeshError,
    InvalidSceneSpecError,
    OutputExistsError,
    SceneExportError,
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
