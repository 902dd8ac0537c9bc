"""Renders `samples/toss_occluded/`: the toss clip again, with a grey card swept between the camera and the box.

Run: `MUJOCO_GL=osmesa .venv/bin/python samples/make_toss_occluded.py [--toss DIR] [--out samples/toss_occluded]`

Same physics, same camera, same frames as `samples/toss` (its truth trajectory is reused as is: the card is a mocap
body without contacts, so the objects move exactly as there); only the picture differs. The card is not part of
any scene the tracker knows, so while it covers the box the box must be flagged lost, not invented. Writes
`video.mp4` and `truth/`: `trajectory.npz`, `objects.json`, `camera.json` (copies of the toss truth) and
`occlusion.json`: per object and frame the fraction of its silhouette the card hides, and the frames where the
box is hidden (at least half covered). The true scene with its meshes is `samples/toss/truth/scene.xml`.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "osmesa")

import mujoco
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import _sample_assets as sa
import make_toss

CARD_HALF_SIZE_M = (0.05, 0.002, 0.06)  # a 10 x 12 cm card, seen face on
CARD_DEPTH_FRACTION = 0.45  # along the ray from the camera to the box
SWEEP_FRAMES = (16, 44)  # the card crosses the image between these frames
SWEEP_HALF_WIDTH_M = 0.1  # from this far below the box's line of sight to this far above
HIDDEN_FRACTION = 0.5


def card_positions(model: mujoco.MjModel, qpos: np.ndarray, world_from_cam: np.ndarray) -> np.ndarray:
    """(T, 3) card centre per frame: on the line of sight to the box's mid-sweep position, swept bottom to top
    (along camera y: across, the card would also hide the can and the bowl, which rest left and right of the box)."""
    box_adr = int(model.joint("box_free").qposadr[0])
    mid = (SWEEP_FRAMES[0] + SWEEP_FRAMES[1]) // 2
    eye = world_from_cam[:3, 3]
    anchor = eye + CARD_DEPTH_FRACTION * (qpos[mid, box_adr : box_adr + 3] - eye)
    down_axis = world_from_cam[:3, 1]
    out = np.tile(eye - 10.0 * world_from_cam[:3, 2], (len(qpos), 1))  # parked behind the camera
    first, last = SWEEP_FRAMES
    for k in range(first, last + 1):
        s = (k - first) / (last - first)
        out[k] = anchor + (1 - 2 * s) * SWEEP_HALF_WIDTH_M * down_axis
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--toss", type=Path, default=Path(__file__).parent / "toss")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "toss_occluded")
    args = parser.parse_args()
    truth_in = args.toss / "truth"
    trajectory = np.load(truth_in / "trajectory.npz", allow_pickle=False)
    qpos = trajectory["qpos"]

    spec = mujoco.MjSpec.from_file(str(truth_in / "scene.xml"))
    card = spec.worldbody.add_body(name="card", mocap=True)
    card.add_geom(
        name="card",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=list(CARD_HALF_SIZE_M),
        rgba=[0.55, 0.56, 0.58, 1],
        contype=0,
        conaffinity=0,
    )
    model = spec.compile()
    data = mujoco.MjData(model)
    cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "video")
    mujoco.mj_forward(model, data)
    world_from_cam = sa.world_from_cam_opencv(data, cam_id)
    # The card faces the camera: its thin y axis along the viewing direction.
    card_quat = np.zeros(4)
    mujoco.mju_mat2Quat(
        card_quat, np.stack([world_from_cam[:3, 0], world_from_cam[:3, 2], -world_from_cam[:3, 1]], 1).flatten()
    )
    positions = card_positions(model, qpos, world_from_cam)
    names = ["box", "can", "bowl"]
    geom_body = model.geom_bodyid
    body_ids = {n: model.body(n).id for n in names}

    renderer = mujoco.Renderer(model, make_toss.HEIGHT_PX, make_toss.WIDTH_PX)
    frames: list[np.ndarray] = []
    covered: dict[str, list[float]] = {n: [] for n in names}
    try:
        for k in range(len(qpos)):
            data.qpos[:] = qpos[k]
            data.mocap_pos[0] = positions[k]
            data.mocap_quat[0] = card_quat
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera=cam_id)
            frames.append(renderer.render()[:, :, :3].copy())
            # Hidden fraction: the object's silhouette without the card vs what is left with it.
            renderer.enable_segmentation_rendering()
            seg_with = renderer.render()[:, :, 0].copy()
            data.mocap_pos[0] = world_from_cam[:3, 3] - 10.0 * world_from_cam[:3, 2]
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera=cam_id)
            seg_without = renderer.render()[:, :, 0].copy()
            renderer.disable_segmentation_rendering()
            for n in names:

                def body_pixels(seg: np.ndarray, body: int = body_ids[n]) -> int:
                    valid = seg >= 0
                    return int((geom_body[np.where(valid, seg, 0)] == body)[valid].sum())

                full = body_pixels(seg_without)
                covered[n].append(round(1.0 - body_pixels(seg_with) / max(full, 1), 4))
            print(f"\rrendered {k + 1}/{len(qpos)}", end="", flush=True)
    finally:
        renderer.close()
    print()
    hidden = [k for k, c in enumerate(covered["box"]) if c >= HIDDEN_FRACTION]
    print(f"box hidden (>= {HIDDEN_FRACTION:.0%} covered) in frames {hidden}")
    print("most covered: " + ", ".join(f"{n} {max(covered[n]):.0%}" for n in names))

    with sa.toss_variant(args.out, truth_in, frames, make_toss.FPS) as truth:
        sa.write_json(
            truth / "occlusion.json",
            {
                "convention": "covered[name][k] = fraction of the object's silhouette in frame k hidden by the card "
                "(a mocap body not in any scene the tracker knows); hidden_frames: covered >= hidden_fraction. "
                "The object states are those of samples/toss (trajectory.npz is a copy).",
                "card_half_size_m": list(CARD_HALF_SIZE_M),
                "sweep_frames": list(SWEEP_FRAMES),
                "hidden_fraction": HIDDEN_FRACTION,
                "hidden_frames": {n: [k for k, c in enumerate(covered[n]) if c >= HIDDEN_FRACTION] for n in names},
                "covered": covered,
            },
        )


if __name__ == "__main__":
    main()
