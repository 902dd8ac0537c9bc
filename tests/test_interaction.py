"""Identifiability screen and constrained calibration of `grounder._interaction` on a small synthetic scene.

A box is thrown along a table and slides to rest (its friction shows); a second box sits still the whole time (its
friction leaves no trace). The recorded motion is simulated with known values, so the answers are known.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from grounder._interaction import InteractionOptions, calibrate_constrained, screen_parameters
from grounder._trajectory import Trajectory

SCENE = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <geom name="table" type="plane" size="2 2 0.1"/>
    <body name="slider" pos="0 0 0.03">
      <freejoint name="slider_free"/>
      <geom type="box" size="0.04 0.03 0.03" density="300" friction="{slider}" priority="1"/>
    </body>
    <body name="still" pos="0.5 0.5 0.03">
      <freejoint name="still_free"/>
      <geom type="box" size="0.04 0.03 0.03" density="300" friction="{still}" priority="1"/>
    </body>
  </worldbody>
</mujoco>
"""
TRUE_FRICTION = 0.4
PARAMS = ("slider.friction.sliding", "still.friction.sliding")
# A short differential evolution: enough for one friction value on a clean recording.
QUICK = InteractionOptions(calibrate_settings={"generations": 4, "popsize": 5, "local_iterations": 5})


def _scene(folder: Path, slider: float, still: float) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    xml = folder / "scene.xml"
    xml.write_text(SCENE.format(slider=slider, still=still))
    return xml


def _recorded(tmp_path: Path) -> Trajectory:
    model = mujoco.MjModel.from_xml_path(str(_scene(tmp_path / "truth", TRUE_FRICTION, TRUE_FRICTION)))
    data = mujoco.MjData(model)
    data.qvel[0] = 1.5  # thrown along +x
    mujoco.mj_forward(model, data)
    time_s, qpos, qvel = [], [], []
    steps_per_frame = round((1 / 30) / model.opt.timestep)
    for _ in range(24):  # 0.8 s at 30 fps: slides ~0.29 m and stops
        time_s.append(data.time)
        qpos.append(data.qpos.copy())
        qvel.append(data.qvel.copy())
        for _ in range(steps_per_frame):
            mujoco.mj_step(model, data)
    return Trajectory(time_s=np.array(time_s), qpos=np.array(qpos), qvel=np.array(qvel), name="toss_00")


def test_screen_flags_only_the_parameter_the_motion_shows(tmp_path: Path) -> None:
    traj = _recorded(tmp_path)
    xml = _scene(tmp_path / "prior", 0.8, 0.8)
    screens = {s.name: s for s in screen_parameters(xml, [traj], PARAMS, grid_points=9, passes=1)}
    assert screens["slider.friction.sliding"].constrained
    assert screens["slider.friction.sliding"].best == pytest.approx(TRUE_FRICTION, rel=0.35)  # a coarse grid
    pos_m, rot_deg = screens["slider.friction.sliding"].change_down
    assert pos_m > 0.003 or rot_deg > 2.0
    assert not screens["still.friction.sliding"].constrained
    assert screens["still.friction.sliding"].change_up[0] < 1e-4  # resting: friction changes (next to) nothing


def test_calibrate_constrained_fits_the_shown_parameter_and_keeps_the_prior_of_the_other(tmp_path: Path) -> None:
    traj = _recorded(tmp_path)
    xml = _scene(tmp_path / "prior", 0.8, 0.8)
    entry = calibrate_constrained(
        xml,
        [traj],
        PARAMS,
        QUICK,
        out=tmp_path / "calibrated",
    )
    slider, still = entry["parameters"]["slider.friction.sliding"], entry["parameters"]["still.friction.sliding"]
    assert entry["status"].startswith("calibrated")
    assert slider["constrained"] and slider["value"] == pytest.approx(TRUE_FRICTION, rel=0.05)
    low, high = slider["indistinguishable"]
    assert low < TRUE_FRICTION < high and high / low < 1.6
    assert not still["constrained"]
    assert still["value"] == 0.8 and still["interval"] == still["bounds"]
    assert (tmp_path / "calibrated" / "scene.xml").is_file()


def test_nothing_constrained_calibrates_nothing(tmp_path: Path) -> None:
    traj = _recorded(tmp_path)
    xml = _scene(tmp_path / "prior", 0.8, 0.8)
    entry = calibrate_constrained(
        xml, [traj], ("still.friction.sliding",), InteractionOptions(), out=tmp_path / "calibrated"
    )
    assert entry["status"].startswith("skipped")
    assert not (tmp_path / "calibrated").exists()


def test_per_object_calibration_fits_each_object_alone_and_writes_the_whole_scene(tmp_path: Path) -> None:
    """The two boxes never touch: each is calibrated in a scene of its own on windows of its own motion; the values
    found are written into the whole scene (its calibration.json says so) and no helper file is left behind."""
    from grounder._interaction import calibrate_per_body, separable_bodies

    traj = _recorded(tmp_path)
    xml = _scene(tmp_path / "prior", 0.8, 0.8)
    assert separable_bodies(xml, [traj])
    entry, used = calibrate_per_body(
        xml,
        [traj],
        PARAMS,
        QUICK,
        out=tmp_path / "calibrated",
    )
    slider, still = entry["parameters"]["slider.friction.sliding"], entry["parameters"]["still.friction.sliding"]
    assert entry["status"].startswith("calibrated per object")
    assert slider["constrained"] and slider["value"] == pytest.approx(TRUE_FRICTION, rel=0.05)
    assert not still["constrained"] and still["value"] == 0.8
    assert used and all(name.startswith("slider:") for name in used)  # the still box shows no motion to fit
    calibrated = mujoco.MjModel.from_xml_path(str(tmp_path / "calibrated" / "scene.xml"))
    assert calibrated.geom_friction[calibrated.body("slider").geomadr[0], 0] == pytest.approx(slider["value"])
    assert calibrated.geom_friction[calibrated.body("still").geomadr[0], 0] == pytest.approx(0.8)
    assert sorted(p.name for p in (tmp_path / "prior").iterdir()) == ["scene.xml"]


def test_touching_objects_are_not_separable(tmp_path: Path) -> None:
    from grounder._interaction import separable_bodies

    traj = _recorded(tmp_path)
    xml = _scene(tmp_path / "prior", 0.8, 0.8)
    touching = traj.qpos.copy()
    touching[5, 7:10] = touching[5, 0:3] + np.array([0.081, 0.0, 0.0])  # 1 mm from the slider's side
    assert not separable_bodies(xml, [Trajectory(time_s=traj.time_s, qpos=touching, qvel=traj.qvel, name="t")])


def test_reliable_starts_skip_the_frames_next_to_an_impact() -> None:
    """A box thrown onto the floor lands between two frames and slides (30 fps, known motion): the samples of the
    flight are good starts (their velocity comes from the ballistic fit) except the last before the landing
    (impacts are resolved to a frame: it may already be past it); the first sample after the landing is not (it may
    still be mid-impact); the rest of the slide is, to the end of the trajectory."""
    from grounder._interaction import reliable_starts

    dt, g = 1 / 30, 9.81
    time_s = np.arange(24) * dt
    landing = 7.5 * dt  # between samples 7 and 8
    x = np.where(
        time_s < landing, 1.0 * time_s, 1.0 * landing + 0.6 * (time_s - landing) - 0.5 * 2.0 * (time_s - landing) ** 2
    )
    z = np.where(time_s < landing, 0.03 + 0.5 * g * (landing**2 - time_s**2), 0.03)
    qpos = np.zeros((24, 7))
    qpos[:, 0], qpos[:, 2], qpos[:, 3] = x, z, 1.0
    good = reliable_starts(Trajectory(time_s=time_s, qpos=qpos, qvel=np.zeros((24, 6)), name="throw"))
    assert good[:7].all()
    assert not good[7] and not good[8]
    assert good[9:].all()
    # A segment that begins mid-slide: what came before its first sample is unknown.
    sliding = Trajectory(time_s=time_s[10:], qpos=qpos[10:], qvel=np.zeros((14, 6)), name="slide")
    good = reliable_starts(sliding)
    assert not good[0] and good[1:].all()


def test_calibrate_separate_bodies_and_initial_values(tmp_path: Path) -> None:
    """`CalibrateOptions.separate_bodies` searches each body's parameters on its own (here the slider's friction is
    found from a prior of 0.8 while the still box's stays put); `initial` with no search budget returns exactly
    the given values, evaluated; a non-body parameter is refused."""
    from grounder._calibrate import CalibrateOptions, calibrate
    from grounder.errors import GrounderError

    traj = _recorded(tmp_path)
    xml = _scene(tmp_path / "prior", 0.8, 0.8)
    settings = {"generations": 4, "popsize": 5, "local_iterations": 5, "validation_fraction": 0.0}
    result = calibrate(xml, [traj], options=CalibrateOptions(params=PARAMS, separate_bodies=True, **settings))
    assert result.values["slider.friction.sliding"] == pytest.approx(TRUE_FRICTION, rel=0.05)
    fixed = calibrate(
        xml,
        [traj],
        options=CalibrateOptions(
            params=PARAMS, initial={"slider.friction.sliding": 0.5}, generations=0, local_iterations=0
        ),
    )
    assert fixed.values == {"slider.friction.sliding": pytest.approx(0.5), "still.friction.sliding": pytest.approx(0.8)}
    with pytest.raises(GrounderError, match="per-body parameters"):
        calibrate(xml, [traj], options=CalibrateOptions(params=("opt.gravity_scale",), separate_bodies=True))


def test_reliable_starts_skip_the_frame_after_a_bounce() -> None:
    """A ball dropped from 20 cm bounces (restitution 0.6) between two frames at 30 fps and flies again: both
    flights are good starts except the two samples around the bounce."""
    from grounder._interaction import reliable_starts

    dt, g = 1 / 30, 9.81
    time_s = np.arange(20) * dt
    bounce = np.sqrt(2 * 0.2 / g)  # 0.202 s, between samples 6 and 7
    after = time_s - bounce
    z = np.where(time_s < bounce, 0.2 - 0.5 * g * time_s**2, 0.6 * g * bounce * after - 0.5 * g * after**2)
    qpos = np.zeros((20, 7))
    qpos[:, 0], qpos[:, 2], qpos[:, 3] = 0.3 * time_s, 0.02 + z, 1.0
    good = reliable_starts(Trajectory(time_s=time_s, qpos=qpos, qvel=np.zeros((20, 6)), name="bounce"))
    assert good[:6].all()
    assert not good[6] and not good[7]
    assert good[8:].all()
