"""Batched re-simulation of trajectories against closed-form answers."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from grounder import Trajectory
from grounder.errors import GrounderError
from grounder.sim.rollout import free_body_errors, simulate, step_indices
from image2sim_common.rotations import quat_angle_rad

FALLING_CUBE = """
<mujoco><option timestep="0.0005"/>
  <worldbody><body name="cube"><freejoint/><geom type="box" size=".05 .05 .05" mass="1"/></body></worldbody>
</mujoco>"""

SLIDER = """
<mujoco><option timestep="0.001" gravity="0 0 0"/>
  <worldbody><body name="cart"><joint name="x" type="slide" axis="1 0 0"/><geom type="sphere" size=".05" mass="2"/>
  </body></worldbody>
  <actuator><motor joint="x" gear="1"/></actuator>
</mujoco>"""


def _ballistic(time_s: np.ndarray, z0: float, vz0: float) -> Trajectory:
    qpos = np.zeros((len(time_s), 7))
    qpos[:, 2] = z0 + vz0 * time_s - 0.5 * 9.81 * time_s**2
    qpos[:, 3] = 1.0
    qvel = np.zeros((len(time_s), 6))
    qvel[:, 2] = vz0 - 9.81 * time_s
    return Trajectory(time_s=time_s, qpos=qpos, qvel=qvel, name="toss")


def test_free_flight_matches_the_parabola_at_data_times() -> None:
    model = mujoco.MjModel.from_xml_string(FALLING_CUBE)
    time_s = np.arange(50) / 100.0  # 100 Hz data, 0.5 ms model steps
    real = _ballistic(time_s, z0=2.0, vz0=1.0)
    predicted = simulate(model, [real])[0]
    assert isinstance(predicted, Trajectory)
    pos_err, rot_err = free_body_errors(model, predicted, real)["cube"]
    # Semi-implicit Euler lags the parabola by 0.5 g dt t: 1.2 mm at 0.49 s.
    assert pos_err.max() < 1.5e-3
    assert pos_err.max() > 0.0
    assert rot_err.max() < 1e-9


def test_controls_are_held_between_samples() -> None:
    model = mujoco.MjModel.from_xml_string(SLIDER)
    time_s = np.arange(11) * 0.01
    ctrl = np.where(time_s < 0.05, 4.0, 0.0)[:, None]  # 2 m/s^2 for 50 ms, then coast
    real = Trajectory(time_s=time_s, qpos=np.zeros((11, 1)), qvel=np.zeros((11, 1)), ctrl=ctrl, name="push")
    predicted = simulate(model, [real])[0]
    assert isinstance(predicted, Trajectory)
    np.testing.assert_allclose(predicted.qvel[-1, 0], 2.0 * 0.05, rtol=1e-6)
    np.testing.assert_allclose(predicted.qpos[5, 0], 0.5 * 2.0 * 0.05**2, rtol=0.05)


def test_many_models_times_many_trajectories() -> None:
    base = mujoco.MjModel.from_xml_string(FALLING_CUBE)
    heavy_gravity = mujoco.MjModel.from_xml_string(FALLING_CUBE)
    heavy_gravity.opt.gravity[2] = -20.0
    time_s = np.arange(20) / 50.0
    trajs = [_ballistic(time_s, 1.0, 0.0), _ballistic(time_s, 3.0, 2.0)]
    out = simulate([base, heavy_gravity], trajs)
    assert len(out) == 2 and all(len(row) == 2 for row in out)
    first = out[0][1]
    second = out[1][1]
    assert isinstance(first, Trajectory) and isinstance(second, Trajectory)
    drop_base = trajs[1].qpos[0, 2] - first.qpos[-1, 2]
    drop_heavy = trajs[1].qpos[0, 2] - second.qpos[-1, 2]
    t = time_s[-1]
    assert drop_heavy - drop_base == pytest.approx(0.5 * (20.0 - 9.81) * t**2, rel=0.02)


def test_quaternion_double_cover_is_the_same_rotation() -> None:
    q = np.array([0.9, 0.1, -0.3, 0.2])
    q /= np.linalg.norm(q)
    assert quat_angle_rad(q, -q) == pytest.approx(0.0, abs=1e-6)
    about_z = np.array([np.cos(0.25), 0.0, 0.0, np.sin(0.25)])  # 0.5 rad about z
    assert quat_angle_rad(np.array([1.0, 0, 0, 0]), about_z) == pytest.approx(0.5, abs=1e-9)


def test_data_faster_than_the_model_is_refused() -> None:
    with pytest.raises(GrounderError, match=r"trajectory toss_3: samples 0 and 1 are 0\.100 ms apart .* shorter"):
        step_indices(np.array([0.0, 0.0001, 0.0002]), 0.001, "toss_3")
    with pytest.raises(GrounderError, match=r"samples 1 and 2 are 0\.000 ms apart .* remove the repeated sample"):
        step_indices(np.array([0.0, 0.01, 0.01, 0.02]), 0.001, "toss_3")


def test_a_time_column_too_long_to_simulate_is_refused_before_allocating() -> None:
    """A trajectory whose times span 1e9 s (milliseconds written as seconds, or a hostile file) used to reach
    `mujoco.rollout` and fail allocating 121 TB; it is now one error naming the trajectory and its span."""
    model = mujoco.MjModel.from_xml_string(FALLING_CUBE)
    qpos = np.array([[0.0, 0.0, 2.0, 1.0, 0.0, 0.0, 0.0]] * 2)  # at rest: a fall over 1e9 s passes MuJoCo's limit
    traj = Trajectory(time_s=np.array([0.0, 1e9]), qpos=qpos, qvel=np.zeros((2, 6)), name="toss")
    with pytest.raises(
        GrounderError, match=r"trajectory 'toss' spans 1e\+09 s, 2000000000000 model steps.*time column"
    ):
        simulate(model, [traj])


_CHILD = '<mujoco><worldbody><body name="b"><freejoint/><geom size=".05"/></body></worldbody></mujoco>'


def _escaping_scene(tmp_path: Path, how: str, rel: str) -> Path:
    """A scene.xml in tmp_path/scene that reads child.xml or box.obj from the folder ``rel`` (relative to it)."""
    import trimesh

    for folder in (tmp_path / "outside", tmp_path / "scene"):
        folder.mkdir(exist_ok=True)
        (folder / "child.xml").write_text(_CHILD)
        trimesh.creation.box((0.1, 0.1, 0.1)).export(folder / "box.obj")
    body = {
        "undefined entity": f'<include file="{rel}/child.xml"/>',
        "attached model": f'<asset><model name="child" file="{rel}/child.xml"/></asset>'
        '<worldbody><attach model="child" prefix="c_"/></worldbody>',
        "flexcomp mesh": f'<worldbody><flexcomp name="f" type="mesh" file="{rel}/box.obj" dim="2">'
        '<edge equality="true"/></flexcomp></worldbody>',
    }[how]
    xml = tmp_path / "scene" / "scene.xml"
    xml.write_text(f'<mujoco model="{"a&undefined;b" if how == "undefined entity" else "a"}">{body}</mujoco>')
    return xml


@pytest.mark.parametrize("how", ["undefined entity", "attached model", "flexcomp mesh"])
def test_scene_files_refuses_what_mujoco_would_read_outside_the_folder(tmp_path: Path, how: str) -> None:
    """Three ways an MJCF made MuJoCo read a file outside its folder past the check: an XML that expat cannot parse
    but MuJoCo's parser accepts (an undefined entity) skipped the check of its <include>s; a <model> asset (attached
    with <attach>) and a <flexcomp> mesh are read as MuJoCo parses, and were not checked at all."""
    from grounder.sim.scene_files import scene_files

    xml = _escaping_scene(tmp_path, how, "../outside")
    mujoco.MjSpec.from_file(str(xml)).compile()  # MuJoCo reads the outside file without a word
    with pytest.raises(GrounderError, match="not well-formed XML" if how == "undefined entity" else "outside the"):
        scene_files(xml)
    if how != "undefined entity":  # the control: the same MJCF reading the copy inside its folder is accepted
        xml = _escaping_scene(tmp_path, how, ".")
        assert scene_files(xml) == [Path("box.obj" if how == "flexcomp mesh" else "child.xml")]


def test_scene_folder_links_that_lead_out_of_the_copy_are_refused(tmp_path: Path) -> None:
    """A scene folder is copied whole into calibrate's output, links as links: a scene.json linking to a file of the
    user's (by an absolute path, or a relative one out of the folder) was copied as that link, and calibrate's note
    then written through it into the user's file. A relative link within the folder stays a link in the copy."""
    import os

    from grounder.sim.scene_files import copy_scene_files

    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "scene.xml").write_text(FALLING_CUBE)
    (scene / "real.json").write_text("{}")
    (scene / "scene.json").symlink_to("real.json")  # the control: relative, inside
    copy_scene_files(scene, tmp_path / "ok")
    assert os.readlink(tmp_path / "ok" / "scene.json") == "real.json"
    (tmp_path / "users.json").write_text("{}")
    for target in (tmp_path / "users.json", Path("../users.json"), scene / "real.json"):
        (scene / "scene.json").unlink()
        (scene / "scene.json").symlink_to(target)
        with pytest.raises(GrounderError, match=r"scene\.json: a link to .* out of the output folder"):
            copy_scene_files(scene, tmp_path / "out")
        assert not (tmp_path / "out").exists()
    copy_scene_files(scene, tmp_path / "skipped", skip=("scene.json",))  # not copied: nothing to refuse
