"""Contact values from an object's whole tracked run by multiple shooting, with every start state fitted.

The windowed calibration (`grounder.interaction.windows`) rolls each 0.3 s window out from its tracked first state, and
a landing turns on that state: on `samples/toss` and a held-out toss, start errors the size tracking makes at 30 fps
(1.5 mm, 1 deg, 0.03 m/s, 0.1 rad/s) send friction and damping ratio tens of percent off, where the true starts
give them within 20% (`benchmarks/start_accuracy.py`). Here the start states are unknowns instead. An object's
tracked run (its moving part, at most `max_run_s`) is cut into short intervals of `node_frames` frames; the state
at each interval's first frame (a node: position, orientation, linear and angular velocity, 12 numbers) is free.
Each interval is rolled out from its node (one batched `mujoco.rollout` call for all of them) and scored against
the tracked poses in it (position errors over `position_sigma_m`, their along-ray part scaled so that its square
counts `along_view_weight`, as in the windowed loss; rotation over `rotation_sigma_deg`); where an interval ends,
its rolled-out state must meet the next node (continuity defects over `defect_sigmas`), and each node has a weak
prior around the tracked pose. With the defects tight the nodes form one trajectory: the state before a landing is
fixed by the flight frames before it and by the slide after it at once, which no single window sees.

`fit_contact` (the calibration `ground --interaction --calibration shooting` runs) searches the contact values
(sliding friction, damping ratio, time constant) by a compass search on a log scale, without derivatives: the cost
is rough in them. At each point the node states are fitted by least squares (`scipy.optimize.least_squares`, a
finite-difference Jacobian from one batched rollout of 24 perturbed node sets: nodes two apart share no residual),
first with the defects loosened (x `continuation`) and then tightened, from the tracked states, from sampling sweeps
started there (`ShootingProblem.sampled_start`: least squares alone stops where a landing's tracked velocity is far
off, since the residuals jump wherever contacts make and break), and from the nearest point's states; the lowest
cost counts. `contact_profile` instead fills a grid of sliding friction x damping ratio with the time constant held
(`benchmarks/shooting.py --grid`).

Opt-in, not the default calibration: the node fit stops in local minima that depend on where it starts (less so
with the sampling sweeps), so the costs it compares are rough. Figures in docs/interaction_history.md ("Multiple
shooting over the whole run").
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import mujoco
import mujoco.rollout
import numpy as np
from scipy.optimize import least_squares

from grounder.calibration.parameters import Parameter
from grounder.core.trajectory import Trajectory
from grounder.errors import GrounderError
from grounder.sim.restitution import body_restitution, body_restitution_over_phases, bounce_spread
from grounder.sim.rollout import along_view_weighted
from image2sim_common.progress import ProgressFn
from image2sim_common.rotations import quat_conj, quat_mul, quat_to_rotvec, rotvec_to_quat

# Units of the node variables (a change of 1 in a variable): position, rotation, linear and angular velocity.
_NODE_UNIT = np.array([1e-3] * 3 + [np.radians(1.0)] * 3 + [0.03] * 3 + [0.3] * 3)
# The finite-difference step, in those units.
_STEP = 0.05
# `fit_contact`'s lattice: `resolution_fraction` (on a log scale) is this many steps; the final checks are that far.
_CHECK = 8


@dataclass(frozen=True, kw_only=True)
class ShootingOptions:
    """Settings of `contact_profile`.

    Attributes:
        node_frames: frames per shooting interval (3 at 30 fps: 0.1 s).
        max_run_s: at most this much of each run's moving part is used (rollout cost grows with it).
        min_motion_m_s: a run's moving part ends 3 frames after the last frame faster than this.
        position_sigma_m, rotation_sigma_deg: the tracked poses' expected error.
        along_view_weight: the along-ray position error's squared residual counts this much.
        defect_sigmas: continuity between intervals: position (m), rotation (deg), velocity (m/s), spin (rad/s).
        prior_sigmas: of a node's pose and velocity around the tracked state (the velocity's is wide: a tracked
            velocity at an impact can be a metre per second off).
        continuation: the defect sigmas' multipliers, fitted in turn (loose to tight).
        max_evaluations: least-squares evaluations per continuation stage.
        friction_grid, damping_grid: the sliding friction and damping ratio values searched.
        resolution_cost: values whose cost is within this of the best are "indistinguishable" (chi-square units).
        search_steps: `fit_contact`'s compass search: its step sizes, coarse to fine, in lattice units of
            `resolution_fraction` / 8 on a log scale (20%: 16 is x1.44, 8 is x1.2, 2 is x1.047).
        max_moves: at most this many moves of the search's centre per step size.
        cold_fit_step: at search steps this large or larger (and at the final 20% checks) each point's node states
            are also fitted from the tracked ones and the sampling sweeps, not only from the nearest point's. The
            default, every step, keeps points comparable: a point fitted only from a neighbour's states costs more
            than the same point fitted from more starts (on the synthetic slider, cold fits at the coarse steps
            alone ended at friction -3.5%, every step at +1%), at 2-4 times the cost per point.
        max_restarts: where a final 20% check costs less than the search's best point, the search goes on from
            there (fine steps), at most this often.
        contact_prior_log_sigma: `fit_contact`'s weak prior on each contact value: the standard deviation of its
            logarithm around the grounded (property model's) value; 1.0 is a factor of e.
        resolution_fraction: `fit_contact` calls a value resolved when every point within `resolution_cost` of
            the best lies within this fraction of it.
        sampling_draws: `fit_contact`'s fits from the tracked states start with sampling sweeps
            (`ShootingProblem.sampled_start`): this many candidate states per node and sweep (0: least squares
            straight from the tracked states only, the behaviour before the sweeps).
        sampling_scales: the sweeps' velocity and spin perturbations, coarse to fine, in units of 0.03 m/s and
            0.3 rad/s (8: 0.24 m/s, 2.4 rad/s: a tracked velocity at a landing can be that far off).
        sampling_sweeps: sweeps per scale.
        sampling_seed: seed of the sweeps' draws (the search is deterministic for a given seed).
        max_bounce_spread: `fit_contact` does not search contact values whose bounce depends on where within a
            time step an impact falls by more than this fraction of its mean (`grounder.sim.restitution.bounce_spread`;
            about 0.2 at a time constant of 10 steps, 0.6-1.4 at 3-4 steps, where some impacts gain energy). There
            the node fit can give each landing its own bounce by moving a node a fraction of a step, and it did: the
            held-out toss's bowl came out at friction +180% with a time constant of 3 steps (spread 1.39). Treated
            as a bound; a start beyond it moves to longer time constants. None: no limit.
        cross_fit_points: every point is also fitted from the node states of the cheapest point so far, and after
            the search (with the final 20% checks) from those of this many of the cheapest points (from the tight
            defects); a point keeps its lowest cost. A point's fits are upper bounds on its cost that depend on where
            they start: on the held-out toss's bowl (scan D2) the rendered values cost 285 fitted from their own
            starts and 32 from the node states of the search's best point (31, friction +155%), so without this the
            point whose fits got lucky wins. Where the cheapest point changes, the search goes on from it (within
            `max_restarts`). 0 (the default): off, nearest-point warm starts only. Not yet the default: it adds two
            fits per point and a pass over all points (the held-out bowl took 23 minutes with it, 22 without; a
            search without sampling sweeps on a thrown ball 4 times as long), and shooting's figures over all
            objects were not measured with it.
    """

    node_frames: int = 3
    max_run_s: float = 1.5
    min_motion_m_s: float = 0.05
    position_sigma_m: float = 1e-3
    rotation_sigma_deg: float = 1.0
    along_view_weight: float = 0.25
    defect_sigmas: tuple[float, float, float, float] = (3e-4, 0.3, 0.02, 0.2)
    prior_sigmas: tuple[float, float, float, float] = (4.5e-3, 3.0, 0.9, 3.0)
    continuation: tuple[float, ...] = (30.0, 10.0, 3.0, 1.0)
    max_evaluations: int = 50
    friction_grid: tuple[float, ...] = (0.25, 0.3, 0.35, 0.4, 0.45, 0.5, 0.55, 0.6, 0.7, 0.8)
    damping_grid: tuple[float, ...] = (0.1, 0.15, 0.2, 0.25, 0.3, 0.4)
    resolution_cost: float = 6.0
    search_steps: tuple[int, ...] = (16, 8, 4, 2)
    max_moves: int = 12
    cold_fit_step: int = 2
    max_restarts: int = 2
    contact_prior_log_sigma: float = 1.0
    resolution_fraction: float = 0.2
    sampling_draws: int = 128
    sampling_scales: tuple[float, ...] = (8.0, 4.0, 2.0, 1.0, 0.5, 0.25)
    sampling_sweeps: int = 3
    sampling_seed: int = 0
    max_bounce_spread: float | None = 0.5
    cross_fit_points: int = 0

    def __post_init__(self) -> None:
        if self.node_frames < 1:
            raise GrounderError(f"node_frames={self.node_frames} but expected 1 or more")
        if not self.max_run_s > 0:
            raise GrounderError(f"max_run_s={self.max_run_s} but expected a duration > 0 s")
        if not 0.0 < self.along_view_weight <= 1.0:
            raise GrounderError(f"along_view_weight={self.along_view_weight} but expected a weight in (0, 1]")
        for name in ("friction_grid", "damping_grid"):
            grid = getattr(self, name)
            if len(grid) < 2 or any(not v > 0 for v in grid) or list(grid) != sorted(grid):
                raise GrounderError(f"{name}={grid} but expected two or more increasing values > 0")
        if not self.search_steps or any(not s >= 1 for s in self.search_steps):
            raise GrounderError(f"search_steps={self.search_steps} but expected one or more lattice steps >= 1")
        if self.max_moves < 1:
            raise GrounderError(f"max_moves={self.max_moves} but expected 1 or more")
        if not self.contact_prior_log_sigma > 0:
            raise GrounderError(f"contact_prior_log_sigma={self.contact_prior_log_sigma} but expected > 0")
        if not 0 < self.resolution_fraction < 1:
            raise GrounderError(f"resolution_fraction={self.resolution_fraction} but expected a fraction in (0, 1)")
        if self.sampling_draws < 0 or self.sampling_draws == 1 or self.sampling_sweeps < 1:
            raise GrounderError(
                f"sampling_draws={self.sampling_draws}, sampling_sweeps={self.sampling_sweeps} but expected 0 (off) or "
                "2 or more draws and 1 or more sweeps"
            )
        if not self.sampling_scales or any(not v > 0 for v in self.sampling_scales):
            raise GrounderError(f"sampling_scales={self.sampling_scales} but expected one or more scales > 0")
        if self.cross_fit_points < 0:
            raise GrounderError(f"cross_fit_points={self.cross_fit_points} but expected 0 (off) or more points")
        if self.max_bounce_spread is not None and not self.max_bounce_spread > 0:
            raise GrounderError(f"max_bounce_spread={self.max_bounce_spread} but expected a fraction > 0, or None")


def moving_runs(body_trajs: Sequence[Trajectory], fps: float, options: ShootingOptions) -> list[Trajectory]:
    """Each run's moving part: from its first frame to 3 frames past its last frame faster than
    `options.min_motion_m_s`, at most `options.max_run_s` long; runs shorter than one interval are dropped."""
    out = []
    for traj in body_trajs:
        speed = np.linalg.norm(traj.qvel[:, :3], axis=1)
        moving = np.flatnonzero(speed > options.min_motion_m_s)
        if len(moving) == 0:
            continue
        last = min(len(speed) - 1, int(moving[-1]) + 3, round(options.max_run_s * fps))
        if last < options.node_frames:
            continue
        end = last + 1
        out.append(Trajectory(time_s=traj.time_s[:end], qpos=traj.qpos[:end], qvel=traj.qvel[:end], name=traj.name))
    return out


class ShootingProblem:
    """The node states of one object's runs in a single-body scene, and their least-squares fit for given contact
    values (set on `model` by the caller)."""

    def __init__(
        self,
        model: mujoco.MjModel,
        runs: Sequence[Trajectory],
        options: ShootingOptions,
        view_point_m: Sequence[float] | None = None,
    ) -> None:
        if model.nq != 7 or model.nv != 6:
            raise GrounderError(f"multiple shooting needs a scene with one free body (nq 7, nv 6), got nq {model.nq}")
        if not runs:
            raise GrounderError("multiple shooting needs at least one run of tracked motion")
        self.model = model
        self.options = options
        self._datas = [mujoco.MjData(model) for _ in range(2)]
        k = options.node_frames
        dt = float(np.median(np.diff(runs[0].time_s)))
        self._steps = np.array([max(1, round(i * dt / model.opt.timestep)) for i in range(1, k + 1)])
        # A node: (run, first frame, frames to the next node or the run's end, whether a next node follows).
        nodes = []
        for r, traj in enumerate(runs):
            firsts = list(range(0, len(traj.time_s) - 1, k))
            nodes += [(r, i, min(k, len(traj.time_s) - 1 - i), i != firsts[-1]) for i in firsts]
        self.nodes = nodes
        n = len(nodes)
        self._base_qpos = np.array([runs[r].qpos[i] for r, i, _, _ in nodes], np.float64)
        self._base_qvel = np.array([runs[r].qvel[i] for r, i, _, _ in nodes], np.float64)
        self._target_pos = np.zeros((n, k + 1, 3))
        self._target_quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, k + 1, 1))
        self._mask = np.zeros((n, k + 1, 1))
        for j, (r, i, length, joined) in enumerate(nodes):
            last = length - 1 if joined else length  # the next node's first frame is scored there
            self._target_pos[j, : last + 1] = runs[r].qpos[i : i + last + 1, :3]
            self._target_quat[j, : last + 1] = runs[r].qpos[i : i + last + 1, 3:7]
            self._mask[j, : last + 1] = 1.0
        self._joined = np.array([[joined] for *_, joined in nodes], np.float64)
        self._view = None if view_point_m is None else np.asarray(view_point_m, np.float64)
        self._ray_scale = float(np.sqrt(options.along_view_weight))
        self._defect_sigma = np.repeat(
            [options.defect_sigmas[0], np.radians(options.defect_sigmas[1]), *options.defect_sigmas[2:]], 3
        )
        self._prior_sigma = np.repeat(
            [options.prior_sigmas[0], np.radians(options.prior_sigmas[1]), *options.prior_sigmas[2:]], 3
        )
        self._looseness = 1.0
        self._frame_rows = 6 * (k + 1)

    @property
    def size(self) -> int:
        """Number of node variables (12 per node)."""
        return 12 * len(self.nodes)

    def node_states(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(..., nodes, 12) node variables -> each node's qpos (..., nodes, 7) and qvel (..., nodes, 6)."""
        x = np.asarray(x, np.float64)
        change = x * _NODE_UNIT
        qpos = np.empty((*x.shape[:-1], 7))
        qpos[..., :3] = self._base_qpos[:, :3] + change[..., :3]
        qpos[..., 3:] = quat_mul(self._base_qpos[:, 3:], rotvec_to_quat(change[..., 3:6]))  # body-frame turn
        return qpos, self._base_qvel + change[..., 6:]

    def _rollout(self, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        batch, n = qpos.shape[:2]
        initial = np.zeros((batch * n, 14))  # mjSTATE_FULLPHYSICS of a single free body: time, qpos, qvel
        initial[:, 1:8] = qpos.reshape(-1, 7)
        initial[:, 8:] = qvel.reshape(-1, 6)
        state = mujoco.rollout.rollout(self.model, self._datas, initial, nstep=int(self._steps[-1]))[0]
        return state[:, self._steps - 1, 1:].reshape(batch, n, len(self._steps), 13)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """(B, nodes, 12) node variables -> (B, nodes, rows) residuals: frames, defect to the next node, prior."""
        qpos, qvel = self.node_states(x)
        rolled = self._rollout(qpos, qvel)
        batch, n = x.shape[:2]
        pos = np.concatenate([qpos[:, :, None, :3], rolled[..., :3]], axis=2)
        quat = np.concatenate([qpos[:, :, None, 3:], rolled[..., 3:7]], axis=2)
        pos_error = along_view_weighted(pos - self._target_pos, self._target_pos, self._view, self._ray_scale)
        rot_error = quat_to_rotvec(quat_mul(quat_conj(self._target_quat), quat))
        frames = np.concatenate([pos_error / self.options.position_sigma_m,
                                 rot_error / np.radians(self.options.rotation_sigma_deg)], axis=-1)  # fmt: skip
        end = rolled[:, :, -1]
        next_qpos, next_qvel = np.roll(qpos, -1, axis=1), np.roll(qvel, -1, axis=1)
        defect = np.concatenate(
            [
                end[..., :3] - next_qpos[..., :3],
                quat_to_rotvec(quat_mul(quat_conj(next_qpos[..., 3:]), end[..., 3:7])),
                end[..., 7:] - next_qvel,
            ],
            axis=-1,
        ) / (self._defect_sigma * self._looseness)
        prior = x * _NODE_UNIT / self._prior_sigma
        return np.concatenate([(frames * self._mask).reshape(batch, n, -1), defect * self._joined, prior], axis=-1)

    def _fun(self, flat: np.ndarray) -> np.ndarray:
        return self.residuals(flat.reshape(1, -1, 12)).reshape(-1)

    def _jacobian(self, flat: np.ndarray) -> np.ndarray:
        n = len(self.nodes)
        x = flat.reshape(n, 12)
        base = self.residuals(x[None])[0]
        moved = np.repeat(x[None], 24, axis=0)
        for parity in range(2):
            for col in range(12):
                moved[12 * parity + col, parity::2, col] += _STEP
        change = (self.residuals(moved) - base) / _STEP
        rows = base.shape[-1]
        jac = np.zeros((n, rows, n, 12))
        defect = slice(self._frame_rows, self._frame_rows + 12)
        for parity in range(2):  # every second node moved alone within its own rows and the previous defect
            moved_nodes = np.arange(parity, n, 2)
            by_column = change[12 * parity : 12 * parity + 12].transpose(1, 2, 0)  # (node, row, column)
            jac[moved_nodes, :, moved_nodes, :] = by_column[moved_nodes]
            later = moved_nodes[moved_nodes > 0]
            jac[later - 1, defect, later, :] = by_column[later - 1, defect]
        return jac.reshape(n * rows, n * 12)

    def _interval_ends(self, x: np.ndarray) -> np.ndarray:
        """(nodes, 12) variables -> where each interval's rollout ends, as the next node's variables (row j: the end
        of interval j - 1; row 0: zeros; a row after a run's last interval is meaningless and `_sweep` skips it)."""
        qpos, qvel = self.node_states(x[None])
        end = self._rollout(qpos, qvel)[0, :, -1]  # (nodes, 13): qpos, qvel
        base_qpos, base_qvel = self._base_qpos[1:], self._base_qvel[1:]
        ends = np.zeros_like(x)
        ends[1:, :3] = end[:-1, :3] - base_qpos[:, :3]
        ends[1:, 3:6] = quat_to_rotvec(quat_mul(quat_conj(base_qpos[:, 3:]), end[:-1, 3:7]))
        ends[1:, 6:] = end[:-1, 7:] - base_qvel
        ends[1:] /= _NODE_UNIT
        return ends

    def _sweep(self, x: np.ndarray, scale: np.ndarray, draws: int, rng: np.random.Generator) -> None:
        """One sampling sweep, in place: every second node at once (nodes two apart share no residual), each node's
        state replaced by the best of `draws` candidates (itself, the previous interval's end state, that state's
        velocities at its own pose, and random perturbations of size `scale`) by the residuals that depend on it:
        its frames, prior and defects into and out of it."""
        n = len(x)
        joined_before = np.r_[0.0, self._joined[:-1, 0]] > 0
        ends = self._interval_ends(x)
        defect = slice(self._frame_rows, self._frame_rows + 12)
        for parity in range(2):
            nodes = np.arange(parity, n, 2)
            candidates = np.repeat(x[None], draws, axis=0)
            candidates[1:, nodes] += rng.normal(size=(draws - 1, len(nodes), 12)) * scale
            follow = nodes[joined_before[nodes]]
            if draws >= 3:
                candidates[1, follow] = ends[follow]
                candidates[2, follow, 6:] = ends[follow, 6:]
            squared = self.residuals(candidates) ** 2
            local = squared.sum(axis=-1)
            local[:, 1:] += squared[:, :-1, defect].sum(axis=-1)
            best = np.argmin(local[:, nodes], axis=0)
            x[nodes] = candidates[best, nodes]
            if parity == 0:
                ends = self._interval_ends(x)

    def sampled_start(self, rng: np.random.Generator) -> np.ndarray:
        """Node variables from the tracked states by sampling sweeps at the tight defects, coarse to fine
        (`ShootingOptions.sampling_scales`), for `fit` to finish.

        Least squares from the tracked states stops where a node's velocity at a landing is still wrong (tracked
        velocities there can be 0.3 m/s and 1.5 rad/s off): the residuals jump with sub-micrometre changes of the
        state wherever contacts make and break, so its finite-difference steps see no way down. Sampling does not
        need a slope. Measured on the can of `samples/toss` (scan D2, 15 nodes, the rendered contact values), the cost
        after least squares: from the tracked states 1705; from the true states 323; from the sweeps (three seeds)
        260-455."""
        x = np.zeros((len(self.nodes), 12))
        options = self.options
        for velocity_scale in options.sampling_scales:
            pose_scale = min(1.0, 2.0 * velocity_scale)
            scale = np.array([0.5 * pose_scale] * 3 + [0.3 * pose_scale] * 3 + [velocity_scale] * 6)
            for _ in range(options.sampling_sweeps):
                self._sweep(x, scale, options.sampling_draws, rng)
        return x.reshape(-1)

    def fit(self, start: np.ndarray, continuation: Sequence[float] | None = None) -> tuple[float, np.ndarray]:
        """Least-squares node variables from `start` through the continuation stages: (cost, variables); the cost
        is the sum of squared residuals at the tight (x1) defects."""
        x = np.asarray(start, np.float64)
        for looseness in continuation or self.options.continuation:
            self._looseness = looseness
            x = least_squares(self._fun, x, jac=self._jacobian, method="trf",
                              max_nfev=self.options.max_evaluations).x  # fmt: skip
        self._looseness = 1.0
        return float(np.sum(self._fun(x) ** 2)), x


@dataclass(frozen=True, kw_only=True)
class ContactProfile:
    """`contact_profile`'s result for one object.

    Attributes:
        friction_grid, damping_grid: the values searched.
        cost: (damping, friction) fitted cost at each grid point.
        friction, damping_ratio: the best grid point.
        friction_range, damping_range: the grid values whose cost is within `resolution_cost` of the best.
        nodes: shooting nodes used.
    """

    friction_grid: tuple[float, ...]
    damping_grid: tuple[float, ...]
    cost: np.ndarray = field(repr=False)
    friction: float
    damping_ratio: float
    friction_range: tuple[float, float]
    damping_range: tuple[float, float]
    nodes: int


def contact_profile(
    model: mujoco.MjModel,
    set_contact: Callable[[mujoco.MjModel, float, float], None],
    runs: Sequence[Trajectory],
    options: ShootingOptions,
    *,
    view_point_m: Sequence[float] | None = None,
    progress: ProgressFn | None = None,
) -> ContactProfile:
    """Fits the node states at every grid point of (sliding friction, damping ratio) and returns the cost table.

    Args:
        model: a single-free-body scene (the object and the table); changed in place by `set_contact`.
        set_contact: sets (friction, damping ratio) on the model (e.g. `Parameter.set_model` of each).
        runs: the object's tracked runs (`moving_runs`): qpos 7 and qvel 6 per frame.
    """
    problem = ShootingProblem(model, runs, options, view_point_m)
    frictions, dampings = options.friction_grid, options.damping_grid
    cost = np.zeros((len(dampings), len(frictions)))
    total, done = cost.size, 0
    for row, damping in enumerate(dampings):
        previous = None
        for col, friction in enumerate(frictions):
            set_contact(model, friction, damping)
            fits = [problem.fit(np.zeros(problem.size))]
            if previous is not None:
                fits.append(problem.fit(previous, continuation=options.continuation[-2:]))
            cost[row, col], previous = min(fits, key=lambda f: f[0])
            done += 1
            if progress is not None:
                progress("multiple shooting", done, total)
    best_row, best_col = np.unravel_index(int(np.argmin(cost)), cost.shape)
    near_rows, near_cols = np.nonzero(cost - cost[best_row, best_col] <= options.resolution_cost)
    return ContactProfile(
        friction_grid=tuple(frictions),
        damping_grid=tuple(dampings),
        cost=cost,
        friction=float(frictions[best_col]),
        damping_ratio=float(dampings[best_row]),
        friction_range=(float(frictions[near_cols.min()]), float(frictions[near_cols.max()])),
        damping_range=(float(dampings[near_rows.min()]), float(dampings[near_rows.max()])),
        nodes=len(problem.nodes),
    )


@dataclass(frozen=True, kw_only=True)
class ContactFit:
    """`fit_contact`'s result for one object.

    Attributes:
        names: the contact parameters searched (calibration's names).
        values: the best point's values.
        ranges: per value, the lowest and highest value among the points evaluated within `resolution_cost` of the
            best cost.
        resolved: per value, whether that range lies within `resolution_fraction` of the best value, and points
            that far off on both sides (or at a bound) were evaluated and cost more.
        cost: the best point's cost (node states fitted; chi-square units, the contact values' prior included).
        evaluations: the points evaluated: (values, cost) each, in search order.
        nodes: shooting nodes.
        restitution: the bounce of the points' contacts (`RestitutionFit`), where solref values are searched.
    """

    names: tuple[str, ...]
    values: tuple[float, ...]
    ranges: tuple[tuple[float, float], ...]
    resolved: tuple[bool, ...]
    cost: float
    evaluations: tuple[tuple[tuple[float, ...], float], ...]
    nodes: int
    restitution: RestitutionFit | None = None


@dataclass(frozen=True, kw_only=True)
class RestitutionFit:
    """The coefficient of restitution of `fit_contact`'s points (`grounder.sim.restitution.body_restitution`, a 1 m/s
    impact): the clip shows bounces, and where the time constant and the damping ratio trade (a few time steps), it
    pins their bounce better than either value.

    Attributes:
        value: the best point's restitution.
        range: the lowest and highest restitution among the points within `resolution_cost` of the best cost.
        resolved: that range lies within `resolution_fraction` of the best point's, and points whose restitution
            lies beyond it on both sides were evaluated (so they cost more). The final checks, each value 20% off,
            provide them: 20% on the damping ratio moves the bounce by 13-15%.
    """

    value: float
    range: tuple[float, float]
    resolved: bool


def _restitution_fit(
    model: mujoco.MjModel,
    contact: Sequence[Parameter],
    points: Sequence[tuple[np.ndarray, float]],
    best: np.ndarray,
    best_cost: float,
    options: ShootingOptions,
) -> RestitutionFit | None:
    """`RestitutionFit` of the evaluated (values, cost) points; None unless a solref value is searched. Leaves the
    model at `best`."""
    if not any(p.name.split(".", 1)[1].startswith("solref.") for p in contact):
        return None
    body = contact[0].name.split(".", 1)[0]

    def restitution(values: np.ndarray) -> float:
        for parameter, value in zip(contact, values, strict=True):
            parameter.set_model(model, float(value))
        return body_restitution(model, body)

    bounces = np.array([restitution(values) for values, _ in points])
    costs = np.array([cost for _, cost in points])
    value = restitution(best)
    near = bounces[costs - best_cost <= options.resolution_cost]
    share = 1.0 + options.resolution_fraction
    resolved = bool(
        near.min() > value / share and near.max() < value * share
        and np.any(bounces < near.min()) and np.any(bounces > near.max())
    )  # fmt: skip
    return RestitutionFit(value=value, range=(float(near.min()), float(near.max())), resolved=resolved)


def fit_contact(
    model: mujoco.MjModel,
    contact: Sequence[Parameter],
    runs: Sequence[Trajectory],
    options: ShootingOptions,
    *,
    view_point_m: Sequence[float] | None = None,
    progress: ProgressFn | None = None,
) -> ContactFit:
    """A compass search over the contact values (log scale, from the scene's), with the node states fitted at
    every point as in `contact_profile`.

    The cost is rough in the contact values (stick-slip, contact points switching: finite differences of it change
    with the step by a factor of ten), so they are searched without derivatives: from the scene's values, each value
    is moved up and down by the step in turn and the centre moves to the lowest point, until no move lowers the
    cost; then the step is halved (`search_steps`). Each point's node states are fitted from those of the nearest
    point evaluated and of the cheapest so far and, at the coarse steps (`cold_fit_step`), also from the tracked
    ones; the lowest cost counts.
    At the end each value is also evaluated `resolution_fraction` below and above the best point (the others held
    there: an approximation of the profile, optimistic where two values trade off), and every point evaluated is
    fitted again from the cheapest points' node states (`ShootingOptions.cross_fit_points`); where another point
    then costs less, the search goes on from it (`max_restarts`).

    Args:
        model: a single-free-body scene (the object and the table); changed in place, left at the best values.
        contact: the object's contact parameters (`resolve_parameters`; positive continuous ones), e.g. sliding
            friction, solref damping ratio and time constant; their scene values centre the search and the prior.
        runs: the object's tracked runs (`moving_runs`): qpos 7 and qvel 6 per frame.
    """
    if not contact:
        raise GrounderError("fit_contact needs at least one contact parameter to search")
    for parameter in contact:
        if not parameter.log_scale or parameter.discrete or not parameter.nominal > 0:
            raise GrounderError(
                f"{parameter.name}: multiple shooting searches positive continuous contact values (friction, solref, "
                "solimp width), not discrete or linear ones"
            )
    search = _ContactSearch(model, contact, runs, options, view_point_m, progress)
    centre = _first_centre(search)
    centre, best_cost = _compass_search(search, centre)
    return _contact_fit(search, centre, best_cost)


class _ContactSearch:
    """`fit_contact`'s search state: the lattice of contact values (integer keys, `_CHECK` steps per
    `resolution_fraction` on a log scale from the scene's values) and every point evaluated so far, each with its
    cost and fitted node states."""

    def __init__(
        self,
        model: mujoco.MjModel,
        contact: Sequence[Parameter],
        runs: Sequence[Trajectory],
        options: ShootingOptions,
        view_point_m: Sequence[float] | None,
        progress: ProgressFn | None,
    ) -> None:
        self.model = model
        self.contact = contact
        self.options = options
        self.progress = progress
        self.problem = ShootingProblem(model, runs, options, view_point_m)
        self.m = len(contact)
        self.unit = np.log(1.0 + options.resolution_fraction) / _CHECK
        self.nominal = np.array([p.nominal for p in contact])
        # The keys' bounds (the parameters' bounds on the lattice): `evaluate` gives keys outside them cost inf.
        self.lower_key = np.ceil(np.log(np.array([p.lower for p in contact]) / self.nominal) / self.unit)
        self.upper_key = np.floor(np.log(np.array([p.upper for p in contact]) / self.nominal) / self.unit)
        self.evaluated: dict[tuple[int, ...], tuple[float, np.ndarray]] = {}
        self.stage = f"multiple shooting: {contact[0].name.split('.', 1)[0]}, points searched"
        self.timeconst = next((j for j, p in enumerate(contact) if p.name.endswith(".solref.timeconst")), None)
        self.stable: dict[tuple[int, ...], bool] = {}
        self.limited = options.max_bounce_spread is not None and self.timeconst is not None
        self.tried: set[tuple[tuple[int, ...], tuple[int, ...], float]] = set()

    def values_at(self, key: tuple[int, ...]) -> np.ndarray:
        return self.nominal * np.exp(np.array(key) * self.unit)

    def steady_bounce(self, key: tuple[int, ...]) -> bool:
        """Whether the point's bounce is within `max_bounce_spread` (always, without a limit or a time constant)."""
        if not self.limited or self.options.max_bounce_spread is None:
            return True
        if key not in self.stable:
            for parameter, value in zip(self.contact, self.values_at(key), strict=True):
                parameter.set_model(self.model, float(value))
            bounces = body_restitution_over_phases(self.model, self.contact[0].name.split(".", 1)[0])
            self.stable[key] = bounce_spread(bounces) <= self.options.max_bounce_spread
        return self.stable[key]

    def prior_cost(self, key: tuple[int, ...]) -> float:
        return float(np.sum((np.log(self.values_at(key) / self.nominal) / self.options.contact_prior_log_sigma) ** 2))

    def cross_fit(self, keys: Sequence[tuple[int, ...]]) -> None:
        """Each of `keys` (where evaluated) refitted from the node states of the `cross_fit_points` cheapest points
        (`ShootingOptions.cross_fit_points`), each pair once per state; a point keeps its lowest cost."""
        evaluated, options = self.evaluated, self.options
        sources = sorted(evaluated, key=lambda k: evaluated[k][0])[: options.cross_fit_points]
        for key in keys:
            if key not in evaluated:
                continue
            for parameter, value in zip(self.contact, self.values_at(key), strict=True):
                parameter.set_model(self.model, float(value))
            for source in sources:
                pair = (key, source, evaluated[source][0])
                if source == key or pair in self.tried:
                    continue
                self.tried.add(pair)
                cost, x = self.problem.fit(evaluated[source][1], continuation=options.continuation[-2:])
                if cost + self.prior_cost(key) < evaluated[key][0]:
                    evaluated[key] = (cost + self.prior_cost(key), x)

    def evaluate(self, key: tuple[int, ...], cold: bool = True) -> float:
        evaluated, options, problem = self.evaluated, self.options, self.problem
        if key in evaluated:
            return evaluated[key][0]
        outside = np.any(np.array(key) < self.lower_key) or np.any(np.array(key) > self.upper_key)
        if outside or not self.steady_bounce(key):
            return float("inf")
        values = self.values_at(key)
        for parameter, value in zip(self.contact, values, strict=True):
            parameter.set_model(self.model, float(value))
        fits = []
        if cold or not evaluated:
            fits.append(problem.fit(np.zeros(problem.size)))
            if options.sampling_draws:
                # Finished at the tight defects (kept the can of `samples/toss` at 260-450 where the loose stages
                # let it drift to 300-960) and through the whole continuation (took a thrown ball from 295 to 24).
                sampled = problem.sampled_start(np.random.default_rng([options.sampling_seed, len(evaluated)]))
                fits += [problem.fit(sampled, continuation=options.continuation[-1:]), problem.fit(sampled)]
        if evaluated:
            near = min(evaluated, key=lambda k: float(np.sum((np.array(k) - key) ** 2)))
            cheapest = min(evaluated, key=lambda k: evaluated[k][0])
            for start in dict.fromkeys([near, cheapest] if options.cross_fit_points else [near]):
                fits.append(problem.fit(evaluated[start][1], continuation=options.continuation[-2:]))
        cost, x = min(fits, key=lambda f: f[0])
        evaluated[key] = (cost + self.prior_cost(key), x)
        cost = evaluated[key][0]
        if self.progress is not None:
            # the search's length is not known ahead
            self.progress(self.stage, len(evaluated), len(evaluated) + 2 * self.m)
        return cost

    @staticmethod
    def moved(key: tuple[int, ...], j: int, step: int) -> tuple[int, ...]:
        return tuple(k + step if i == j else k for i, k in enumerate(key))


def _first_centre(search: _ContactSearch) -> tuple[int, ...]:
    """Where the search starts: the scene's values, with the time constant softened until the bounce is steady
    (`max_bounce_spread`); where none within bounds is, the search goes on without that limit."""
    centre = tuple([0] * search.m)
    timeconst, upper = search.timeconst, search.upper_key
    while timeconst is not None and not search.steady_bounce(centre) and centre[timeconst] + 2 <= upper[timeconst]:
        centre = search.moved(centre, timeconst, 2)  # a stiffer start than the step resolves: softer, x1.047 at a time
    if not search.steady_bounce(centre):
        search.limited = False  # no time constant within bounds bounces steadily: search without the limit
    return centre


def _compass_search(search: _ContactSearch, centre: tuple[int, ...]) -> tuple[tuple[int, ...], float]:
    """The compass search from `centre` (`fit_contact`'s docstring), with its restarts: the final centre and its
    cost."""
    options, m, evaluate, moved = search.options, search.m, search.evaluate, search.moved
    best_cost = evaluate(centre)
    steps = options.search_steps
    for _ in range(1 + options.max_restarts):
        for step in steps:
            for _ in range(options.max_moves):
                around = [moved(centre, j, sign * step) for j in range(m) for sign in (-1, 1)]
                costs = [evaluate(key, cold=step >= options.cold_fit_step) for key in around]
                if min(costs) >= best_cost:
                    break
                best_cost = min(costs)
                centre = around[int(np.argmin(costs))]
        # Each value 20% off both ways, the others at the best point, fitted from the tracked states too, and (with
        # cross fits) every point refitted from the cheapest points' node states: where another point now costs
        # less (the fits had stopped in a local minimum), the search goes on from there with the steps below 20%.
        checks = [moved(centre, j, sign * _CHECK) for j in range(m) for sign in (-1, 1)]
        costs = [evaluate(key) for key in checks]
        if options.cross_fit_points:
            search.cross_fit(list(search.evaluated))
        evaluated = search.evaluated
        # the centre, unless a check or a cross fit beat it
        cheapest = min(evaluated, key=lambda k: evaluated[k][0])
        best_cost = evaluated[cheapest][0]
        if cheapest == centre:
            break
        centre = cheapest
        steps = tuple(s for s in options.search_steps if s < _CHECK) or options.search_steps[-1:]
    return centre, best_cost


def _contact_fit(search: _ContactSearch, centre: tuple[int, ...], best_cost: float) -> ContactFit:
    """The search's result at its final centre: each value's range within `resolution_cost` of the best cost and
    whether it is resolved, the restitution; leaves the model at the best values."""
    contact, options, evaluated, values_at = search.contact, search.options, search.evaluated, search.values_at
    # The final centre's checks (already evaluated unless the last restart moved it; out of bounds: inf).
    rises = [
        [search.evaluate(search.moved(centre, j, sign * _CHECK)) - best_cost for sign in (-1, 1)]
        for j in range(search.m)
    ]
    best = values_at(centre)
    keys = list(evaluated)
    bounce = _restitution_fit(
        search.model, contact, [(values_at(k), evaluated[k][0]) for k in keys], best, best_cost, options
    )
    for parameter, value in zip(contact, best, strict=True):
        parameter.set_model(search.model, float(value))
    near = np.array([values_at(k) for k in keys if evaluated[k][0] - best_cost <= options.resolution_cost])
    low, high = near.min(axis=0), near.max(axis=0)
    share = 1.0 + options.resolution_fraction
    resolved = [
        bool(
            min(rise) > options.resolution_cost
            and low[j] > best[j] / share * 0.999
            and high[j] < best[j] * share * 1.001
        )
        for j, rise in enumerate(rises)
    ]
    return ContactFit(
        names=tuple(p.name for p in contact),
        values=tuple(float(v) for v in best),
        ranges=tuple((float(a), float(b)) for a, b in zip(low, high, strict=True)),
        resolved=tuple(resolved),
        cost=best_cost,
        evaluations=tuple((tuple(float(v) for v in values_at(k)), evaluated[k][0]) for k in keys),
        nodes=len(search.problem.nodes),
        restitution=bounce,
    )
