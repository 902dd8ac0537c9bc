"""Renders an interaction clip of a scene-family tabletop: its objects thrown onto the table again and again, with
one effect withheld from the grounded scene on one object, for diagnosing a tracked clip against known truth.

Run: `MUJOCO_GL=osmesa .venv/bin/python samples/make_family_clip.py FAMILY_SCENE --scene GROUNDED -o OUT [--seed S]`

`FAMILY_SCENE` is a folder `samples/make_scene_family.py` wrote (it needs the table's ArUco marker: `image2sim track`
places the camera by it) and `GROUNDED` the scene `image2sim ground` made of it. "Reality" in the clip is the
family's true geometry with the physics the grounded scene believes (per object: its sliding, torsional and rolling
friction, its contact solref and its mass), except for one withheld effect on one object: that object's sliding
friction is scaled by a factor drawn from 0.55-0.7 or 1.4-1.7. A diagnosis of the grounded scene against the
tracked clip should therefore name `sliding_friction` on that object (or on its only contact pair, with the table)
near the clip's value; everything else the scan got wrong (shape, inertia) is model error it must not mistake for it.

The clip: `THROWS` throws filmed at 25 fps by one static camera that sees the marker, with the scan's intrinsics
(one phone films both). In each throw every
object is released together from 5-10 cm above its scanned place, tilted, with a horizontal speed of 0.3-0.9 m/s
(balls a third of that) and a spin, and bounces and slides for `THROW_S`; objects never touch each other, stay in
view and end on the table (throws that break this are redrawn). Between throws the objects are gone for
`GAP_FRAMES` frames (picked up, out of view), so the tracker loses them and cuts one trajectory per throw.

Writes `OUT/video.mp4` and `OUT/truth/`: `scene.xml` + `assets/` (the clip's true scene, free joints), `camera.json`
(intrinsics, `world_from_cam`, OpenCV axes), `throws/throw_<k>.npz` (project trajectory format, true object names,
time from the clip's first frame) and `withheld.json` (the effect, the true and the grounded object, the scene's and
the clip's value, the grounded object each true object was matched to, and the grounded bodies none matched).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "osmesa")

import mujoco
import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repo root, for `grounder`
import _sample_assets as sa
import make_toss

from grounder import Trajectory, save_trajectory
from image2sim_common.rotations import look_at_world_from_cam
from scene_export import ExportOptions

FPS = 25.0  # 20 physics steps of 2 ms a frame: frame k shows the state at exactly k / FPS
THROWS = 8
THROW_S = 1.2
GAP_FRAMES = 4
MATCH_TOLERANCE_M = 0.04  # a grounded object's centre of mass within this of a true one's is that object
IMAGE_MARGIN_PX = 6.0
OBJECT_PRIORITY = 1  # as `ground` exports: object-table contacts take the object geom's values
MAX_DRAWS = 400
PHYSICS = ExportOptions()


# ------------------------------------------------------------------------------------ the grounded scene's beliefs
def grounded_bodies(scene_xml: Path) -> dict[str, dict[str, Any]]:
    """Per free body of the grounded scene: centre of mass at its scanned pose (world, m), mass (kg) and the friction
    and solref of its first colliding geom."""
    model = mujoco.MjModel.from_xml_path(str(scene_xml))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    out: dict[str, dict[str, Any]] = {}
    for jnt in range(model.njnt):
        if model.jnt_type[jnt] != mujoco.mjtJoint.mjJNT_FREE:
            continue
        body = int(model.jnt_bodyid[jnt])
        geoms = [
            g
            for g in range(model.ngeom)
            if model.geom_bodyid[g] == body and (model.geom_contype[g] or model.geom_conaffinity[g])
        ]
        if not geoms:
            continue
        out[model.body(body).name] = {
            "com_m": data.xipos[body].copy(),
            "mass_kg": float(model.body_mass[body]),
            "friction": model.geom_friction[geoms[0]].tolist(),
            "solref": model.geom_solref[geoms[0]].tolist(),
        }
    return out


def match_objects(truth_model: mujoco.MjModel, names: list[str], grounded: dict[str, dict[str, Any]]) -> dict[str, str]:
    """True object name -> grounded body name, by centre of mass at the scanned pose (one to one)."""
    data = mujoco.MjData(truth_model)
    mujoco.mj_forward(truth_model, data)
    out: dict[str, str] = {}
    for name in names:
        com = data.body(name).xipos
        dist = {
            g: float(np.linalg.norm(np.asarray(v["com_m"]) - com)) for g, v in grounded.items() if g not in out.values()
        }
        if not dist or min(dist.values()) > MATCH_TOLERANCE_M:
            raise RuntimeError(
                f"{name}: no grounded object within {MATCH_TOLERANCE_M * 100:.0f} cm of it; not a clip to show"
            )
        out[name] = min(dist, key=lambda g: dist[g])
    return out


# ------------------------------------------------------------------------------------------------------- the clip
def clip_spec(
    family_truth: Path,
    objects: list[dict[str, Any]],
    grounded: dict[str, dict[str, Any]],
    matched: dict[str, str],
    withheld: dict[str, Any],
    world_from_cam: np.ndarray,
    fovy_deg: float,
) -> mujoco.MjSpec:
    """The family's true scene with free objects carrying the grounded scene's physics (and the withheld effect)
    and the clip's camera."""
    spec = mujoco.MjSpec.from_file(str(family_truth / "scene.xml"))
    spec.option.timestep = PHYSICS.timestep_s
    spec.option.integrator = getattr(mujoco.mjtIntegrator, f"mjINT_{PHYSICS.integrator.upper()}")
    spec.option.cone = getattr(mujoco.mjtCone, f"mjCONE_{PHYSICS.cone.upper()}")
    spec.option.impratio = PHYSICS.impratio
    for obj in objects:
        name = str(obj["name"])
        belief = grounded[matched[name]]
        spec.body(name).add_freejoint(name=f"{name}_free")
        geom = spec.geom(f"{name}_geom")
        friction = list(belief["friction"])
        if name == withheld["truth_object"]:
            friction[0] = float(withheld["clip_value"])
        geom.friction = friction
        geom.solref = list(belief["solref"])
        geom.priority = OBJECT_PRIORITY
        geom.density = float(belief["mass_kg"]) / float(obj["volume_m3"])
    camera = spec.camera("video")
    camera.pos = world_from_cam[:3, 3].tolist()
    camera.quat = sa.camera_quat_wxyz(world_from_cam).tolist()
    camera.fovy = fovy_deg
    return spec


def camera_pose(rng: np.random.Generator) -> np.ndarray:
    """A static camera in front of the table, 0.42-0.5 m out and 0.38-0.45 m up, looking at the marker."""
    azimuth = np.deg2rad(rng.uniform(-115.0, -65.0))
    radius, height = rng.uniform(0.42, 0.5), rng.uniform(0.38, 0.45)
    eye = np.array([radius * np.cos(azimuth), radius * np.sin(azimuth), height])
    return look_at_world_from_cam(eye, np.array([0.0, 0.0, 0.03]))


def _quat_axis_angle(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    return np.array([np.cos(angle_rad / 2), *(np.sin(angle_rad / 2) * axis)])


def draw_throw(
    rng: np.random.Generator, model: mujoco.MjModel, objects: list[dict[str, Any]]
) -> tuple[np.ndarray, np.ndarray]:
    """(qpos, qvel) of one release: each object above its scanned place, tilted, thrown and spinning."""
    qpos, qvel = model.qpos0.copy(), np.zeros(model.nv)
    for obj in objects:
        joint = model.joint(f"{obj['name']}_free")
        qa, va = int(joint.qposadr[0]), int(joint.dofadr[0])
        pos = np.asarray(obj["pos_m"], dtype=float) + np.array([*rng.uniform(-0.03, 0.03, 2), rng.uniform(0.05, 0.10)])
        tilt_axis = np.array([*rng.normal(size=2), 0.0])
        tilt = _quat_axis_angle(tilt_axis, np.deg2rad(rng.uniform(0.0, 15.0)))
        quat = make_toss.quat_mul_wxyz(tilt, np.asarray(obj["quat_wxyz"], dtype=float))
        speed = rng.uniform(0.3, 0.9) * (1 / 3 if obj["class"] == "ball" else 1.0)
        heading = rng.uniform(0, 2 * np.pi)
        qpos[qa : qa + 7] = [*pos, *(quat / np.linalg.norm(quat))]
        qvel[va : va + 6] = [speed * np.cos(heading), speed * np.sin(heading), 0.0, 0.0, 0.0, rng.uniform(-3, 3)]
    return qpos, qvel


def simulate_throw(
    model: mujoco.MjModel,
    qpos0: np.ndarray,
    qvel0: np.ndarray,
    num_frames: int,
    objects: list[dict[str, Any]],
    meshes: dict[str, trimesh.Trimesh],
    world_from_cam: np.ndarray,
    intrinsics: dict[str, float],
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str:
    """time_s, qpos, qvel at the frames of one throw, or why the throw does not make a clip."""
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = qpos0, qvel0
    mujoco.mj_forward(model, data)
    bodies = {model.body(str(o["name"])).id for o in objects}
    steps_per_frame = round(1.0 / (FPS * model.opt.timestep))
    if not np.isclose(steps_per_frame * FPS * model.opt.timestep, 1.0):
        raise RuntimeError(f"timestep {model.opt.timestep} s does not divide a frame (1/{FPS:g} s)")
    cam_from_world = np.linalg.inv(world_from_cam)
    times, qs, vs = [], [], []
    step = 0
    for k in range(num_frames):
        target = k * steps_per_frame
        while step < target:
            mujoco.mj_step(model, data)
            step += 1
            for contact in data.contact[: data.ncon]:
                if {int(model.geom_bodyid[contact.geom1]), int(model.geom_bodyid[contact.geom2])} <= bodies:
                    return "objects touch"
        for obj in objects:
            body = data.body(str(obj["name"]))
            points = np.asarray(meshes[str(obj["name"])].vertices) @ body.xmat.reshape(3, 3).T + body.xpos
            cam = points @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
            u = intrinsics["fx"] * cam[:, 0] / cam[:, 2] + intrinsics["cx"]
            v = intrinsics["fy"] * cam[:, 1] / cam[:, 2] + intrinsics["cy"]
            if (
                u.min() < IMAGE_MARGIN_PX
                or v.min() < IMAGE_MARGIN_PX
                or u.max() > intrinsics["width"] - IMAGE_MARGIN_PX
                or v.max() > intrinsics["height"] - IMAGE_MARGIN_PX
            ):
                return f"{obj['name']} leaves the image"
            if k == num_frames - 1:
                hx, hy = sa.TABLE_HALF_EXTENTS_M
                if points[:, 2].min() > 0.01 or np.abs(points[:, 0]).max() > hx or np.abs(points[:, 1]).max() > hy:
                    return f"{obj['name']} does not end on the table"
        times.append(step * model.opt.timestep)
        qs.append(data.qpos.copy())
        vs.append(data.qvel.copy())
    return np.array(times), np.array(qs), np.array(vs)


def hidden_state(model: mujoco.MjModel, objects: list[dict[str, Any]]) -> np.ndarray:
    """qpos with every object far under the floor: out of view."""
    qpos = model.qpos0.copy()
    for i, obj in enumerate(objects):
        qa = int(model.joint(f"{obj['name']}_free").qposadr[0])
        qpos[qa : qa + 3] = [0.5 * i, 0.0, -5.0]
    return qpos


def make_clip(family_scene: Path, grounded_scene: Path, out: Path, seed: int, throws: int = THROWS) -> dict[str, Any]:
    """Writes the clip into `out` (which must not exist); returns `withheld.json`'s record."""
    rng = np.random.default_rng(seed)
    family_truth = family_scene / "truth"
    record = json.loads((family_truth / "family.json").read_text())
    if record["scale_by"] != "marker":
        raise RuntimeError(
            f"{family_scene}: no ArUco marker on its table; image2sim track needs one to place the camera"
        )
    objects = json.loads((family_truth / "objects.json").read_text())["objects"]
    grounded = grounded_bodies(grounded_scene / "scene.xml")
    truth_model = mujoco.MjModel.from_xml_path(str(family_truth / "scene.xml"))
    matched = match_objects(truth_model, [str(o["name"]) for o in objects], grounded)
    candidates = [o for o in objects if o["class"] != "ball"] or objects
    chosen = candidates[int(rng.integers(len(candidates)))]
    factor = float(rng.uniform(0.55, 0.7) if rng.random() < 0.5 else rng.uniform(1.4, 1.7))
    scene_value = float(grounded[matched[str(chosen["name"])]]["friction"][0])
    withheld: dict[str, Any] = {
        "effect": "sliding_friction",
        "truth_object": chosen["name"],
        "grounded_body": matched[str(chosen["name"])],
        "scene_value": scene_value,
        "clip_value": scene_value * factor,
        "factor": factor,
        "matched": matched,
        # Grounded bodies no true object matches (phantoms the scan left): not in the clip, so never tracked.
        "unmatched_grounded": sorted(set(grounded) - set(matched.values())),
    }
    world_from_cam = camera_pose(rng)
    # The scan's camera films the clip too (one phone): same intrinsics and size, so `track` needs no --intrinsics.
    scan_camera = json.loads((family_truth / "cameras.json").read_text())
    intrinsics, fovy_deg = scan_camera["intrinsics"], float(scan_camera["fovy_deg"])
    truth = out / "truth"
    shutil.copytree(family_truth / "assets", truth / "assets")
    spec = clip_spec(family_truth, objects, grounded, matched, withheld, world_from_cam, fovy_deg)
    spec.modelfiledir = str(truth)
    (truth / "scene.xml").write_text(spec.to_xml())
    model = mujoco.MjModel.from_xml_path(str(truth / "scene.xml"))
    meshes = {str(o["name"]): trimesh.load_mesh(family_truth / str(o["mesh"]), process=False) for o in objects}
    frames_per_throw = round(THROW_S * FPS)
    states: list[np.ndarray] = []
    throws_dir = truth / "throws"
    throws_dir.mkdir(parents=True)
    frame = 0
    for k in range(throws):
        draws = 0
        while True:
            draws += 1
            qpos0, qvel0 = draw_throw(rng, model, objects)
            result = simulate_throw(model, qpos0, qvel0, frames_per_throw, objects, meshes, world_from_cam, intrinsics)
            if not isinstance(result, str):
                break
            if draws == MAX_DRAWS:
                raise RuntimeError(
                    f"throw {k}: no draw of {MAX_DRAWS} keeps the objects apart, in view and on the table ({result})"
                )
        time_s, qpos, qvel = result
        start_s = frame / FPS
        save_trajectory(
            Trajectory(name=f"throw_{k}", time_s=time_s + start_s, qpos=qpos, qvel=qvel),
            throws_dir / f"throw_{k}.npz",
        )
        states.extend(qpos)
        states.extend([hidden_state(model, objects)] * GAP_FRAMES)
        frame += frames_per_throw + GAP_FRAMES
        print(f"throw {k + 1}/{throws}: {draws} draw(s)", flush=True)
    model_cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "video")
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    if not np.allclose(sa.world_from_cam_opencv(data, model_cam), world_from_cam, atol=1e-6):
        raise RuntimeError("the clip's camera is not the planned one")
    frames = sa.render_states(model, np.array(states), "video", int(intrinsics["height"]), int(intrinsics["width"]))
    sa.encode_video(frames, out / "video.mp4", FPS)
    sa.write_json(
        truth / "camera.json",
        {
            "convention": "world_from_cam maps OpenCV camera coordinates (x right, y down, z forward) to world, metres",
            "intrinsics": intrinsics,
            "world_from_cam": world_from_cam.round(9).tolist(),
            "fps": FPS,
        },
    )
    sa.write_json(truth / "withheld.json", withheld)
    return withheld


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("family_scene", type=Path, help="a scene folder make_scene_family.py wrote (with a marker)")
    parser.add_argument("--scene", type=Path, required=True, help="the scene image2sim ground made of it")
    parser.add_argument("-o", "--out", type=Path, required=True, help="clip folder to write (must not exist)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the throws, the camera and the withheld effect")
    parser.add_argument("--throws", type=int, default=THROWS, help="throws in the clip")
    args = parser.parse_args()
    if args.out.exists():
        parser.error(f"{args.out} exists; choose a new folder")
    if args.throws < 1:
        parser.error(f"--throws {args.throws}: give 1 or more")
    for folder, wants in ((args.family_scene, "truth/family.json"), (args.scene, "scene.xml")):
        if not (folder / wants).is_file():
            parser.error(f"{folder} has no {wants}; pass the folder make_scene_family.py or image2sim ground wrote")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=args.out.parent) as tmp:
        built = Path(tmp) / args.out.name
        withheld = make_clip(args.family_scene, args.scene, built, args.seed, args.throws)
        sa.move_into_place(built, args.out)
    print(
        f"withheld: {withheld['effect']} of {withheld['truth_object']} (grounded {withheld['grounded_body']}) "
        f"{withheld['scene_value']:.3f} in the scene, {withheld['clip_value']:.3f} in the clip"
    )


if __name__ == "__main__":
    main()
