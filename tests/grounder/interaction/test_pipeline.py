"""Identifiability screen and constrained calibration of `grounder.interaction` (`screen`, `windows`, `per_object`)
on a small synthetic scene.

A box is thrown along a table and slides to rest (its friction shows); a second box sits still the whole time (its
friction leaves no trace). The recorded motion is simulated with known values, so the answers are known.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest

from grounder.core.trajectory import Trajectory
from grounder.interaction.options import InteractionOptions
from grounder.interaction.screen import screen_parameters
from grounder.interaction.windows import calibrate_constrained

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


def _simulated(model: mujoco.MjModel, qvel0: dict[int, float], frames: int, name: str) -> Trajectory:
    """`frames` states at 30 fps of `model` started at rest where it stands, with qvel[i] = qvel0[i]."""
    data = mujoco.MjData(model)
    for i, value in qvel0.items():
        data.qvel[i] = value
    mujoco.mj_forward(model, data)
    time_s, qpos, qvel = [], [], []
    steps_per_frame = round((1 / 30) / model.opt.timestep)
    for _ in range(frames):
        time_s.append(data.time)
        qpos.append(data.qpos.copy())
        qvel.append(data.qvel.copy())
        for _ in range(steps_per_frame):
            mujoco.mj_step(model, data)
    return Trajectory(time_s=np.array(time_s), qpos=np.array(qpos), qvel=np.array(qvel), name=name)


def _recorded(tmp_path: Path) -> Trajectory:
    model = mujoco.MjModel.from_xml_path(str(_scene(tmp_path / "truth", TRUE_FRICTION, TRUE_FRICTION)))
    # Thrown along +x; 0.8 s at 30 fps: slides ~0.29 m and stops.
    return _simulated(model, {0: 1.5}, 24, "toss_00")


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


def test_a_value_the_screen_passed_but_unresolved_where_the_fit_lands_keeps_the_prior(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The screen looks at its grid best; the fit may land where the clip says nothing. With a screen that passes
    everything, the still box's friction is fitted (any value matches a box that never moves), then found unresolved
    at the fitted value: it keeps the prior, the slider is fitted again alone, and the written scene holds the prior."""
    import grounder.interaction.windows as interaction

    real_screen = interaction.screen_parameters

    def screen_passing_everything(*args: object, **kwargs: object) -> list[interaction.ParameterScreen]:
        return [replace(screen, constrained=True) for screen in real_screen(*args, **kwargs)]  # type: ignore[arg-type]

    monkeypatch.setattr(interaction, "screen_parameters", screen_passing_everything)
    traj = _recorded(tmp_path)
    xml = _scene(tmp_path / "prior", 0.8, 0.8)
    entry = calibrate_constrained(xml, [traj], PARAMS, QUICK, out=tmp_path / "calibrated")
    slider, still = entry["parameters"]["slider.friction.sliding"], entry["parameters"]["still.friction.sliding"]
    assert slider["constrained"] and slider["value"] == pytest.approx(TRUE_FRICTION, rel=0.05)
    assert not still["constrained"] and still["value"] == 0.8 and "unresolved_fit" in still
    assert entry["status"] == "calibrated; unconstrained by the clip, prior kept: ['still.friction.sliding']"
    written = mujoco.MjModel.from_xml_path(str(tmp_path / "calibrated" / "scene.xml"))
    assert written.geom_friction[written.body("still").geomadr[0], 0] == pytest.approx(0.8)
    assert written.geom_friction[written.body("slider").geomadr[0], 0] == pytest.approx(slider["value"])


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
    from grounder.interaction.per_object import calibrate_per_body, separable_bodies

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
    # It only slides: no flight, no impact, so the default calibration (impacts) hands it to the windows.
    assert slider["method"] == "windows" and "no impact" in entry["per_object"]["slider"]["status"]
    assert not still["constrained"] and still["value"] == 0.8
    assert used and all(name.startswith("slider:") for name in used)  # the still box shows no motion to fit
    calibrated = mujoco.MjModel.from_xml_path(str(tmp_path / "calibrated" / "scene.xml"))
    assert calibrated.geom_friction[calibrated.body("slider").geomadr[0], 0] == pytest.approx(slider["value"])
    assert calibrated.geom_friction[calibrated.body("still").geomadr[0], 0] == pytest.approx(0.8)
    assert sorted(p.name for p in (tmp_path / "prior").iterdir()) == ["scene.xml"]
    # The report's window match: the slider's windows, rolled out at the prior friction (0.8: it stops too soon) and
    # at the calibrated one (the recording's own value, so within what a 5% friction error leaves).
    match = entry["per_object"]["slider"]["window_match"]
    assert match["windows"] == sum(name.startswith("slider:") for name in used)
    assert match["before"]["median_position_error_mm"] > 10.0
    assert match["after"]["median_position_error_mm"] < 0.2 * match["before"]["median_position_error_mm"]
    assert entry["per_object"]["still"]["window_match"] == {}


def test_per_object_calibration_writes_nothing_into_the_scene_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each object's own scene is written to a private folder, its meshes still found: the scene folder (a mesh under
    `assets/`) is exactly as it was while the calibration runs. A fixed-name helper file beside scene.xml let two
    calibrations of one scene at once delete each other's (seen: `ParseXML: Error opening file .calibrate_...xml`)."""
    import trimesh

    import grounder.interaction.per_object as interaction

    folder = tmp_path / "prior"
    (folder / "assets").mkdir(parents=True)
    trimesh.creation.box(extents=(0.08, 0.06, 0.06)).export(folder / "assets" / "slider.obj")
    meshed = SCENE.replace(
        '<geom type="box" size="0.04 0.03 0.03" density="300" friction="{slider}" priority="1"/>',
        '<geom type="mesh" mesh="slider" density="300" friction="{slider}" priority="1"/>',
    )
    meshed = meshed.replace(
        "<mujoco>", '<mujoco>\n  <compiler meshdir="assets"/>\n  <asset><mesh name="slider" file="slider.obj"/></asset>'
    )
    xml = folder / "scene.xml"
    xml.write_text(meshed.format(slider=0.8, still=0.8))
    before = sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))
    seen: list[list[str]] = []
    real = interaction.calibrate_constrained

    def spy(sub_xml: Path, *args: object, **kwargs: object) -> dict:
        seen.append(sorted(str(p.relative_to(folder)) for p in folder.rglob("*")))
        assert folder not in Path(sub_xml).parents
        return real(sub_xml, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(interaction, "calibrate_constrained", spy)
    entry, _ = interaction.calibrate_per_body(xml, [_recorded(tmp_path)], PARAMS, QUICK)
    assert seen and all(listing == before for listing in seen)
    assert sorted(str(p.relative_to(folder)) for p in folder.rglob("*")) == before
    slider = entry["parameters"]["slider.friction.sliding"]
    assert slider["constrained"] and slider["value"] == pytest.approx(TRUE_FRICTION, rel=0.05)


def test_per_object_values_are_written_without_any_segment(tmp_path: Path) -> None:
    """No frame has both boxes tracked (no segment): each box's own runs still calibrate it, and the values are
    written into the whole scene (`write_values`), said to be unevaluated on it."""
    from grounder.interaction.per_object import _single_body_trajectory, calibrate_per_body

    traj = _recorded(tmp_path)
    xml = _scene(tmp_path / "prior", 0.8, 0.8)
    model = mujoco.MjModel.from_xml_path(str(xml))
    half = len(traj.time_s) // 2
    own = {
        "slider": [_single_body_trajectory(model, traj, "slider")],
        "still": [_single_body_trajectory(model, traj, "still")],
    }
    own["still"] = [  # the still box is only seen in the second half, the slider in the whole clip
        Trajectory(time_s=t.time_s[half:], qpos=t.qpos[half:], qvel=t.qvel[half:], name=t.name) for t in own["still"]
    ]
    entry, used = calibrate_per_body(xml, [], PARAMS, QUICK, object_tracks=own, out=tmp_path / "calibrated")
    slider = entry["parameters"]["slider.friction.sliding"]
    assert "not evaluated on the whole scene" in entry["status"]
    assert slider["constrained"] and slider["value"] == pytest.approx(TRUE_FRICTION, rel=0.05)
    calibrated = mujoco.MjModel.from_xml_path(str(tmp_path / "calibrated" / "scene.xml"))
    assert calibrated.geom_friction[calibrated.body("slider").geomadr[0], 0] == pytest.approx(slider["value"])
    assert calibrated.geom_friction[calibrated.body("still").geomadr[0], 0] == pytest.approx(0.8)
    assert sorted(p.name for p in (tmp_path / "calibrated").iterdir()) == ["scene.xml"]
    assert used and all(name.startswith("slider:") for name in used)


def test_touching_objects_are_not_separable(tmp_path: Path) -> None:
    from grounder.interaction.per_object import separable_bodies

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
    from grounder.interaction.windows import reliable_starts

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
    # A run that begins two samples before the landing: a flight of two samples gives no start (its velocity is
    # their difference alone).
    late = Trajectory(time_s=time_s[6:], qpos=qpos[6:], qvel=np.zeros((18, 6)), name="late")
    good = reliable_starts(late)
    assert not good[:3].any() and good[3:].all()


def test_calibrate_separate_bodies_and_initial_values(tmp_path: Path) -> None:
    """`CalibrateOptions.separate_bodies` searches each body's parameters on its own (here the slider's friction is
    found from a prior of 0.8 while the still box's stays put); `initial` with no search budget returns exactly
    the given values, evaluated; a non-body parameter is refused."""
    from grounder.calibration.fit import calibrate
    from grounder.calibration.options import CalibrateOptions
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
    from grounder.interaction.windows import reliable_starts

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


BALL = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <geom name="table" type="plane" size="2 2 0.1"/>
    <body name="ball" pos="0 0 0.035">
      <freejoint name="ball_free"/>
      <geom type="sphere" size="0.03" density="300" friction="{friction}" priority="1"/>
    </body>
  </worldbody>
</mujoco>
"""


def _ball(tmp_path: Path, friction: float) -> tuple[Path, Trajectory]:
    """A ball thrown with backspin from 5 mm above the table: it lands, skids for 0.2 s and rolls (its friction
    decides when skidding stops), 0.5 s at 30 fps with the true friction; and a scene with `friction`."""
    (tmp_path / "ball").mkdir(exist_ok=True)
    truth = tmp_path / "ball" / "truth.xml"
    truth.write_text(BALL.format(friction=TRUE_FRICTION))
    model = mujoco.MjModel.from_xml_path(str(truth))
    throw = _simulated(model, {0: 2.0, 4: -30.0}, 15, "throw_00")  # backspin: it skids long after landing
    scene = tmp_path / "ball" / "scene.xml"
    scene.write_text(BALL.format(friction=friction))
    return scene, throw


def _corrupted(traj: Trajectory, dx_m: float, dv_m_s: float) -> Trajectory:
    """The recording with its first position and velocity off along the throw, as a fresh detection's can be."""
    qpos, qvel = traj.qpos.copy(), traj.qvel.copy()
    qpos[0, 0] += dx_m
    qvel[0, 0] += dv_m_s
    return Trajectory(time_s=traj.time_s, qpos=qpos, qvel=qvel, name=traj.name)


def test_start_refit_recovers_the_true_start_from_the_motion_after_it(tmp_path: Path) -> None:
    """A start 4 mm and 0.15 m/s off (a fresh detection's error): the refit brings it back from the motion after
    it, to within the roughness the landing gives the cost (about a millimetre and 3 cm/s here)."""
    from grounder.interaction.starts import refine_window_starts

    scene, traj = _ball(tmp_path, TRUE_FRICTION)
    bad = _corrupted(traj, 0.004, 0.15)
    refit, fits = refine_window_starts(mujoco.MjModel.from_xml_path(str(scene)), [bad], rotation_weight=0.25)
    assert fits[0].accepted and fits[0].cost_after < 1e-3 * fits[0].cost_before
    assert np.abs(refit[0].qpos[0, :3] - traj.qpos[0, :3]).max() < 1e-3  # 1 mm, from 4 mm off
    assert np.abs(refit[0].qvel[0, :3] - traj.qvel[0, :3]).max() < 0.04  # 4 cm/s, from 15 cm/s off
    assert np.abs(refit[0].qvel[0, 3:] - traj.qvel[0, 3:]).max() < 1.5  # rad/s: the 30 rad/s backspin stays
    np.testing.assert_array_equal(refit[0].qpos[1:], bad.qpos[1:])  # only the start is a nuisance parameter


def test_start_refits_leave_a_clean_recording_at_its_true_start_and_friction(tmp_path: Path) -> None:
    """On an exact recording two rounds of refits barely move the start and keep the friction."""
    traj = _recorded(tmp_path)
    xml = _scene(tmp_path / "prior", 0.8, 0.8)
    entry = calibrate_constrained(xml, [traj], ("slider.friction.sliding",), replace(QUICK, start_rounds=2))
    assert entry["parameters"]["slider.friction.sliding"]["value"] == pytest.approx(TRUE_FRICTION, rel=0.05)
    assert [r["round"] for r in entry["start_refinement"]] == [1, 2]
    for refits in entry["start_refinement"]:
        (fit,) = refits["windows"]
        assert fit["position_change_mm"] < 1.0 and fit["velocity_change_m_s"] < 0.02


def test_along_view_weight_scales_only_the_error_along_the_camera_ray(tmp_path: Path) -> None:
    from grounder.calibration.evaluator import Evaluator
    from grounder.calibration.parameters import resolve_parameters
    from grounder.sim.rollout import along_view_weighted

    view_m = np.array([0.0, -0.5, 0.5])
    seen_m = np.array([0.0, 0.0, 0.0])
    ray = (seen_m - view_m) / np.linalg.norm(seen_m - view_m)
    across = np.array([1.0, 0.0, 0.0])
    error_m = 0.004 * ray + 0.001 * across
    weighted = along_view_weighted(error_m, seen_m, view_m, 0.25)
    np.testing.assert_allclose(weighted, 0.001 * ray + 0.001 * across, atol=1e-12)
    np.testing.assert_array_equal(along_view_weighted(error_m, seen_m, None, 0.25), error_m)

    # In the calibration loss: a recording offset along the ray from the camera to each sample by 5 mm.
    traj = _recorded(tmp_path)
    model = mujoco.MjModel.from_xml_path(str(tmp_path / "truth" / "scene.xml"))
    shifted = traj.qpos.copy()
    for body in (0, 7):  # the first sample stays: the rollout starts on the truth
        rays = shifted[1:, body : body + 3] - view_m
        shifted[1:, body : body + 3] += 0.005 * rays / np.linalg.norm(rays, axis=1, keepdims=True)
    offset = Trajectory(time_s=traj.time_s, qpos=shifted, qvel=traj.qvel, name="offset")
    params = resolve_parameters(model, ["slider.friction.sliding"])
    true_value = np.array([[TRUE_FRICTION]])
    plain = Evaluator(model, params, [offset], rotation_weight=0.0).loss_of_values(true_value)[0, 0]
    quarter = Evaluator(
        model, params, [offset], rotation_weight=0.0, view_point_m=view_m, along_view_weight=0.25
    ).loss_of_values(true_value)[0, 0]
    assert plain > 3.0  # 5 mm of a 10 cm box, in percent, on every sample but the first
    assert quarter == pytest.approx(0.25 * plain, rel=1e-6)


def test_view_point_is_the_mean_camera_centre_where_the_camera_is_known() -> None:
    from grounder.interaction.tracks import view_point_of

    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[0, :3, 3] = [0.0, -0.5, 0.5]
    poses[1] = np.nan  # marker unseen in that frame
    poses[2, :3, 3] = [0.1, -0.5, 0.5]
    np.testing.assert_allclose(view_point_of(poses), [0.05, -0.5, 0.5])
    assert view_point_of(np.full((2, 4, 4), np.nan)) is None


DROPPED_BALL = """
<mujoco>
  <option integrator="implicitfast" cone="elliptic"/>
  <worldbody>
    <geom name="table" type="plane" size="2 2 0.1"/>
    <body name="ball" pos="0 0 0.1">
      <freejoint/>
      <geom type="sphere" size="0.035" density="500" friction="0.4 0.005 0.0001" solref="{timeconst} {dampratio}"
            priority="1"/>
    </body>
  </worldbody>
</mujoco>
"""


def test_the_time_constant_is_calibrated_with_the_damping_ratio(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A ball dropped from 10 cm bounces with solref (0.02 s, 0.2); the prior says (0.008 s, 0.35), as the property
    model's guess for the tabletop's ceramic bowl was 0.0086 s. How high a bounce goes depends on both solref values
    at MuJoCo's time step: with the time constant held at the prior the damping ratio comes out biased; calibrated
    together (`default_params`), both come out right, and the time constant stays fitted with its damping ratio even
    where a step of it alone does not show at the fit."""
    import grounder.interaction.windows as interaction
    from grounder.interaction.options import CONTACT_FIELDS, default_params

    assert "solref.timeconst" in CONTACT_FIELDS and "ball.solref.timeconst" in default_params(["ball"])
    true_xml = tmp_path / "truth.xml"
    true_xml.write_text(DROPPED_BALL.format(timeconst=0.02, dampratio=0.2))
    # 0.8 s at 30 fps: the drop and two bounces
    traj = _simulated(mujoco.MjModel.from_xml_path(str(true_xml)), {0: 0.3}, 24, "drop_00")
    prior = tmp_path / "prior" / "scene.xml"
    prior.parent.mkdir()
    prior.write_text(DROPPED_BALL.format(timeconst=0.008, dampratio=0.35))
    options = InteractionOptions(calibrate_settings={"generations": 12, "popsize": 8, "local_iterations": 10})
    held = calibrate_constrained(prior, [traj], ("ball.solref.dampratio",), options)["parameters"]
    assert held["ball.solref.dampratio"]["value"] > 0.2 * 1.25  # the bias: +43% measured
    both = calibrate_constrained(prior, [traj], ("ball.solref.dampratio", "ball.solref.timeconst"), options)
    fitted = both["parameters"]
    assert fitted["ball.solref.dampratio"]["value"] == pytest.approx(0.2, rel=0.05)
    assert fitted["ball.solref.timeconst"]["value"] == pytest.approx(0.02, rel=0.1)
    # The bowl of `benchmarks/track.py --truth`: its time constant's step did not show at the fit; dropped, the
    # damping ratio refitted without it came out -12%.
    monkeypatch.setattr(interaction, "_unresolved_at", lambda scene, trajs, fit, values, opts: list(fit)[1:])
    kept = calibrate_constrained(prior, [traj], ("ball.solref.dampratio", "ball.solref.timeconst"), options)
    assert kept["parameters"]["ball.solref.timeconst"]["constrained"]
    assert kept["parameters"]["ball.solref.dampratio"]["value"] == pytest.approx(0.2, rel=0.05)


def test_a_time_constant_is_fitted_wherever_its_damping_ratio_is() -> None:
    """The screen moves one parameter at a time by 20%; a time constant whose prior is off by a factor of 2 shows
    little that way, yet held there it biases the damping ratio. It is fitted whenever its body's damping ratio is."""
    from grounder.interaction.screen import ParameterScreen
    from grounder.interaction.windows import _paired

    def screen(name: str, constrained: bool) -> ParameterScreen:
        return ParameterScreen(
            name=name, body=name.split(".")[0], nominal=0.1, lower=0.0, upper=1.0, best=0.1,
            change_down=(0.0, 0.0), change_up=(0.0, 0.0), constrained=constrained, curve=(),
        )  # fmt: skip

    screens = {
        s.name: s
        for s in (
            screen("bowl.solref.dampratio", True),
            screen("bowl.solref.timeconst", False),
            screen("can.solref.dampratio", False),
            screen("can.solref.timeconst", False),
            screen("can.friction.sliding", True),
        )
    }
    assert _paired("bowl.solref.timeconst", screens, screens)
    assert not _paired("can.solref.timeconst", screens, screens)  # its damping ratio is not fitted either
    assert not _paired("can.friction.sliding", screens, screens)  # only time constants are paired
    assert not _paired("box.solref.timeconst", screens, screens)  # no damping ratio in the calibration


def test_robust_scale_keeps_one_badly_measured_trajectory_from_deciding(tmp_path: Path) -> None:
    """Five pushes of the box at 0.8-1.6 m/s sliding to rest at friction 0.4; one recording's start velocity is 2 m/s
    too fast (as a tracked start next to an impact can be). The mean loss lets that one pull friction far up to
    stop it in time; with `robust_scale` it weighs like a few trajectories, and the other four decide."""
    from grounder.calibration.fit import calibrate
    from grounder.calibration.options import CalibrateOptions
    from grounder.errors import GrounderError
    from grounder.interaction.options import CALIBRATE_SETTINGS

    model = mujoco.MjModel.from_xml_path(str(_scene(tmp_path / "truth", TRUE_FRICTION, TRUE_FRICTION)))
    pushes = [_simulated(model, {0: v_m_s}, 15, f"push_{i}") for i, v_m_s in enumerate((0.8, 1.0, 1.2, 1.4, 1.6))]
    bad_qvel = pushes[4].qvel.copy()
    bad_qvel[0, 0] += 2.0  # a badly measured start
    pushes[4] = Trajectory(time_s=pushes[4].time_s, qpos=pushes[4].qpos, qvel=bad_qvel, name=pushes[4].name)
    xml = _scene(tmp_path / "prior", 0.8, 0.8)
    budget = {"generations": 6, "popsize": 6, "local_iterations": 10, "validation_fraction": 0.0}

    def fitted(robust_scale: float | None) -> float:
        options = CalibrateOptions(params=("slider.friction.sliding",), robust_scale=robust_scale, **budget)
        return calibrate(xml, pushes, options=options).values["slider.friction.sliding"]

    assert fitted(None) > 2 * TRUE_FRICTION  # the mean loss: 1.13 measured
    assert fitted(CALIBRATE_SETTINGS["robust_scale"]) == pytest.approx(TRUE_FRICTION, rel=0.05)  # 0.408 measured
    with pytest.raises(GrounderError, match="robust_scale"):
        CalibrateOptions(robust_scale=0.0)
    with pytest.raises(GrounderError, match="raw mode only"):
        CalibrateOptions(robust_scale=0.5, mode="embedding")


def test_start_error_ranges_follow_the_slide_length_a_start_speed_error_implies(tmp_path: Path) -> None:
    """The slider is thrown at 1.5 m/s and slides to rest: its slide length v^2 / (2 mu g) trades friction against
    the start speed. With the start 10% too fast (slow), the friction that fits best is about 1.1^2 (0.9^2) times the
    true one; the report's range must span that, and no range is computed when the error is 0."""
    from grounder.errors import GrounderError
    from grounder.interaction.windows import start_error_ranges

    traj = _recorded(tmp_path)
    base = mujoco.MjModel.from_xml_path(str(_scene(tmp_path / "truth", TRUE_FRICTION, TRUE_FRICTION)))
    params = ["slider.friction.sliding"]
    at_truth = np.array([TRUE_FRICTION])
    options = replace(QUICK, start_speed_error_m_s=0.15, start_state_draws=0)  # the speed-only profile
    low, high = start_error_ranges(base, [traj], params, at_truth, options)["slider.friction.sliding"]
    assert low == pytest.approx(TRUE_FRICTION * 0.9**2, rel=0.08)
    assert high == pytest.approx(TRUE_FRICTION * 1.1**2, rel=0.08)
    small = start_error_ranges(base, [traj], params, at_truth, replace(options, start_speed_error_m_s=0.01))
    assert small["slider.friction.sliding"][0] >= TRUE_FRICTION * 0.95  # 0.7% of the speed: within a scan step
    assert small["slider.friction.sliding"][1] <= TRUE_FRICTION * 1.05
    assert start_error_ranges(base, [traj], params, at_truth, replace(QUICK, start_speed_error_m_s=0.0)) == {}
    with pytest.raises(GrounderError, match="start_speed_error_m_s"):
        InteractionOptions(start_speed_error_m_s=-0.1)


def test_start_error_ranges_also_move_the_whole_start_where_a_landing_turns_on_it(tmp_path: Path) -> None:
    """A ball dropped from rest bounces with damping ratio 0.2. Its start has no speed, so the speed-only profile
    cannot move it; but a start 5 mm too low (what a tracked depth can be) puts the best damping ratio 35% low. The
    default profile also draws whole-state start errors of tracking's size (`InteractionOptions.start_state_draws`):
    its range must reach past the screen's -20% step, so the value is flagged as resting on the starts."""
    from grounder.calibration.evaluator import Evaluator
    from grounder.calibration.parameters import resolve_parameters
    from grounder.errors import GrounderError
    from grounder.interaction.windows import start_error_ranges

    true_xml = tmp_path / "truth.xml"
    true_xml.write_text(DROPPED_BALL.format(timeconst=0.02, dampratio=0.2))
    model = mujoco.MjModel.from_xml_path(str(true_xml))
    traj = _simulated(model, {}, 24, "drop_00")  # 0.8 s at 30 fps: the drop and two bounces
    params = ["ball.solref.dampratio"]
    at_truth = np.array([0.2])
    low_start = traj.qpos.copy()
    low_start[0, 2] -= 0.005
    grid = 0.2 * np.geomspace(0.5, 2.0, 61)
    evaluator = Evaluator(
        model, resolve_parameters(model, params), [replace(traj, qpos=low_start)], rotation_weight=0.25
    )
    loss = evaluator.loss_of_values(grid[:, None])
    assert grid[int(np.argmin(loss.sum(axis=1)))] < 0.2 * 0.8  # 0.132 measured
    speed_only = start_error_ranges(model, [traj], params, at_truth, InteractionOptions(start_state_draws=0))
    assert speed_only == {"ball.solref.dampratio": [0.2, 0.2]}
    low, high = start_error_ranges(model, [traj], params, at_truth, InteractionOptions())["ball.solref.dampratio"]
    assert low < 0.2 * (1.0 - InteractionOptions().identify_relative_change) and high >= 0.2  # 0.156..0.210
    with pytest.raises(GrounderError, match="start_state_draws"):
        InteractionOptions(start_state_draws=-1)
    with pytest.raises(GrounderError, match="start_position_error_m"):
        InteractionOptions(start_position_error_m=-0.001)


def test_report_names_the_clips_frame_rate_where_a_value_rests_on_the_starts() -> None:
    """A value flagged as resting on the start states' accuracy gets the advice to film faster, with the clip's own
    frame rate; without such a value the advice is not given."""
    from grounder.interaction.report import markdown_report

    record = {"nominal": 0.45, "value": 0.25, "interval": [0.23, 0.27], "start_error_range": [0.2, 0.3]}
    payload = {
        "scan": "scan.mp4",
        "clip": "toss.mp4",
        "tracking": {"frames": 90, "fps": 30.0, "objects": {}, "segments": []},
        "start_speed_error_m_s": 0.03,
        "calibration": {"status": "calibrated", "parameters": {"bowl.friction.sliding": record}},
        "match_before": {},
    }
    assert "60 fps or more" not in markdown_report(payload)
    assert "best value with start speeds +-0.03 m/s" in markdown_report(payload)  # a report written before the draws
    payload["start_state_errors"] = {"draws": 6}
    assert "best value with starts off (speeds +-0.03 m/s; 6 random whole-state errors)" in markdown_report(payload)
    record["start_sensitive"] = True
    text = markdown_report(payload)
    assert "**rests on the start states' accuracy**" in text
    assert "60 fps or more" in text and "This clip has 30 frames per second." in text


def test_a_slow_interaction_clip_gets_the_advice_to_film_faster() -> None:
    from grounder.interaction.pipeline import frame_rate_advice

    advice = frame_rate_advice(30.0)
    assert advice is not None and "30 frames per second" in advice and "60 fps" in advice
    assert frame_rate_advice(59.94) is None and frame_rate_advice(None) is None


def test_videos_are_checked_before_any_work_and_only_those_read(tmp_path: Path) -> None:
    """An unreadable clip fails at once, before the grounding; the scan is checked only when it will be read (not
    when a grounded scene is reused)."""
    from grounder.interaction.pipeline import ground_with_interaction
    from reconstruction.errors import InputError

    clip = tmp_path / "toss.mp4"
    clip.write_text("not a video")
    scene = tmp_path / "grounded"
    scene.mkdir()
    with pytest.raises(InputError, match=r"missing_scan\.mp4"):
        ground_with_interaction(tmp_path / "missing_scan.mp4", clip, tmp_path / "a")
    with pytest.raises(InputError, match=r"toss\.mp4 is not a readable video"):
        ground_with_interaction(tmp_path / "missing_scan.mp4", clip, tmp_path / "b", grounded_scene=scene)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["grounded", "toss.mp4"]


def test_a_missing_marker_size_fails_before_the_grounding(tmp_path: Path) -> None:
    """Tracking needs the table marker's size; without it `ground --interaction` failed only after grounding the
    scan (about 3 minutes). Now it fails at once, saying which option to pass, and writes nothing."""
    from grounder.errors import GrounderError
    from grounder.interaction.pipeline import ground_with_interaction

    samples = Path(__file__).resolve().parents[3] / "samples"
    with pytest.raises(GrounderError, match=r"pass --aruco-size M \(--known-extent cannot stand in for it\)"):
        ground_with_interaction(samples / "tabletop" / "video.mp4", samples / "toss" / "video.mp4", tmp_path / "out")
    assert list(tmp_path.iterdir()) == []
