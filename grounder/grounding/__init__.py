"""`ground`: film a tabletop, get a MuJoCo scene folder; and how a grounded scene compares with the truth.

- `pipeline`: `ground` itself (reconstruct -> dense -> objects -> meshes -> textures -> hulls -> properties -> MJCF),
  its options and result.
- `scan_markers`: ArUco markers stuck on objects, found and measured in the scan.
- `evaluate`: a grounded scene scored against a ground truth (centre, Chamfer, extents, normals, topology).

The names load on first use: `ground` pulls in COLMAP, Open3D and trimesh.
"""

from typing import TYPE_CHECKING

from image2sim_common.lazy import lazy_attributes

_LAZY = {
    "GroundOptions": "grounder.grounding.pipeline",
    "GroundResult": "grounder.grounding.pipeline",
    "ground": "grounder.grounding.pipeline",
    "ScanMarker": "grounder.grounding.scan_markers",
    "find_scan_markers": "grounder.grounding.scan_markers",
    "SceneScore": "grounder.grounding.evaluate",
    "compare_to_truth": "grounder.grounding.evaluate",
    "score_scene": "grounder.grounding.evaluate",
}
__getattr__ = lazy_attributes(__name__, _LAZY)

if TYPE_CHECKING:
    from grounder.grounding.evaluate import SceneScore, compare_to_truth, score_scene
    from grounder.grounding.pipeline import GroundOptions, GroundResult, ground
    from grounder.grounding.scan_markers import ScanMarker, find_scan_markers

__all__ = [
    "GroundOptions",
    "GroundResult",
    "ScanMarker",
    "SceneScore",
    "compare_to_truth",
    "find_scan_markers",
    "ground",
    "score_scene",
]
