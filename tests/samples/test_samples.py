"""The committed sample truths agree with themselves: scene, meshes, masses, video, camera poses, trajectory.

Nothing is re-rendered; the videos are only decoded. Each sample's tests skip if its folder is missing
(`make samples` regenerates them).
"""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path

import cv2
import mujoco
import numpy as np
import pytest
import trimesh

from grounder import Trajectory, load_trajectory, validate_against_model

SAMPLES = Path(__file__).resolve().parents[2] / "samples"
MARKER_HALF_M = 0.06
MARKER_TOP_Z_M = 0.0003
# ArUco corner order: top-left, top-right, bottom-right, bottom-left of the marker image (image top = world +y).
MARKER_CORNERS_WORLD = np.array(
    [[-MARKER_HALF_M, MARKER_HALF_M, MARKER_TOP_Z_M], [MARKER_HALF_M, MARKER_HALF_M, MARKER_TOP_Z_M],
     [MARKER_HALF_M, -MARKER_HALF_M, MARKER_TOP_Z_M], [-MARKER_HALF_M, -MARKER_HALF_M, MARKER_TOP_Z_M]]
)  # fmt: skip
MARKER_OUTER_HALF_M = 0.08  # the white border's outer edge
MAX_MARKER_ERROR_PX = 1.5


def _sample_dir(name: str, required: tuple[str, ...]) -> Path:
    path = SAMPLES / name
    missing = [f for f in required if not (path / f).exists()]
    if missing:
        pytest.skip(f"samples/{name} lacks {missing}: run `make samples`")
    return path


@cache
def _video_frames(path: Path) -> tuple[np.ndarray, ...]:
    """All frames of a video, BGR uint8 (decoded once per test session)."""
    capture = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    capture.release()
    return tuple(frames)


def _project_px(points_world: np.ndarray, world_from_cam: np.ndarray, intrinsics: dict) -> np.ndarray:
    """(N, 2) pixel coordinates, upper-left pixel centre at (0.5, 0.5), of world points seen by an OpenCV camera."""
    cam_from_world = np.linalg.inv(world_from_cam)
    points_cam = points_world @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    assert (points_cam[:, 2] > 0).all(), "points behind the camera"
    u = intrinsics["fx"] * points_cam[:, 0] / points_cam[:, 2] + intrinsics["cx"]
    v = intrinsics["fy"] * points_cam[:, 1] / points_cam[:, 2] + intrinsics["cy"]
    return np.column_stack([u, v])


def _detect_marker_px(image_bgr: np.ndarray) -> np.ndarray | None:
    """(4, 2) ArUco id-0 corners with the (0.5, 0.5) pixel-centre convention, or None if not found."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), params)
    corners, ids, _ = detector.detectMarkers(cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY))
    if ids is None or 0 not in ids.ravel():
        return None
    # OpenCV puts pixel centres at integers; the truths put the upper-left one at (0.5, 0.5).
    return corners[list(ids.ravel()).index(0)].reshape(4, 2) + 0.5


def _mesh(truth: Path, record: dict) -> trimesh.Trimesh:
    return trimesh.load(truth / record["mesh"], force="mesh", process=False)


# ---------------------------------------------------------------- tabletop


@pytest.fixture(scope="module")
def tabletop() -> Path:
    return _sample_dir("tabletop", ("video.mp4", "truth/scene.xml", "truth/cameras.json", "truth/objects.json"))


@pytest.fixture(scope="module")
def tabletop_model(tabletop: Path) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(tabletop / "truth" / "scene.xml"))


@pytest.fixture(scope="module")
def tabletop_objects(tabletop: Path) -> dict[str, dict]:
    payload = json.loads((tabletop / "truth" / "objects.json").read_text())
    return {record["name"]: record for record in payload["objects"]}


@pytest.fixture(scope="module")
def tabletop_cameras(tabletop: Path) -> dict:
    return json.loads((tabletop / "truth" / "cameras.json").read_text())


def test_tabletop_scene_compiles_with_every_object(tabletop_model: mujoco.MjModel, tabletop_objects: dict) -> None:
    for name in tabletop_objects:
        assert mujoco.mj_name2id(tabletop_model, mujoco.mjtObj.mjOBJ_BODY, name) >= 0, name


def test_tabletop_volumes_and_masses_match_meshes(tabletop: Path, tabletop_objects: dict) -> None:
    for name, record in tabletop_objects.items():
        mesh = _mesh(tabletop / "truth", record)
        assert mesh.is_watertight, name
        # The OBJ stores 6 decimals (micrometres), so its volume differs from the generator's in the 5th digit.
        assert mesh.volume == pytest.approx(record["volume_m3"], rel=1e-4), name
        assert record["mass_kg"] == pytest.approx(record["volume_m3"] * record["density_kg_m3"], rel=1e-12), name
        np.testing.assert_allclose(mesh.extents, record["extents_m"], atol=2e-6, err_msg=name)


@pytest.mark.parametrize("name", ["box", "can", "bowl"])
def test_tabletop_model_masses_match_objects_json(
    name: str, tabletop_model: mujoco.MjModel, tabletop_objects: dict
) -> None:
    mass_kg = float(tabletop_model.body(name).mass[0])
    assert mass_kg == pytest.approx(tabletop_objects[name]["mass_kg"], rel=1e-6)


def test_tabletop_bowl_is_concave(tabletop: Path, tabletop_objects: dict) -> None:
    mesh = _mesh(tabletop / "truth", tabletop_objects["bowl"])
    assert mesh.volume < 0.7 * mesh.convex_hull.volume
    assert tabletop_objects["bowl"]["concave"]


def test_tabletop_video_matches_cameras_json(tabletop: Path, tabletop_cameras: dict) -> None:
    frames = _video_frames(tabletop / "video.mp4")
    assert len(frames) == len(tabletop_cameras["frames"])
    assert all(frame.shape == (480, 640, 3) for frame in frames)
    intrinsics = tabletop_cameras["intrinsics"]
    assert (intrinsics["width"], intrinsics["height"]) == (640, 480)


def _marker_occluded(model: mujoco.MjModel, data: mujoco.MjData, camera_world_m: np.ndarray) -> bool:
    """True if an object hides a marker corner or part of its white border (which detection needs) from the camera."""
    border = np.linspace(-MARKER_OUTER_HALF_M, MARKER_OUTER_HALF_M, 9)
    edge = [[a, b] for a in border for b in (-MARKER_OUTER_HALF_M, MARKER_OUTER_HALF_M)]
    points = np.vstack([MARKER_CORNERS_WORLD, [[a, b, MARKER_TOP_Z_M] for a, b in edge + [e[::-1] for e in edge]]])
    geom_id = np.zeros(1, np.int32)
    for point in points:
        # flg_static=0 ignores the world body's geoms (table, marker sheet), so only objects count as occluders.
        hit = mujoco.mj_ray(model, data, camera_world_m, point - camera_world_m, None, 0, -1, geom_id)
        if 0 <= hit < 1:
            return True
    return False


def test_tabletop_marker_projects_onto_detected_corners(
    tabletop: Path, tabletop_cameras: dict, tabletop_model: mujoco.MjModel
) -> None:
    """In every sharp frame with the marker in full view, ArUco finds it where the true camera pose puts it."""
    frames = _video_frames(tabletop / "video.mp4")
    data = mujoco.MjData(tabletop_model)
    mujoco.mj_forward(tabletop_model, data)  # the objects stand at their true poses (the scene's qpos0)
    blurred = set(tabletop_cameras["blurred_frames"])
    checked = 0
    for i, frame in enumerate(frames):
        world_from_cam = np.array(tabletop_cameras["frames"][i]["world_from_cam"])
        if i in blurred or _marker_occluded(tabletop_model, data, world_from_cam[:3, 3]):
            continue
        detected = _detect_marker_px(frame)
        assert detected is not None, f"frame {i}: marker in full view but not detected"
        expected = _project_px(MARKER_CORNERS_WORLD, world_from_cam, tabletop_cameras["intrinsics"])
        error_px = np.linalg.norm(detected - expected, axis=1).max()
        assert error_px < MAX_MARKER_ERROR_PX, f"frame {i}: corners off by {error_px:.2f} px"
        checked += 1
    assert checked >= 10, f"only {checked} frames show the whole marker"


# ---------------------------------------------------------------- toss


@pytest.fixture(scope="module")
def toss() -> Path:
    required = ("video.mp4", "truth/scene.xml", "truth/camera.json", "truth/objects.json", "truth/trajectory.npz")
    return _sample_dir("toss", required)


@pytest.fixture(scope="module")
def toss_model(toss: Path) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(toss / "truth" / "scene.xml"))


@pytest.fixture(scope="module")
def toss_objects(toss: Path) -> dict:
    return json.loads((toss / "truth" / "objects.json").read_text())


@pytest.fixture(scope="module")
def toss_camera(toss: Path) -> dict:
    return json.loads((toss / "truth" / "camera.json").read_text())


@pytest.fixture(scope="module")
def toss_traj(toss: Path) -> Trajectory:
    return load_trajectory(toss / "truth" / "trajectory.npz")


@pytest.fixture(scope="module")
def toss_vertices(
    toss: Path, toss_model: mujoco.MjModel, toss_objects: dict, toss_traj: Trajectory
) -> dict[str, np.ndarray]:
    """Per object, (T, V, 3) world positions of its mesh vertices at every recorded frame."""
    data = mujoco.MjData(toss_model)
    meshes = {r["name"]: np.asarray(_mesh(toss / "truth", r).vertices) for r in toss_objects["objects"]}
    out: dict[str, list[np.ndarray]] = {name: [] for name in meshes}
    for qpos in toss_traj.qpos:
        data.qpos[:] = qpos
        mujoco.mj_kinematics(toss_model, data)
        for name, vertices in meshes.items():
            body = data.body(name)
            out[name].append(vertices @ body.xmat.reshape(3, 3).T + body.xpos)
    return {name: np.array(v) for name, v in out.items()}


def _linear_velocity(model: mujoco.MjModel, traj: Trajectory, name: str) -> np.ndarray:
    """(T, 3) world linear velocity of an object's free joint, m/s."""
    dof_adr = int(model.joint(f"{name}_free").dofadr[0])
    return traj.qvel[:, dof_adr : dof_adr + 3]


def test_toss_trajectory_fits_scene(toss_model: mujoco.MjModel, toss_traj: Trajectory, toss_objects: dict) -> None:
    validate_against_model(toss_traj, toss_model)
    joint_names = [mujoco.mj_id2name(toss_model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(toss_model.njnt)]
    assert toss_objects["joint_order"] == joint_names
    assert toss_objects["timestep_s"] == pytest.approx(toss_model.opt.timestep)
    assert toss_traj.time_s[0] == 0.0
    for record in toss_objects["objects"]:
        qpos_adr, dof_adr = record["qpos_adr"], record["dof_adr"]
        joint = toss_model.joint(record["joint"])
        assert (int(joint.qposadr[0]), int(joint.dofadr[0])) == (qpos_adr, dof_adr)
        np.testing.assert_array_equal(toss_traj.qpos[0, qpos_adr : qpos_adr + 7], record["initial_qpos"])
        np.testing.assert_array_equal(toss_traj.qvel[0, dof_adr : dof_adr + 6], record["initial_qvel"])


def test_toss_masses_match_meshes_and_model(toss: Path, toss_model: mujoco.MjModel, toss_objects: dict) -> None:
    for record in toss_objects["objects"]:
        name = record["name"]
        assert _mesh(toss / "truth", record).volume == pytest.approx(record["volume_m3"], rel=1e-4), name
        assert record["mass_kg"] == pytest.approx(record["volume_m3"] * record["density_kg_m3"], rel=1e-12)
        assert float(toss_model.body(name).mass[0]) == pytest.approx(record["mass_kg"], rel=1e-6), name
        geom = toss_model.geom(f"{name}_geom")
        np.testing.assert_allclose(geom.friction, record["friction"], err_msg=name)
        np.testing.assert_allclose(geom.solref, record["solref"], err_msg=name)


def test_toss_objects_share_tabletop_parameters(toss_objects: dict, tabletop_objects: dict) -> None:
    """The toss is an interaction clip of the scanned scene: same objects, same physical parameters, except the
    contact damping ratio (solref[1]), lowered in the toss so that every object bounces visibly."""
    keys = ("volume_m3", "density_kg_m3", "mass_kg", "friction", "material", "extents_m")
    for record in toss_objects["objects"]:
        scanned = tabletop_objects[record["name"]]
        for key in keys:
            assert record[key] == scanned[key], (record["name"], key)
        assert record["solref"][0] == scanned["solref"][0], record["name"]
        assert 0.1 <= record["solref"][1] < scanned["solref"][1], record["name"]


def test_toss_table_contacts_use_the_object_values(
    toss_model: mujoco.MjModel, toss_traj: Trajectory, toss_objects: dict
) -> None:
    """Object geoms outrank the table, so MuJoCo does not mix (max friction, mean solref) with the table's
    defaults: each object-table contact uses exactly the object's friction and solref (as objects.json says)."""
    data = mujoco.MjData(toss_model)
    data.qpos[:] = toss_traj.qpos[-1]
    mujoco.mj_forward(toss_model, data)
    records = {r["name"]: r for r in toss_objects["objects"]}
    seen = set()
    for contact in data.contact[: data.ncon]:
        bodies = [toss_model.body(int(toss_model.geom_bodyid[g])).name for g in (contact.geom1, contact.geom2)]
        assert "world" in bodies, bodies
        name = next(b for b in bodies if b != "world")
        record = records[name]
        assert toss_model.geom(f"{name}_geom").priority[0] == record["priority"] > 0
        np.testing.assert_allclose(contact.friction[[0, 2, 3]], record["friction"], err_msg=name)
        np.testing.assert_allclose(contact.solref, record["solref"], err_msg=name)
        np.testing.assert_allclose(record["table_contact"]["friction"], record["friction"], err_msg=name)
        np.testing.assert_allclose(record["table_contact"]["solref"], record["solref"], err_msg=name)
        seen.add(name)
    assert seen == set(records)


def test_toss_resimulation_reproduces_trajectory(toss_model: mujoco.MjModel, toss_traj: Trajectory) -> None:
    """Stepping the true scene from the first recorded state lands on every recorded state."""
    data = mujoco.MjData(toss_model)
    data.qpos[:] = toss_traj.qpos[0]
    data.qvel[:] = toss_traj.qvel[0]
    steps = np.round(toss_traj.time_s / toss_model.opt.timestep).astype(int)
    np.testing.assert_allclose(steps * toss_model.opt.timestep, toss_traj.time_s, atol=1e-12)
    positions = [int(toss_model.jnt_qposadr[j]) + i for j in range(toss_model.njnt) for i in range(3)]
    step = 0
    for k, target in enumerate(steps):
        if target > step:
            mujoco.mj_step(toss_model, data, nstep=int(target - step))
            step = int(target)
        error_m = np.abs(data.qpos[positions] - toss_traj.qpos[k, positions]).max()
        assert error_m < 1e-6, f"frame {k} (t={toss_traj.time_s[k]:.3f} s): position off by {error_m:.2e} m"
        np.testing.assert_allclose(data.qpos, toss_traj.qpos[k], atol=1e-6, err_msg=f"frame {k}")


def test_toss_ends_at_rest_on_table(
    toss_model: mujoco.MjModel, toss_traj: Trajectory, toss_vertices: dict[str, np.ndarray]
) -> None:
    """Still for the last 0.5 s: every vertex within 0.5 mm of where it ends. (Not a speed bound: with the toss's
    low damping ratios a resting object's soft contacts chatter at a few mm/s with hundredths of a mm amplitude,
    and the box, resting on one contact point at a time, creeps by ~0.5 deg/s: ~0.2 mm at its corners in 0.5 s.)"""
    last = toss_traj.time_s >= toss_traj.time_s[-1] - 0.5
    for name, vertices in toss_vertices.items():
        drift_m = np.linalg.norm(vertices[last] - vertices[-1], axis=2).max()
        assert drift_m < 5e-4, f"{name} still moves: {drift_m * 1e3:.3f} mm in the last 0.5 s"
        assert abs(vertices[-1, :, 2].min()) < 2e-3, f"{name}: lowest vertex at z={vertices[-1, :, 2].min():.4f} m"


def test_toss_shows_a_bounce(
    toss_model: mujoco.MjModel, toss_traj: Trajectory, toss_vertices: dict[str, np.ndarray]
) -> None:
    """Every object falls onto the table and bounces: from one frame to the next its vertical velocity turns from
    below -0.5 m/s to above +0.2 m/s (no free flight does that: an impact), and afterwards it leaves the table
    again (lowest vertex above 5 mm): the flight after an impact that shows its restitution."""
    for name, vertices in toss_vertices.items():
        lowest_z = vertices[:, :, 2].min(axis=1)
        vz = _linear_velocity(toss_model, toss_traj, name)[:, 2]
        bounces = np.nonzero((vz[:-1] < -0.5) & (vz[1:] > 0.2))[0]
        assert len(bounces), f"{name} never bounces off the table: vz {np.round(vz[:15], 2)}"
        assert lowest_z[bounces[0] + 1 :].max() > 5e-3, f"{name} does not leave the table after its first impact"


def _object_rollout(model: mujoco.MjModel, traj: Trajectory) -> np.ndarray:
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = traj.qpos[0], traj.qvel[0]
    mujoco.mj_forward(model, data)
    steps = np.rint((traj.time_s - traj.time_s[0]) / model.opt.timestep).astype(int)
    out, step = [], 0
    for target in steps:
        if target > step:
            mujoco.mj_step(model, data, nstep=int(target - step))
        step = int(target)
        out.append(data.qpos.copy())
    return np.array(out)


def test_toss_constrains_every_friction_and_restitution(toss_model: mujoco.MjModel, toss_traj: Trajectory) -> None:
    """The clip is an identification experiment: moving any object's sliding friction or contact damping ratio by
    -/+20% moves that object, re-simulated from the first frame, by at least 3 mm on average over the clip (what
    tracking resolves), so calibration can tell each of the six values to within 20%."""
    reference = _object_rollout(toss_model, toss_traj)
    for joint in range(toss_model.njnt):
        body = toss_model.body(int(toss_model.jnt_bodyid[joint])).name
        adr = int(toss_model.jnt_qposadr[joint])
        geom = toss_model.geom(f"{body}_geom").id
        for field, index in (("geom_friction", 0), ("geom_solref", 1)):
            for factor in (0.8, 1.2):
                model = mujoco.MjModel.from_xml_path(str(SAMPLES / "toss" / "truth" / "scene.xml"))
                getattr(model, field)[geom, index] *= factor
                moved = _object_rollout(model, toss_traj)
                change_m = np.linalg.norm(moved[:, adr : adr + 3] - reference[:, adr : adr + 3], axis=1).mean()
                assert change_m > 3e-3, f"{body} {field}[{index}] x{factor}: rollout moves only {change_m * 1e3:.1f} mm"


def test_toss_objects_stay_in_view(toss_camera: dict, toss_vertices: dict[str, np.ndarray]) -> None:
    intrinsics = toss_camera["intrinsics"]
    world_from_cam = np.array(toss_camera["world_from_cam"])
    for name, vertices in toss_vertices.items():
        uv = _project_px(vertices.reshape(-1, 3), world_from_cam, intrinsics)
        assert uv.min() > 0 and uv[:, 0].max() < intrinsics["width"] and uv[:, 1].max() < intrinsics["height"], name


def test_toss_video_and_marker_match_camera(
    toss: Path, toss_camera: dict, toss_traj: Trajectory, toss_model: mujoco.MjModel
) -> None:
    frames = _video_frames(toss / "video.mp4")
    assert len(frames) == toss_camera["num_frames"] == toss_traj.num_steps
    assert all(frame.shape == (480, 640, 3) for frame in frames)
    np.testing.assert_allclose(np.diff(toss_traj.time_s), 1 / toss_camera["fps"], atol=toss_model.opt.timestep)
    world_from_cam = np.array(toss_camera["world_from_cam"])
    expected = _project_px(MARKER_CORNERS_WORLD, world_from_cam, toss_camera["intrinsics"])
    data = mujoco.MjData(toss_model)
    checked = 0
    for i, frame in enumerate(frames):
        data.qpos[:] = toss_traj.qpos[i]
        mujoco.mj_kinematics(toss_model, data)
        if _marker_occluded(toss_model, data, world_from_cam[:3, 3]):
            continue
        detected = _detect_marker_px(frame)
        assert detected is not None, f"frame {i}: marker in full view but not detected"
        error_px = np.linalg.norm(detected - expected, axis=1).max()
        assert error_px < MAX_MARKER_ERROR_PX, f"frame {i}: corners off by {error_px:.2f} px"
        checked += 1
    assert checked == len(frames), "in the toss clip no object should ever hide the marker"


def test_toss_at_60_fps_shows_every_30_fps_frame(
    toss_model: mujoco.MjModel, toss_traj: Trajectory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`samples/make_toss.py --fps 60` renders the same toss: its even frames are the physics steps of
    `samples/toss`'s frames, so the two clips show the same states (docs/interaction_history.md, "Frame rate")."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[2] / "samples"))
    import make_toss

    at_30 = make_toss.frame_steps(len(toss_traj.time_s), 30.0)
    at_60 = make_toss.frame_steps(2 * len(toss_traj.time_s), 60.0)
    np.testing.assert_array_equal(at_60[::2], at_30)
    np.testing.assert_allclose(at_30 * toss_model.opt.timestep, toss_traj.time_s, atol=1e-12)
    assert np.all(np.diff(at_60) >= 8) and np.all(np.diff(at_60) <= 9)  # 1/60 s = 8.33 steps of 2 ms


def test_heldout_toss_is_a_valid_clip_with_other_values(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`samples/make_toss.py --heldout` (docs/interaction_history.md, "Held-out toss") simulates a clip that passes
    the toss's own checks (every object in view, apart, on the table and at rest for the last 0.7 s), renders each
    object with `HELDOUT_CONTACT`'s values, and those differ from `samples/toss`'s by more than the 20% the target
    allows, so calibrating it checks other values than the ones the defaults were chosen on."""
    monkeypatch.syspath_prepend(str(SAMPLES))
    import make_toss

    objects = make_toss.toss_objects(heldout=True)
    starts = make_toss.heldout_starts()
    clip = make_toss.simulate_clip(tmp_path, objects, starts, make_toss.NUM_FRAMES)  # raises if the clip breaks
    model, qpos = clip.model, clip.qpos
    assert clip.rest_s >= make_toss.MIN_REST_S
    toss = {obj.name: obj for obj in make_toss.toss_objects()}
    for obj in objects:
        geom = model.geom(f"{obj.name}_geom")
        friction, dampratio = make_toss.HELDOUT_CONTACT[obj.name]
        assert geom.friction[0] == pytest.approx(friction) and geom.solref[1] == pytest.approx(dampratio)
        assert abs(friction / toss[obj.name].friction[0] - 1.0) > 0.2, obj.name
        assert abs(dampratio / toss[obj.name].solref[1] - 1.0) > 0.2, obj.name
        moved_m = np.linalg.norm(qpos[-1, model.joint(f"{obj.name}_free").qposadr[0] :][:3] - starts[obj.name].pos_m)
        assert moved_m > 0.1, f"{obj.name} moved only {moved_m:.3f} m: nothing to calibrate"
