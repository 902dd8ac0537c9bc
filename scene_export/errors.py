"""Errors raised while turning meshes into MJCF scenes.

Every message says what was expected, what was received and what to do; the CLI prints it as one line.
"""


class SceneExportError(Exception):
    """Base class for everything the scene export stage rejects or cannot do."""


class InvalidMeshError(SceneExportError):
    """A mesh cannot become a rigid body: wrong shapes, NaN/inf, empty, zero volume or not watertight."""


class DecompositionError(SceneExportError):
    """Convex decomposition (CoACD) failed or is not installed."""


class InvalidSceneSpecError(SceneExportError):
    """An object, table, camera or option of the scene is malformed (pose, physical parameter, size)."""


class DuplicateNameError(InvalidSceneSpecError):
    """Two objects or two cameras would get the same MJCF name."""


class OutputExistsError(SceneExportError):
    """The output folder exists and is not empty, and overwriting was not asked for."""


class CompileError(SceneExportError):
    """MuJoCo could not compile or load a scene (the exported one, or one passed to render/settle)."""
