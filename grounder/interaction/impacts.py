"""Contact values from the contacts after free flights: `ground --interaction` (`--calibration impacts`, the
default).

The windowed calibration (`grounder.interaction.windows`) rolls 0.3 s windows out from tracked start states, and a
landing turns on that state: a velocity from a few tracked frames, at 30 fps, is tens of mm/s off, and the friction and
bounce that explain a window move with it. A free flight pins the state far better: between contacts a thrown object
moves on a parabola whose curvature is known (gravity), so the flight's centre-of-mass state comes from a least-squares
line fit over all of its frames, with a covariance.

Per object (in a scene of its own with the table, `grounder.interaction.per_object.single_body_scene`):

1. **Flights** (`find_flights`): frames at which the object's collision geometry is more than `clearance_m` from
   every static geom (`mujoco.mj_geomDistance`) are clear. Runs of clear frames are fitted as free flights of the
   centre of mass (a line per axis plus the gravity term); a run whose fit improves by more than the BIC penalty when
   cut in two is cut, but only between two frames near enough to the table to touch it in between (a bounce between
   two clear frames at 30 fps). A single frame more than `outlier_sigmas` off the fit is dropped.
2. **Impacts** (`find_impacts`): a flight followed by a tracked frame within `max_gap_s` ends in a contact. Its
   start state is the flight's fitted state at its last frame: centre of mass position and velocity from the
   parabola, orientation and spin from a torque-free rigid-body fit of its tracked orientations (`spin_at_end`),
   the contact still ahead; with a covariance from those fits and the tracking noise, which is estimated from the
   object's own flights across and along the camera's viewing rays (`tracking_noise`).
3. **Grid** (`fit_impacts`): for each sliding friction x restitution x time constant of the grid, each impact is
   simulated (one batched `mujoco.rollout` per chunk of points) from its start state over the tracked frames after
   it (`compare` "frames", the default: for `max_post_s`, in flight, bouncing or sliding; "flight": only the next
   flight's, where one follows), and the simulated centre of mass and orientation are compared with the tracked
   ones (`compare_rotation`). The residuals' covariance is the frames' tracking noise, plus a tracking error that
   drifts slowly (depth and orientation, `drift_sigma_m`, `drift_rotation_deg`: it moves the flight's fitted start
   and the compared frames together), plus the start's errors carried through the contact (the spread of 64
   rollouts from starts drawn from the start's covariance and the drift, at the best point, refined twice). A
   tumbling landing on convex hulls can be chaotic: `benchmarks/impacts_stability.py` measures how far a fit moves
   under sub-micrometre changes of the tracked poses (docs/results/interaction.md). The restitution is the bounce
   at 1 m/s (`grounder.sim.restitution.contact_solref` gives the damping ratio for it at each time constant), so the
   grid's axes are the quantities the clip shows, not the knobs MuJoCo trades against each other.
4. **Resolution** (`profile_range`): a value's range is the span of grid points within a chi-square increase of
   `delta_chi2` (scaled by the misfit per degree of freedom where that exceeds 1) of the best, widened halfway to
   the next grid values; it is resolved where that range lies within `resolution_fraction` of the best value and
   inside the grid. A landing that only sticks bounds friction from below: its range reaches the grid's top.

An object that never flies (pushed, only sliding) has no impacts: `grounder.interaction.windows` calibrates it on
windows. Described in docs/cli.md ("Contacts after free flights"); figures in docs/results/interaction.md.

Steps 1 and 2 are in `grounder.interaction.flights`; this module holds steps 3 and 4 (`fit_impacts`, `stable_fit`)
and `impacts_body`, which runs them all for one object.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, cast

import mujoco
import numpy as np
import scipy.linalg

from grounder.calibration.parameters import Parameter, collision_geoms, contact_priority
from grounder.core.trajectory import Trajectory
from grounder.errors import GrounderError
from grounder.interaction.flights import Impact, body_com_m, find_impacts, free_state
from grounder.interaction.options import ImpactOptions
from grounder.interaction.record import fit_status, fitted_record, prior_record
from grounder.sim.restitution import REFERENCE_IMPACT_SPEED_M_S, contact_solref
from grounder.sim.rollout import simulate
from image2sim_common.progress import ProgressFn
from image2sim_common.rotations import quat_conj, quat_mul, quat_to_mat, quat_to_rotvec, rotvec_to_quat

_CONTACT_FIELDS = ("friction.sliding", "solref.timeconst", "solref.dampratio")
# Grid points simulated per batched rollout call (memory: about 0.2 MB per point and impact).
_CHUNK = 192


@dataclass(frozen=True, kw_only=True)
class ImpactFit:
    """`fit_impacts`' result for one object.

    Attributes:
        friction, restitution, timeconst_s: the best grid point (restitution at 1 m/s).
        dampratio: the damping ratio that bounces at `restitution` with `timeconst_s` (`contact_solref`).
        friction_range, restitution_range, dampratio_range: the span of each over the grid points within the chi-square
            threshold of the best.
        friction_resolved, restitution_resolved: whether that range lies within `resolution_fraction` of the best value
            and away from the grid's ends.
        chi2, dof: the best point's chi-square and its degrees of freedom (residuals minus the 3 values fitted).
        threshold: the chi-square increase that bounded the ranges.
        impacts: the impacts' names.
        chi2_per_impact: the best point's chi-square per impact.
        noise_m: the tracking noise across and along the viewing rays the fit assumed (`ImpactOptions.estimate_noise`).
        profile: (restitutions, frictions) the lowest chi-square over the time constants at each grid point, minus
            the best (the picture's heat map).
        traces: per impact (name, times, tracked centre-of-mass height, simulated height at the best point), m.
        copies: the fits of the stability copies (`ImpactOptions.stability_copies`): per copy (friction, restitution,
            friction resolved, restitution resolved).
    """

    friction: float
    restitution: float
    timeconst_s: float
    dampratio: float
    friction_range: tuple[float, float]
    restitution_range: tuple[float, float]
    dampratio_range: tuple[float, float]
    friction_resolved: bool
    restitution_resolved: bool
    chi2: float
    dof: int
    threshold: float
    impacts: tuple[str, ...]
    chi2_per_impact: tuple[float, ...] = field(default_factory=tuple)
    noise_m: tuple[float, float] = (0.0, 0.0)
    profile: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    traces: tuple[tuple[str, np.ndarray, np.ndarray, np.ndarray], ...] = ()
    copies: tuple[tuple[float, float, bool, bool], ...] = ()


def profile_range(values: np.ndarray, chi2: np.ndarray, threshold: float) -> tuple[float, float]:
    """The span of `values` over the grid points whose chi-square is within `threshold` of the lowest."""
    near = values[chi2 <= chi2.min() + threshold]
    return float(near.min()), float(near.max())


def widened(span: tuple[float, float], grid: Sequence[float]) -> tuple[float, float]:
    """The span pushed out halfway to the next grid values (the truth may lie between grid points); at a grid end,
    the end."""
    values = np.asarray(grid, np.float64)
    lo, hi = int(np.searchsorted(values, span[0])), int(np.searchsorted(values, span[1]))
    low = 0.5 * (values[lo - 1] + values[lo]) if lo > 0 else values[0]
    high = 0.5 * (values[hi] + values[hi + 1]) if hi < len(values) - 1 else values[-1]
    return float(low), float(high)


def _resolved(best: float, span: tuple[float, float], grid: Sequence[float], fraction: float) -> bool:
    share = 1.0 + fraction
    return bool(span[0] > best / share and span[1] < best * share and span[0] > grid[0] and span[1] < grid[-1])


def _impact_trajectory(impact: Impact, qpos: np.ndarray, qvel: np.ndarray) -> Trajectory:
    """The rollout of an impact from a start state: its first row at the first flight's last frame, then the
    second flight's compared frames."""
    times = np.concatenate([[impact.before.ref_s], impact.after_s])
    return Trajectory(
        time_s=times, qpos=np.tile(qpos, (len(times), 1)), qvel=np.tile(qvel, (len(times), 1)), name=impact.name
    )


def _frames_cov(impact: Impact, rotation: bool) -> np.ndarray:
    """(D, D) covariance of the compared frames' tracked values (`_compared`'s order): centre of mass, then, with
    `rotation`, orientation (`impact.rotation_sigma_rad` per axis)."""
    if not rotation:
        return impact.frame_cov
    return scipy.linalg.block_diag(impact.frame_cov, impact.rotation_sigma_rad**2 * np.eye(3 * len(impact.after_s)))


def _compared_size(impact: Impact, rotation: bool) -> int:
    """D: how many values `_compared` gives for the impact (3 per frame, 6 with `rotation`)."""
    return (6 if rotation else 3) * len(impact.after_s)


def _compared(model: mujoco.MjModel, body: str, impact: Impact, qpos: np.ndarray, rotation: bool) -> np.ndarray:
    """(D,) what is compared at the impact's frames for simulated states `qpos` (P, nq): the centre of mass
    (3P, frame by frame) minus the tracked one, then, with `rotation`, the rotation from the tracked orientation
    to the simulated one (3P, world-frame rotation vectors)."""
    com = (body_com_m(model, body, qpos) - impact.after_com_m).reshape(-1)
    if not rotation:
        return com
    adr = int(model.jnt_qposadr[model.body_jntadr[model.body(body).id]])
    turn = quat_to_rotvec(quat_mul(qpos[:, adr + 3 : adr + 7], quat_conj(impact.after_quat_wxyz)))
    return np.concatenate([com, turn.reshape(-1)])


def _ballistic_covariance(impact: Impact, rotation: bool) -> np.ndarray:
    """(D, D) covariance of the compared frames' residuals as if the start's errors went on ballistically (position
    and velocity; with `rotation`, orientation and constant spin): a first guess, before the contact's own
    propagation is known."""
    dt = impact.after_s - impact.before.ref_s
    design = np.stack([np.ones_like(dt), dt], axis=1)
    lift = np.kron(design, np.eye(3))  # (3P, 6): position and velocity to each frame's position
    start = lift @ impact.start_cov[:6, :6] @ lift.T
    if rotation:
        start = scipy.linalg.block_diag(start, lift @ impact.start_cov[6:, 6:] @ lift.T)
    if impact.drift_cov.size:
        lifted = [lift @ impact.drift_start[:6]] + ([lift @ impact.drift_start[6:]] if rotation else [])
        drift_map = np.concatenate(lifted) - impact.drift_after[: _compared_size(impact, rotation)]
        start = start + drift_map @ impact.drift_cov @ drift_map.T
    return start + _frames_cov(impact, rotation)


def _start_variant(model: mujoco.MjModel, body: str, impact: Impact, delta: np.ndarray) -> Trajectory:
    """The impact's rollout from its start state moved by `delta` (12: centre of mass position and velocity, a world
    rotation, world angular velocity)."""
    rot0 = quat_to_mat(impact.qpos[3:7])
    lever0 = rot0 @ model.body_ipos[model.body(body).id]
    spin0 = rot0 @ impact.qvel[3:]
    com0, vel0 = impact.qpos[:3] + lever0, impact.qvel[:3] + np.cross(spin0, lever0)
    quat = quat_mul(rotvec_to_quat(delta[6:9]), impact.qpos[3:7])
    qpos, qvel = free_state(model, body, com0 + delta[:3], vel0 + delta[3:6], quat, spin0 + delta[9:])
    return _impact_trajectory(impact, qpos, qvel)


def _gaussian_draws(rng: np.random.Generator, cov: np.ndarray, size: int) -> np.ndarray:
    """(size, D) zero-mean draws of covariance ``cov`` (D, D; positive semi-definite, maybe singular), the same on
    every machine for one seed.

    NumPy's ``multivariate_normal`` factors by an SVD, whose singular vectors' signs (and, for a near-singular
    matrix such as a drift's squared-exponential covariance, the vectors themselves) depend on the CPU's LAPACK
    kernels: one seed gave other draws, and other fits, on another CPU. A Cholesky factor is unique; a relative
    1e-12 on the diagonal makes a singular covariance definite without changing any variance measurably.
    """
    jitter = 1e-12 * max(float(np.max(np.diag(cov), initial=0.0)), 1e-300)
    sym = 0.5 * (cov + cov.T) + jitter * np.eye(len(cov))
    try:
        factor = np.linalg.cholesky(sym)
    except np.linalg.LinAlgError:  # not semi-definite beyond rounding: the nearest that is, by its eigenvalues
        values, vectors = np.linalg.eigh(sym)
        factor = vectors * np.sqrt(np.clip(values, 0.0, None))
    return rng.standard_normal((size, len(cov))) @ factor.T


def _propagated_covariance(model: mujoco.MjModel, body: str, impact: Impact, options: ImpactOptions) -> np.ndarray:
    """(D, D) covariance of the compared frames' residuals (`_compared`'s): the tracked frames' own error plus the
    start's errors carried through the contact. With `options.start_samples`, the sample covariance of the simulated
    values over that many start states drawn from `impact.start_cov` and the drift (`Impact.drift_cov`, which also
    moves the compared frames), seeded; over several contacts the map from start to frames is far from linear. Else
    J start_cov J^T + the frames' noise, with J the central difference over each start-state direction (steps of one
    standard deviation, so across the contact's switches a secant, not a tangent); the drift is then left out."""
    if options.start_samples:
        rng = np.random.default_rng(options.start_seed)
        deltas = _gaussian_draws(rng, impact.start_cov, options.start_samples)
        shifts = np.zeros((options.start_samples, 0))
        if impact.drift_cov.size:  # the drift moves the start and the compared frames together
            drift = _gaussian_draws(rng, impact.drift_cov, len(deltas))
            deltas += drift @ impact.drift_start.T
            shifts = drift @ impact.drift_after[: _compared_size(impact, options.compare_rotation)].T
        trajs = [_start_variant(model, body, impact, d) for d in deltas]
        drawn = np.stack(
            [
                _compared(model, body, impact, pred.qpos[1:], options.compare_rotation)
                for pred in cast(list[Trajectory], simulate(model, trajs))
            ]
        )
        drawn[:, : shifts.shape[1]] -= shifts
        return np.cov(drawn, rowvar=False) + _frames_cov(impact, options.compare_rotation)
    steps = np.sqrt(np.clip(np.diag(impact.start_cov), 1e-12, None))
    trajs = [
        _start_variant(model, body, impact, sign * steps[k] * np.eye(12)[k]) for k in range(12) for sign in (1, -1)
    ]
    values = [
        _compared(model, body, impact, pred.qpos[1:], options.compare_rotation)
        for pred in cast(list[Trajectory], simulate(model, trajs))
    ]
    jac = np.stack([(values[2 * k] - values[2 * k + 1]) / (2.0 * steps[k]) for k in range(12)], axis=1)
    return jac @ impact.start_cov @ jac.T + _frames_cov(impact, options.compare_rotation)


def _chi2_all(residual: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(G,) chi-square of each grid point's (G, D) residuals (`_compared`'s) under covariance `cov` (D, D)."""
    chol = np.linalg.cholesky(cov)
    white = np.linalg.solve(chol, residual.T)
    return np.sum(white**2, axis=0)


def fit_impacts(
    model: mujoco.MjModel,
    contact: Sequence[Parameter],
    impacts: Sequence[Impact],
    options: ImpactOptions,
    *,
    progress: ProgressFn | None = None,
) -> ImpactFit:
    """Sliding friction, restitution and time constant of one object's contact from its impacts (module docstring).

    Args:
        model: the object's single-body scene.
        contact: its parameters friction.sliding, solref.timeconst and solref.dampratio (calibration's names), which
            `fit_impacts` sets on copies of `model`.
        impacts: `find_impacts`' result (at least one).

    Raises:
        GrounderError: no impacts, or a contact parameter missing.
    """
    if not impacts:
        raise GrounderError("no contact after a free flight to fit; use the windowed calibration for this clip")
    by_field = {p.name.split(".", 1)[1]: p for p in contact}
    missing = {"friction.sliding", "solref.timeconst", "solref.dampratio"} - set(by_field)
    if missing:
        raise GrounderError(f"fit_impacts needs the contact parameters {sorted(missing)} of the object as well")
    body = contact[0].name.split(".", 1)[0]
    solimp = model.geom_solimp[collision_geoms(model, model.body(body).id)[0]]
    grid = [
        (mu, e, tc) for tc in options.timeconst_grid for e in options.restitution_grid for mu in options.friction_grid
    ]
    solrefs = {(e, tc): contact_solref(e, tc, solimp=tuple(solimp)) for _, e, tc in grid}
    pool = [copy.copy(model) for _ in range(min(_CHUNK, len(grid)))]
    priority = contact_priority(model)  # the object's values win over the table's when contacts mix them
    for m in pool:
        for parameter in contact:
            m.geom_priority[list(parameter.contact_geoms)] = priority

    def set_point(m: mujoco.MjModel, point: tuple[float, float, float]) -> None:
        timeconst, dampratio = solrefs[(point[1], point[2])]
        by_field["friction.sliding"].set_model(m, point[0])
        by_field["solref.timeconst"].set_model(m, timeconst)
        by_field["solref.dampratio"].set_model(m, dampratio)

    trajs = [_impact_trajectory(impact, impact.qpos, impact.qvel) for impact in impacts]
    rotation = options.compare_rotation
    # Every grid point's residuals at every impact's compared frames (the costs are recomputed from these as the
    # start-error covariance is refined, without simulating again).
    residuals: list[np.ndarray] = [np.zeros((len(grid), _compared_size(i, rotation))) for i in impacts]
    for start in range(0, len(grid), _CHUNK):
        chunk = grid[start : start + _CHUNK]
        models = pool[: len(chunk)]
        for m, point in zip(models, chunk, strict=True):
            set_point(m, point)
        for i, per_model in enumerate(cast(list[list[Trajectory]], simulate(models, trajs))):
            for j, pred in enumerate(per_model):
                residuals[j][start + i] = _compared(model, body, impacts[j], pred.qpos[1:], rotation)
        if progress is not None:
            progress(f"impacts of {body}", min(start + _CHUNK, len(grid)), len(grid))
    # The start's errors reach the compared frames through the contact: linearised at the best point (first with
    # a ballistic guess, then at the best point under the covariance found), twice.
    covariances = [_ballistic_covariance(impact, rotation) for impact in impacts]
    for _ in range(3):
        chi2 = np.stack([_chi2_all(residuals[j], covariances[j]) for j in range(len(impacts))], 1)
        best = int(np.argmin(chi2.sum(axis=1)))
        set_point(pool[0], grid[best])
        covariances = [_propagated_covariance(pool[0], body, impact, options) for impact in impacts]
    chi2 = np.stack([_chi2_all(residuals[j], covariances[j]) for j in range(len(impacts))], 1)
    total = chi2.sum(axis=1)
    best = int(np.argmin(total))
    dof = max(1, sum(r.shape[1] for r in residuals) - 3)
    threshold = options.delta_chi2 * max(1.0, float(total[best]) / dof)
    points = np.array(grid)
    mu_best, e_best, tc_best = grid[best]
    timeconst_best, dampratio_best = solrefs[(e_best, tc_best)]
    mu_span = widened(profile_range(points[:, 0], total, threshold), options.friction_grid)
    e_span = widened(profile_range(points[:, 1], total, threshold), options.restitution_grid)
    # The damping ratios that bounce at the range's ends with the time constants of the points within the threshold.
    near_timeconsts = sorted({float(tc) for tc in points[total <= total[best] + threshold, 2]})
    corner_dampratios = [contact_solref(e, tc, solimp=tuple(solimp))[1] for e in e_span for tc in near_timeconsts]
    return ImpactFit(
        friction=float(mu_best),
        restitution=float(e_best),
        timeconst_s=float(timeconst_best),
        dampratio=float(dampratio_best),
        friction_range=mu_span,
        restitution_range=e_span,
        dampratio_range=(float(min(corner_dampratios)), float(max(corner_dampratios))),
        friction_resolved=_resolved(mu_best, mu_span, options.friction_grid, options.resolution_fraction),
        restitution_resolved=_resolved(e_best, e_span, options.restitution_grid, options.resolution_fraction),
        chi2=float(total[best]),
        dof=dof,
        threshold=threshold,
        impacts=tuple(i.name for i in impacts),
        chi2_per_impact=tuple(float(c) for c in chi2[best]),
        profile=(
            total.reshape(len(options.timeconst_grid), len(options.restitution_grid), -1).min(axis=0) - total[best]
        ),
        # The simulated centre of mass at the best point: its residual (`_compared`'s first 3P values) plus the tracked.
        traces=tuple(
            (
                i.name,
                i.after_s,
                i.after_com_m[:, 2],
                residuals[j][best][2 : 3 * len(i.after_s) : 3] + i.after_com_m[:, 2],
            )
            for j, i in enumerate(impacts)
        ),
        noise_m=impacts[0].noise_m,
    )


def _moved(trajs: Sequence[Trajectory], sigma_m: float, seed: int) -> list[Trajectory]:
    """Copies of single-body runs with every tracked position moved by `sigma_m` per axis (seeded)."""
    rng = np.random.default_rng(seed)
    out = []
    for t in trajs:
        qpos = t.qpos.copy()
        qpos[:, :3] += rng.normal(scale=sigma_m, size=qpos[:, :3].shape)
        out.append(Trajectory(time_s=t.time_s, qpos=qpos, qvel=t.qvel, ctrl=t.ctrl, name=t.name))
    return out


def stable_fit(
    model: mujoco.MjModel,
    contact: Sequence[Parameter],
    trajs: Sequence[Trajectory],
    impacts: Sequence[Impact],
    options: ImpactOptions,
    view_point_m: Sequence[float] | None = None,
    *,
    progress: ProgressFn | None = None,
) -> ImpactFit:
    """`fit_impacts` on the impacts found in the object's runs `trajs`, then on `options.stability_copies` copies of
    the runs moved by `stability_m`; a value stays resolved only where every copy resolves it within
    `resolution_fraction` of the first fit's best (`ImpactFit.copies` lists them).

    Raises:
        GrounderError: no impacts (`fit_impacts`).
    """
    body = contact[0].name.split(".", 1)[0]
    fit = fit_impacts(model, contact, impacts, options, progress=progress)
    copies = []
    for k in range(options.stability_copies):
        seed = options.start_seed + 1 + k
        moved = find_impacts(model, body, _moved(trajs, options.stability_m, seed), options, view_point_m)
        # Each copy also draws its own start states: a value resolved under one draw of them only is not measured.
        other = fit_impacts(model, contact, moved, replace(options, start_seed=seed)) if moved else None
        copies.append(
            (float("nan"), float("nan"), False, False)
            if other is None
            else (other.friction, other.restitution, other.friction_resolved, other.restitution_resolved)
        )
    share = options.resolution_fraction

    def holds(index: int, best: float) -> bool:
        return all(bool(c[index + 2]) and abs(c[index] / best - 1.0) <= share for c in copies)

    return replace(
        fit,
        friction_resolved=fit.friction_resolved and holds(0, fit.friction),
        restitution_resolved=fit.restitution_resolved and holds(1, fit.restitution),
        copies=tuple(copies),
    )


def impacts_body(
    scene_xml: Path,
    body_trajs: Sequence[Trajectory],
    params: Sequence[str],
    options: ImpactOptions,
    *,
    view_point_m: Sequence[float] | None = None,
    progress: ProgressFn | None = None,
) -> tuple[dict[str, Any], list[str]]:
    """Calibrates one object's contact values in its own scene from its impacts (`InteractionOptions.calibration`
    "impacts"). `view_point_m`: the camera's centre (world), for the tracking noise along its viewing rays.

    Returns the object's calibration entry (as `grounder.interaction.windows.calibrate_constrained`'s: `status`, per
    parameter `nominal`, `value`, `interval`, `bounds`, `unit`, `constrained`, `indistinguishable`; an unresolved
    value keeps the prior and its best grid value is `unresolved_fit`; `restitution`: the bounce at 1 m/s and its
    range; `impacts`: the impacts used and the fit's chi-square) and the impacts' names.
    """
    from grounder.calibration.parameters import resolve_parameters

    model = mujoco.MjModel.from_xml_path(str(scene_xml))
    body = params[0].split(".", 1)[0]
    impacts = find_impacts(model, body, body_trajs, options, view_point_m)
    if not impacts:
        return {"status": "skipped: no impact: no tracked free flight ends in a contact", "parameters": {}}, []
    contact = resolve_parameters(model, [f"{body}.{f}" for f in _CONTACT_FIELDS])
    fit = stable_fit(model, contact, body_trajs, impacts, options, view_point_m, progress=progress)
    fitted = {
        "friction.sliding": (fit.friction, fit.friction_range, fit.friction_resolved),
        "solref.dampratio": (fit.dampratio, fit.dampratio_range, fit.restitution_resolved),
        # The bounce pins the pair (time constant, damping ratio), not each: the time constant goes with the bounce.
        "solref.timeconst": (fit.timeconst_s, (fit.timeconst_s, fit.timeconst_s), fit.restitution_resolved),
    }
    by_name = {p.name: p for p in resolve_parameters(model, list(params))}
    records: dict[str, Any] = {}
    for name, parameter in by_name.items():
        sub = name.split(".", 1)[1]
        record = fitted_record(parameter, *fitted[sub]) if sub in fitted else prior_record(parameter)
        if record["constrained"] and sub == "solref.timeconst":
            record["set_with_restitution"] = True
        records[name] = record
    checked = (
        f", checked on {len(fit.copies)} copies of the tracks moved by {1e6 * options.stability_m:g} um"
        if fit.copies
        else ""
    )
    status = fit_status(
        f"{len(impacts)} contact(s) after a tracked free flight, chi-square {fit.chi2:.1f} for {fit.dof} residuals"
        + checked,
        records,
    )
    entry = {
        "status": status,
        "parameters": records,
        "restitution": {
            "value": fit.restitution,
            "range": list(fit.restitution_range),
            "resolved": fit.restitution_resolved,
            "impact_speed_m_s": REFERENCE_IMPACT_SPEED_M_S,
        },
        "impacts": {
            "names": list(fit.impacts),
            "chi2": round(fit.chi2, 3),
            "dof": fit.dof,
            "threshold": round(fit.threshold, 3),
            "chi2_per_impact": [round(c, 3) for c in fit.chi2_per_impact],
            "noise_mm": [round(1e3 * v, 3) for v in fit.noise_m],
            "best": {"friction": fit.friction, "restitution": fit.restitution, "timeconst_s": fit.timeconst_s},
            "stability_um": 1e6 * options.stability_m,
            "stability_copies": [
                {"friction": f, "restitution": e, "friction_resolved": fr, "restitution_resolved": er}
                for f, e, fr, er in fit.copies
            ],
            "profile": {
                "friction": list(options.friction_grid),
                "restitution": list(options.restitution_grid),
                "chi2_above_best": np.round(fit.profile, 2).tolist(),
            },
            "traces": [
                {
                    "name": name,
                    "time_s": np.round(t, 4).tolist(),
                    "tracked_com_z_m": np.round(z_track, 5).tolist(),
                    "simulated_com_z_m": np.round(z_sim, 5).tolist(),
                }
                for name, t, z_track, z_sim in fit.traces
            ],
        },
    }
    return entry, list(fit.impacts)


def impacts_figure(per_object: Mapping[str, Mapping[str, Any]], path: Path) -> Path | None:
    """Writes a picture of each object's impact fit (`impacts_body`'s report entries, by object): the chi-square
    over friction x restitution (lowest over the time constants, above the best; the threshold's contour and the
    best point marked) and the tracked centre-of-mass height after each flight against the rollout at the best
    point. None (nothing written) where no object has impacts."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fitted = {body: info for body, info in per_object.items() if info.get("impacts", {}).get("profile")}
    if not fitted:
        return None
    fig, axes = plt.subplots(len(fitted), 2, figsize=(11, 3.6 * len(fitted)), squeeze=False)
    for row, (body, info) in zip(axes, fitted.items(), strict=True):
        hits = info["impacts"]
        profile = hits["profile"]
        friction, restitution = np.array(profile["friction"]), np.array(profile["restitution"])
        above = np.array(profile["chi2_above_best"])
        image = row[0].pcolormesh(friction, restitution, np.log10(1.0 + above), shading="nearest", cmap="viridis")
        row[0].contour(friction, restitution, above, levels=[hits["threshold"]], colors="white", linewidths=1.2)
        row[0].plot(hits["best"]["friction"], hits["best"]["restitution"], "r+", markersize=14, mew=2)
        row[0].set_xscale("log")
        row[0].set(xlabel="sliding friction", ylabel="restitution at 1 m/s", title=f"{body}: chi-square above the best")
        fig.colorbar(image, ax=row[0], label="log10(1 + chi-square above best)")
        for k, trace in enumerate(hits["traces"]):
            color = f"C{k % 10}"
            time_s = np.array(trace["time_s"])
            row[1].plot(time_s, 1e3 * np.array(trace["tracked_com_z_m"]), "o", color=color, ms=4, label=trace["name"])
            row[1].plot(time_s, 1e3 * np.array(trace["simulated_com_z_m"]), "-", color=color)
        row[1].set(xlabel="time (s)", ylabel="centre of mass height (mm)", title="tracked (dots), rollout at the best")
        row[1].legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
