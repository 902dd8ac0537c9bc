"""Pixels -> cameras -> geometry: structure from motion in a metric, gravity-aligned world frame.

```python
from reconstruction import ReconstructOptions, reconstruct

result = reconstruct("video.mp4", "out/recon", ReconstructOptions(aruco_size_m=0.12))
```

The names below load on first use (PEP 562): importing `reconstruction` (its types, its errors) does not load
pycolmap or Open3D (OpenCV it does load: see below); the stages that need pycolmap import it through
`reconstruction._colmap`.
"""

import sys
import warnings
from typing import TYPE_CHECKING

# OpenCV before pycolmap: both carry zlib/libpng, and whichever loads first provides them to the other. With
# pycolmap first, OpenCV's first PNG write frees a buffer the other copy allocated and the process aborts ("double
# free or corruption", `python -c "import pycolmap, cv2; cv2.imwrite('x.png', ...)"`); cv2 first is safe. So the
# package loads cv2 at once (0.1 s), though its other names load on first use.
if "pycolmap" in sys.modules and "cv2" not in sys.modules:
    warnings.warn(
        "pycolmap was imported before cv2: OpenCV's PNG writing may then abort the process (double free); "
        "import cv2 (or reconstruction, grounder) before pycolmap",
        RuntimeWarning,
        stacklevel=2,
    )
import cv2  # noqa: F401

from image2sim_common.lazy import lazy_attributes
from image2sim_common.outdir import register_record_files
from reconstruction.errors import InputError, ReconstructionError, RegistrationError, WorldFrameError

register_record_files("reconstruct.json")

# name -> module that defines it
_LAZY = {
    "Frame": "reconstruction._frames",
    "FrameSelection": "reconstruction._frames",
    "read_frames": "reconstruction._frames",
    "select_frames": "reconstruction._frames",
    "check_source": "reconstruction._frames",
    "opened_video": "reconstruction._frames",
    "MAX_DECODED_BYTES": "reconstruction._frames",
    "check_decoded_all": "reconstruction._frames",
    "check_frame_pixels": "reconstruction._frames",
    "image_paths": "reconstruction._frames",
    "image_size": "reconstruction._frames",
    "read_image": "reconstruction._frames",
    "reconstruct": "reconstruction._reconstruct",
    "rescale_written": "reconstruction._reconstruct",
    "SIZE_RANGE_M": "reconstruction._reconstruct",
    "ObjectsOptions": "reconstruction._scene_objects",
    "SceneObjects": "reconstruction._scene_objects",
    "find_objects": "reconstruction._scene_objects",
    "TextureOptions": "reconstruction._texture",
    "TextureView": "reconstruction._texture",
    "bake_table_texture": "reconstruction._texture",
    "bake_texture": "reconstruction._texture",
    "bake_texture_report": "reconstruction._texture",
    "texture_coverage": "reconstruction._texture",
    "CameraIntrinsics": "reconstruction._types",
    "FrameSelectionOptions": "reconstruction._types",
    "ObjectInstance": "reconstruction._types",
    "ReconstructionResult": "reconstruction._types",
    "ReconstructOptions": "reconstruction._types",
    "RegisteredFrame": "reconstruction._types",
    "ScaleSource": "reconstruction._types",
    "SfmOptions": "reconstruction._types",
    "TexturedMesh": "reconstruction._types",
    "WorldFrame": "reconstruction._types",
    "CylinderFit": "reconstruction._primitives",
    "CylinderSnapOptions": "reconstruction._primitives",
    "snap_to_upright_cylinder": "reconstruction._primitives",
    "aruco_detector": "reconstruction._world",
    "detect_marker_corners_px": "reconstruction._world",
    "marker_corners_marker_frame": "reconstruction._world",
    "triangulate_point": "reconstruction._world",
    "umeyama": "reconstruction._world",
    "check_output_dir": "image2sim_common.outdir",
    "check_outside_inputs": "image2sim_common.outdir",
    "staged_output_dir": "image2sim_common.outdir",
}

__getattr__ = lazy_attributes(__name__, _LAZY)


if TYPE_CHECKING:  # what the lazy names are, for type checkers and editors
    from image2sim_common.outdir import check_output_dir, check_outside_inputs, staged_output_dir
    from reconstruction._frames import (
        MAX_DECODED_BYTES,
        Frame,
        FrameSelection,
        check_decoded_all,
        check_frame_pixels,
        check_source,
        image_paths,
        image_size,
        opened_video,
        read_frames,
        read_image,
        select_frames,
    )
    from reconstruction._primitives import CylinderFit, CylinderSnapOptions, snap_to_upright_cylinder
    from reconstruction._reconstruct import SIZE_RANGE_M, reconstruct, rescale_written
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
    from reconstruction._world import (
        aruco_detector,
        detect_marker_corners_px,
        marker_corners_marker_frame,
        triangulate_point,
        umeyama,
    )

__all__ = [
    "MAX_DECODED_BYTES",
    "SIZE_RANGE_M",
    "CameraIntrinsics",
    "CylinderFit",
    "CylinderSnapOptions",
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
    "aruco_detector",
    "bake_table_texture",
    "bake_texture",
    "bake_texture_report",
    "check_decoded_all",
    "check_frame_pixels",
    "check_output_dir",
    "check_outside_inputs",
    "check_source",
    "detect_marker_corners_px",
    "find_objects",
    "image_paths",
    "image_size",
    "marker_corners_marker_frame",
    "opened_video",
    "read_frames",
    "read_image",
    "reconstruct",
    "rescale_written",
    "select_frames",
    "snap_to_upright_cylinder",
    "staged_output_dir",
    "texture_coverage",
    "triangulate_point",
    "umeyama",
]
