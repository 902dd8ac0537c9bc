"""Errors raised while turning meshes into MJCF scenes."""


class SceneExportError(Exception):
    """Base class for everything the scene export stage rejects or cannot do."""
