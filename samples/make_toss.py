"""Renders `samples/toss/`: a static camera watches the tabletop objects being tossed and dropped until they rest.

Run: `MUJOCO_GL=osmesa .venv/bin/python samples/make_toss.py [--out samples/toss] [--fps 60]`; `--heldout --out
DIR` renders a second toss with other throws and other contact values (`heldout_starts`, `HELDOUT_CONTACT`).

The objects are those of `samples/tabletop` (same meshes, textures, masses and friction; same solref time
constant), so this clip is an interaction clip of the scanned scene. Only the contact damping ratio (solref[1],
MuJoCo's restitution knob) is lowered (`TOSS_DAMPRATIO`) so that every object visibly bounces. Each object geom
has `priority` 1 (the table's is 0), so MuJoCo does not mix an object-table contact's parameters with the table's
defaults (max friction, mean solref): the contact uses exactly the object's friction and solref, which is what the
calibration is asked to recover. Each object is thrown from 8-12 cm above the table
(see `toss_starts`): it bounces two or three times and slides to rest; all are released at t = 0 and rest well
before the end of the clip.

Writes `video.mp4` (640x480, 30 fps, H.264) and `truth/`:
- `scene.xml` + `assets/`: the true MuJoCo scene with free joints (world = marker frame, table top z = 0);
  its `video` camera is the one that filmed the clip;
- `camera.json`: intrinsics and the one `world_from_cam` (4x4, OpenCV axes: x right, y down, z forward);
- `objects.json`: per object its mesh, material, physical parameters (geom `friction`, `solref`, `priority`, and
  `table_contact`: the friction and solref of its contacts with the table as MuJoCo resolved them, equal to the
  geom's), joint addresses, initial state and rest pose, plus `joint_order`;
- `trajectory.npz`: the project's trajectory format (see `grounder`), row k = the state shown in video frame k.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
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
from scene_export import ExportOptions

WIDTH_PX, HEIGHT_PX, FOVY_DEG, FPS = 640, 480, 50.0, 30.0
CLIP_S = 3.0  # NUM_FRAMES = CLIP_S * FPS at the default rate
NUM_FRAMES = round(CLIP_S * FPS)
# The physics settings of every scene `ground` exports (timestep, integrator, friction cone, impratio), so that the
# values the clip is rendered with mean the same in a grounded scene: calibration can recover them like for like.
PHYSICS = ExportOptions()
TIMESTEP_S = PHYSICS.timestep_s
CAMERA_EYE_M = np.array([0.0, -0.53, 0.5])  # 0.71 m from the target, 39 deg above the table
CAMERA_TARGET_M = np.array([0.0, 0.02, 0.05])
MIN_REST_S = 0.7  # the clip must end with at least this long at rest
REST_TOLERANCE_M = 1e-4
REST_TOLERANCE_DEG = 0.5
IMAGE_MARGIN_PX = 8.0
OBJECT_PRIORITY = 1  # > the table's 0: object-table contacts take the object geom's friction and solref as they are
# Contact damping ratio (solref[1], MuJoCo's restitution knob) in the toss: lower than the scan's so that every
# object visibly bounces; friction, timeconst and everything else are the scan's.
TOSS_DAMPRATIO = {"box": 0.3, "can": 0.15, "bowl": 0.2}
# `--heldout`: a second toss of the same objects with other throws and other contact values (sliding friction,
# damping ratio), for checking `ground --interaction` on a clip none of its defaults was chosen on (they were
# chosen on `samples/toss` and the clips rendered from its motion).
HELDOUT_CONTACT = {"box": (0.70, 0.20), "can": (0.55, 0.25), "bowl": (0.30, 0.30)}


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
    """Released together at t = 0 in separate lanes, far enough apart that they never touch each other.

    Each is thrown from 8-12 cm above the table with a horizontal speed: it lands, bounces two or three times (hops
    of 2-4 cm over several frames: the contact damping ratio) and slides to rest (sliding friction), in view of
    the camera all along; none passes in front of the marker. Moving any object's friction or damping ratio by 20%
    moves its rollout by 4-50 mm on average over the clip (checked when the design was chosen), so the clip
    constrains all six.
    """
    return {
        # Far lane, flat, thrown along -x (its long side).
        "box": TossStart(
            pos_m=(0.36, 0.19, 0.03 + 0.12),
            quat_wxyz=quat_axis_angle_wxyz((0, 0, 1), 5.0),
            linvel_world_m_s=(-1.5, 0.0, 0.0),
            angvel_body_rad_s=(0.0, 0.0, 0.0),
        ),
        # Near left, upright, thrown away from the camera (+y) and spinning about its axis.
        "can": TossStart(
            pos_m=(-0.17, -0.22, 0.055 + 0.12),
            quat_wxyz=quat_axis_angle_wxyz((0, 0, 1), -40.0),
            linvel_world_m_s=(0.0, 1.0, 0.0),
            angvel_body_rad_s=(0.0, 0.0, 3.0),
        ),
        # Right, flat, thrown towards the camera (-y).
        "bowl": TossStart(
            pos_m=(0.22, 0.06, 0.0275 + 0.08),
            quat_wxyz=quat_axis_angle_wxyz((0, 0, 1), 10.0),
            linvel_world_m_s=(0.0, -1.3, 0.0),
            angvel_body_rad_s=(0.0, 0.0, 0.0),
        ),
    }


def heldout_starts() -> dict[str, TossStart]:
    """`--heldout`'s throws: other lanes, directions, heights and spins than `toss_starts`; still apart, in view,
    clear of the marker and at rest well before the end (`check_clip`)."""
    return {
        # Far lane, thrown along +x (the other way), spinning about the vertical.
        "box": TossStart(
            pos_m=(-0.27, 0.21, 0.03 + 0.11),
            quat_wxyz=quat_axis_angle_wxyz((0, 0, 1), -8.0),
            linvel_world_m_s=(1.3, 0.0, 0.0),
            angvel_body_rad_s=(0.0, 0.0, 2.0),
        ),
        # Near right, upright, thrown away from the camera and to the right, spinning the other way.
        "can": TossStart(
            pos_m=(0.12, -0.25, 0.055 + 0.10),
            quat_wxyz=quat_axis_angle_wxyz((0, 0, 1), 30.0),
            linvel_world_m_s=(0.35, 0.9, 0.0),
            angvel_body_rad_s=(0.0, 0.0, -4.0),
        ),
        # Left, flat, thrown towards the camera and to the right.
        "bowl": TossStart(
            pos_m=(-0.22, 0.0, 0.0275 + 0.10),
            quat_wxyz=quat_axis_angle_wxyz((0, 0, 1), -20.0),
            linvel_world_m_s=(0.5, -0.7, 0.0),
            angvel_body_rad_s=(0.0, 0.0, 1.0),
        ),
    }


def frame_steps(num_frames: int, fps: float = FPS) -> np.ndarray:
    """Physics step shown in each video frame: the one nearest k / fps (the timestep does not divide 1/30 s)."""
    steps_per_s = round(1.0 / TIMESTEP_S)
    return np.array([(k * steps_per_s * 2 + round(fps)) // (2 * round(fps)) for k in range(num_frames)])


def toss_objects(heldout: bool = False) -> list[sa.SampleObject]:
    """The tabletop objects with the toss's contact damping ratios (`TOSS_DAMPRATIO`), or with `HELDOUT_CONTACT`'s
    sliding friction and damping ratio."""
    if heldout:
        return [
            dataclasses.replace(
                obj,
                friction=(HELDOUT_CONTACT[obj.name][0], *obj.friction[1:]),
                solref=(obj.solref[0], HELDOUT_CONTACT[obj.name][1]),
            )
            for obj in sa.default_objects()
        ]
    return [dataclasses.replace(obj, solref=(obj.solref[0], TOSS_DAMPRATIO[obj.name])) for obj in sa.default_objects()]


def build_true_spec(assets_dir: Path, objects: list[sa.SampleObject], starts: dict[str, TossStart]) -> mujoco.MjSpec:
    spec = sa.build_scene_spec(assets_dir, objects, free_objects=True, timestep_s=TIMESTEP_S)
    spec.option.integrator = getattr(mujoco.mjtIntegrator, f"mjINT_{PHYSICS.integrator.upper()}")
    spec.option.cone = getattr(mujoco.mjtCone, f"mjCONE_{PHYSICS.cone.upper()}")
    spec.option.impratio = PHYSICS.impratio
    # Each object's geom outranks the table's (MuJoCo's defaults: friction 1, solref 0.02 1), so an object-table
    # contact uses exactly the object's friction and solref instead of the mix (max friction, mean solref).
    for obj in objects:
        spec.geom(f"{obj.name}_geom").priority = OBJECT_PRIORITY
    # The bodies' default pose is the released pose, so the scene's qpos0 is (up to XML rounding) the first state.
    for name, start in starts.items():
        spec.body(name).pos = list(start.pos_m)
        spec.body(name).quat = list(start.quat_wxyz)
    camera = spec.camera("video")
    camera.pos = list(CAMERA_EYE_M)
    camera.quat = list(sa.look_at_quat_wxyz(CAMERA_EYE_M, CAMERA_TARGET_M.copy()))
    camera.fovy = FOVY_DEG
    return spec


def simulate(
    model: mujoco.MjModel, starts: dict[str, TossStart], num_frames: int, fps: float = FPS
) -> tuple[np.ndarray, ...]:
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
    steps = frame_steps(num_frames, fps)
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


def table_contact_values(model: mujoco.MjModel, qpos: np.ndarray) -> dict[str, dict[str, list[float]]]:
    """Per object, the friction and solref of its contacts with the table as MuJoCo resolved them, at `qpos`
    (a resting state); raises if they are not the object geom's own values (the point of `OBJECT_PRIORITY`)."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    out: dict[str, dict[str, list[float]]] = {}
    for contact in data.contact[: data.ncon]:
        geoms = (int(contact.geom1), int(contact.geom2))
        objects = [g for g in geoms if model.geom_bodyid[g] != 0]
        if len(objects) != 1:
            continue
        geom = objects[0]
        name = model.body(int(model.geom_bodyid[geom])).name
        values = {"friction": contact.friction[[0, 2, 3]].tolist(), "solref": contact.solref.tolist()}
        expected = {"friction": model.geom_friction[geom].tolist(), "solref": model.geom_solref[geom].tolist()}
        if not all(np.allclose(values[k], expected[k]) for k in values):
            raise RuntimeError(f"{name}: table contact uses {values}, not the geom's {expected}")
        out[name] = values
    return out


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
    fps: float = FPS,
) -> float:
    """Fails loudly if a retuned start breaks the clip; returns the time at rest before the end, seconds.

    Every object must stay fully inside the image, end on the table (lowest vertex at z = 0 within 2 mm, inside
    the table top) and stay within REST_TOLERANCE_M and REST_TOLERANCE_DEG of its final pose for the last MIN_REST_S.
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
    # At rest = within REST_TOLERANCE_M / REST_TOLERANCE_DEG of the final pose. (Not a speed threshold: with the
    # low damping ratios the soft contacts of a resting object chatter at a few mm/s with < 0.05 mm amplitude, and
    # the box, on one contact point at a time, creeps by ~0.5 deg/s.)
    moving_frames = []
    for obj in objects:
        qpos_adr = int(model.joint(f"{obj.name}_free").qposadr[0])
        pos, quat = qpos[:, qpos_adr : qpos_adr + 3], qpos[:, qpos_adr + 3 : qpos_adr + 7]
        angle_deg = np.rad2deg(2 * np.arccos(np.clip(np.abs(quat @ quat[-1]), 0.0, 1.0)))
        off = (np.linalg.norm(pos - pos[-1], axis=1) >= REST_TOLERANCE_M) | (angle_deg >= REST_TOLERANCE_DEG)
        moving_frames.extend(np.nonzero(off)[0].tolist())
    rest_frames = len(qpos) - 1 - max(moving_frames, default=-1)
    rest_s = rest_frames / fps
    if rest_s < MIN_REST_S:
        raise RuntimeError(f"objects rest only {rest_s:.2f} s before the end; lengthen the clip")
    return rest_s


@dataclass(frozen=True, kw_only=True)
class SimulatedClip:
    """What `simulate_clip` wrote and simulated: the model read back from `truth/scene.xml`, the states at the video
    frames, the camera (`world_from_cam`, OpenCV axes) and its intrinsics, and the time at rest before the end."""

    model: mujoco.MjModel
    time_s: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    world_from_cam: np.ndarray
    intrinsics: dict[str, float]
    rest_s: float


def simulate_clip(
    truth: Path, objects: list[sa.SampleObject], starts: dict[str, TossStart], num_frames: int, fps: float = FPS
) -> SimulatedClip:
    """Writes `truth/assets` and `truth/scene.xml`, simulates the toss and checks it (`check_clip`; raises if a
    start breaks the clip)."""
    sa.write_assets(truth / "assets", objects)
    (truth / "scene.xml").write_text(build_true_spec(truth / "assets", objects, starts).to_xml())
    # Simulate and render with the model read back from scene.xml, so the truth re-simulates bit for bit.
    model = mujoco.MjModel.from_xml_path(str(truth / "scene.xml"))
    for obj in objects:
        mass_kg = float(model.body(obj.name).mass[0])
        if not np.isclose(mass_kg, obj.mesh.volume * obj.density_kg_m3, rtol=1e-6):
            raise RuntimeError(f"{obj.name}: model mass {mass_kg} kg != mesh volume * density")
    time_s, qpos, qvel = simulate(model, starts, num_frames, fps)
    data = mujoco.MjData(model)
    cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "video")
    mujoco.mj_forward(model, data)
    world_from_cam = sa.world_from_cam_opencv(data, cam_id)
    intrinsics = sa.intrinsics_from_fovy(FOVY_DEG, WIDTH_PX, HEIGHT_PX)
    rest_s = check_clip(model, objects, qpos, qvel, world_from_cam, intrinsics, fps)
    return SimulatedClip(
        model=model,
        time_s=time_s,
        qpos=qpos,
        qvel=qvel,
        world_from_cam=world_from_cam,
        intrinsics=intrinsics,
        rest_s=rest_s,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "toss")
    parser.add_argument(
        "--fps", type=float, default=FPS, help="frame rate of the clip (same motion, same 3 s; default 30)"
    )
    parser.add_argument(
        "--heldout",
        action="store_true",
        help="render the held-out toss (other throws and contact values, `HELDOUT_CONTACT`) into --out",
    )
    args = parser.parse_args()
    if args.heldout and args.out == parser.get_default("out"):
        parser.error("--heldout renders a benchmark clip, not samples/toss: give --out DIR")
    fps = float(args.fps)
    num_frames = round(CLIP_S * fps)

    objects = toss_objects(args.heldout)
    starts = heldout_starts() if args.heldout else toss_starts()
    with tempfile.TemporaryDirectory(dir=args.out.parent if args.out.parent.exists() else None) as tmp:
        out = Path(tmp) / "toss"
        truth = out / "truth"
        clip = simulate_clip(truth, objects, starts, num_frames, fps)
        model, time_s, qpos, qvel = clip.model, clip.time_s, clip.qpos, clip.qvel
        world_from_cam, intrinsics = clip.world_from_cam, clip.intrinsics
        print(f"simulated {time_s[-1]:.3f} s in {num_frames} frames")
        print(f"all objects in view and on the table; at rest for the last {clip.rest_s:.2f} s")

        frames = sa.render_states(model, qpos, "video", HEIGHT_PX, WIDTH_PX)
        sa.encode_video(frames, out / "video.mp4", fps)

        save_trajectory(Trajectory(time_s=time_s, qpos=qpos, qvel=qvel, name="trajectory"), truth / "trajectory.npz")
        sa.write_json(
            truth / "camera.json",
            {
                "convention": "world = ArUco marker frame (x right, y top, z up; table top z=0); world_from_cam "
                "maps OpenCV camera coordinates (x right, y down, z forward) to world, metres; pixel centre of "
                "the upper-left pixel is (0.5, 0.5); the camera is static",
                "intrinsics": intrinsics,
                "fovy_deg": FOVY_DEG,
                "fps": fps,
                "num_frames": num_frames,
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
        contacts = table_contact_values(model, qpos[-1])
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
                    "priority": OBJECT_PRIORITY,
                    "table_contact": {
                        "note": "the object geom's priority beats the table's, so its contacts with the table use "
                        "exactly this geom's friction and solref (read back from MuJoCo's resting contacts)",
                        **contacts[obj.name],
                    },
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
        sa.move_into_place(out, args.out)


if __name__ == "__main__":
    main()
