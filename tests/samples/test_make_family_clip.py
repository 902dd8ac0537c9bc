"""`samples/make_family_clip.py` films what it says: the grounded scene's physics on the true geometry, one object's
sliding friction withheld, throws that keep the objects apart, and a truth that re-simulates.

A two-box family scene and its "grounded" scene are written here (boxes with known friction, solref and mass, the
grounded bodies listed in the other order so that the matching by position is exercised); one small clip is
rendered (160 x 120, two throws). The end-to-end demonstration (ground, film, track, diagnose) is
`benchmarks/diagnose_tracked.py`.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import mujoco
import numpy as np
import pytest
import trimesh

from grounder import load_trajectory

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "samples"))
import make_family_clip as clip_maker  # noqa: E402

BOXES = {  # name: (half extents m, position m, grounded name, friction, solref, grounded mass kg)
    "box_0": ((0.03, 0.02, 0.015), (0.12, -0.05, 0.015), "object_1", (0.45, 0.004, 0.0002), (0.012, 0.3), 0.09),
    "box_1": ((0.025, 0.025, 0.02), (-0.1, 0.06, 0.02), "object_0", (0.6, 0.002, 0.0001), (0.015, 0.4), 0.07),
}


def _family_scene(root: Path) -> Path:
    """A family-like scene folder: truth/scene.xml (welded boxes), objects.json, family.json, cameras.json."""
    truth = root / "scene_00000" / "truth"
    (truth / "assets").mkdir(parents=True)
    objects, bodies = [], []
    for name, (half, pos, *_rest) in BOXES.items():
        mesh = trimesh.creation.box(extents=2 * np.array(half))
        mesh.export(truth / "assets" / f"{name}.obj")
        objects.append(
            {
                "name": name,
                "class": "box",
                "mesh": f"assets/{name}.obj",
                "pos_m": list(pos),
                "quat_wxyz": [1.0, 0.0, 0.0, 0.0],
                "volume_m3": float(mesh.volume),
            }
        )
        bodies.append(
            f'<body name="{name}" pos="{pos[0]} {pos[1]} {pos[2]}"><geom name="{name}_geom" type="mesh" '
            f'mesh="{name}" rgba="0.8 0.3 0.2 1"/></body>'
        )
    meshes = "".join(f'<mesh name="{n}" file="{n}.obj"/>' for n in BOXES)
    (truth / "scene.xml").write_text(
        f'<mujoco><compiler meshdir="assets"/><asset>{meshes}</asset><worldbody>'
        '<light pos="0 0 2" dir="0 0 -1"/><geom name="table" type="box" size="0.7 0.5 0.02" pos="0 0 -0.02"/>'
        f'{"".join(bodies)}<camera name="video" pos="0 -0.6 0.45"/></worldbody></mujoco>'
    )
    (truth / "objects.json").write_text(json.dumps({"objects": objects}))
    (truth / "family.json").write_text(json.dumps({"scale_by": "marker", "objects": ["box/a", "box/b"]}))
    fy = 0.5 * 120 / np.tan(np.deg2rad(50) / 2)
    intrinsics = {"fx": fy, "fy": fy, "cx": 80.0, "cy": 60.0, "width": 160, "height": 120}
    (truth / "cameras.json").write_text(json.dumps({"intrinsics": intrinsics, "fovy_deg": 50.0}))
    return truth.parent


def _grounded_scene(root: Path) -> Path:
    """What `ground` would have made: free bodies object_0/1 (in the other order) with their own physics."""
    scene = root / "grounded"
    (scene / "assets").mkdir(parents=True)
    bodies = []
    for _name, (half, pos, grounded, friction, solref, mass) in sorted(BOXES.items(), key=lambda kv: kv[1][2]):
        trimesh.creation.box(extents=2 * np.array(half)).export(scene / "assets" / f"{grounded}.obj")
        bodies.append(
            f'<body name="{grounded}" pos="{pos[0]} {pos[1]} {pos[2]}"><freejoint name="{grounded}_free"/>'
            f'<geom type="mesh" mesh="{grounded}" mass="{mass}" priority="1" friction="{" ".join(map(str, friction))}" '
            f'solref="{solref[0]} {solref[1]}"/></body>'
        )
    meshes = "".join(f'<mesh name="{v[2]}" file="{v[2]}.obj"/>' for v in BOXES.values())
    (scene / "scene.xml").write_text(
        f'<mujoco><compiler meshdir="assets"/><asset>{meshes}</asset><worldbody>'
        f'<geom name="table" type="box" size="0.7 0.5 0.02" pos="0 0 -0.02"/>{"".join(bodies)}</worldbody></mujoco>'
    )
    return scene


@pytest.fixture(scope="module")
def clip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("family_clip")
    out = root / "clip"
    clip_maker.make_clip(_family_scene(root), _grounded_scene(root), out, seed=5, throws=2)
    return out


def test_objects_matched_by_place_and_one_friction_withheld(clip: Path) -> None:
    withheld = json.loads((clip / "truth" / "withheld.json").read_text())
    assert withheld["matched"] == {name: v[2] for name, v in BOXES.items()}
    truth = withheld["truth_object"]
    assert withheld["grounded_body"] == BOXES[truth][2]
    assert withheld["scene_value"] == pytest.approx(BOXES[truth][3][0])
    factor = withheld["clip_value"] / withheld["scene_value"]
    assert 0.55 <= factor <= 0.7 or 1.4 <= factor <= 1.7
    model = mujoco.MjModel.from_xml_path(str(clip / "truth" / "scene.xml"))
    for name, (_half, _pos, _grounded, friction, solref, mass) in BOXES.items():
        geom = model.geom(f"{name}_geom")
        expected = np.array(friction) * ([factor, 1, 1] if name == truth else [1, 1, 1])
        np.testing.assert_allclose(geom.friction, expected, rtol=1e-6)
        np.testing.assert_allclose(geom.solref, solref, rtol=1e-6)
        assert model.body(name).mass[0] == pytest.approx(mass, rel=1e-5)


def test_throws_resimulate_and_keep_the_objects_apart_and_on_the_table(clip: Path) -> None:
    model = mujoco.MjModel.from_xml_path(str(clip / "truth" / "scene.xml"))
    bodies = {model.body(name).id for name in BOXES}
    frames_per_throw = round(clip_maker.THROW_S * clip_maker.FPS)
    for k in range(2):
        traj = load_trajectory(clip / "truth" / "throws" / f"throw_{k}.npz")
        assert len(traj.time_s) == frames_per_throw
        # Video frame f shows the state at f / FPS, the time `track` gives it (gaps between throws included).
        first_frame = k * (frames_per_throw + clip_maker.GAP_FRAMES)
        expected = (first_frame + np.arange(frames_per_throw)) / clip_maker.FPS
        np.testing.assert_allclose(traj.time_s, expected, atol=1e-9)
        data = mujoco.MjData(model)
        data.qpos[:], data.qvel[:] = traj.qpos[0], traj.qvel[0]
        steps = round((traj.time_s[-1] - traj.time_s[0]) / model.opt.timestep)
        for _ in range(steps):
            mujoco.mj_step(model, data)
            touching = [
                {int(model.geom_bodyid[c.geom1]), int(model.geom_bodyid[c.geom2])} for c in data.contact[: data.ncon]
            ]
            assert not any(pair <= bodies for pair in touching)
        np.testing.assert_allclose(data.qpos, traj.qpos[-1], atol=1e-6)
        for name in BOXES:
            z = traj.qpos[-1, model.joint(f"{name}_free").qposadr[0] + 2]
            assert z < BOXES[name][0][2] + 0.01  # back on the table, not left in the air


def test_video_holds_every_throw_and_the_gaps(clip: Path) -> None:
    cap = cv2.VideoCapture(str(clip / "video.mp4"))
    count = 0
    while cap.read()[0]:
        count += 1
    frames_per_throw = round(clip_maker.THROW_S * clip_maker.FPS)
    assert count == 2 * (frames_per_throw + clip_maker.GAP_FRAMES)
    assert cap.get(cv2.CAP_PROP_FRAME_WIDTH) == 160
