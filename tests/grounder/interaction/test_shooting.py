"""Multiple shooting over a whole run (`grounder.interaction.shooting`): the node states are fitted, so velocities
as far off as a tracked one at a landing do not move the contact values."""

from __future__ import annotations

import itertools
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest

from grounder.core.trajectory import Trajectory
from grounder.errors import GrounderError
from grounder.interaction.shooting import ShootingOptions, ShootingProblem, contact_profile, moving_runs
from tests.grounder.interaction.test_pipeline import DROPPED_BALL

TRUE = (0.4, 0.2)  # friction, damping ratio: DROPPED_BALL's friction and the damping ratio written below


def _thrown() -> tuple[mujoco.MjModel, Trajectory]:
    """A ball thrown down onto the table with backspin, 0.6 s at 30 fps: it bounces twice (damping ratio) and
    skids until its spin matches its speed (friction). Returns a scene with other contact values and the truth."""
    truth = mujoco.MjModel.from_xml_string(DROPPED_BALL.format(timeconst=0.02, dampratio=TRUE[1]))
    data = mujoco.MjData(truth)
    data.qvel[:] = [1.0, 0.0, -0.5, 0.0, -40.0, 0.0]
    qpos, qvel = [], []
    for frame in range(19):  # frame f at model step round(f / 30 / timestep), as rollouts read frames
        mujoco.mj_step(truth, data, round(frame / 30 / truth.opt.timestep) - round(data.time / truth.opt.timestep))
        qpos.append(data.qpos.copy())
        qvel.append(data.qvel.copy())
    model = mujoco.MjModel.from_xml_string(DROPPED_BALL.format(timeconst=0.02, dampratio=0.4))
    _set_contact(model, 0.8, 0.4)
    return model, Trajectory(time_s=np.arange(19) / 30.0, qpos=np.array(qpos), qvel=np.array(qvel), name="throw")


def _set_contact(model: mujoco.MjModel, friction: float, dampratio: float) -> None:
    model.geom_friction[1, 0] = friction
    model.geom_solref[1, 1] = dampratio


QUICK = ShootingOptions(
    friction_grid=(0.2, 0.4, 0.8), damping_grid=(0.1, 0.2, 0.4), continuation=(10.0, 1.0), max_evaluations=25
)


def test_shooting_finds_the_contact_values_from_tracked_velocities_far_off() -> None:
    """Positions with 0.3 mm of noise and every velocity 0.1 m/s and 1 rad/s off per axis (seeded): a window
    rolled out from such a start would land elsewhere; with the node states fitted the grid's best point is the
    truth, and its four neighbours (half and double each value) cost more than the resolution threshold above it."""
    model, truth = _thrown()
    rng = np.random.default_rng(3)
    qpos = truth.qpos.copy()
    qpos[:, :3] += rng.normal(scale=3e-4, size=(len(qpos), 3))
    qvel = truth.qvel + rng.normal(size=truth.qvel.shape) * np.array([0.1] * 3 + [1.0] * 3)
    tracked = replace(truth, qpos=qpos, qvel=qvel)
    runs = moving_runs([tracked], 30.0, QUICK)
    assert len(runs) == 1 and len(runs[0].time_s) == 19
    profile = contact_profile(model, _set_contact, runs, QUICK)
    assert (profile.friction, profile.damping_ratio) == TRUE
    assert profile.nodes == 6
    best = profile.cost.min()
    assert profile.cost[1, 0] > best + QUICK.resolution_cost and profile.cost[1, 2] > best + QUICK.resolution_cost
    assert profile.cost[0, 1] > best + QUICK.resolution_cost and profile.cost[2, 1] > best + QUICK.resolution_cost


def test_the_jacobian_from_two_batched_rollouts_is_the_dense_one() -> None:
    """Nodes two apart share no residual row, so moving every second node at once (24 perturbed node sets in one
    batched rollout) gives the same finite-difference Jacobian as moving one variable at a time."""
    from grounder.interaction.shooting import _STEP

    model, truth = _thrown()
    problem = ShootingProblem(model, [truth], QUICK)
    x = np.random.default_rng(0).normal(scale=0.5, size=problem.size)
    batched = problem._jacobian(x)
    base = problem._fun(x)
    dense = np.stack(
        [(problem._fun(x + _STEP * np.eye(problem.size)[c]) - base) / _STEP for c in range(problem.size)], 1
    )
    np.testing.assert_allclose(batched, dense, rtol=0, atol=1e-9)
    assert np.abs(dense).max() > 1.0  # not trivially zero


def test_the_fit_recovers_the_throw_and_is_exact_at_the_truth() -> None:
    """At the true values the true states cost nothing. From velocities 0.1 m/s off (per axis), the fit brings
    the throw's velocity (the first node, before the first bounce) back to within 1 cm/s and the cost down by 90%.
    Not to zero: around the bounces the nodes' vertical velocities stay 3-13 cm/s off (a local minimum, cost 31
    against 0; docs/interaction_history.md, "Multiple shooting")."""
    model, truth = _thrown()
    _set_contact(model, *TRUE)
    exact = ShootingProblem(model, [truth], ShootingOptions())
    assert np.sum(exact.residuals(np.zeros((1, len(exact.nodes), 12))) ** 2) < 1e-12
    off = replace(truth, qvel=truth.qvel + np.array([0.1, -0.1, 0.1, 0.0, 0.0, 0.0]))
    problem = ShootingProblem(model, [off], ShootingOptions())
    start_cost = float(np.sum(problem.residuals(np.zeros((1, len(problem.nodes), 12))) ** 2))
    cost, x = problem.fit(np.zeros(problem.size))
    assert cost < 0.1 * start_cost
    _, qvel = problem.node_states(x.reshape(-1, 12))
    assert np.abs(qvel[0, :3] - truth.qvel[0, :3]).max() < 0.01


def test_sampling_sweeps_get_below_where_least_squares_stops() -> None:
    """From velocities 0.1 m/s off, least squares from the tracked states stops at cost 31 (the bounces' vertical
    velocities stay centimetres per second off). Each sampling sweep replaces a node's state only by a candidate
    that lowers every residual depending on it, so the cost never rises; from the sweeps (four seeds, each finished
    both ways `fit_contact` finishes it) the fit gets below least squares alone, on the median and by 90% at best."""
    model, truth = _thrown()
    _set_contact(model, *TRUE)
    off = replace(truth, qvel=truth.qvel + np.array([0.1, -0.1, 0.1, 0.0, 0.0, 0.0]))
    problem = ShootingProblem(model, [off], ShootingOptions())
    plain, _ = problem.fit(np.zeros(problem.size))
    assert plain > 25.0
    x = np.zeros((len(problem.nodes), 12))
    history = [float(np.sum(problem.residuals(x[None]) ** 2))]
    rng = np.random.default_rng(0)
    for scale in (8.0, 2.0, 0.5):
        problem._sweep(x, np.array([0.5] * 3 + [0.3] * 3 + [scale] * 6), 64, rng)
        history.append(float(np.sum(problem.residuals(x[None]) ** 2)))
    assert all(b <= a for a, b in itertools.pairwise(history)) and history[-1] < 0.5 * history[0]
    costs = []
    for seed in range(4):
        sampled = problem.sampled_start(np.random.default_rng(seed))
        costs.append(min(problem.fit(sampled, continuation=(1.0,))[0], problem.fit(sampled)[0]))
    assert np.median(costs) < plain and min(costs) < 0.1 * plain


def test_bad_settings_and_scenes_are_refused() -> None:
    model, truth = _thrown()
    with pytest.raises(GrounderError, match="friction_grid"):
        ShootingOptions(friction_grid=(0.5, 0.2))
    with pytest.raises(GrounderError, match="node_frames"):
        ShootingOptions(node_frames=0)
    with pytest.raises(GrounderError, match="sampling_draws=1"):
        ShootingOptions(sampling_draws=1)
    with pytest.raises(GrounderError, match="sampling_scales"):
        ShootingOptions(sampling_scales=(4.0, 0.0))
    with pytest.raises(GrounderError, match="cross_fit_points"):
        ShootingOptions(cross_fit_points=-1)
    with pytest.raises(GrounderError, match="at least one run"):
        ShootingProblem(model, [], QUICK)
    two = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><freejoint/><geom size='.1'/></body><body pos='1 0 0'><freejoint/>"
        "<geom size='.1'/></body></worldbody></mujoco>"
    )
    with pytest.raises(GrounderError, match="one free body"):
        ShootingProblem(two, [truth], QUICK)
    still = replace(truth, qvel=np.zeros_like(truth.qvel))
    assert moving_runs([still], 30.0, QUICK) == []


def test_shooting_calibration_fits_the_moving_object_and_keeps_the_still_ones_prior(tmp_path: Path) -> None:
    """`InteractionOptions(calibration="shooting")` through the per-object calibration: the slider's friction
    (prior 0.8, recorded at 0.4) comes out within 3% and resolved (every point searched within the resolution cost
    lies within 20%); the still box shows no motion and keeps its prior; the values are written into the scene.
    The node fits start from the tracked states without sampling sweeps (`sampling_draws=0`): a third of the default's
    time on this clean slide (44 s against 132 s on 2 cores); the sweeps have their own test
    (`test_sampling_sweeps_get_below_where_least_squares_stops`)."""
    from grounder.interaction.options import InteractionOptions
    from grounder.interaction.per_object import calibrate_per_body
    from grounder.interaction.report import markdown_report
    from tests.grounder.interaction.test_pipeline import PARAMS, TRUE_FRICTION, _recorded, _scene

    traj = _recorded(tmp_path)
    xml = _scene(tmp_path / "prior", 0.8, 0.8)
    options = InteractionOptions(calibration="shooting", shooting=ShootingOptions(sampling_draws=0))
    entry, used = calibrate_per_body(xml, [traj], PARAMS, options, out=tmp_path / "calibrated")
    slider, still = entry["parameters"]["slider.friction.sliding"], entry["parameters"]["still.friction.sliding"]
    assert slider["constrained"] and slider["value"] == pytest.approx(TRUE_FRICTION, rel=0.03)
    assert slider["interval"][0] > TRUE_FRICTION / 1.2 and slider["interval"][1] < TRUE_FRICTION * 1.2
    assert entry["per_object"]["slider"]["status"].startswith("calibrated by multiple shooting")
    assert entry["per_object"]["slider"]["shooting"]["nodes"] >= 3
    assert not still["constrained"] and still["value"] == 0.8
    assert entry["per_object"]["still"]["status"].startswith("skipped")
    assert used and all(name.startswith("slider:") for name in used)
    calibrated = mujoco.MjModel.from_xml_path(str(tmp_path / "calibrated" / "scene.xml"))
    assert calibrated.geom_friction[calibrated.body("slider").geomadr[0], 0] == pytest.approx(slider["value"], rel=1e-5)
    shooting = entry["per_object"]["slider"]["shooting"]
    payload = {
        "scan": "scan.mp4",
        "clip": "toss.mp4",
        "tracking": {"frames": 24, "fps": 30.0, "objects": {}, "segments": []},
        "calibration": entry,
        "match_before": {},
    }
    assert f"- slider: multiple shooting over {shooting['nodes']} nodes (1 run(s))" in markdown_report(payload)


def test_an_unknown_calibration_method_is_refused() -> None:
    from grounder.interaction.options import InteractionOptions

    with pytest.raises(GrounderError, match="calibration='grid'"):
        InteractionOptions(calibration="grid")
    with pytest.raises(GrounderError, match="search_steps"):
        ShootingOptions(search_steps=())


def test_cli_calibration_option_rejects_bad_input(tmp_path: Path) -> None:
    """`ground --calibration` takes a known method and needs --interaction: one line, exit 2, nothing written."""
    from typer.testing import CliRunner

    from grounder.cli import app

    scan = Path(__file__).resolve().parents[3] / "samples" / "tabletop" / "video.mp4"
    clip = Path(__file__).resolve().parents[3] / "samples" / "toss" / "video.mp4"
    runner = CliRunner()
    out = tmp_path / "o"
    result = runner.invoke(app, ["ground", str(scan), "-o", str(out), "--calibration", "shooting"])
    assert result.exit_code == 2 and "needs --interaction" in result.output and not out.exists()
    result = runner.invoke(
        app, ["ground", str(scan), "-o", str(out), "--interaction", str(clip), "--calibration", "grid"]
    )
    assert result.exit_code == 2 and "'grid' is not a method" in result.output and not out.exists()


def test_the_search_judges_its_last_centre_even_when_a_check_moved_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """A cost whose minimum lies far above the start: with one move per step and no restart, a 20% check is lower
    and becomes the centre as the search ends; that centre's own checks are then evaluated (a KeyError before) and
    the value, still falling, is reported unresolved."""
    from grounder.calibration.parameters import resolve_parameters
    from grounder.interaction.shooting import fit_contact

    model, truth = _thrown()
    (friction,) = resolve_parameters(model, ["ball.friction.sliding"])
    target = friction.nominal * 1.2**2.5  # 2.5 checks above the start

    def fit(self: ShootingProblem, start: np.ndarray, continuation: object = None) -> tuple[float, np.ndarray]:
        return 100.0 * float(np.log(model.geom_friction[1, 0] / target) ** 2), np.zeros(self.size)

    monkeypatch.setattr(ShootingProblem, "fit", fit)
    options = ShootingOptions(
        search_steps=(2,), max_moves=1, max_restarts=0, contact_prior_log_sigma=100.0, sampling_draws=0
    )
    result = fit_contact(model, [friction], [truth], options)
    assert result.values[0] == pytest.approx(friction.nominal * 1.2 ** (10 / 8))  # moved 2, then checked +8
    assert result.resolved == (False,)
    assert any(v[0] == pytest.approx(friction.nominal * 1.2 ** (18 / 8)) for v, _ in result.evaluations)


def test_a_resolved_bounce_sets_both_solref_values_where_one_alone_is_not(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A clip that shows only bounces (the node fit's cost stood in for by the error of the contact's restitution):
    the search over time constant and damping ratio (from 0.02 s, 0.4) finds the bounce of the truth (0.02 s, 0.2)
    within 20% and calls it resolved, and both solref values are reported calibrated, one of them with the bounce
    where it is not resolved by itself, so the scene bounces as the fit did."""
    from grounder.interaction.per_object import shoot_body
    from grounder.sim.restitution import body_restitution

    _, truth = _thrown()
    e_true = body_restitution(
        mujoco.MjModel.from_xml_string(DROPPED_BALL.format(timeconst=0.02, dampratio=0.2)), "ball"
    )

    def fit(self: ShootingProblem, start: np.ndarray, continuation: object = None) -> tuple[float, np.ndarray]:
        return 300.0 * float(np.log(body_restitution(self.model, "ball") / e_true) ** 2), np.zeros(self.size)

    monkeypatch.setattr(ShootingProblem, "fit", fit)
    xml = tmp_path / "ball.xml"
    xml.write_text(DROPPED_BALL.format(timeconst=0.02, dampratio=0.4))
    options = ShootingOptions(contact_prior_log_sigma=100.0, sampling_draws=0)
    params = ["ball.solref.timeconst", "ball.solref.dampratio"]
    entry, runs = shoot_body(xml, [truth], params, options)
    bounce = entry["restitution"]
    assert runs and bounce["resolved"] and bounce["value"] == pytest.approx(e_true, rel=0.2)
    assert e_true / 1.2 < bounce["range"][0] <= bounce["range"][1] < e_true * 1.2
    records = entry["parameters"]
    assert all(records[name]["constrained"] for name in params)
    assert entry["status"].startswith("calibrated by multiple shooting") and "prior kept" not in entry["status"]
    best = mujoco.MjModel.from_xml_string(DROPPED_BALL.format(timeconst=0.02, dampratio=0.4))
    best.geom_solref[1] = [records["ball.solref.timeconst"]["value"], records["ball.solref.dampratio"]["value"]]
    assert body_restitution(best, "ball") == pytest.approx(bounce["value"])


def test_the_search_keeps_to_contacts_whose_bounce_the_time_step_resolves(monkeypatch: pytest.MonkeyPatch) -> None:
    """From a prior as stiff as the grounded bowl's (0.0087 s, 0.27: its bounce varies by 60% with where in a 2 ms
    step the impact falls), the search first softens the start and never evaluates a contact whose bounce varies by
    more than `max_bounce_spread`; it still finds the bounce of the truth (0.02 s, 0.3) within 20%. A node fit could
    give each landing of such a contact its own bounce by moving a node a fraction of a step."""
    from grounder.calibration.parameters import resolve_parameters
    from grounder.interaction.shooting import fit_contact
    from grounder.sim.restitution import body_restitution, body_restitution_over_phases, bounce_spread

    _, truth = _thrown()
    e_true = body_restitution(
        mujoco.MjModel.from_xml_string(DROPPED_BALL.format(timeconst=0.02, dampratio=0.3)), "ball"
    )
    model = mujoco.MjModel.from_xml_string(DROPPED_BALL.format(timeconst=0.0087, dampratio=0.27))
    assert bounce_spread(body_restitution_over_phases(model, "ball")) > 0.5
    spreads = []

    def fit(self: ShootingProblem, start: np.ndarray, continuation: object = None) -> tuple[float, np.ndarray]:
        spreads.append(bounce_spread(body_restitution_over_phases(self.model, "ball")))
        return 300.0 * float(np.log(body_restitution(self.model, "ball") / e_true) ** 2), np.zeros(self.size)

    monkeypatch.setattr(ShootingProblem, "fit", fit)
    contact = resolve_parameters(model, ["ball.solref.timeconst", "ball.solref.dampratio"])
    options = ShootingOptions(contact_prior_log_sigma=100.0, sampling_draws=0)
    result = fit_contact(model, contact, [truth], options)
    assert spreads and max(spreads) <= 0.5
    assert result.evaluations[0][0][0] > 0.0087 * 1.04  # the start was softened
    assert result.restitution is not None and result.restitution.value == pytest.approx(e_true, rel=0.2)
    with pytest.raises(GrounderError, match="max_bounce_spread"):
        ShootingOptions(max_bounce_spread=0.0)


def test_cross_fits_keep_a_lucky_fit_from_resolving_a_wrong_friction() -> None:
    """The thrown ball's friction searched alone (damping ratio at the truth) with velocities 0.1 m/s off and
    least squares straight from them: each point's cost is an upper bound that depends on where its fit started.
    Fitted only from its own and its nearest neighbour's starts, one point's fit landed lower than the rest and
    friction came out +27% and resolved. With every point also fitted from the cheapest points' node states
    (`cross_fit_points`) every cost shared with that search is as low or lower, the best is no worse, and the
    costs from 0.46 to 0.8 lie within 1 of each other: the run does not pin the friction, and no wrong value is
    called resolved."""
    from grounder.calibration.parameters import resolve_parameters
    from grounder.interaction.shooting import fit_contact

    def search(cross_fit_points: int) -> tuple[object, dict[float, float]]:
        model, truth = _thrown()
        model.geom_solref[1, 1] = TRUE[1]
        off = replace(truth, qvel=truth.qvel + np.array([0.1, -0.1, 0.1, 0.0, 0.0, 0.0]))
        options = ShootingOptions(
            sampling_draws=0, continuation=(1.0,), max_evaluations=15, search_steps=(16, 4),
            cross_fit_points=cross_fit_points,
        )  # fmt: skip
        result = fit_contact(model, resolve_parameters(model, ["ball.friction.sliding"]), [off], options)
        return result, {round(values[0], 6): cost for values, cost in result.evaluations}

    plain, plain_costs = search(0)
    assert plain.resolved == (True,) and plain.values[0] > TRUE[0] * 1.2  # the lucky point wins
    crossed, crossed_costs = search(1)
    shared = set(plain_costs) & set(crossed_costs)
    assert len(shared) >= 5 and all(crossed_costs[f] <= plain_costs[f] + 1e-9 for f in shared)
    assert crossed.cost <= plain.cost + 1e-9
    assert sum(crossed_costs[f] < plain_costs[f] - 3.0 for f in shared) >= 3
    assert not crossed.resolved[0] or abs(crossed.values[0] / TRUE[0] - 1.0) < 0.2


def test_a_restarted_search_can_move_down_to_the_optimum(monkeypatch: pytest.MonkeyPatch) -> None:
    """A cost whose minimum lies one check (+20%, 8 lattice steps) above the start, searched with one move of 2 steps
    per round: the first round moves to +2, and its +8 check (+10) costs less and becomes the centre; the restart must
    move DOWN to +8. The search used to keep its lattice's lower bound and its best point in one attribute, so after a
    round every point below the best one in any value was out of bounds (cost inf): the restart could only move up,
    and stopped at +10. Points below the centre but within the bounds now get a real cost."""
    from grounder.calibration.parameters import resolve_parameters
    from grounder.interaction.shooting import _compass_search, _contact_fit, _ContactSearch, _first_centre

    model, truth = _thrown()
    (friction,) = resolve_parameters(model, ["ball.friction.sliding"])
    unit = np.log(1.2) / 8  # one lattice step

    def fit(self: ShootingProblem, start: np.ndarray, continuation: object = None) -> tuple[float, np.ndarray]:
        key = np.log(model.geom_friction[1, 0] / friction.nominal) / unit
        return float((key - 8.0) ** 2), np.zeros(self.size)

    monkeypatch.setattr(ShootingProblem, "fit", fit)
    options = ShootingOptions(
        search_steps=(2,), max_moves=1, max_restarts=1, contact_prior_log_sigma=100.0, sampling_draws=0
    )
    search = _ContactSearch(model, [friction], [truth], options, None, None)
    centre, best_cost = _compass_search(search, _first_centre(search))
    assert centre == (8,) and best_cost == pytest.approx(0.0, abs=1e-4)
    assert (10,) in search.evaluated  # the first round's check, where the restart started
    assert search.evaluate((-3,)) == pytest.approx(121.0, rel=1e-6)  # below the centre, within bounds: a real cost
    assert search.evaluate((-200,)) == float("inf")  # below the bound
    result = _contact_fit(search, centre, best_cost)
    assert result.values[0] == pytest.approx(friction.nominal * 1.2)
