"""Renders `samples/tabletop/`: a hand-held-style orbit around a table with three objects and an ArUco marker.

Run: `MUJOCO_GL=osmesa .venv/bin/python samples/make_tabletop.py [--out samples/tabletop] [--frames 70]`
With `--object-markers --out samples/tabletop_markers`: the same scan with printed ArUco markers stuck on the box and
the can (`_sample_assets.OBJECT_MARKERS`), as a user would before filming a scan and a toss (`samples/toss_markers`).

Writes `video.mp4` (640x480, 10 fps, H.264) and `truth/`:
- `scene.xml` + `assets/`: the true MuJoCo scene (world = marker frame, table top z = 0);
- `cameras.json`: intrinsics and, per video frame, `world_from_cam` (4x4, OpenCV axes: x right, y down, z forward),
  plus which frames were deliberately made blurred or near-duplicate (frame selection must drop them);
- `objects.json`: per object its mesh file (object frame = bbox centre), `world_from_object` position and
  `quat_wxyz`, extents, volume and the physical parameters used; with markers, `object_markers`: each marker's
  object, id, side and pose in the object's body frame.
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

WIDTH_PX, HEIGHT_PX, FOVY_DEG, FPS = 640, 480, 50.0, 10.0


def orbit_eye_target(frame: float, num_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera centre and look-at point of a slightly wobbly full orbit (frame may be fractional, for blur)."""
    phase = 2 * np.pi * frame / num_frames
    azimuth = -np.pi / 2 + phase * (num_frames + 1.5) / num_frames  # a little more than one turn: loop closure
    radius = 0.62 + 0.05 * np.sin(2 * phase)
    height = 0.42 + 0.06 * np.sin(3 * phase + 0.4)
    eye = np.array([radius * np.cos(azimuth), radius * np.sin(azimuth), height])
    target = np.array([0.03 * np.sin(phase), 0.03 * np.cos(2 * phase), 0.02])
    return eye, target


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "tabletop")
    parser.add_argument("--frames", type=int, default=70)
    parser.add_argument(
        "--object-markers",
        action="store_true",
        help="stick ArUco markers on the box and the can (`samples/tabletop_markers`)",
    )
    args = parser.parse_args()
    num_frames: int = args.frames
    # Frame 0..2 hold still (near-duplicates); two frames mid-orbit are motion-blurred by a fast pan.
    duplicate_frames = [1, 2]
    blurred_frames = [num_frames // 2, num_frames // 2 + 1]

    objects = sa.default_objects()
    with tempfile.TemporaryDirectory(dir=args.out.parent if args.out.parent.exists() else None) as tmp:
        out = Path(tmp) / "tabletop"
        truth = out / "truth"
        sa.write_assets(truth / "assets", objects)
        spec = sa.build_scene_spec(truth / "assets", objects, free_objects=True)
        markers = sa.add_object_markers(spec, truth / "assets", objects) if args.object_markers else []
        (truth / "scene.xml").write_text(spec.to_xml())
        model = spec.compile()
        data = mujoco.MjData(model)
        cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "video")
        model.cam_fovy[cam_id] = FOVY_DEG
        renderer = mujoco.Renderer(model, HEIGHT_PX, WIDTH_PX)

        def render_at(frame_time: float) -> tuple[np.ndarray, np.ndarray]:
            eye, target = orbit_eye_target(frame_time, num_frames)
            model.cam_pos[cam_id] = eye
            model.cam_quat[cam_id] = sa.look_at_quat_wxyz(eye, target)
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera=cam_id)
            return renderer.render().astype(np.float32), sa.world_from_cam_opencv(data, cam_id)

        frames, poses = [], []
        try:
            for i in range(num_frames):
                t = 0.0 if i in duplicate_frames else float(i)
                image, pose = render_at(t)
                if i in blurred_frames:
                    # Average sub-frames over a fast pan of +-1.5 frames: strong horizontal motion blur.
                    subs = [render_at(t + s)[0] for s in np.linspace(-1.5, 1.5, 13)]
                    image = np.mean(subs, axis=0)
                frames.append(np.clip(image, 0, 255).astype(np.uint8)[:, :, :3])
                poses.append(pose)
                print(f"\rrendered {i + 1}/{num_frames}", end="", flush=True)
        finally:
            renderer.close()
        print()
        sa.encode_video(frames, out / "video.mp4", FPS)

        sa.write_json(
            truth / "cameras.json",
            {
                "convention": "world = ArUco marker frame (x right, y top, z up; table top z=0); world_from_cam "
                "maps OpenCV camera coordinates (x right, y down, z forward) to world, metres; pixel centre of "
                "the upper-left pixel is (0.5, 0.5)",
                "intrinsics": sa.intrinsics_from_fovy(FOVY_DEG, WIDTH_PX, HEIGHT_PX),
                "fovy_deg": FOVY_DEG,
                "fps": FPS,
                "aruco": {
                    "dictionary": "DICT_4X4_50",
                    "id": sa.ARUCO_ID,
                    "size_m": sa.MARKER_SIZE_M,
                    "margin_m": sa.MARKER_MARGIN_M,
                    "top_z_m": sa.MARKER_THICKNESS_M,
                },
                "duplicate_frames": duplicate_frames,
                "blurred_frames": blurred_frames,
                "frames": [
                    {"frame_index": i, "world_from_cam": pose.round(9).tolist()} for i, pose in enumerate(poses)
                ],
            },
        )
        sa.write_json(
            truth / "objects.json",
            {
                "convention": "object frame = mesh bounding-box centre; world_from_object = (pos_m, quat_wxyz)",
                "table": {"top_z_m": 0.0, "half_extents_m": list(sa.TABLE_HALF_EXTENTS_M)},
                "objects": [
                    {
                        "name": obj.name,
                        "mesh": f"assets/{obj.name}.obj",
                        "pos_m": list(obj.pos_m),
                        "quat_wxyz": obj.quat_wxyz.round(12).tolist(),
                        "extents_m": obj.mesh.extents.round(9).tolist(),
                        "volume_m3": float(obj.mesh.volume),
                        "concave": bool(obj.mesh.volume < 0.9 * obj.mesh.convex_hull.volume),
                        "material": obj.material,
                        "density_kg_m3": obj.density_kg_m3,
                        "mass_kg": float(obj.mesh.volume * obj.density_kg_m3),
                        "friction": list(obj.friction),
                        "solref": list(obj.solref),
                    }
                    for obj in objects
                ],
                **({"object_markers": markers} if markers else {}),
            },
        )
        sa.move_into_place(out, args.out)


if __name__ == "__main__":
    main()
