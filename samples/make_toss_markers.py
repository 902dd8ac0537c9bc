"""Renders `samples/toss_markers/`: the toss clip again, with printed ArUco markers stuck on the box and the can.

Run: `MUJOCO_GL=osmesa .venv/bin/python samples/make_toss_markers.py [--toss DIR] [--out samples/toss_markers]`

Same physics, camera and frames as `samples/toss` (its truth trajectory is reused as is: the markers are thin
sheets without contacts or mass, so the objects move exactly as there); only the picture differs. The scan
(`samples/tabletop`) was filmed without them, as a user would stick markers on after scanning: the grounded
meshes' textures do not show them. The bowl carries none (a tracked object need not have one).

Writes `video.mp4` and `truth/`: `trajectory.npz`, `objects.json`, `camera.json` (copies of the toss truth) and
`markers.json`, the marker layout `image2sim track --object-markers` reads, in the true scene's body frames
(`samples/toss/truth/scene.xml`): each marker's id, side (of the black square) and pose on its object. A grounded
scene's body frames are its own, so for it give only ids and sides (`markers_unplaced.json`): the tracker places
each marker on its object from the frames where both are seen.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "osmesa")

import mujoco
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import _sample_assets as sa
import make_toss


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--toss", type=Path, default=Path(__file__).parent / "toss")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "toss_markers")
    args = parser.parse_args()
    truth_in = args.toss / "truth"
    qpos = np.load(truth_in / "trajectory.npz", allow_pickle=False)["qpos"]

    with tempfile.TemporaryDirectory() as assets_tmp:
        spec = mujoco.MjSpec.from_file(str(truth_in / "scene.xml"))
        layout = sa.add_object_markers(spec, Path(assets_tmp), sa.default_objects(), absolute_paths=True)
        model = spec.compile()
    frames = sa.render_states(model, qpos, "video", make_toss.HEIGHT_PX, make_toss.WIDTH_PX)

    with sa.toss_variant(args.out, truth_in, frames, make_toss.FPS) as truth:
        note = (
            "ArUco DICT_4X4_50 markers on the objects of samples/toss/truth/scene.xml; size_m = side of the black "
            "square; pos_m / quat_wxyz = the marker frame (origin at the square's centre, x along its top edge, y "
            "up the marker image, z out of the face) in the object's body frame (mesh bounding-box centre)"
        )
        sa.write_json(truth / "markers.json", {"convention": note, "markers": layout})
        unplaced = [{"id": m["id"], "size_m": m["size_m"]} for m in layout]
        sa.write_json(
            truth / "markers_unplaced.json",
            {"convention": "the same markers without their place: for a grounded scene", "markers": unplaced},
        )


if __name__ == "__main__":
    main()
