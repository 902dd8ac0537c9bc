"""Meshes -> collision geometry -> MJCF and assets (grows with the film-a-scene issue)."""

from scene_export.errors import SceneExportError

__all__ = ["SceneExportError"]
