"""Pixels -> cameras -> geometry: structure from motion in a metric, gravity-aligned world frame."""

from reconstruction import _colmap  # noqa: F401  (first: pycolmap without the SIGTERM handler its import installs)
from reconstruction._frames import Frame, FrameSelection, read_frames, select_frames
from reconstruction._outdir import check_output_dir, check_outside_inputs, staged_output_dir
from reconstruction._reconstruct import reconstruct, rescale_written
from reconstruction._scene_objects import ObjectsOptions, SceneObjects, find_objects
from reconstruction._texture import (
    TextureOptions,
    TextureView,
    bake_table_texture,
    bake_texture,
    bake_texture_report,
    texture_coverage,
)
from reconstruction._types import (
    CameraIntrinsics,
    FrameSelectionOptions,
    ObjectInstance,
    ReconstructionResult,
    ReconstructOptions,
    RegisteredFrame,
    ScaleSource,
    SfmOptions,
    TexturedMesh,
    WorldFrame,
)
from reconstruction.errors import InputError, ReconstructionError, RegistrationError, WorldFrameError

__all__ = [
    "CameraIntrinsics",
    "Frame",
    "FrameSelection",
    "FrameSelectionOptions",
    "InputError",
    "ObjectInstance",
    "ObjectsOptions",
    "ReconstructOptions",
    "ReconstructionError",
    "ReconstructionResult",
    "RegisteredFrame",
    "RegistrationError",
    "ScaleSource",
    "SceneObjects",
    "SfmOptions",
    "TextureOptions",
    "TextureView",
    "TexturedMesh",
    "WorldFrame",
    "WorldFrameError",
    "bake_table_texture",
    "bake_texture",
    "bake_texture_report",
    "check_output_dir",
    "check_outside_inputs",
    "find_objects",
    "read_frames",
    "reconstruct",
    "rescale_written",
    "select_frames",
    "staged_output_dir",
    "texture_coverage",
]
