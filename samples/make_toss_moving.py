"""Renders `samples/toss_moving/`: the toss clip again, filmed by a camera that moves, as a hand-held phone does.

Run: `MUJOCO_GL=osmesa .venv/bin/python samples/make_toss_moving.py [--toss DIR] [--out samples/toss_moving]`

Same physics and frames as `samples/toss` (its truth trajectory is reused as is); only the camera differs. It
sways about the point its optical axis meets the table at (yaw `SWAY_YAW_DEG`, one and a half periods over the
clip) and bobs in height (`BOB_M`), always looking at that point, with the same intrinsics. The table's ArUco
marker stays in view, so `image2sim track` can place the camera in every frame (its moving-camera path). Writes
`video.mp4` and `truth/`: `trajectory.npz` and `objects.json` (copies of the toss truth) and `camera.json`, which
here also holds `world_from_cam_per_frame` (the true camera pose of every frame; `world_from_cam` is frame 0's).
The true scene with its meshes is `samples/toss/truth/scene.xml`.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "osmesa")

import mujoco
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import _sample_assets as sa
import make_toss

SWAY_YAW_DEG = 10.0  # amplitude of the sway about the vertical through the look-at point
SWAY_PERIODS = 1.5  # over the clip
BOB_M = 0.02  # amplitude of the height change, at twice the sway's rate


def camera_poses(world_from_cam0: np.ndarray, num_frames: int) -> np.ndarray:
    """(T, 4, 4) OpenCV world_from_cam per frame: the start pose swayed about the vertical through the point where
    its optical axis meets the table (z = 0), raised or lowered, and turned to look at that point again."""
    eye0 = world_from_cam0[:3, 3]
    forward0 = world_from_cam0[:3, 2]
    target = eye0 + (-eye0[2] / forward0[2]) * forward0
    out = np.empty((num_frames, 4, 4))
    for k in range(num_frames):
        phase = 2.0 * np.pi * SWAY_PERIODS * k / max(num_frames - 1, 1)
        yaw = np.radians(SWAY_YAW_DEG) * np.sin(phase)
        c, s = np.cos(yaw), np.sin(yaw)
        offset = eye0 - target
        eye = target + np.array([c * offset[0] - s * offset[1], s * offset[0] + c * offset[1], offset[2]])
        eye[2] += BOB_M * np.sin(2.0 * phase)
        forward = (target - eye) / np.linalg.norm(target - eye)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        out[k] = np.eye(4)
        out[k, :3, :3] = np.stack([right, down, forward], axis=1)
        out[k, :3, 3] = eye
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--toss", type=Path, default=Path(__file__).parent / "toss")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "toss_moving")
    args = parser.parse_args()
    truth_in = args.toss / "truth"
    qpos = np.load(truth_in / "trajectory.npz", allow_pickle=False)["qpos"]
    model = mujoco.MjModel.from_xml_path(str(truth_in / "scene.xml"))
    data = mujoco.MjData(model)
    cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "video")
    mujoco.mj_forward(model, data)
    poses = camera_poses(sa.world_from_cam_opencv(data, cam_id), len(qpos))
    frames = sa.render_states(model, qpos, "video", make_toss.HEIGHT_PX, make_toss.WIDTH_PX, world_from_cam=poses)
    travel_mm = 1000 * np.linalg.norm(poses[:, :3, 3] - poses[0, :3, 3], axis=1).max()
    print(f"camera moves up to {travel_mm:.0f} mm from its start")
    with sa.toss_variant(args.out, truth_in, frames, make_toss.FPS) as truth:
        camera = json.loads((truth / "camera.json").read_text())
        camera["convention"] = camera["convention"].replace(
            "the camera is static",
            "the camera moves: world_from_cam_per_frame[k] is frame k's pose, world_from_cam frame 0's",
        )
        camera["world_from_cam"] = poses[0].round(9).tolist()
        camera["world_from_cam_per_frame"] = poses.round(9).tolist()
        camera["motion"] = {"sway_yaw_deg": SWAY_YAW_DEG, "sway_periods": SWAY_PERIODS, "bob_m": BOB_M}
        sa.write_json(truth / "camera.json", camera)


if __name__ == "__main__":
    main()
