"""Contact values from impacts between free flights (`grounder.interaction.impacts`): a box thrown onto a table
with known friction and restitution, tracked with noise, must give those values back where an impact shows them,
and leave a value unresolved where it does not."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest

from grounder.calibration.parameters import resolve_parameters
from grounder.core.trajectory import Trajectory
from grounder.errors import GrounderError
from grounder.interaction.flights import find_flights, find_impacts, spin_at_end
from grounder.interaction.impacts import fit_impacts, impacts_figure
from grounder.interaction.options import ImpactOptions
from grounder.sim.restitution import contact_solref, simulated_restitution
from image2sim_common.rotations import quat_mul, quat_to_mat, rotvec_to_quat

CONTACT = ("box.friction.sliding", "box.solref.timeconst", "box.solref.dampratio")


def _scene(friction: float, restitution: float, timeconst_s: float = 0.02) -> mujoco.MjSpec:
    """A 8 x 6 x 4 cm box over a table, in the physics settings of every exported scene, bouncing at `restitution`
    (1 m/s) with `timeconst_s`."""
    from scene_export._mjcf import ExportOptions

    spec = mujoco.MjSpec()
    ExportOptions().set_physics(spec.option)
    spec.worldbody.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=[2, 2, 0.02], pos=[0, 0, -0.02])
    body = spec.worldbody.add_body(name="box", pos=[0, 0, 0.2])
    body.add_freejoint()
    solref = contact_solref(restitution, timeconst_s)
    body.add_geom(
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[0.04, 0.03, 0.02],
        density=400,
        friction=[friction, 0.005, 0.0001],
        solref=list(solref),
        priority=1,
    )
    return spec


def _throw(
    model: mujoco.MjModel, velocity: tuple[float, ...], spin: tuple[float, ...], frames: int = 36, fps: float = 30.0
) -> tuple[Trajectory, np.ndarray]:
    """The box thrown from 18 cm, sampled at `fps` (frame f at model step round(f / fps / timestep), as a clip
    rendered from MuJoCo shows it), and the times (s) at which it touches the table."""
    data = mujoco.MjData(model)
    data.qpos[2] = 0.18
    data.qpos[3:7] = np.array([0.96, 0.2, 0.1, 0.17]) / np.linalg.norm([0.96, 0.2, 0.1, 0.17])
    data.qvel[:] = [*velocity, *spin]
    qpos, qvel, touching = [], [], []
    for frame in range(frames):
        target = round(frame / fps / model.opt.timestep)
        while round(data.time / model.opt.timestep) < target:
            mujoco.mj_step(model, data)
            if data.ncon:
                touching.append(data.time)
        qpos.append(data.qpos.copy())
        qvel.append(data.qvel.copy())
    traj = Trajectory(time_s=np.arange(frames) / fps, qpos=np.array(qpos), qvel=np.array(qvel), name="throw")
    return traj, np.array(touching)


def _tracked(traj: Trajectory, seed: int = 0) -> Trajectory:
    """Tracking noise: 0.5 mm per axis on positions, 0.3 deg per axis on orientations (seeded)."""
    rng = np.random.default_rng(seed)
    qpos = traj.qpos.copy()
    qpos[:, :3] += rng.normal(scale=5e-4, size=(len(qpos), 3))
    qpos[:, 3:7] = quat_mul(rotvec_to_quat(rng.normal(scale=np.radians(0.3), size=(len(qpos), 3))), qpos[:, 3:7])
    return Trajectory(time_s=traj.time_s, qpos=qpos, qvel=traj.qvel, name=traj.name)


def _prior() -> mujoco.MjModel:
    """The scene as grounded: other contact values than the throw's."""
    return _scene(0.9, 0.2, 0.03).compile()


def test_a_sliding_landing_between_two_flights_gives_friction_and_restitution_back() -> None:
    """Thrown fast and low with friction 0.3 and restitution 0.6, the box slides through its first landing and flies
    again: compared with the flight after it (`compare="flight"`), both values come back resolved within 10%, each
    range holding the truth, and the chi-square is what the noise explains."""
    truth = _scene(0.3, 0.6).compile()
    traj, _ = _throw(truth, (1.5, 0.3, -0.8), (1.0, -3.0, 0.5))
    model = _prior()
    options = ImpactOptions(compare="flight")
    impacts = find_impacts(model, "box", [_tracked(traj)], options)
    assert impacts
    fit = fit_impacts(model, resolve_parameters(model, list(CONTACT)), impacts, options)
    assert fit.friction_resolved and fit.restitution_resolved
    assert fit.friction == pytest.approx(0.3, rel=0.1)
    assert fit.restitution == pytest.approx(0.6, rel=0.1)
    assert fit.friction_range[0] <= 0.3 <= fit.friction_range[1]
    assert fit.restitution_range[0] <= 0.6 <= fit.restitution_range[1]
    assert fit.chi2 < 3.0 * fit.dof  # the noise model fits: no large misfit hidden in a scaled threshold


def test_the_frames_after_a_sticking_landing_resolve_its_friction() -> None:
    """A tumbling box landing with friction 0.5 does not slip at its contacts: any friction above what it needs
    explains the next flight's centre of mass as well (`compare="flight"` without the orientations: unresolved, the
    range reaching the grid's top and holding the truth). The frames after the landing (`compare="frames"`, the
    default: 0.3 s of bouncing and sliding, centre of mass and orientation) do resolve it, within 10%; the
    restitution comes back within 10% either way."""
    truth = _scene(0.5, 0.5).compile()
    traj, _ = _throw(truth, (0.9, 0.1, -0.3), (2.0, -6.0, 1.0))
    model = _prior()
    contact = resolve_parameters(model, list(CONTACT))
    flight = ImpactOptions(compare="flight", compare_rotation=False)
    fit = fit_impacts(model, contact, find_impacts(model, "box", [_tracked(traj)], flight), flight)
    assert not fit.friction_resolved
    assert fit.friction_range[1] == flight.friction_grid[-1] and fit.friction_range[0] <= 0.5
    assert fit.restitution_resolved and fit.restitution == pytest.approx(0.5, rel=0.1)
    frames = ImpactOptions()
    assert frames.compare == "frames"
    fit = fit_impacts(model, contact, find_impacts(model, "box", [_tracked(traj)], frames), frames)
    assert fit.friction_resolved and fit.friction == pytest.approx(0.5, rel=0.1)
    assert fit.restitution_resolved and fit.restitution == pytest.approx(0.5, rel=0.1)


def test_flights_bracket_the_true_contacts() -> None:
    """Every impact found lies between two flights with the box's true contacts between them, and no flight holds
    a contact: the clearance test and the cut of a run of clear frames at a hidden bounce find the landings."""
    truth = _scene(0.5, 0.5).compile()
    traj, touching = _throw(truth, (0.9, 0.1, -0.3), (2.0, -6.0, 1.0))
    options = ImpactOptions(compare="flight")
    flights = find_flights(truth, "box", [traj], options)[0]
    assert len(flights) >= 3
    for flight in flights:
        inside = (touching >= flight.time_s[0] - 1e-9) & (touching <= flight.time_s[-1] + 1e-9)
        assert not inside.any()
    impacts = find_impacts(truth, "box", [traj], options)
    assert len(impacts) >= 2
    for impact in impacts:
        between = (touching > impact.before.ref_s) & (touching < impact.after_s[0])
        assert between.any()


def test_the_spin_before_a_landing_follows_a_tumbling_body() -> None:
    """After its first bounce the box tumbles at about 18 rad/s and its spin axis turns by some 10 degrees a frame
    at 30 fps: a constant spin fitted to three frames is rad/s off; the torque-free fit is within 1% (0.2 rad/s:
    MuJoCo's 2 ms steps, run backwards, are not exactly its steps forwards)."""
    truth = _scene(0.5, 0.5).compile()
    traj, _ = _throw(truth, (0.9, 0.1, -0.3), (2.0, -6.0, 1.0))
    flight = find_flights(truth, "box", [traj], ImpactOptions())[0][1]
    last = int(flight.rows[-1])
    true_spin = quat_to_mat(traj.qpos[last, 3:7]) @ traj.qvel[last, 3:]
    assert np.linalg.norm(true_spin) > 10.0
    quat, spin, _, _ = spin_at_end(truth, "box", traj.qpos[flight.rows, 3:7], flight.time_s)
    fitted_error = np.linalg.norm(spin - true_spin)
    assert fitted_error < 0.2
    assert abs(abs(float(quat @ traj.qpos[last, 3:7])) - 1.0) < 1e-6
    # The constant-spin guess it starts from: the mean rate over the frames.
    first = int(flight.rows[0])
    rel = quat_mul(traj.qpos[last, 3:7], np.array([1.0, -1.0, -1.0, -1.0]) * traj.qpos[first, 3:7])
    from image2sim_common.rotations import quat_to_rotvec

    constant = quat_to_rotvec(rel) / (flight.time_s[-1] - flight.time_s[0])
    assert np.linalg.norm(constant - true_spin) > max(0.5, 5.0 * fitted_error)


def test_ground_interaction_calibrates_from_impacts(tmp_path: Path) -> None:
    """The default calibration (impacts, `compare="frames"`) through the per-object calibration: the sliding throw's
    friction (within 10%) and bounce (within the issue's 20%: over 0.3 s of bouncing and sliding, with this noise
    seed, the best restitution is -17%; with seeds 1 and 2 it is exact, and compared with the next flight alone it
    is within 10%, above) are calibrated, the time constant is set with the bounce, and the report names the impacts
    and the restitution."""
    from grounder.interaction.options import InteractionOptions, default_params
    from grounder.interaction.per_object import calibrate_per_body

    truth = _scene(0.3, 0.6).compile()
    traj, _ = _throw(truth, (1.5, 0.3, -0.8), (1.0, -3.0, 0.5))
    scene_xml = tmp_path / "scene.xml"
    scene_xml.write_text(_scene(0.9, 0.2, 0.03).to_xml())
    entry, used = calibrate_per_body(
        scene_xml,
        [],
        default_params(["box"]),
        InteractionOptions(),
        object_tracks={"box": [_tracked(traj)]},
    )
    records = entry["parameters"]
    assert records["box.friction.sliding"]["constrained"]
    assert records["box.friction.sliding"]["value"] == pytest.approx(0.3, rel=0.1)
    assert records["box.solref.dampratio"]["constrained"]
    assert records["box.solref.timeconst"].get("set_with_restitution")
    # The written pair (time constant, damping ratio) bounces as the box was thrown with (a drop test).
    prior = _prior()
    solref = (records["box.solref.timeconst"]["value"], records["box.solref.dampratio"]["value"])
    assert simulated_restitution(solref, prior.geom_solimp[1], prior.opt) == pytest.approx(0.6, rel=0.2)
    bounce = entry["per_object"]["box"]["restitution"]
    assert bounce["resolved"] and bounce["value"] == pytest.approx(0.6, rel=0.2)
    # The stability copies that confirmed the friction are in the report, and in its words.
    from grounder.interaction.report import _copies_text

    hits = entry["per_object"]["box"]["impacts"]
    copies = hits["stability_copies"]
    assert len(copies) == 2 and hits["stability_um"] == pytest.approx(0.1)
    friction = records["box.friction.sliding"]["value"]
    assert all(c["friction_resolved"] and c["friction"] == pytest.approx(friction, rel=0.2) for c in copies)
    text = _copies_text(copies, hits["stability_um"])
    assert "moved by 0.1 um" in text and text.count(f"{copies[0]['friction']:.3g}") >= 1
    assert used and all(name.startswith("box:throw@") for name in used)
    assert entry["per_object"]["box"]["impacts"]["names"]
    # The picture the report links: one row per object with impacts, nothing for none.
    import cv2

    picture = impacts_figure(entry["per_object"], tmp_path / "impacts.png")
    assert picture is not None and cv2.imread(str(picture)).shape[0] > 200
    assert impacts_figure({"box": {"status": "skipped"}}, tmp_path / "none.png") is None
    assert not (tmp_path / "none.png").exists()


def test_no_flights_no_impacts_and_bad_options_say_what_to_do() -> None:
    """A box resting on the table has no flights, so `fit_impacts` is refused with what to use instead; options
    out of range are refused with the value and what was expected."""
    model = _prior()
    data = mujoco.MjData(model)
    data.qpos[2] = 0.02
    rest = Trajectory(
        time_s=np.arange(20) / 30.0, qpos=np.tile(data.qpos, (20, 1)), qvel=np.zeros((20, 6)), name="rest"
    )
    assert find_impacts(model, "box", [rest], ImpactOptions()) == []
    with pytest.raises(GrounderError, match="windowed calibration"):
        fit_impacts(model, resolve_parameters(model, list(CONTACT)), [], ImpactOptions())
    with pytest.raises(GrounderError, match="clearance_m"):
        ImpactOptions(clearance_m=0.0)
    with pytest.raises(GrounderError, match="restitution_grid"):
        ImpactOptions(restitution_grid=(0.5, 1.2))
    with pytest.raises(GrounderError, match="min_flight_frames"):
        ImpactOptions(min_flight_frames=1)


VIEW_POINT_M = np.array([0.0, -0.6, 0.45])


def _drifting(traj: Trajectory, seed: int, drift_m: float, drift_time_s: float) -> Trajectory:
    """Tracking whose depth error drifts, as a tracker's does: an error along the viewing ray from `VIEW_POINT_M`
    that changes slowly (a Gaussian process, `drift_m`, correlation time `drift_time_s`), plus 0.3 mm and 0.3 deg of
    frame-to-frame noise per axis (seeded)."""
    rng = np.random.default_rng(seed)
    qpos = traj.qpos.copy()
    lag = traj.time_s[:, None] - traj.time_s[None, :]
    cov = drift_m**2 * np.exp(-0.5 * (lag / drift_time_s) ** 2) + 1e-12 * np.eye(len(lag))
    depth = rng.multivariate_normal(np.zeros(len(lag)), cov, method="cholesky")  # SVD's draws vary by CPU
    rays = qpos[:, :3] - VIEW_POINT_M
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    qpos[:, :3] += depth[:, None] * rays + rng.normal(scale=3e-4, size=(len(qpos), 3))
    qpos[:, 3:7] = quat_mul(rotvec_to_quat(rng.normal(scale=np.radians(0.3), size=(len(qpos), 3))), qpos[:, 3:7])
    return Trajectory(time_s=traj.time_s, qpos=qpos, qvel=traj.qvel, name=traj.name)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_drifting_depth_error_leaves_the_values_within_10_percent(seed: int) -> None:
    """Tracked with a depth error that drifts by 6 mm over 0.3 s (which no flight's residuals show; the scanned can of
    `samples/toss` was 4.4-9.4 mm off for 0.45 s), more than the default drift model's 4 mm, the sliding throw's
    friction and restitution still come back within 10%, compared in position and orientation. (Not for every draw:
    of seeds 2-7, seed 2 gives a restitution of 0.525, -12.5%; the other five are within 10%.)"""
    truth = _scene(0.3, 0.6).compile()
    traj, _ = _throw(truth, (1.5, 0.3, -0.8), (1.0, -3.0, 0.5))
    model = _prior()
    options = ImpactOptions()
    assert options.compare_rotation and options.drift_sigma_m > 0
    impacts = find_impacts(model, "box", [_drifting(traj, seed, 6e-3, 0.3)], options, VIEW_POINT_M)
    # `fit_impacts` alone: the stability check (`stable_fit`, tested below) refits copies and changes no best value.
    fit = fit_impacts(model, resolve_parameters(model, list(CONTACT)), impacts, options)
    assert fit.dof == sum(6 * len(i.after_s) for i in impacts) - 3  # centre of mass and orientation per frame
    assert fit.friction == pytest.approx(0.3, rel=0.1)
    assert fit.restitution == pytest.approx(0.6, rel=0.1)


def test_a_constant_depth_error_moves_the_start_and_the_frames_together() -> None:
    """The drift model's point: a depth error shared by the flight and the frames after it shifts the fitted start
    and the compared frames alike (seen from afar, every ray is the same), so ballistically it leaves the residuals
    as they were, while each frame itself moves by it."""
    truth = _scene(0.3, 0.6).compile()
    traj, _ = _throw(truth, (1.5, 0.3, -0.8), (1.0, -3.0, 0.5))
    far = np.array([0.0, -300.0, 200.0])
    options = ImpactOptions(compare="flight", drift_rotation_deg=0.0)
    impact = find_impacts(truth, "box", [traj], options, far)[0]
    count = len(impact.drift_cov)
    assert impact.drift_start.shape == (12, count) and impact.drift_after.shape == (6 * len(impact.after_s), count)
    shared = np.ones(count)  # 1 m along the ray at every frame
    lift = np.kron(np.stack([np.ones(len(impact.after_s)), impact.after_s - impact.before.ref_s], 1), np.eye(3))
    moved = lift @ impact.drift_start[:6] @ shared - impact.drift_after[: 3 * len(impact.after_s)] @ shared
    assert np.abs(moved).max() < 1e-3  # mm per metre of shared depth error
    assert np.abs(impact.drift_after @ shared).max() > 0.5  # while each frame itself moves by it


def test_a_value_stays_resolved_only_where_copies_of_the_tracks_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    """The stability check (`stable_fit`): on the sliding throw, copies of the tracks moved by 0.1 um give the same
    values, so both stay resolved (within 10%); copies moved by 2 cm (far past any tracking error, standing in for
    a chaotic landing) disagree, and the values they do not confirm lose their resolved flag. Each copy draws its
    own start states (another seed): the copies shared the first fit's draws, so a call resting on one draw of them
    (the can of `samples/toss`, start seeds 0-3: +29%, +29%, unresolved, +5%) passed the check."""
    import grounder.interaction.impacts as impacts_module
    from grounder.interaction.impacts import stable_fit

    seeds: list[int] = []
    real_fit = impacts_module.fit_impacts

    def spy(model, contact, impacts, options, **kwargs):  # type: ignore[no-untyped-def]
        seeds.append(options.start_seed)
        return real_fit(model, contact, impacts, options, **kwargs)

    monkeypatch.setattr(impacts_module, "fit_impacts", spy)

    truth = _scene(0.3, 0.6).compile()
    traj, _ = _throw(truth, (1.5, 0.3, -0.8), (1.0, -3.0, 0.5))
    model = _prior()
    contact = resolve_parameters(model, list(CONTACT))
    tracked = [_tracked(traj)]
    options = ImpactOptions(compare="flight")
    assert options.stability_copies == 2
    impacts = find_impacts(model, "box", tracked, options)
    fit = stable_fit(model, contact, tracked, impacts, options)
    assert len(fit.copies) == 2 and seeds == [0, 1, 2]  # the fit, then each copy with draws of its own
    assert fit.friction_resolved and fit.friction == pytest.approx(0.3, rel=0.1)
    assert fit.restitution_resolved and fit.restitution == pytest.approx(0.6, rel=0.1)
    shaken = stable_fit(model, contact, tracked, impacts, replace(options, stability_m=0.02))
    assert (shaken.friction, shaken.restitution) == (fit.friction, fit.restitution)  # the first fit is unchanged
    confirmed = [
        all(c[2 + k] and abs(c[k] / best - 1.0) <= 0.2 for c in shaken.copies)
        for k, best in enumerate((fit.friction, fit.restitution))
    ]
    assert not all(confirmed)
    assert shaken.friction_resolved == confirmed[0] and shaken.restitution_resolved == confirmed[1]


def test_start_draws_are_the_cholesky_factors_and_keep_a_singular_covariance() -> None:
    """The start states are drawn by a Cholesky factor, unique, where NumPy's `multivariate_normal` factors by an SVD
    whose vectors' signs depend on the CPU's LAPACK: one seed gave other draws, and a restitution of 0.525 instead of
    0.6, on an AMD EPYC. A drift's squared-exponential covariance is singular (plain Cholesky fails on it); the draws
    still have its covariance, and a matrix a rounding error below semi-definite is drawn from too."""
    from grounder.interaction.impacts import _gaussian_draws

    time_s = np.arange(12) / 30.0
    cov = 0.004**2 * np.exp(-0.5 * ((time_s[:, None] - time_s[None, :]) / 0.3) ** 2)
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.cholesky(cov)
    draws = _gaussian_draws(np.random.default_rng(0), cov, 200_000)
    assert np.abs(np.cov(draws, rowvar=False) - cov).max() < 0.02 * cov.max()
    expected = (
        np.random.default_rng(0).standard_normal((3, 12)) @ np.linalg.cholesky(cov + 1e-12 * cov.max() * np.eye(12)).T
    )
    assert np.array_equal(_gaussian_draws(np.random.default_rng(0), cov, 3), expected)
    below = cov - 1e-9 * cov.max() * np.eye(12)  # eigenvalues down to -1e-9 of the largest variance
    draws = _gaussian_draws(np.random.default_rng(1), below, 200_000)
    assert np.isfinite(draws).all() and np.abs(np.cov(draws, rowvar=False) - cov).max() < 0.02 * cov.max()
