"""ArUco markers stuck on objects: measured in the scan, placed from a clip, and tracked, against the truth.

Samples: `samples/tabletop_markers` (the scan with printed markers on the box and the can) and `samples/toss_markers`
(the toss with the same markers); the true marker layout is in their `truth/objects.json` / `truth/markers.json`.
The end-to-end figure (a grounded scene of the marker scan, tracked through the marker toss) is measured by
`benchmarks/track.py --markers`.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from grounder.errors import GrounderError
from grounder.grounding.scan_markers import find_scan_markers
from grounder.tracking.inputs import read_clip
from grounder.tracking.markers import (
    MarkerPoses,
    MarkerViews,
    ObjectMarker,
    check_markers,
    combined_markers,
    load_object_markers,
    marker_agreement,
    place_markers,
)
from grounder.tracking.options import TrackOptions
from grounder.tracking.pipeline import track
from image2sim_common.rotations import matrix_from_quat, quat_angle_rad, quat_from_matrix, rotation_angle_deg
from reconstruction._texture import TextureView
from reconstruction._types import CameraIntrinsics

REPO = Path(__file__).resolve().parents[3]
SCAN = REPO / "samples" / "tabletop_markers"
TOSS = REPO / "samples" / "toss_markers"
TOSS_SCENE = REPO / "samples" / "toss" / "truth"


def _pose(pos: list[float] | np.ndarray, quat_wxyz: list[float] | np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = pos
    out[:3, :3] = matrix_from_quat(np.asarray(quat_wxyz, float))
    return out


def _need(path: Path) -> None:
    if not (path / "video.mp4").exists():
        pytest.skip(f"{path.relative_to(REPO)} is missing: run `make samples`")


def test_scan_markers_are_placed_on_their_objects_within_half_a_millimetre() -> None:
    """`ground`'s marker measurement, on the marker scan with its true cameras: each marker on the right object,
    within 0.5 mm and 0.5 deg of where it was stuck, its side within 2%; the bowl carries none."""
    _need(SCAN)
    cams = json.loads((SCAN / "truth" / "cameras.json").read_text())
    objects = json.loads((SCAN / "truth" / "objects.json").read_text())
    intr = cams["intrinsics"]
    frames, _ = read_clip(SCAN / "video.mp4")
    intrinsics = CameraIntrinsics(
        width_px=intr["width"],
        height_px=intr["height"],
        fx_px=intr["fx"],
        fy_px=intr["fy"],
        cx_px=intr["cx"],
        cy_px=intr["cy"],
    )
    views = [
        TextureView(image_bgr=frame, world_from_cam=np.array(cam["world_from_cam"]), intrinsics=intrinsics)
        for frame, cam in zip(frames, cams["frames"], strict=True)
    ]
    bodies = {o["name"]: (_pose(o["pos_m"], o["quat_wxyz"]), np.array(o["extents_m"])) for o in objects["objects"]}
    found, notes = find_scan_markers(views, bodies, "DICT_4X4_50", 0)
    truth = {m["id"]: m for m in objects["object_markers"]}
    assert sorted(m.marker_id for m in found) == sorted(truth) and not notes
    for marker in found:
        true = truth[marker.marker_id]
        body_from_marker = _pose(true["pos_m"], true["quat_wxyz"])
        assert marker.object_name == true["object"]
        assert np.linalg.norm(marker.body_from_marker[:3, 3] - body_from_marker[:3, 3]) < 5e-4
        assert rotation_angle_deg(marker.body_from_marker[:3, :3], body_from_marker[:3, :3]) < 0.5
        assert abs(marker.size_m / true["size_m"] - 1) < 0.02
        assert marker.views >= 10 and marker.rms_px < 0.5
    # Objects moved away from where the scan saw them: the markers are on none, and say so.
    far = {name: (pose @ _pose([0.0, 0.0, 0.3], [1, 0, 0, 0]), ext) for name, (pose, ext) in bodies.items()}
    found, notes = find_scan_markers(views, far, "DICT_4X4_50", 0)
    assert not found and len(notes) == 2 and all("not on any object" in n for n in notes)


def test_a_marker_is_placed_on_the_object_it_moves_with() -> None:
    """Clip placement: a marker rigidly on object 1 (1 mm / 0.3 deg of noise per frame) goes to object 1, at its
    true place within 1 mm; object 0 rests still most of the time, which must not win it the marker. A marker moving
    on its own is on none."""
    rng = np.random.default_rng(0)
    frames = 60
    body_from_marker = _pose([0.01, -0.02, 0.03], [np.cos(0.2), 0.0, np.sin(0.2), 0.0])
    objects = np.tile(np.eye(4), (frames, 2, 1, 1))
    objects[:, 0, :3, 3] = [0.3, 0.0, 0.03]
    for f in range(frames):
        moving = min(f, 15)  # object 1 slides and turns for 15 frames, then rests (like the toss)
        objects[f, 1] = _pose([0.01 * moving, 0.1, 0.05], [np.cos(0.05 * moving), 0, 0, np.sin(0.05 * moving)])
    markers = np.full((frames, 2, 2, 4, 4), np.nan)
    for f in range(frames):
        noise = np.eye(4)
        noise[:3, :3] = cv2.Rodrigues(rng.normal(0.0, np.deg2rad(0.3), 3))[0]
        noise[:3, 3] = rng.normal(0.0, 0.6e-3, 3)
        markers[f, 0, 0] = objects[f, 1] @ body_from_marker @ noise
        markers[f, 1, 0] = _pose([0.2 + 0.004 * f, -0.1, 0.02], [1, 0, 0, 0])  # moves with neither
    rms = np.full((frames, 2, 2), np.nan)
    rms[:, :, 0] = 0.05  # one solution only: unambiguous
    views = MarkerViews(world_from_marker=markers, rms_px=rms)
    layout = (ObjectMarker(marker_id=3, size_m=0.04), ObjectMarker(marker_id=4, size_m=0.04))
    placed, report = place_markers(
        views, layout, ["a", "b"], objects, np.ones((frames, 2), bool), ambiguity_ratio=3.0, max_spread_m=0.01
    )
    assert report[0].object_name == "b" and placed[0].body_from_marker is not None
    assert np.linalg.norm(placed[0].body_from_marker[:3, 3] - body_from_marker[:3, 3]) < 1e-3
    assert report[1].object_name is None and "no tracked object moves with it" in report[1].note


def test_markers_on_objects_track_the_toss_to_a_third_of_a_degree(tmp_path: Path) -> None:
    """The marker toss tracked against the true scene, whose textures lack the markers (stuck on after the scan):
    the model-based track alone is 7.6 mm / 3.2 deg off on the box there (the marker hides texture it looks for);
    with the true layout the box and the can are within 1.5 mm and 0.5 deg (median), every frame of both is
    measured by its marker, and track.json records the markers."""
    _need(TOSS)
    cam = json.loads((TOSS / "truth" / "camera.json").read_text())["intrinsics"]
    options = TrackOptions(
        aruco_size_m=0.12,
        intrinsics_colmap=(cam["fx"], cam["fy"], cam["cx"], cam["cy"]),
        object_markers=load_object_markers(TOSS / "truth" / "markers.json"),
        detect_views=20,
    )
    out = tmp_path / "traj"
    result = track(TOSS / "video.mp4", TOSS_SCENE, out, options)
    qpos = np.load(TOSS / "truth" / "trajectory.npz")["qpos"]
    for i, name in enumerate(result.object_names[:2]):  # box, can
        assert result.valid[:, i].all()
        sources = [row[i].source for row in result.scores]
        assert sources.count("marker") >= 0.95 * len(sources), (name, sources)
        pos_mm = [
            1e3 * np.linalg.norm(result.world_from_objects[f, i, :3, 3] - qpos[f, 7 * i : 7 * i + 3]) for f in range(90)
        ]
        rot_deg = [
            np.rad2deg(
                quat_angle_rad(
                    quat_from_matrix(result.world_from_objects[f, i, :3, :3]), qpos[f, 7 * i + 3 : 7 * i + 7]
                )
            )
            for f in range(90)
        ]
        assert np.median(pos_mm) < 1.5 and np.median(rot_deg) < 0.5, (name, np.median(pos_mm), np.median(rot_deg))
    meta = json.loads((out / "track.json").read_text())
    assert [m["object"] for m in meta["object_markers"]] == ["box", "can"]
    assert all(m["placed_by"] == "layout" for m in meta["object_markers"])
    # Where both exist, the marker poses and the model-based track agree within the latter's error (box 7.6 mm).
    assert all(0 < m["model_agreement"]["median_across_ray_mm"] < 10 for m in meta["object_markers"])
    assert meta["objects"]["bowl"]["scores"][50]["source"] == "track"


def test_a_misplaced_marker_shows_as_disagreement_with_the_model_based_track() -> None:
    """A marker given 30 mm off its true place, across the camera's view: its object's poses lie 30 mm from the
    model-based track in every frame both see (what `track` warns about); an offset along the view (the track's
    weak axis) does not count; an object never seen by both has no figure."""
    frames = 20
    model = np.tile(np.eye(4), (frames, 2, 1, 1))
    model[:, 0, 0, 3] = np.linspace(0.0, 0.2, frames)
    marker = np.full((frames, 2, 4, 4), np.nan)
    marker[:, 0] = model[:, 0] @ _pose([0.0, 0.03, 0.0], [1, 0, 0, 0])
    seen = np.zeros((frames, 2), bool)
    seen[:, 0] = True
    measured = MarkerPoses(world_from_objects=marker, seen=seen, rms_px=np.where(seen, 0.05, np.nan))
    model_based = np.ones((frames, 2), bool)
    model_based[:5, 0] = False  # e.g. frames the marker filled in
    cameras = np.tile(_pose([0.0, 0.0, 1.0], [1, 0, 0, 0]), (frames, 1, 1))  # above, looking down -z
    cameras[:, :3, 3] += model[:, 0, :3, 3]  # straight above the object: the ray is vertical
    (count, off_mm, off_deg), (none, nan_mm, _) = marker_agreement(measured, model, model_based, cameras)
    assert count == 15 and abs(off_mm - 30.0) < 1e-6 and off_deg < 1e-6
    assert none == 0 and np.isnan(nan_mm)
    along = measured.world_from_objects.copy()
    along[:, 0] = model[:, 0] @ _pose([0.0, 0.0, 0.03], [1, 0, 0, 0])  # 30 mm along the vertical ray
    shifted = MarkerPoses(world_from_objects=along, seen=seen, rms_px=measured.rms_px)
    assert marker_agreement(shifted, model, model_based, cameras)[0][1] < 1e-6


def test_marker_layout_errors_are_one_actionable_line(tmp_path: Path) -> None:
    path = tmp_path / "markers.json"
    cases = {
        "not json": "not valid JSON",
        '{"markers": [{"id": 1, "size_m": 0.05, "id": 2}]}': 'key "id" appears twice',  # was read as marker 2
        '{"markers": []}': "at least one marker",
        '{"markers": [{"id": 1}]}': "needs id and size_m",
        '{"markers": [{"id": 1, "size_m": 48}]}': "expected the square's side in metres",
        '{"markers": [{"id": 1, "size_m": 0.05, "pos_m": [0, 0, 0.03]}]}': "name the object too",
        '{"markers": [{"id": 1, "size_m": 0.05, "object": "box", "pos_m": [0, 0], "quat_wxyz": [1, 0, 0, 0]}]}': (
            "pos_m must be 3 numbers"
        ),
        '{"markers": [{"id": 1, "size_m": 0.05, "object": "box", "pos_m": [0, 0, 0], "quat_wxyz": [2, 0, 0, 0]}]}': (
            "unit quaternion"
        ),
        '{"markers": [{"id": 1, "size_m": 0.05}, {"id": 1, "size_m": 0.04}]}': "repeat",
        # an OverflowError traceback, and marker 2 read from 2.9 without a word
        '{"markers": [{"id": Infinity, "size_m": 0.05}]}': "id must be a whole number, got Infinity",
        '{"markers": [{"id": 2.9, "size_m": 0.05}]}': "id must be a whole number, got 2.9",
        '{"markers": [{"id": true, "size_m": 0.05}]}': "id must be a whole number, got true",
        "[" * 100_000: "nested too deeply",  # was a RecursionError traceback
    }
    for text, expected in cases.items():
        path.write_text(text)
        with pytest.raises(GrounderError, match=expected) as info:
            load_object_markers(path)
        assert "\n" not in str(info.value)
    path.write_text('{"markers": [{"id": 2.0, "size_m": 0.05}]}')  # the control: a whole number written as a float
    assert load_object_markers(path)[0].marker_id == 2
    box = ObjectMarker(marker_id=1, size_m=0.05, object_name="box")
    check_markers([box], ["box", "can"], "DICT_4X4_50", 0)
    for bad, expected in [
        (ObjectMarker(marker_id=1, size_m=0.05, object_name="cup"), "scene's objects are"),
        (ObjectMarker(marker_id=0, size_m=0.05), "table marker's id"),
        (ObjectMarker(marker_id=77, size_m=0.05), "not in DICT_4X4_50"),
    ]:
        with pytest.raises(GrounderError, match=expected):
            check_markers([bad], ["box", "can"], "DICT_4X4_50", 0)
    # A layout entry overrides the scan's marker of the same id; the scan's others stay.
    scan = (
        ObjectMarker(marker_id=1, size_m=0.048, origin="scan"),
        ObjectMarker(marker_id=2, size_m=0.036, origin="scan"),
    )
    assert [(m.marker_id, m.origin) for m in combined_markers((box,), scan)] == [(1, "layout"), (2, "scan")]
    # The scene's own record of its markers comes with the scene: a number there was "'int' object is not iterable".
    from grounder.tracking.markers import scene_markers

    (tmp_path / "scene.json").write_text('{"object_markers": 5}')
    with pytest.raises(GrounderError, match=r"'object_markers' is int 5, not a list of markers; ground the scene"):
        scene_markers(tmp_path / "scene.json")
    (tmp_path / "scene.json").write_text('{"object_markers": ' + "[" * 100_000)
    with pytest.raises(GrounderError, match=r"scene\.json: JSON nested too deeply.*; ground the scene again"):
        scene_markers(tmp_path / "scene.json")
    (tmp_path / "scene.json").write_text("[1]")  # was an AttributeError message
    with pytest.raises(GrounderError, match=r"scene\.json: expected a JSON object, not \[1\]; ground the scene"):
        scene_markers(tmp_path / "scene.json")


def test_cli_marker_options_reject_bad_input(tmp_path: Path) -> None:
    from grounder.cli import app

    layout = tmp_path / "markers.json"
    layout.write_text('{"markers": [{"id": 1}]}')
    runner = CliRunner()
    out = tmp_path / "o"
    result = runner.invoke(
        app,
        ["track", str(TOSS / "video.mp4"), "--scene", str(TOSS_SCENE), "-o", str(out), "--object-markers", str(layout)],
    )
    assert result.exit_code == 2 and "needs id and size_m" in result.output and not out.exists()
    result = runner.invoke(app, ["ground", str(SCAN / "video.mp4"), "-o", str(out), "--object-markers", str(layout)])
    assert result.exit_code == 2 and "needs --interaction" in result.output and not out.exists()
