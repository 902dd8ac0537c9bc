"""Contact values from the contacts after free flights: `ground --interaction` (`--calibration impacts`, the
default).

The windowed calibration (`grounder.interaction.pipeline`) rolls 0.3 s windows out from tracked start states, and a
landing turns on that state: a velocity from a few tracked frames, at 30 fps, is tens of mm/s off, and the friction and
bounce that explain a window move with it. A free flight pins the state far better: between contacts a thrown object
moves on a parabola whose curvature is known (gravity), so the flight's centre-of-mass state comes from a least-squares
line fit over all of its frames, with a covariance.

Per object (in a scene of its own with the table, `grounder.interaction.pipeline.single_body_scene`):

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

An object that never flies (pushed, only sliding) has no impacts: `grounder.interaction.pipeline` calibrates it on
windows. Described in docs/cli.md ("Contacts after free flights"); figures in docs/results/interaction.md.
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
from grounder.sim.restitution import REFERENCE_IMPACT_SPEED_M_S, contact_solref
from grounder.sim.rollout import simulate
from image2sim_common.progress import ProgressFn
from image2sim_common.rotations import quat_conj, quat_mul, quat_to_mat, quat_to_rotvec, rotvec_to_quat

_CONTACT_FIELDS = ("friction.sliding", "solref.timeconst", "solref.dampratio")
# Grid points simulated per batched rollout call (memory: about 0.2 MB per point and impact).
_CHUNK = 192


@dataclass(frozen=True, kw_only=True)
class ImpactOptions:
    """Settings of `fit_impacts`.

    Attributes:
        clearance_m: a frame is clear (in flight) when the object's collision geometry is farther than this from every
            static geom.
        min_flight_frames: a flight has at least this many frames (2: the least that gives a position and a velocity
            with known curvature; the start covariance carries how uncertain that is). A run of clear frames is
            cut in two only into flights of 3 frames or more, which can show that they are not one flight.
        max_gap_s: two flights at most this far apart (last frame of one to first of the next) bracket one impact.
        position_sigma_m: the tracked centre of mass's error per axis where it cannot be estimated (and the scale
            outliers are measured in).
        rotation_sigma_deg: the tracked orientation's error per axis where it cannot be estimated.
        estimate_noise: estimate both from the object's own flights (the residuals of its flights of 3 frames or
            more, pooled), floored at `min_position_sigma_m` and `min_rotation_sigma_deg`. The residuals see only
            the frame-to-frame part of the tracking error; the part that drifts slowly over a few frames bends no
            parabola but does move a flight's end velocity. On `samples/toss` the bowl's flight residuals give
            0.2 mm while its tracked centre is 0.2-1.8 mm off the true one, in runs of frames; hence the floor of
            0.5 mm, about the per-axis tracking error against the truth (with 0.2 mm: 19 of 21 resolved values
            within 20% and 9 unresolved on scan D's five clips; with 0.5 mm 21 of 23 and 7).
        drift_sigma_m, drift_time_s: the part of the tracking error that drifts: an error along the camera's viewing
            ray (depth) that changes slowly, modelled as a Gaussian process with this standard deviation and
            correlation time (squared exponential) over the flight's frames and the frames compared after it. It
            moves the flight's fitted start and the compared frames together, and no flight's residuals show it.
            Model-based tracking reads depth from apparent size, so a grounded mesh or texture a little off places
            the object off along the ray. Sized (4 mm, 0.3 s; 2026-11-26) with the can's visual mesh snapped onto
            its cylinder (`GroundOptions.cylinder_snap`): tracked against that scan, `samples/toss`'s can is about
            1 mm nearer than true in flight (along-ray RMS of the moving objects 2.4 mm; the scan's rippled can was
            4.4-9.4 mm nearer, RMS 6.7 mm, and the drift was sized from it, 6 mm, and before from the bowl, 1 mm
            over 0.1 s). With 2 or 3 mm the can's values held in every sub-micrometre copy of `samples/toss` too,
            but 2 mm gave two wrong values on the held-out clips and 3 mm one; figures of each in
            docs/results/interaction.md and docs/interaction_history.md. Carried by the sampled propagation
            (`start_samples`) and the first, ballistic guess; needs a view point. 0 turns it off.
        drift_rotation_deg: the same for the tracked orientation (per axis, world frame; same correlation time).
        outlier_sigmas: a single frame this many sigmas off its flight's fit is dropped.
        friction_grid, restitution_grid, timeconst_grid: the grid searched (restitution at 1 m/s; time constants
            below `grounder.sim.restitution.MIN_TIMECONST_STEPS` steps are raised to it).
        delta_chi2: a value's range is that of the grid points within this chi-square increase of the best, times
            the misfit per degree of freedom where that exceeds 1 (4: two sigmas).
        resolution_fraction: a value is resolved where its range lies within this fraction of the best value (and
            away from the grid's ends).
        max_post_s: at most this much after the contact is compared (longer flights add little but cost steps).
        start_samples: how the start's uncertainty is carried to the compared frames: N, the sample covariance of N
            rollouts from starts drawn from it (seed `start_seed`); 0, a linear map (a secant Jacobian, 24 rollouts
            per impact). Over 0.3 s of bouncing and sliding the map is far from linear: on synthetic throws (three
            noise seeds, two throws) the secant left the chi-square at 2.5-7 per degree of freedom against 1.2-3
            sampled; on five tracked clips of scan D (noise floor 0.2 mm) it gave 21 of 27 resolved values within
            20% (6 wrong, mostly the held-out can) against 19 of 21 (2 wrong) sampled, which leaves more unresolved.
        start_seed: the draws' seed.
        compare: "flight": a contact counts where a second flight follows it, and that flight's frames are compared;
            "frames": every flight that ends in a contact counts, and every tracked frame after it (in flight, in
            contact, sliding) is compared, for at most `max_post_s`.
        compare_rotation: compare the simulated orientation with the tracked one at the compared frames as well as
            the centre of mass (rotation residuals, world frame, with the tracking's rotation noise): the friction
            that turns a landing's slide into spin shows in the orientation more than in the centre's path.
        stability_copies, stability_m: the fit is repeated on this many copies of the tracks with every tracked
            position moved by `stability_m` per axis (seeded; 0.1 um, the rounding of `track.json`), and a value
            stays resolved only where every copy resolves it within `resolution_fraction` of the first fit's best.
            A tumbling landing on convex hulls can be chaotic at that scale (which hull vertex touches first turns
            the spin): on `samples/toss`, with a drift of 1 mm (below the can's), the can's friction was -5% from
            the saved tracks and +29%, +57% or unresolved from such copies (`benchmarks/impacts_stability.py`), so
            a single fit would report a value the clip does not measure. Each copy also draws its own start states
            (`start_seed` + 1, + 2, ...): from the tracks of 2026-11-27's `ground --interaction` run on
            `samples/toss`, the can's friction fitted with start seeds 0-3 came out +29%, +29% (resolved), best
            +42% (unresolved) and +5% (resolved). 0 turns the check off.
        windows_for_unresolved: in `ground --interaction`, the values the impacts leave unresolved (friction where
            every landing sticks, everything of an object that only slides) are then screened and calibrated on
            windows, as the windowed calibration does, with the impacts' values written in
            (`grounder.interaction.pipeline._windows_for_unresolved`).
    """

    clearance_m: float = 0.01
    min_flight_frames: int = 2
    max_gap_s: float = 0.12
    position_sigma_m: float = 1e-3
    rotation_sigma_deg: float = 1.0
    estimate_noise: bool = True
    min_position_sigma_m: float = 5e-4
    min_rotation_sigma_deg: float = 0.5
    drift_sigma_m: float = 4e-3
    drift_time_s: float = 0.3
    drift_rotation_deg: float = 1.0
    outlier_sigmas: float = 4.0
    friction_grid: tuple[float, ...] = tuple(float(v) for v in np.geomspace(0.1, 1.5, 28))
    restitution_grid: tuple[float, ...] = tuple(float(v) for v in np.linspace(0.1, 0.9, 33))
    timeconst_grid: tuple[float, ...] = tuple(float(v) for v in np.geomspace(0.012, 0.04, 6))
    delta_chi2: float = 4.0
    resolution_fraction: float = 0.2
    max_post_s: float = 0.3
    compare: str = "frames"
    start_samples: int = 64
    start_seed: int = 0
    compare_rotation: bool = True
    stability_copies: int = 2
    stability_m: float = 1e-7
    windows_for_unresolved: bool = True

    def __post_init__(self) -> None:
        if not self.clearance_m > 0:
            raise GrounderError(f"clearance_m={self.clearance_m} but expected a positive distance in metres")
        if self.min_flight_frames < 2:
            raise GrounderError(f"min_flight_frames={self.min_flight_frames} but expected 2 or more")
        if not self.max_gap_s > 0 or not self.max_post_s > 0:
            raise GrounderError("max_gap_s and max_post_s must be positive durations in seconds")
        if not self.drift_sigma_m >= 0 or not self.drift_rotation_deg >= 0 or not self.drift_time_s > 0:
            raise GrounderError("drift_sigma_m and drift_rotation_deg must be >= 0 and drift_time_s positive (s)")
        if not self.position_sigma_m > 0 or not self.outlier_sigmas > 0 or not self.delta_chi2 > 0:
            raise GrounderError("position_sigma_m, outlier_sigmas and delta_chi2 must be positive")
        for name in ("friction_grid", "restitution_grid", "timeconst_grid"):
            grid = np.asarray(getattr(self, name), np.float64)
            if len(grid) < 1 or np.any(grid <= 0) or np.any(np.diff(grid) <= 0):
                raise GrounderError(f"{name} must be positive values in increasing order")
        if self.stability_copies < 0 or not self.stability_m > 0:
            raise GrounderError("stability_copies must be >= 0 and stability_m a positive distance in metres")
        if self.compare not in ("flight", "frames"):
            raise GrounderError(f"compare={self.compare!r} but expected 'flight' or 'frames'")
        if np.any(np.asarray(self.restitution_grid) > 1.0):
            raise GrounderError("restitution_grid values must lie in (0, 1]")


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


def _com_m(model: mujoco.MjModel, body: str, qpos: np.ndarray) -> np.ndarray:
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
        com = _com_m(model, body, traj.qpos)
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
        run_com = _com_m(model, body, trajs[run].qpos)
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
    com = (_com_m(model, body, qpos) - impact.after_com_m).reshape(-1)
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

    Returns the object's calibration entry (as `grounder.interaction.pipeline.calibrate_constrained`'s: `status`, per
    parameter `nominal`, `value`, `interval`, `bounds`, `unit`, `constrained`, `indistinguishable`; an unresolved
    value keeps the prior and its best grid value is `unresolved_fit`; `restitution`: the bounce at 1 m/s and its
    range; `impacts`: the impacts used and the fit's chi-square) and the impacts' names.
    """
    from grounder.calibration.parameters import resolve_parameters
    from grounder.interaction.pipeline import _prior_record, fit_status, fitted_record

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
        record = fitted_record(parameter, *fitted[sub]) if sub in fitted else _prior_record(parameter)
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
