"""Free flights and the impacts after them, for the impacts calibration (`grounder.interaction.impacts`, whose
docstring describes the method): an object's flights in its tracked runs (`find_flights`: clear of the table,
fitted as parabolas, `fit_flight`; orientation and spin by a torque-free fit, `spin_at_end`), the tracking noise
estimated from them (`tracking_noise`), and each contact after a flight with the start state before it and the
tracked frames after it (`find_impacts`, `Impact`).
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass, field

import mujoco
import numpy as np
import scipy.linalg

from grounder.calibration.parameters import collision_geoms
from grounder.core.trajectory import Trajectory
from grounder.interaction.options import ImpactOptions
from image2sim_common.rotations import quat_conj, quat_mul, quat_to_mat, quat_to_rotvec, rotvec_to_quat


@dataclass(frozen=True, kw_only=True)
class Flight:
    """A free flight of one object: frames `rows` of trajectory `run` (its index), and the fit of its centre of mass.

    Attributes:
        run: index of the single-body trajectory the flight is in.
        rows: (K,) row indices of the frames used (outliers dropped).
        time_s: (K,) their times.
        com_m: (K, 3) tracked centre-of-mass positions, world frame.
        ref_s: the time the fit is expressed at (the flight's last frame).
        com_ref_m, vel_ref_m_s: fitted centre of mass position and velocity at `ref_s`.
        cov: (2, 2) covariance of (position, velocity) per axis in units of sigma^2 (same for every axis).
        residual_m: (K, 3) the fit's residuals (tracked minus fitted centre of mass).
    """

    run: int
    rows: np.ndarray
    time_s: np.ndarray
    com_m: np.ndarray
    ref_s: float
    com_ref_m: np.ndarray
    vel_ref_m_s: np.ndarray
    cov: np.ndarray
    residual_m: np.ndarray


@dataclass(frozen=True, kw_only=True)
class Impact:
    """A contact after a free flight: the start state (before it) and the tracked frames after it that a rollout from
    that state must reach.

    Attributes:
        name: a label (run, the flight's last frame and the first frame compared).
        before: the flight before the contact.
        qpos, qvel: the free joint's start state at `before.ref_s` (body origin; angular velocity in the body frame).
        start_cov: (12, 12) covariance of the start state's errors: centre of mass position (m) and velocity (m/s),
            a rotation (rad) and the angular velocity (rad/s), all world frame.
        after_s: (P,) the times of the frames compared (`ImpactOptions.compare`).
        after_com_m: (P, 3) their tracked centre of mass.
        after_quat_wxyz: (P, 4) their tracked orientations.
        rotation_sigma_rad: the tracked orientation's error per axis used for this object.
        noise_m: the tracked centre of mass's error across and along the camera's viewing ray used for this object
            (`ImpactOptions.estimate_noise`; equal without a view point).
        frame_cov: (3P, 3P) covariance of the compared frames' tracked centre of mass (block diagonal, each frame's
            noise across and along its own viewing ray).
        drift_cov: (Z, Z) covariance of the drifting tracking error (`ImpactOptions.drift_sigma_m`,
            `drift_rotation_deg`) at the flight's K frames and the P compared frames: the depth error (m, K + P
            values, with a view point), then the orientation error (rad, 3 (K + P)); empty without drift.
        drift_start: (12, Z) the start state's error (`start_cov`'s order) per unit of that drift.
        drift_after: (6P, Z) the compared frames' centre-of-mass error (3P), then orientation error (3P), per unit.
    """

    name: str
    before: Flight
    qpos: np.ndarray
    qvel: np.ndarray
    start_cov: np.ndarray
    after_s: np.ndarray
    after_com_m: np.ndarray
    after_quat_wxyz: np.ndarray
    rotation_sigma_rad: float
    noise_m: tuple[float, float]
    frame_cov: np.ndarray
    drift_cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    drift_start: np.ndarray = field(default_factory=lambda: np.zeros((12, 0)))
    drift_after: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))


def _static_geoms(model: mujoco.MjModel) -> list[int]:
    """Collision geoms fixed to the world (the table and the floor)."""
    return [
        g
        for g in range(model.ngeom)
        if model.body_weldid[model.geom_bodyid[g]] == 0 and (model.geom_contype[g] or model.geom_conaffinity[g])
    ]


def clearances_m(model: mujoco.MjModel, body: str, qpos: np.ndarray, cap_m: float = 0.1) -> np.ndarray:
    """(T,) distance from the body's collision geometry to the nearest static geom at each free-joint pose (7,),
    capped at `cap_m`; negative where they overlap. `model` holds the body's free joint first (a single-body scene)."""
    data = mujoco.MjData(model)
    body_id = model.body(body).id
    moving = collision_geoms(model, body_id)
    static = _static_geoms(model)
    adr = int(model.jnt_qposadr[model.body_jntadr[body_id]])
    out = np.full(len(qpos), cap_m)
    for t, row in enumerate(np.asarray(qpos, np.float64)):
        data.qpos[adr : adr + 7] = row
        mujoco.mj_kinematics(model, data)
        for g in moving:
            for s in static:
                out[t] = min(out[t], mujoco.mj_geomDistance(model, data, g, s, cap_m, None))
    return out


def body_com_m(model: mujoco.MjModel, body: str, qpos: np.ndarray) -> np.ndarray:
    """(T, 3) world centre of mass of the body at free-joint poses (T, 7)."""
    ipos = model.body_ipos[model.body(body).id]
    return qpos[:, :3] + np.einsum("tij,j->ti", quat_to_mat(qpos[:, 3:7]), ipos)


def fit_flight(run: int, rows: np.ndarray, time_s: np.ndarray, com_m: np.ndarray, gravity_m_s2: np.ndarray) -> Flight:
    """The least-squares free flight (known gravity) through the centre-of-mass samples, expressed at the last one."""
    ref = float(time_s[-1])
    dt = time_s - ref
    design = np.stack([np.ones_like(dt), dt], axis=1)
    target = com_m - 0.5 * gravity_m_s2[None, :] * dt[:, None] ** 2
    coef, *_ = np.linalg.lstsq(design, target, rcond=None)
    residual = target - design @ coef
    return Flight(
        run=run,
        rows=rows,
        time_s=time_s,
        com_m=com_m,
        ref_s=ref,
        com_ref_m=coef[0],
        vel_ref_m_s=coef[1],
        cov=np.linalg.inv(design.T @ design),
        residual_m=residual,
    )


def _chi2(flight: Flight, sigma_m: float) -> float:
    return float(np.sum(flight.residual_m**2) / sigma_m**2)


def _flights_in(
    run: int,
    rows: np.ndarray,
    time_s: np.ndarray,
    com_m: np.ndarray,
    clearance_m: np.ndarray,
    gravity_m_s2: np.ndarray,
    options: ImpactOptions,
) -> list[Flight]:
    """The flights in one run of clear frames: one, or cut in two (recursively) where a bounce hides between two
    clear frames, with a single outlier dropped per flight."""
    n = len(rows)
    if n < options.min_flight_frames:
        return []
    sigma = options.position_sigma_m
    whole = fit_flight(run, rows, time_s, com_m, gravity_m_s2)
    chi_whole = _chi2(whole, sigma)
    shortest_cut = max(3, options.min_flight_frames)
    if n >= 2 * shortest_cut:
        # A cut costs 6 more coefficients and a cut position (BIC: 7 log(3n)); allowed only where the object could
        # reach the table between the two frames (its clearance less than the distance it covers in a frame).
        step_m = np.linalg.norm(np.diff(com_m, axis=0), axis=1)
        best: tuple[float, int] | None = None
        for k in range(shortest_cut, n - shortest_cut + 1):
            if min(clearance_m[k - 1], clearance_m[k]) > 1.5 * step_m[k - 1]:
                continue
            first = fit_flight(run, rows[:k], time_s[:k], com_m[:k], gravity_m_s2)
            second = fit_flight(run, rows[k:], time_s[k:], com_m[k:], gravity_m_s2)
            chi = _chi2(first, sigma) + _chi2(second, sigma)
            if best is None or chi < best[0]:
                best = (chi, k)
        if best is not None and chi_whole - best[0] > 7.0 * np.log(3 * n):
            k = best[1]
            return _flights_in(
                run, rows[:k], time_s[:k], com_m[:k], clearance_m[:k], gravity_m_s2, options
            ) + _flights_in(run, rows[k:], time_s[k:], com_m[k:], clearance_m[k:], gravity_m_s2, options)
    residual = np.linalg.norm(whole.residual_m, axis=1)
    worst = int(np.argmax(residual))
    if residual[worst] > options.outlier_sigmas * sigma and n > options.min_flight_frames:
        keep = np.arange(n) != worst
        return [fit_flight(run, rows[keep], time_s[keep], com_m[keep], gravity_m_s2)]
    return [whole]


def step_times_s(model: mujoco.MjModel, time_s: np.ndarray) -> np.ndarray:
    """Frame times on the model's step grid, where rollouts read them (`grounder.sim.rollout.step_indices`) and a clip
    rendered from MuJoCo shows them: at 30 fps a frame falls up to 1 ms off its nominal time, 2 mm at 2 m/s."""
    step_s = float(model.opt.timestep)
    return np.rint(np.asarray(time_s, np.float64) / step_s) * step_s


def find_flights(
    model: mujoco.MjModel, body: str, trajs: Sequence[Trajectory], options: ImpactOptions
) -> list[list[Flight]]:
    """Per single-body trajectory, its free flights in time order (`fit_flight`)."""
    gravity = np.asarray(model.opt.gravity, np.float64)
    out = []
    for run, traj in enumerate(trajs):
        clearance = clearances_m(model, body, traj.qpos)
        com = body_com_m(model, body, traj.qpos)
        clear = clearance > options.clearance_m
        time_s = step_times_s(model, traj.time_s)
        flights: list[Flight] = []
        edges = np.flatnonzero(np.diff(np.concatenate([[0], clear.astype(np.int8), [0]])))
        for first, end in zip(edges[::2], edges[1::2], strict=True):
            rows = np.arange(first, end)
            flights += _flights_in(run, rows, time_s[rows], com[rows], clearance[rows], gravity, options)
        out.append(flights)
    return out


def _free_spin_model(model: mujoco.MjModel) -> mujoco.MjModel:
    """A copy of the scene without gravity and contacts: a body in it turns as it does in free flight."""
    free = copy.copy(model)
    free.opt.gravity[:] = 0.0
    free.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    return free


def _turned(
    free: mujoco.MjModel, adr: tuple[int, int], quat: np.ndarray, spin_body: np.ndarray, steps: np.ndarray
) -> np.ndarray:
    """(len(steps), 4) orientations of a body turning freely from `quat` with body-frame angular velocity `spin_body`
    after each number of steps (increasing)."""
    data = mujoco.MjData(free)
    data.qpos[adr[0] + 3 : adr[0] + 7] = quat
    data.qvel[adr[1] + 3 : adr[1] + 6] = spin_body
    out = np.empty((len(steps), 4))
    done = 0
    for k, step in enumerate(steps):
        if step > done:
            mujoco.mj_step(free, data, int(step - done))
            done = int(step)
        out[k] = data.qpos[adr[0] + 3 : adr[0] + 7]
    return out


def spin_at_end(
    model: mujoco.MjModel, body: str, quats_wxyz: np.ndarray, time_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Orientation and world angular velocity at the last of a free flight's frames, fitted to all its tracked
    orientations as a torque-free rigid body (least squares on the rotation angles): a tumbling body's spin is not
    constant in any frame (a box bounced to 18 rad/s turns its spin axis by 10 degrees a frame at 30 fps). Run
    backwards in time: a body turning freely with its angular velocity negated retraces its motion.

    Returns:
        The orientation (w, x, y, z), the world angular velocity (rad/s), the (6, 6) covariance of a world
        rotation (rad) of that orientation and of the angular velocity per unit variance of the orientations (rad^2),
        and the sum of the squared residuals (rad^2).
    """
    from scipy.optimize import least_squares

    last = quats_wxyz[-1]
    rel = quat_to_rotvec(quat_mul(quats_wxyz, np.broadcast_to(quat_conj(last), quats_wxyz.shape)))
    dt = time_s - time_s[-1]
    design = np.stack([np.ones_like(dt), dt], axis=1)
    coef, *_ = np.linalg.lstsq(design, rel, rcond=None)  # a constant spin: the starting guess
    free = _free_spin_model(model)
    body_id = model.body(body).id
    adr = (int(model.jnt_qposadr[model.body_jntadr[body_id]]), int(model.jnt_dofadr[model.body_jntadr[body_id]]))
    order = np.argsort(-dt)  # the frames from the last one backwards
    steps = np.rint(-dt[order] / free.opt.timestep).astype(np.int64)

    def pose(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        quat = quat_mul(rotvec_to_quat(x[:3]), last)
        return quat / np.linalg.norm(quat), x[3:]

    def residuals(x: np.ndarray) -> np.ndarray:
        quat, spin_world = pose(x)
        turned = np.empty((len(order), 4))
        turned[order] = _turned(free, adr, quat, -(quat_to_mat(quat).T @ spin_world), steps)
        return quat_to_rotvec(quat_mul(turned, quat_conj(quats_wxyz))).reshape(-1)

    x0 = np.concatenate([coef[0], coef[1]])
    fit = least_squares(residuals, x0, x_scale=np.array([0.01] * 3 + [1.0] * 3), max_nfev=60)
    x = fit.x if fit.cost <= 0.5 * np.sum(residuals(x0) ** 2) else x0
    quat, spin_world = pose(x)
    return quat, spin_world, np.linalg.pinv(fit.jac.T @ fit.jac), float(np.sum(residuals(x) ** 2))


def free_state(
    model: mujoco.MjModel,
    body: str,
    com_m: np.ndarray,
    vel_m_s: np.ndarray,
    quat_wxyz: np.ndarray,
    spin_world: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The free joint's (qpos, qvel) for a centre-of-mass position and velocity, an orientation and a world angular
    velocity: body origin pose and velocity, angular velocity in the body frame (MuJoCo's free-joint convention)."""
    rot = quat_to_mat(quat_wxyz)
    lever = rot @ model.body_ipos[model.body(body).id]
    qpos = np.concatenate([com_m - lever, quat_wxyz])
    qvel = np.concatenate([vel_m_s - np.cross(spin_world, lever), rot.T @ spin_world])
    return qpos, qvel


def _start(
    model: mujoco.MjModel,
    body: str,
    flight: Flight,
    spin: tuple[np.ndarray, np.ndarray, np.ndarray, float],
    position_cov: np.ndarray,
    rotation_sigma_rad: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The free joint's state at the flight's last frame from its fits (`spin`: `spin_at_end`'s), and the covariance
    of its errors (`Impact.start_cov`) for tracked positions with noise `position_cov` (3, 3) and orientations
    `rotation_sigma_rad` per axis."""
    quat, spin_world, spin_cov, _ = spin
    qpos, qvel = free_state(model, body, flight.com_ref_m, flight.vel_ref_m_s, quat, spin_world)
    cov = np.zeros((12, 12))
    cov[:6, :6] = np.kron(flight.cov, position_cov)
    cov[6:, 6:] = spin_cov * rotation_sigma_rad**2
    return qpos, qvel, cov


def _rays(com_m: np.ndarray, view_point_m: np.ndarray | None) -> np.ndarray | None:
    """(K, 3) unit viewing rays from the camera to each position; None without a view point."""
    if view_point_m is None:
        return None
    rays = com_m - view_point_m
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def frame_noise_cov(rays: np.ndarray | None, noise_m: tuple[float, float], count: int) -> np.ndarray:
    """(count, 3, 3) covariance of tracked positions with `noise_m` (across, along) the viewing rays (isotropic,
    the first value, without rays)."""
    across, along = noise_m
    if rays is None:
        return np.broadcast_to(across**2 * np.eye(3), (count, 3, 3)).copy()
    outer = np.einsum("ki,kj->kij", rays, rays)
    return across**2 * (np.eye(3) - outer) + along**2 * outer


def tracking_noise(
    flights: Sequence[Flight],
    spins: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, float]],
    options: ImpactOptions,
    view_point_m: np.ndarray | None = None,
) -> tuple[float, float, float]:
    """Per-axis tracking noise: position across and along the camera's viewing rays (m; tracked depth is several
    times noisier than the position across the image), and rotation (rad). Pooled over the flights of 3 frames or
    more: their fits' residuals over the degrees of freedom left (n - 2 per position axis, 3 n - 6 for the
    orientations), floored; the options' values where `estimate_noise` is off or fewer than 6 degrees of freedom
    are left. Without a view point both position values are the isotropic estimate."""
    position, rotation = options.position_sigma_m, float(np.radians(options.rotation_sigma_deg))
    long = [(f, s) for f, s in zip(flights, spins, strict=True) if len(f.rows) >= 3]
    dof = sum(len(f.rows) - 2 for f, _ in long)
    if not options.estimate_noise or 3 * dof < 6:
        return position, position, rotation
    floor = options.min_position_sigma_m
    along_ss = across_ss = 0.0
    for f, _ in long:
        residual = f.residual_m
        rays = _rays(f.com_m, view_point_m)
        along = np.zeros(len(residual)) if rays is None else np.sum(residual * rays, axis=1)
        along_ss += float(np.sum(along**2))
        across_ss += float(np.sum(residual**2)) - float(np.sum(along**2))
    rotation = max(
        float(np.sqrt(sum(s[3] for _, s in long) / (3 * dof))), float(np.radians(options.min_rotation_sigma_deg))
    )
    if view_point_m is None:
        iso = max(float(np.sqrt(across_ss / (3 * dof))), floor)
        return iso, iso, rotation
    return max(float(np.sqrt(across_ss / (2 * dof))), floor), max(float(np.sqrt(along_ss / dof)), floor), rotation


def _drift(
    flight: Flight, after_s: np.ndarray, after_com_m: np.ndarray, view: np.ndarray | None, options: ImpactOptions
) -> dict[str, np.ndarray]:
    """`Impact`'s drift fields for a flight and the frames compared after it (`ImpactOptions.drift_sigma_m`)."""
    times = np.concatenate([flight.time_s, after_s])
    k, p = len(flight.time_s), len(after_s)
    lag = times[:, None] - times[None, :]
    shape = np.exp(-0.5 * (lag / options.drift_time_s) ** 2)
    dt = flight.time_s - flight.ref_s
    fit = np.linalg.pinv(np.stack([np.ones_like(dt), dt], axis=1))  # (2, K): a fit's value and rate at its end
    covs, starts, afters = [], [], []
    if view is not None and options.drift_sigma_m > 0:  # the depth error, along each frame's viewing ray
        rays_before, rays_after = _rays(flight.com_m, view), _rays(after_com_m, view)
        assert rays_before is not None and rays_after is not None
        start = np.zeros((12, k + p))
        start[:3, :k] = rays_before.T * fit[0]
        start[3:6, :k] = rays_before.T * fit[1]
        after = np.zeros((6 * p, k + p))
        after[np.arange(3 * p), k + np.repeat(np.arange(p), 3)] = rays_after.reshape(-1)
        covs.append(options.drift_sigma_m**2 * shape)
        starts.append(start)
        afters.append(after)
    if options.drift_rotation_deg > 0:  # the orientation error, per world axis (the spin fit, as a constant spin)
        start = np.zeros((12, 3 * (k + p)))
        start[6:9, : 3 * k] = np.kron(fit[0], np.eye(3))
        start[9:12, : 3 * k] = np.kron(fit[1], np.eye(3))
        after = np.zeros((6 * p, 3 * (k + p)))
        after[3 * p :, 3 * k :] = np.eye(3 * p)
        covs.append(np.radians(options.drift_rotation_deg) ** 2 * np.kron(shape, np.eye(3)))
        starts.append(start)
        afters.append(after)
    if not covs:
        return {}
    return {
        "drift_cov": scipy.linalg.block_diag(*covs),
        "drift_start": np.concatenate(starts, axis=1),
        "drift_after": np.concatenate(afters, axis=1),
    }


def find_impacts(
    model: mujoco.MjModel,
    body: str,
    trajs: Sequence[Trajectory],
    options: ImpactOptions,
    view_point_m: Sequence[float] | None = None,
) -> list[Impact]:
    """The impacts of one object's tracked runs: each flight followed within `max_gap_s` by a tracked frame
    (`compare` "frames") or by another flight (`compare` "flight"). `view_point_m`: the camera's centre (world), for
    the tracking noise along its viewing rays (`tracking_noise`)."""
    view = None if view_point_m is None else np.asarray(view_point_m, np.float64)
    per_run = find_flights(model, body, trajs, options)
    spins = [
        [spin_at_end(model, body, trajs[run].qpos[f.rows, 3:7], f.time_s) for f in flights]
        for run, flights in enumerate(per_run)
    ]
    across, along, rotation = tracking_noise(
        [f for flights in per_run for f in flights], [s for run_spins in spins for s in run_spins], options, view
    )
    impacts = []
    for run, flights in enumerate(per_run):
        run_s = step_times_s(model, trajs[run].time_s)
        run_com = body_com_m(model, body, trajs[run].qpos)
        for k, before in enumerate(flights):
            if options.compare == "flight":
                if k + 1 == len(flights) or flights[k + 1].time_s[0] - before.ref_s > options.max_gap_s:
                    continue
                after = flights[k + 1]
                keep = after.time_s <= after.time_s[0] + options.max_post_s
                after_s, after_com = after.time_s[keep], after.com_m[keep]
                after_quat = trajs[run].qpos[after.rows[keep], 3:7]
            else:  # every tracked frame after the flight, in flight or in contact
                later = np.flatnonzero(run_s > before.ref_s + 1e-9)
                if not len(later) or run_s[later[0]] - before.ref_s > options.max_gap_s:
                    continue
                later = later[run_s[later] <= run_s[later[0]] + options.max_post_s]
                after_s, after_com = run_s[later], run_com[later]
                after_quat = trajs[run].qpos[later, 3:7]
            ref_cov = frame_noise_cov(_rays(before.com_ref_m[None], view), (across, along), 1)[0]
            qpos, qvel, cov = _start(model, body, before, spins[run][k], ref_cov, rotation)
            frames = frame_noise_cov(_rays(after_com, view), (across, along), len(after_s))
            impacts.append(
                Impact(
                    name=f"{trajs[run].name}@{before.ref_s:.3f}-{after_s[0]:.3f}s",
                    before=before,
                    qpos=qpos,
                    qvel=qvel,
                    start_cov=cov,
                    after_s=after_s,
                    after_com_m=after_com,
                    after_quat_wxyz=after_quat,
                    rotation_sigma_rad=rotation,
                    noise_m=(across, along),
                    frame_cov=scipy.linalg.block_diag(*frames),
                    **_drift(before, after_s, after_com, view, options),
                )
            )
    return impacts
