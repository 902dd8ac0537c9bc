"""Pixels -> cameras -> geometry: structure from motion in a metric, gravity-aligned world frame."""

from reconstruction._frames import Frame, FrameSelection, read_frames, select_frames
from reconstruction._outdir import staged_output_dir
from reconstruction._reconstruct import reconstruct
from reconstruction._types import (
    CameraIntrinsics,
    FrameSelectionOptions,
    ReconstructionResult,
    ReconstructOptions,
    RegisteredFrame,
    ScaleSource,
    SfmOptions,
    WorldFrame,
)
from reconstruction.errors import InputError, ReconstructionError, RegistrationError, WorldFrameError

__all__ = [
    "CameraIntrinsics",
    "Frame",
    "FrameSelection",
    "FrameSelectionOptions",
    "InputError",
    "ReconstructOptions",
    "ReconstructionError",
    "ReconstructionResult",
    "RegisteredFrame",
    "RegistrationError",
    "ScaleSource",
    "SfmOptions",
    "WorldFrame",
    "WorldFrameError",
    "read_frames",
    "reconstruct",
    "select_frames",
    "staged_output_dir",
]
