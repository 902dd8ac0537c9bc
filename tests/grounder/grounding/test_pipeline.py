"""Film-a-scene end to end (issue 3) on the embedded tabletop sample and the real apple video.

Acceptance per object on the sample: bounding-box centre within 5 mm of the truth, Chamfer distance <= 3 mm,
extents within 8%; after 2 s of simulation every object within 2 mm and 1 deg of where it started; the concave
object's collision hulls keep its cavity.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np
import pytest

from grounder.grounding.evaluate import ObjectError, compare_to_truth
from reconstruction import ReconstructionResult
from scene_export import settle_test
from tests.conftest import PROGRESS_LINE, assert_one_line_error


def _ground(source: Path, out: Path, *flags: str) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "grounder.cli", "ground", str(source), "-o", str(out), *flags]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=900)


@pytest.fixture(scope="module")
def scene_dir(grounded_tabletop: Path) -> Path:
    return grounded_tabletop


@pytest.fixture(scope="module")
def errors(scene_dir: Path, tabletop_dir: Path) -> dict[str, ObjectError]:
    return {e.true_name: e for e in compare_to_truth(scene_dir, tabletop_dir / "truth")}


def test_object_count_and_centres(errors: dict[str, ObjectError], tabletop_dir: Path) -> None:
    truth = json.loads((tabletop_dir / "truth" / "objects.json").read_text())["objects"]
    assert sorted(errors) == sorted(o["name"] for o in truth)  # exactly one grounded object per true object
    for name, err in errors.items():
        assert err.centre_error_m <= 0.005, f"{name}: centre off by {err.centre_error_m * 1000:.1f} mm"


@pytest.mark.parametrize("name", ["box", "can", "bowl"])
def test_chamfer_within_3mm(errors: dict[str, ObjectError], name: str) -> None:
    """Measured over 10 benchmark runs: box 1.24-1.32 mm, can 1.14-1.18 mm, bowl 2.64-2.95 mm (the bowl was 2.83-3.11
    mm before the meshing kept only the fused surface depth maps measured, 3.05-3.26 before the tapered underside)."""
    assert errors[name].chamfer_m <= 0.003, f"{name}: Chamfer {errors[name].chamfer_m * 1000:.2f} mm"


@pytest.mark.parametrize("name", ["box", "can", "bowl"])
def test_extents_within_8_percent(errors: dict[str, ObjectError], name: str) -> None:
    """Measured over 10 runs: box 0.8-1.5%, can 5.6-6.6%, bowl 3.1-5.1% (bowl 6.2-7.4% before the meshing kept only
    measured surface; can up to 8.8% and bowl up to 8.3% before the tapered underside)."""
    assert errors[name].extent_error <= 0.08, f"{name}: extents off by {errors[name].extent_error:.1%}"


def test_scene_is_self_contained_and_stays_put(scene_dir: Path, tmp_path: Path) -> None:
    moved = tmp_path / "moved"
    shutil.copytree(scene_dir, moved)  # relative asset paths: the folder works anywhere
    model = mujoco.MjModel.from_xml_path(str(moved / "scene.xml"))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    free_bodies = [model.jnt_bodyid[j] for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
    assert len(free_bodies) == 3
    start_pos = data.xpos[free_bodies].copy()
    start_quat = data.xquat[free_bodies].copy()
    while data.time < 2.0:
        mujoco.mj_step(model, data)
    drift_m = np.linalg.norm(data.xpos[free_bodies] - start_pos, axis=1)
    dots = np.abs(np.sum(data.xquat[free_bodies] * start_quat, axis=1)).clip(0, 1)
    rot_deg = np.degrees(2 * np.arccos(dots))
    assert drift_m.max() <= 0.002, drift_m
    assert rot_deg.max() <= 1.0, rot_deg
    # Visual geoms in group 2 without contacts, collision hulls in group 3; the table is a static geom at z = 0.
    for g in range(model.ngeom):
        if model.geom_bodyid[g] in free_bodies:
            if model.geom_group[g] == 2:
                assert model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0
            else:
                assert model.geom_group[g] == 3


def test_manifest_and_preview(scene_dir: Path) -> None:
    manifest = json.loads((scene_dir / "scene.json").read_text())
    assert manifest["provenance"]["scale_source"] == "aruco"
    assert len(manifest["provenance"]["frames_used"]) >= 60
    for obj in manifest["objects"].values():
        assert obj["mass_kg"] == pytest.approx(obj["volume_m3"] * obj["density_kg_m3"], rel=1e-6)
        assert len(obj["extents_m"]) == 3 and obj["num_hulls"] >= 1
    assert all(v["closed_bottom"] for v in manifest["objects_extra"].values())
    assert (scene_dir / "preview.png").stat().st_size > 10_000


def test_only_the_can_is_snapped_onto_a_cylinder_and_lands_on_the_true_radius(
    scene_dir: Path, errors: dict[str, ObjectError]
) -> None:
    """`GroundOptions.cylinder_snap`: the scanned can's visual mesh is moved onto its fitted upright cylinder (the true
    can: radius 35 mm), its side's ripple recorded; the box and the bowl are left as scanned."""
    extra = json.loads((scene_dir / "scene.json").read_text())["objects_extra"]
    snapped = {true_name: extra[e.name]["visual_snapped_to_cylinder"] for true_name, e in errors.items()}
    assert snapped["box"] is None and snapped["bowl"] is None
    can = snapped["can"]
    assert can is not None and can["radius_m"] == pytest.approx(0.035, abs=5e-4)
    assert 0.0 < can["ripple_rms_m"] < 0.05 * can["radius_m"]
    assert errors["can"].extent_error < 0.02  # the ripple's outward bumps no longer widen it (5.6-6.6% before)


def test_concave_object_holds_a_ball(scene_dir: Path, errors: dict[str, ObjectError], tmp_path: Path) -> None:
    """Drop a 1.5 cm ball into the grounded bowl: its hulls must keep the cavity."""
    bowl = errors["bowl"].name
    manifest = json.loads((scene_dir / "scene.json").read_text())
    centre = np.array(manifest["objects"][bowl]["pos_m"])
    top = centre[2] + manifest["objects"][bowl]["extents_m"][2] / 2
    spec = mujoco.MjSpec.from_file(str(scene_dir / "scene.xml"))
    ball = spec.worldbody.add_body(name="ball", pos=[centre[0], centre[1], top + 0.03])
    ball.add_freejoint()
    ball.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.015, 0, 0], density=800, group=3)
    model = spec.compile()
    data = mujoco.MjData(model)
    while data.time < 1.5:
        mujoco.mj_step(model, data)
    ball_pos = data.body("ball").xpos
    assert np.linalg.norm(ball_pos[:2] - centre[:2]) < 0.05  # inside the rim radius (~7.5 cm)
    assert ball_pos[2] < top  # below the rim: in the cavity, not resting on a lid


def test_real_apple_video(grounded_apple: Path, shared_data: Path) -> None:
    manifest = json.loads((grounded_apple / "scene.json").read_text())
    assert list(manifest["objects"]) == ["object_0"]  # exactly one object: the apple
    (apple,) = manifest["objects"].values()
    assert max(apple["extents_m"]) == pytest.approx(0.08, rel=1e-3)  # the --known-extent given: scale applied
    assert 0.05 < apple["extents_m"][2] < 0.1  # an apple-sized height, resting on the table
    settle = manifest["settle_test"]["objects"]["object_0"]
    assert settle["displacement_m"] <= 0.002 and settle["rotation_deg"] <= 1.0
    # The scene and its reconstruction/ folder are in the same metres (the known extent is refined on the segmented
    # mesh after reconstruct, x 0.60 here: the folder used to keep the unrefined cameras, 1.65x too far out), and
    # the apple mesh seen from frame 0's camera covers the data's hand-drawn mask of the apple (IoU 0.77 measured;
    # 0.28 with the unrefined camera).
    transforms = json.loads((grounded_apple / "reconstruction" / "transforms.json").read_text())
    first = next(f for f in transforms["frames"] if f["frame_index"] == 0)
    model = mujoco.MjModel.from_xml_path(str(grounded_apple / "scene.xml"))
    np.testing.assert_allclose(model.cam_pos[0], np.array(first["transform_matrix"])[:3, 3], atol=1e-6)
    iou = _mask_iou_from_frame_camera(grounded_apple, apple, transforms, first, shared_data / "apple_video")
    assert iou > 0.7, iou


def _mask_iou_from_frame_camera(scene: Path, obj: dict, transforms: dict, frame: dict, data: Path) -> float:
    """IoU of the object's visual mesh, projected with the frame's camera from transforms.json, and the data's mask."""
    import cv2
    import trimesh

    from reconstruction._reconstruct import OPENGL_FROM_OPENCV

    mask = cv2.imread(str(data / "apple_mask.png"), cv2.IMREAD_GRAYSCALE) > 127
    mesh = trimesh.load(scene / obj["visual_mesh"], force="mesh", process=False)
    w, x, y, z = obj["quat_wxyz"]
    world_from_object = trimesh.transformations.quaternion_matrix([w, x, y, z])
    world_from_object[:3, 3] = obj["pos_m"]
    cam_from_world = np.linalg.inv(np.array(frame["transform_matrix"]) @ OPENGL_FROM_OPENCV)  # OpenCV camera axes
    cam_from_object = cam_from_world @ world_from_object
    camera = np.array([[transforms["fl_x"], 0, transforms["cx"]], [0, transforms["fl_y"], transforms["cy"]], [0, 0, 1]])
    dist = np.array([transforms[k] for k in ("k1", "k2", "p1", "p2")])
    rvec, _ = cv2.Rodrigues(cam_from_object[:3, :3])
    pixels, _ = cv2.projectPoints(mesh.vertices, rvec, cam_from_object[:3, 3], camera, dist)
    silhouette = np.zeros(mask.shape, np.uint8)
    for triangle in np.round(pixels.reshape(-1, 2)[mesh.faces] * 8).astype(np.int32):
        cv2.fillConvexPoly(silhouette, triangle, 1, shift=3)
    return float((mask & (silhouette > 0)).sum() / (mask | (silhouette > 0)).sum())


def test_ground_bad_input_exits_2(tmp_path: Path) -> None:
    import cv2

    folder = tmp_path / "imgs"
    folder.mkdir()
    for i in range(5):
        cv2.imwrite(str(folder / f"{i}.png"), np.full((120, 160, 3), 90, np.uint8))
    proc = _ground(folder, tmp_path / "out")
    assert proc.returncode == 2 and proc.stderr.count("image2sim: error:") == 1
    assert not (tmp_path / "out").exists()


def test_no_object_on_the_table_is_reported(
    reconstruction_of_points: Callable[[np.ndarray], ReconstructionResult],
) -> None:
    from reconstruction._scene_objects import region_of_interest
    from reconstruction._segment import SegmentationError

    rng = np.random.default_rng(0)
    table = np.c_[rng.uniform(-0.4, 0.4, (3000, 2)), rng.normal(0, 0.0005, 3000)]  # only a flat table
    with pytest.raises(SegmentationError, match="no object found"):
        region_of_interest(reconstruction_of_points(table), 0.08)


def test_a_failed_background_decomposition_falls_back_to_one_hull() -> None:
    """Collision hulls are computed in a background thread while textures bake. A CoACD failure there used to fail
    the whole scene; now (issue 60: one object's failure never loses the scene) that object gets its convex hull,
    is marked "fallback" with the reason, and a warning names it. A mesh too flat even for a hull still surfaces as
    the `DecompositionError` it is (the CLI's one line, exit 2)."""
    from concurrent.futures import ThreadPoolExecutor

    from grounder.grounding.pipeline import GroundOptions, _object_specs
    from reconstruction._types import ObjectInstance, TexturedMesh
    from scene_export import CollisionGeometry
    from scene_export.errors import DecompositionError

    def fail() -> CollisionGeometry:
        raise DecompositionError("CoACD returned no usable hulls for object_0")

    corners = np.array([[x, y, z] for x in (0.0, 0.02) for y in (0.0, 0.03) for z in (0.0, 0.04)])
    box = TexturedMesh(vertices_m=corners, faces=np.array([[0, 1, 2]]))  # only the vertices reach the hull
    obj = ObjectInstance(name="object_0", mesh=box, world_from_object=np.eye(4))
    flat = TexturedMesh(vertices_m=np.eye(3), faces=np.array([[0, 1, 2]]))
    with ThreadPoolExecutor(max_workers=1) as pool:
        objects, warnings = [obj], []
        specs = _object_specs(
            objects, {"object_0": pool.submit(fail)}, {}, GroundOptions(), lambda stage, done, total: None, warnings
        )
        assert len(specs) == 1 and len(specs[0].collision.hulls) == 1
        np.testing.assert_allclose(np.ptp(specs[0].collision.hulls[0], axis=0), [0.02, 0.03, 0.04])
        assert objects[0].mesh_quality == "fallback" and "no usable hulls" in (objects[0].mesh_reason or "")
        assert warnings == [
            "object_0: convex decomposition failed (DecompositionError: CoACD returned no usable hulls for object_0); "
            "one hull"
        ]
        flat_obj = ObjectInstance(name="object_0", mesh=flat, world_from_object=np.eye(4))
        with pytest.raises(DecompositionError, match="flat"):
            _object_specs([flat_obj], {"object_0": pool.submit(fail)}, {}, GroundOptions(), lambda s, d, t: None, [])


def test_the_warm_up_fills_the_caches_the_property_stage_reads_and_keeps_its_failures_to_itself(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """`ground` loads the property model and the bounce table in a thread while mapping runs: afterwards the
    property stage finds the model in its cache (no second load) and asks for the bounce table with the very
    arguments the warm-up built it for (an lru_cache hit; the table itself is a stand-in here, its 4 s build is
    `tests/grounder/sim/test_restitution.py`'s), and a model that cannot load does not escape the thread (the property
    stage meets that error itself and turns it into a warning)."""
    import threading

    import grounder.properties.prior as _properties
    import grounder.sim.restitution as _restitution
    from grounder.grounding.pipeline import GroundOptions, _start_warm_up

    asked: list[tuple[object, ...]] = []

    def stand_in(*args: object) -> tuple[np.ndarray, np.ndarray]:
        asked.append(args)
        return np.geomspace(0.012, 0.2, 8), np.tile(
            np.linspace(0.99, 0.01, len(_restitution._TABLE_DAMPRATIOS)), (8, 1)
        )

    monkeypatch.setattr(_restitution, "_bounce_table", stand_in)
    _properties.load_property_model.cache_clear()
    _start_warm_up(GroundOptions(), threading.Event()).join()
    assert _properties.load_property_model.cache_info().currsize == 1
    assert len(asked) == 1
    _properties.load_property_model()
    assert _properties.load_property_model.cache_info().hits >= 1
    _properties._natural(np.array([6.0, -0.5, -5.0, -9.0, 0.0, -3.9]), np.full(6, 0.2))  # the stage's decoding
    assert len(asked) > 1 and set(asked) == {asked[0]}

    escaped: list[BaseException] = []
    monkeypatch.setattr(threading, "excepthook", lambda args: escaped.append(args.exc_value))
    _properties.load_property_model.cache_clear()
    monkeypatch.setattr(_properties, "WEIGHTS_DIR", Path("/nonexistent/weights"))
    _start_warm_up(GroundOptions(), threading.Event()).join()
    assert escaped == []
    assert _properties.load_property_model.cache_info().currsize == 0
    with pytest.raises(_properties.PropertyModelError, match="no property model"):
        _properties.load_property_model()


def test_scan_frames_for_the_feature_models_read_back_with_their_cameras(scene_dir: Path, tabletop_dir: Path) -> None:
    """`track --scan-features` reads the scene folder's scan frames back (`load_scan`): each frame's camera pose,
    converted from transforms.json's OpenGL axes, agrees with the true camera of that video frame (within 5 mm and
    0.5 deg), and each object's scan pose is the one scene.json gives."""
    from grounder.tracking.inputs import load_scan
    from grounder.tracking.options import TrackOptions
    from image2sim_common.rotations import rotation_angle_deg

    names = list(json.loads((scene_dir / "scene.json").read_text())["objects"])
    loaded = load_scan(
        scene_dir / "scene.xml", names, TrackOptions(scan_feature_frames=6), lambda image: image, (480, 640)
    )
    assert loaded is not None
    frames, poses = loaded
    assert len(frames) == 6 and len(poses) == len(names)
    rows = json.loads((scene_dir / "reconstruction" / "transforms.json").read_text())["frames"]
    truth = json.loads((tabletop_dir / "truth" / "cameras.json").read_text())["frames"]
    picks = np.unique(np.linspace(0, len(rows) - 1, 6).round().astype(int))
    for frame, k in zip(frames, picks, strict=True):
        true_pose = np.array(truth[rows[k]["frame_index"]]["world_from_cam"])
        assert np.linalg.norm(frame.world_from_cam[:3, 3] - true_pose[:3, 3]) < 5e-3
        assert rotation_angle_deg(frame.world_from_cam[:3, :3], true_pose[:3, :3]) < 0.5
        assert frame.gray.shape == (480, 640)


@pytest.mark.parametrize(
    ("field", "value"),
    [("default_density_kg_m3", float("inf")), ("default_density_kg_m3", 0.0), ("default_friction", (0.5, -1.0, 0.0)),
     ("settle_seconds", float("nan"))],
)  # fmt: skip
def test_ground_options_refuse_values_that_cannot_work(field: str, value: object) -> None:
    """From Python, GroundOptions(default_density_kg_m3=inf) used to run a minute of reconstruction and then fail
    naming another value; the options now refuse it when built."""
    from grounder.errors import GrounderError
    from grounder.grounding.pipeline import GroundOptions

    with pytest.raises(GrounderError, match=field):
        GroundOptions(**{field: value})


def test_known_extent_goes_to_the_longest_object_not_the_bulkiest() -> None:
    """Family scene 101 (issue 60): a 16 cm bowl beside a 19.8 cm plate, `--known-extent 0.198`. The refinement
    gave the bowl (larger by bounding-box volume) the plate's length and scaled the scene by 1.18; the sparse
    estimate and the option's help both mean the object with the longest extent."""
    from types import SimpleNamespace

    from grounder.grounding.pipeline import _extent_factor

    scene = SimpleNamespace(objects=(_box("bowl", (0.16, 0.16, 0.06)), _box("plate", (0.19, 0.19, 0.02))))
    factor, largest = _extent_factor(scene, 0.198)
    assert largest == "plate"
    assert factor == pytest.approx(0.198 / 0.19)


def _box(name: str, extents: tuple[float, float, float], quality: str = "full", at_edge: bool = False) -> object:
    from types import SimpleNamespace

    corners = np.array(np.meshgrid(*[[0, e] for e in extents])).reshape(3, -1).T
    return SimpleNamespace(
        name=name, mesh=SimpleNamespace(vertices_m=corners), mesh_quality=quality, at_region_edge=at_edge
    )


def test_known_extent_keeps_the_sparse_scale_when_the_longest_mesh_cannot_be_measured() -> None:
    """Held-out 1031, 1033 (issue 60): the meshes' correction of the sparse points' scale came from a cup measured
    short while the longer mug was a hull of its points (x 1.41), and from a 23 cm phantom sheet (x 0.64); the sparse
    estimate was within 8% each time. A correction beyond 10% is taken only from a fused mesh nothing doubtful could
    outgrow; small ones, and large ones from a mesh that can be measured (held-out 1029: x 1.38, right), stand. A
    mesh cut by the region's side is measured by its height (tuning seed 50, once declined for a bottle cut short,
    x 1.36, was a bottle whose neck neither the sparse points nor the fused surface reached: x 1.43 either way on the
    AVX-512 machine; held-out 1067 needed it)."""
    from types import SimpleNamespace

    from grounder.grounding.pipeline import _extent_step

    def step(*objects: object, known: float) -> tuple[float, str, str | None]:
        return _extent_step(SimpleNamespace(objects=objects), known)

    bottle, can = _box("bottle", (0.06, 0.06, 0.16)), _box("can", (0.066, 0.066, 0.11))
    # measured fused meshes: the correction stands, large or small
    assert step(bottle, can, known=0.22) == (pytest.approx(0.22 / 0.16), "bottle", None)
    assert step(bottle, _box("ball", (0.04, 0.04, 0.04), "silhouette"), known=0.22)[2] is None
    # a visual hull counts by its height (tuning seed 53: a plain bottle corrected the sparse scale x 0.65, rightly,
    # beside a thin can's fallback hull a little shorter)
    plain_bottle, thin_can = (
        _box("plain bottle", (0.12, 0.13, 0.286), "silhouette"),
        _box("thin can", (0.05, 0.05, 0.263), "fallback"),
    )
    assert step(thin_can, plain_bottle, known=0.1859) == (pytest.approx(0.1859 / 0.286), "plain bottle", None)
    # the longest is cut by the region's side: it counts by its height, which upright sides leave whole (held-out
    # 1067: two bowls as one sparse cluster scaled the scene x 0.79; the bottle, cut across, corrected it x 1.29)
    factor, name, why = step(_box("bottle", (0.06, 0.06, 0.16), at_edge=True), can, known=0.22)
    assert (factor, name, why) == (pytest.approx(0.22 / 0.16), "bottle", None)
    # ... and one lying down, cut short along its length, is no measure, nor lets a shorter object take the length
    factor, name, why = step(_box("lying bottle", (0.16, 0.06, 0.06), at_edge=True), can, known=0.22)
    assert (factor, name) == (1.0, "can") and why == "lying bottle (cut by the region's side) may be longer than can"
    # a visual hull counts by its height, but its footprint may be the longer object's (held-out 1081: two bowls
    # only their silhouettes found let an 8.9 cm L-block take their 17.6 cm, x 1.97): declined
    l_block, bowl_hull = _box("l_block", (0.089, 0.03, 0.05)), _box("bowl", (0.175, 0.17, 0.05), "silhouette")
    factor, name, why = step(l_block, bowl_hull, known=0.1756)
    assert (factor, name) == (1.0, "l_block") and why == "bowl (a visual hull) may be longer than l_block"
    # a hull of smeared points (1033): declined
    factor, name, why = step(can, _box("sheet", (0.015, 0.23, 0.12), "fallback"), known=0.08)
    assert (factor, name) == (1.0, "sheet") and "convex hull of its points" in why
    # a hull whose footprint might be the longer object, while a shorter fused cup took the length (1031)
    cup, mug_hull = _box("cup", (0.06, 0.06, 0.087)), _box("mug", (0.107, 0.1, 0.083), "fallback")
    factor, name, why = step(cup, mug_hull, known=0.1233)
    assert (factor, name) == (1.0, "cup") and why == "mug (the convex hull of its points) may be longer than cup"
    # within 10% the correction stands whatever measured it (tuning seed 41: x 0.99 from a hull)
    factor, name, why = step(_box("sheet", (0.018, 0.24, 0.213), "fallback"), can, known=0.2113)
    assert factor == pytest.approx(0.2113 / 0.213) and why is None


def test_known_extent_refinement_judges_the_total_against_the_sparse_scale() -> None:
    """The two passes of `_refine_known_extent` (a correction beyond 10% segments again at the corrected scale and
    measures there): the 10% doubt rule applies to the total off the sparse estimate, not to each step; a second
    measure that is declined returns the scale to the sparse estimate, with the warning; with a provisional scale
    (no sparse point on any object) whatever the meshes say is taken, and the warning names the final object."""
    from types import SimpleNamespace

    from grounder.grounding.pipeline import _refine_known_extent

    calls: list[float] = []

    def resegment_to(*objects: object):  # type: ignore[no-untyped-def]
        def resegment(factor: float) -> object:
            calls.append(factor)
            return SimpleNamespace(objects=objects)

        return resegment

    def scene(*objects: object) -> object:
        return SimpleNamespace(objects=objects)

    can = _box("can", (0.066, 0.066, 0.11))
    # within 10%: taken, no second segmentation
    calls.clear()
    small = _refine_known_extent(scene(_box("bottle", (0.06, 0.06, 0.21)), can), 0.22, False, resegment_to())
    assert calls == [] and small.step == pytest.approx(0.22 / 0.21) and small.warning is None
    # a measured bottle x 1.375, confirmed on the second segmentation
    calls.clear()
    first = scene(_box("bottle", (0.06, 0.06, 0.16)), can)
    again = resegment_to(_box("object_0", (0.08, 0.08, 0.219)), _box("object_1", (0.09, 0.09, 0.15)))
    good = _refine_known_extent(first, 0.22, False, again)
    assert calls == [pytest.approx(1.375)] and good.factor == pytest.approx(0.22 / 0.16 * 0.22 / 0.219)
    assert good.warning is None and "mesh of object_0" in good.note
    # ... but there a fallback hull is the longest and asks x 1.05 more: 1.44 off the sparse points on a hull, declined
    calls.clear()
    hull_again = resegment_to(_box("object_0", (0.08, 0.08, 0.21), "fallback"), _box("object_1", (0.09, 0.09, 0.15)))
    back = _refine_known_extent(first, 0.22, False, hull_again)
    assert calls == [pytest.approx(1.375)] and back.factor == pytest.approx(1.0)
    assert back.step == pytest.approx(1 / 1.375) and "sparse points only" in back.warning
    assert "object_0 is the convex hull of its points" in back.note
    # declined on the first pass (a bottle lying down, cut by the region's side): no second segmentation
    calls.clear()
    cut = _refine_known_extent(scene(_box("bottle", (0.16, 0.06, 0.06), at_edge=True), can), 0.22, False, again)
    assert calls == [] and cut.step == 1.0 and cut.factor == 1.0 and "cut by the region's side" in cut.warning
    # provisional: the hull's measure is taken on both passes, and the warning names the object of the final scene
    calls.clear()
    hull = scene(_box("hull", (0.06, 0.05, 0.05), "fallback"))
    trusted = _refine_known_extent(hull, 0.10, True, resegment_to(_box("object_0", (0.06, 0.05, 0.098), "fallback")))
    assert calls == [pytest.approx(2.0)] and trusted.factor == pytest.approx(2.0 * 0.10 / 0.098)
    assert "measured on the mesh of object_0 alone" in trusted.warning


def test_known_extent_counts_a_visual_hull_by_its_height() -> None:
    """Tuning seed 5 (issue 60): a plate and a plain mug came out of the silhouettes as one 22 cm wide hull, longer
    than the 22.2 cm bottle the fused surface measured, and took the bottle's known extent: the scene was x 1.31.
    Tuning seed 8: a plain 21 cm bottle only the silhouettes found lost its known extent to a 10 cm fused can: x 2.06.
    A hull may join objects side by side, not make them taller, so it counts by its height."""
    from types import SimpleNamespace

    from grounder.grounding.pipeline import _extent_factor

    bottle, wide_hull = _box("bottle", (0.06, 0.06, 0.222)), _box("hull", (0.23, 0.14, 0.07), "silhouette")
    assert _extent_factor(SimpleNamespace(objects=(bottle, wide_hull)), 0.224)[1] == "bottle"
    factor, name = _extent_factor(SimpleNamespace(objects=(wide_hull,)), 0.07)
    assert name == "hull" and factor == pytest.approx(1.0)
    can, tall_hull = _box("can", (0.08, 0.08, 0.10)), _box("hull", (0.08, 0.086, 0.177), "silhouette")
    factor, name = _extent_factor(SimpleNamespace(objects=(can, tall_hull)), 0.2106)
    assert name == "hull" and factor == pytest.approx(0.2106 / 0.177)
    # Held-out scene 1006: two bottles meshed as one convex hull of their points (20.6 cm wide, 20 cm tall) took
    # the 20.2 cm bottle's length: x 0.95. A fallback hull counts by its height too.
    bottle, joined = _box("bottle", (0.067, 0.068, 0.202)), _box("joined", (0.065, 0.206, 0.2), "fallback")
    assert _extent_factor(SimpleNamespace(objects=(bottle, joined)), 0.2123)[1] == "bottle"


def test_known_extent_is_measured_along_the_footprint_not_the_world_axes() -> None:
    """Tuning seed 15 (issue 60): a 10.8 x 8.8 cm carton turned on the table spans 12.8 cm along a world axis; that
    span given the carton's known 10.8 cm scaled the scene x 0.84. The footprint's own sides are measured."""
    from types import SimpleNamespace

    from grounder.grounding.pipeline import _extent_factor

    box = _box("carton", (0.108, 0.088, 0.051))
    turn = np.deg2rad(40.0)
    rotation = np.array([[np.cos(turn), -np.sin(turn), 0.0], [np.sin(turn), np.cos(turn), 0.0], [0.0, 0.0, 1.0]])
    box.mesh.vertices_m = box.mesh.vertices_m @ rotation.T
    assert np.ptp(box.mesh.vertices_m[:, 0]) > 0.12
    factor, _ = _extent_factor(SimpleNamespace(objects=(box,)), 0.108)
    assert factor == pytest.approx(1.0, abs=1e-4)
    # A round footprint has no sides: its span on the world axes stands (held-out 1017: a fused, slightly oval
    # bowl measured on its smallest rectangle came out 4% small and scaled the scene x 1.04).
    angle = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    oval = np.c_[0.0825 * np.cos(angle), 0.079 * np.sin(angle)] @ rotation[:2, :2].T
    bowl = _box("bowl", (0.16, 0.16, 0.065))
    bowl.mesh.vertices_m = np.r_[np.c_[oval, np.zeros(64)], np.c_[oval, np.full(64, 0.065)]]
    factor, _ = _extent_factor(SimpleNamespace(objects=(bowl,)), 0.1585)
    assert factor == pytest.approx(0.1585 / np.ptp(bowl.mesh.vertices_m[:, :2], axis=0).max())


def test_table_top_carries_the_texture_the_cameras_saw(scene_dir: Path) -> None:
    """Issue 60 item 6: the table was one flat colour where the video shows wood. Rendered from the first frame's
    camera, the table top's fine detail now matches the frame's (normalised cross-correlation of the high-passed
    grey levels over the table's pixels: 0.86 measured; a plain top scores 0.07 and is checked as the control)."""
    import cv2

    manifest = json.loads((scene_dir / "scene.json").read_text())
    assert manifest["table"]["texture"] == "assets/table_texture.png"
    assert (scene_dir / manifest["table"]["texture"]).is_file()
    model = mujoco.MjModel.from_xml_path(str(scene_dir / "scene.xml"))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    transforms = json.loads((scene_dir / "reconstruction" / "transforms.json").read_text())
    frame = cv2.imread(str(scene_dir / "reconstruction" / transforms["frames"][0]["file_path"]))
    top = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "table_top")
    renderer = mujoco.Renderer(model, *frame.shape[:2])
    try:
        renderer.update_scene(data, camera="video")
        textured = renderer.render()[:, :, ::-1]
        renderer.enable_segmentation_rendering()
        renderer.update_scene(data, camera="video")
        on_table = renderer.render()[:, :, 0] == top
        renderer.disable_segmentation_rendering()
        model.geom_rgba[top, 3] = 0.0  # hide the sheet: the plain box top beneath
        renderer.update_scene(data, camera="video")
        plain = renderer.render()[:, :, ::-1]
    finally:
        renderer.close()

    def detail(image: np.ndarray) -> np.ndarray:
        grey = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_BGR2GRAY).astype(np.float32)
        values = (grey - cv2.GaussianBlur(grey, (0, 0), 8))[on_table]
        return values - values.mean()

    def ncc(a: np.ndarray, b: np.ndarray) -> float:
        return float((detail(a) * detail(b)).sum() / np.sqrt((detail(a) ** 2).sum() * (detail(b) ** 2).sum()))

    assert on_table.mean() > 0.3
    assert ncc(textured, frame) > 0.6
    assert ncc(plain, frame) < 0.3


def test_real_cake_photos_give_a_resting_scene_or_one_line(shared_data: Path, tmp_path: Path) -> None:
    """Issue 60 item 7: 8 real photos (683x384) of a cake slice on a plate, for which COLMAP's defaults register 0
    of 8. `ground` must give a scene that loads and rests, or one line saying why with exit 2; never a crash.
    Measured 2026-12-02: the one line (structure from motion could not start a model)."""
    out = tmp_path / "cake"
    proc = _ground(shared_data / "real_photos" / "cake", out, "--known-extent", "0.2")
    assert "Traceback" not in proc.stderr + proc.stdout
    if proc.returncode == 0:
        motion = settle_test(out / "scene.xml", seconds=2.0)
        assert all(m.displacement_m <= 0.002 and m.rotation_deg <= 1.0 for m in motion.values()), motion
    else:
        assert_one_line_error(proc)
        # Besides progress bars, nothing but that line (COLMAP's own "E... Failed to create any sparse model" was).
        others = [line for line in proc.stderr.splitlines() if line.strip() and not PROGRESS_LINE.search(line)]
        assert [line for line in others if not line.startswith("image2sim: error:")] == [], proc.stderr
        assert not out.exists()
