"""Tracking: 6-DoF poses of a grounded scene's objects in every frame of a clip, by model-based tracking.

- `pipeline`: `track`, the entry point (how it tracks: its module docstring), and putting object markers in;
- `options`: `TrackOptions`, `TrackError`, `FrameScore`, `TrackResult`, what `track` takes and gives;
- `inputs`: reading the clip's frames (`read_clip`) and the scan's frames for the feature models (`load_scan`);
- `camera`: the clip's intrinsics and undistortion, and the camera pose from the table's ArUco marker;
- `tracker`: the per-frame pose search (render-and-compare, detection, the checks a pose must pass), both passes;
- `output`: segments and trajectories, `track.json` and the output folder, and reading the trajectories back;
- `markers`: ArUco marker alignment, and markers stuck on objects;
- `render`: rendering the scene at candidate poses, and the objects' feature models;
- `smooth`: velocities from a smoothing fit, and the rotation helpers;
- `support`: depth from the table where an object rests;
- `overview`: the `overview.png` of a run.

The names below are loaded on first use (PEP 562), so that importing one module does not import them all.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from image2sim_common.lazy import lazy_attributes

# name -> module that defines it
_LAZY = {
    "track": "grounder.tracking.pipeline",
    "TRACK_JSON": "grounder.tracking.options",
    "FrameScore": "grounder.tracking.options",
    "TrackError": "grounder.tracking.options",
    "TrackOptions": "grounder.tracking.options",
    "TrackResult": "grounder.tracking.options",
    "read_clip": "grounder.tracking.inputs",
    "load_object_trajectories": "grounder.tracking.output",
    "object_trajectories": "grounder.tracking.output",
    "track_payload_trajectories": "grounder.tracking.output",
    "ObjectMarker": "grounder.tracking.markers",
    "load_object_markers": "grounder.tracking.markers",
    "SmoothingOptions": "grounder.tracking.smooth",
}


__getattr__ = lazy_attributes(__name__, _LAZY)


if TYPE_CHECKING:  # what the lazy names are, for type checkers and editors
    from grounder.tracking.inputs import read_clip
    from grounder.tracking.markers import ObjectMarker, load_object_markers
    from grounder.tracking.options import TRACK_JSON, FrameScore, TrackError, TrackOptions, TrackResult
    from grounder.tracking.output import load_object_trajectories, object_trajectories, track_payload_trajectories
    from grounder.tracking.pipeline import track
    from grounder.tracking.smooth import SmoothingOptions

__all__ = [  # spelled out (not built from _LAZY) so that linters and type checkers read it
    "TRACK_JSON",
    "FrameScore",
    "ObjectMarker",
    "SmoothingOptions",
    "TrackError",
    "TrackOptions",
    "TrackResult",
    "load_object_markers",
    "load_object_trajectories",
    "object_trajectories",
    "read_clip",
    "track",
    "track_payload_trajectories",
]
