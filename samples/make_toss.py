"""Renders `samples/toss/`: a static camera watches the tabletop objects being tossed and dropped until they rest.

Run: `MUJOCO_GL=osmesa .venv/bin/python samples/make_toss.py [--out samples/toss]`

The objects are those of `samples/tabletop` (same meshes, textures, masses, friction and solref), so this clip is
an interaction clip of the scanned scene: the box is tossed sideways and slides (friction), the can is dropped
tilted and spinning (impact, torsional friction), the bowl is dropped flat. All are released at t = 0 and rest
well before the end of the clip.

Writes `video.mp4` (640x480, 30 fps, H.264) and `truth/`:
- `scene.xml` + `assets/`: the true MuJoCo scene with free joints (world = marker frame, table top z = 0);
  its `video` camera is the one that filmed the clip;
- `camera.json`: intrinsics and the one `world_from_cam` (4x4, OpenCV axes: x right, y down, z forward);
- `objects.json`: per object its mesh, material, physical parameters, joint addresses, initial state and rest
  pose, plus `joint_order`;
- `trajectory.npz`: the project's trajectory format (see `grounder`), row k = the state shown in video frame k.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "osmesa")

import mujoco
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repo root, for `grounder`
import _sample_assets as sa

from grounder import Trajectory, save_trajectory

WIDTH_PX, HEIGHT_PX, FOVY_DEG, FPS = 640, 480, 50.0, 30.0
NUM_FRAMES = 90  # 3 s
TIMESTEP_S = 0.001
CAMERA_EYE_M = np.array([0.0, -0.53, 0.5])  # 0.71 m from the target, 39 deg above the table
CAMERA_TARGET_M = np.array([0.0, 0.02, 0.05])
MIN_REST_S = 0.7  # the clip must end with at least this long at rest
REST_SPEED_M_S = 1e-4
IMAGE_MARGIN_PX = 8.0


@dataclass(frozen=True, kw_only=True)
class TossStart:
    """Initial state of one object's free joint, in MuJoCo's conventions."""

    pos_m: tuple[float, float, float]  # world position of the object frame (bbox centre)
    quat_wxyz: np.ndarray
    linvel_world_m_s: tuple[float, float, float]
    angvel_body_rad_s: tuple[float, float, float]


def quat_axis_angle_wxyz(axis: tuple[float, float, float], angle_deg: float) -> np.ndarray:
    quat = np.zeros(4)
    mujoco.mju_axisAngle2Quat(quat, np.asarray(axis, float), np.deg2rad(angle_deg))
    return quat


def quat_mul_wxyz(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, a, b)
    return out


def toss_starts() -> dict[str, TossStart]:
    """Released together at t = 0, far enough apart that they never touch each other."""
    return {
        # Bottom 5 cm above the table, thrown fast along +x (its long side): lands, pitches over its leading edge
        # and hops ~1.5 cm, lands again and slides ~3.5 cm. (Dropped from higher, the friction of the landing
        # impulse stops it almost dead: 15 cm at 2.6 m/s leaves ~1.5 cm of slide.)
        "box": TossStart(
            pos_m=(-0.31, 0.2, 0.08),
            quat_wxyz=quat_axis_angle_wxyz((0, 0, 1), 8.0),
            linvel_world_m_s=(3.0, 0.0, 0.0),
            angvel_body_rad_s=(0.0, 0.0, 1.5),
        ),
        # Bottom 20 cm above the table, tilted 6 deg and spinning about its axis: lands on its rim and rocks.
        "can": TossStart(
            pos_m=(0.21, -0.1, 0.255),
            quat_wxyz=quat_mul_wxyz(quat_axis_angle_wxyz((0, 0, 1), -40.0), quat_axis_angle_wxyz((1, 0, 0), 6.0)),
            linvel_world_m_s=(0.0, 0.0, 0.0),
            angvel_body_rad_s=(0.0, 0.0, 6.0),
        ),
        # Dropped flat from 8 cm.
        "bowl": TossStart(
            pos_m=(-0.2, -0.1, 0.0275 + 0.08),
            quat_wxyz=quat_axis_angle_wxyz((0, 0, 1), 10.0),
            linvel_world_m_s=(0.0, 0.0, 0.0),
            angvel_body_rad_s=(0.0, 0.0, 0.0),
        ),
    }


def frame_steps(num_frames: int) -> np.ndarray:
    """Physics step shown in each video frame: the one nearest k / FPS (the timestep does not divide 1/30 s)."""
    steps_per_s = round(1.0 / TIMESTEP_S)
    return np.array([(k * steps_per_s * 2 + round(FPS)) // (2 * round(FPS)) for k in range(num_frames)])


def build_true_spec(assets_dir: Path, objects: list[sa.SampleObject], starts: dict[str, TossStart]) -> mujoco.MjSpec:
    spec = sa.build_scene_spec(assets_dir, objects, free_objects=True, timestep_s=TIMESTEP_S)
    # The bodies' default pose is the released pose, so the scene's qpos0 is (up to XML rounding) the first state.
    for name, start in starts.items():
        spec.body(name).pos = list(start.pos_m)
        spec.body(name).quat = list(start.quat_wxyz)
    camera = spec.camera("video")
    camera.pos = list(CAMERA_EYE_M)
    camera.quat = list(sa.look_at_quat_wxyz(CAMERA_EYE_M, CAMERA_TARGET_M.copy()))
    camera.fovy = FOVY_DEG
    return spec


def simulate(model: mujoco.MjModel, starts: dict[str, TossStart], num_frames: int) -> tuple[np.ndarray, ...]:
    """Steps from the released state; returns time_s (T,), qpos (T, nq), qvel (T, nv) at the video frames.

    Raises RuntimeError if two objects ever touch: the clip is meant to show each object against the table only.
    """
    data = mujoco.MjData(model)
    for name, start in starts.items():
        joint = model.joint(f"{name}_free")
        qpos_adr, dof_adr = int(joint.qposadr[0]), int(joint.dofadr[0])
        quat = start.quat_wxyz / np.linalg.norm(start.quat_wxyz)
        data.qpos[qpos_adr : qpos_adr + 7] = [*start.pos_m, *quat]
        data.qvel[dof_adr : dof_adr + 6] = [*start.linvel_world_m_s, *start.angvel_body_rad_s]
    mujoco.mj_forward(model, data)
    object_bodies = {model.body(name).id for name in starts}
    steps = frame_steps(num_frames)
    time_s, qpos, qvel = [], [], []
    step = 0
    for target in steps:
        while step < target:
            mujoco.mj_step(model, data)
            step += 1
            for contact in data.contact[: data.ncon]:
                bodies = {int(model.geom_bodyid[contact.geom1]), int(model.geom_bodyid[contact.geom2])}
                if bodies <= object_bodies:
                    names = sorted(model.body(b).name for b in bodies)
                    raise RuntimeError(f"objects {names} touch at t={step * TIMESTEP_S:.3f} s; move them apart")
        time_s.append(step * TIMESTEP_S)
        qpos.append(data.qpos.copy())
        qvel.append(data.qvel.copy())
    return np.array(time_s), np.array(qpos), np.array(qvel)


def vertices_world(model: mujoco.MjModel, data: mujoco.MjData, obj: sa.SampleObject) -> np.ndarray:
    """(V, 3) mesh vertices in the world at the state in data (object frame = body frame)."""
    body = data.body(obj.name)
    return np.asarray(obj.mesh.vertices) @ body.xmat.reshape(3, 3).T + body.xpos


def check_clip(
    model: mujoco.MjModel,
    objects: list[sa.SampleObject],
    qpos: np.ndarray,
    qvel: np.ndarray,
    world_from_cam: np.ndarray,
    intrinsics: dict[str, float],
) -> float:
    """Fails loudly if a retuned start breaks the clip; returns the time at rest before the end, seconds.

    Every object must stay fully inside the image, end on the table (lowest vertex at z = 0 within 2 mm, inside
    the table top) and be still (speed < REST_SPEED_M_S) for the last MIN_REST_S.
    """
    data = mujoco.MjData(model)
    cam_from_world = np.linalg.inv(world_from_cam)
    for k in range(len(qpos)):
        data.qpos[:] = qpos[k]
        mujoco.mj_kinematics(model, data)
        for obj in objects:
            points_cam = vertices_world(model, data, obj) @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
            u = intrinsics["fx"] * points_cam[:, 0] / points_cam[:, 2] + intrinsics["cx"]
            v = intrinsics["fy"] * points_cam[:, 1] / points_cam[:, 2] + intrinsics["cy"]
            inside = (
                (u.min() > IMAGE_MARGIN_PX)
                and (u.max() < intrinsics["width"] - IMAGE_MARGIN_PX)
                and (v.min() > IMAGE_MARGIN_PX)
                and (v.max() < intrinsics["height"] - IMAGE_MARGIN_PX)
            )
            if not inside:
                span = f"u {u.min():.0f}..{u.max():.0f}, v {v.min():.0f}..{v.max():.0f}"
                raise RuntimeError(f"{obj.name} leaves the image in frame {k}: {span}")
    hx, hy = sa.TABLE_HALF_EXTENTS_M
    for obj in objects:
        points = vertices_world(model, data, obj)  # data holds the last frame
        if abs(points[:, 2].min()) > 2e-3 or np.abs(points[:, 0]).max() > hx or np.abs(points[:, 1]).max() > hy:
            raise RuntimeError(f"{obj.name} does not end on the table: lowest z {points[:, 2].min():.4f} m")
    speeds = np.stack(
        [np.linalg.norm(qvel[:, model.joint(f"{o.name}_free").dofadr[0] :][:, :3], axis=1) for o in objects], 1
    )
    moving = np.nonzero(speeds.max(axis=1) >= REST_SPEED_M_S)[0]
    rest_frames = len(qvel) - 1 - (moving[-1] if len(moving) else -1)
    rest_s = rest_frames / FPS
    if rest_s < MIN_REST_S:
        raise RuntimeError(f"objects rest only {rest_s:.2f} s before the end; lengthen the clip")
    return rest_s


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "toss")
    args = parser.parse_args()

    objects = sa.default_objects()
    starts = toss_starts()
    with tempfile.TemporaryDirectory(dir=args.out.parent if args.out.parent.exists() else None) as tmp:
        out = Path(tmp) / "toss"
        truth = out / "truth"
        sa.write_assets(truth / "assets", objects)
        (truth / "scene.xml").write_text(build_true_spec(truth / "assets", objects, starts).to_xml())
        # Simulate and render with the model read back from scene.xml, so the truth re-simulates bit for bit.
        model = mujoco.MjModel.from_xml_path(str(truth / "scene.xml"))
        for obj in objects:
            mass_kg = float(model.body(obj.name).mass[0])
            if not np.isclose(mass_kg, obj.mesh.volume * obj.density_kg_m3, rtol=1e-6):
                raise RuntimeError(f"{obj.name}: model mass {mass_kg} kg != mesh volume * density")
        time_s, qpos, qvel = simulate(model, starts, NUM_FRAMES)
        print(f"simulated {time_s[-1]:.3f} s in {NUM_FRAMES} frames")

        data = mujoco.MjData(model)
        cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "video")
        mujoco.mj_forward(model, data)
        world_from_cam = sa.world_from_cam_opencv(data, cam_id)
        intrinsics = sa.intrinsics_from_fovy(FOVY_DEG, WIDTH_PX, HEIGHT_PX)
        rest_s = check_clip(model, objects, qpos, qvel, world_from_cam, intrinsics)
        print(f"all objects in view and on the table; at rest for the last {rest_s:.2f} s")

        renderer = mujoco.Renderer(model, HEIGHT_PX, WIDTH_PX)
        frames = []
        try:
            for k in range(NUM_FRAMES):
                data.qpos[:] = qpos[k]
                data.qvel[:] = qvel[k]
                mujoco.mj_forward(model, data)
                renderer.update_scene(data, camera=cam_id)
                frames.append(renderer.render()[:, :, :3].copy())
                print(f"\rrendered {k + 1}/{NUM_FRAMES}", end="", flush=True)
        finally:
            renderer.close()
        print()
        sa.encode_video(frames, out / "video.mp4", FPS)

        save_trajectory(Trajectory(time_s=time_s, qpos=qpos, qvel=qvel, name="trajectory"), truth / "trajectory.npz")
        sa.write_json(
            truth / "camera.json",
            {
                "convention": "world = ArUco marker frame (x right, y top, z up; table top z=0); world_from_cam "
                "maps OpenCV camera coordinates (x right, y down, z forward) to world, metres; pixel centre of "
                "the upper-left pixel is (0.5, 0.5); the camera is static",
                "intrinsics": intrinsics,
                "fovy_deg": FOVY_DEG,
                "fps": FPS,
                "num_frames": NUM_FRAMES,
                "aruco": {
                    "dictionary": "DICT_4X4_50",
                    "id": sa.ARUCO_ID,
                    "size_m": sa.MARKER_SIZE_M,
                    "margin_m": sa.MARKER_MARGIN_M,
                    "top_z_m": sa.MARKER_THICKNESS_M,
                },
                "world_from_cam": world_from_cam.round(9).tolist(),
            },
        )
        joint_order = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(model.njnt)]
        records = []
        for obj in objects:
            joint = model.joint(f"{obj.name}_free")
            qpos_adr, dof_adr = int(joint.qposadr[0]), int(joint.dofadr[0])
            records.append(
                {
                    "name": obj.name,
                    "mesh": f"assets/{obj.name}.obj",
                    "extents_m": obj.mesh.extents.round(9).tolist(),
                    "volume_m3": float(obj.mesh.volume),
                    "concave": bool(obj.mesh.volume < 0.9 * obj.mesh.convex_hull.volume),
                    "material": obj.material,
                    "density_kg_m3": obj.density_kg_m3,
                    "mass_kg": float(obj.mesh.volume * obj.density_kg_m3),
                    "friction": list(obj.friction),
                    "solref": list(obj.solref),
                    "joint": joint.name,
                    "qpos_adr": qpos_adr,
                    "dof_adr": dof_adr,
                    "initial_qpos": qpos[0, qpos_adr : qpos_adr + 7].tolist(),
                    "initial_qvel": qvel[0, dof_adr : dof_adr + 6].tolist(),
                    "rest_pos_m": qpos[-1, qpos_adr : qpos_adr + 3].round(9).tolist(),
                    "rest_quat_wxyz": qpos[-1, qpos_adr + 3 : qpos_adr + 7].round(12).tolist(),
                }
            )
        sa.write_json(
            truth / "objects.json",
            {
                "convention": "object frame = mesh bounding-box centre = body frame; free joint qpos = world "
                "position (m) then quaternion w-first; qvel = world linear velocity (m/s) then body-frame angular "
                "velocity (rad/s); trajectory.npz row k is video frame k (time_s = nearest physics step to k/fps)",
                "table": {"top_z_m": 0.0, "half_extents_m": list(sa.TABLE_HALF_EXTENTS_M)},
                "timestep_s": TIMESTEP_S,
                "joint_order": joint_order,
                "objects": records,
            },
        )
        if args.out.exists():
            shutil.rmtree(args.out)
        shutil.move(str(out), args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
