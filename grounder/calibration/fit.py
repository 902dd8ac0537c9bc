"""Calibration: fit a scene's physical parameters to recorded trajectories, with intervals and a validation split.

Parameter names (``box.mass``, ``box.friction.sliding``, ``box.solref.timeconst``, ``geom:NAME.friction.sliding``,
``joint:NAME.damping``, ``actuator:NAME.gain``, ``opt.gravity_scale``, ...) and their defaults are documented in
:mod:`grounder.calibration.parameters`; in short:

- ``BODY.mass``, ``BODY.com.x|y|z``, ``BODY.friction.sliding|torsional|rolling``, ``BODY.solref.timeconst|dampratio``,
  ``BODY.solimp.dmin|dmax|width|midpoint|power``, ``BODY.size_scale`` (contact parameters apply to every collision
  geom of the body, whose priority is raised so that its values govern its contacts);
- ``geom:NAME.<same contact fields>``, ``joint:NAME.damping|frictionloss|armature|stiffness``,
  ``actuator:NAME.gain|kp|kv``, ``opt.gravity_scale`` (compensates a timing/length bias of the measurement),
  ``opt.impratio``.

How it fits (raw mode):

1. The trajectories are split once, reproducibly: the names in natural order are shuffled with
   ``numpy.random.default_rng(split_seed)``; the first ``round(validation_fraction * N)`` are validation, the rest
   training (at least one of each when N >= 2). Trajectories that record the same motion twice
   (`grounder.core.repeats`: e.g. one toss stored again, turned and shifted) stay together, on the side the shuffle
   put the first of them (in natural order) on, and a warning names them. Optionally a seeded subset of the
   training split is used.
2. Loss of a trajectory: re-simulated open loop from its first recorded state (:mod:`grounder.sim.rollout`), for each
   free body the time-average of the position error as a percentage of the body's size (largest extent of its
   collision geoms: the cube's width) plus ``rotation_weight`` times the time-average geodesic rotation error in
   degrees, averaged over free bodies; plus, for hinge/slide joints, the time-average joint error (rad, or m as a
   percentage of 0.1 m). The objective is the mean over training trajectories: exactly the metric of Acosta, Yang
   & Posa (RA-L 2022) when ``rotation_weight = 0``.
3. Global search (contact losses have many local minima): SciPy's differential evolution in the unit box (log scale
   for time constants, masses, gains), seeded, with the scene's own values in the first population. Each
   generation is one batched `mujoco.rollout` call over (candidate models x training trajectories).
4. Local refinement: `mujoco.minimize.least_squares` from the best candidate, residual per trajectory
   ``sqrt(loss)`` (so the sum of squares is the objective), finite differences batched in one rollout per
   Jacobian. The better of the two is kept.
5. Intervals: Gauss-Newton (Laplace) approximation at the optimum, as in ``mujoco.sysid.calculate_intervals``:
   ``cov = s^2 (J^T J)^-1`` with ``s^2`` the residual variance, a z-interval in search coordinates mapped back to
   physical units and clipped to the bounds. A parameter the data does not constrain gets its whole bounds.

Embedding mode fits the objects' property embeddings instead (prior: the grounded scene's ``scene.json``
``properties.embedding`` / ``embedding_std``), decoded to density/friction/solref by the property model; see
:func:`calibrate`.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import mujoco
import numpy as np

import grounder.sim.rollout as sim
from grounder.calibration.parameters import (
    Parameter,
    apply_to_model,
    apply_to_spec,
    body_size_m,
    resolve_parameters,
)
from grounder.core.html_report import write_text_atomic
from grounder.core.json_files import read_json_file
from grounder.core.repeats import describe_repeats, repeated_motions, split_keeping_together
from grounder.core.trajectory import Trajectory, _natural_key, validate_against_model
from grounder.errors import GrounderError, finite_number, integer_in, shown
from grounder.residual.model import RESIDUAL_FILES
from image2sim_common.progress import ProgressFn

log = logging.getLogger(__name__)

MAX_SEED = 2**32 - 1  # numpy's and scipy's seeds


@dataclass(frozen=True, kw_only=True)
class CalibrateOptions:
    """Settings of one calibration (also the ``image2sim calibrate`` options and a batch job's ``settings``).

    Attributes:
        params: Parameter specifications ``NAME`` or ``NAME=LOW:HIGH``; empty: the scene kind's defaults.
        mode: ``raw`` (parameters within bounds) or ``embedding`` (the object's property embedding).
        validation_fraction: Share of trajectories held out for validation.
        split_seed: Seed of the train/validation shuffle.
        max_train_trajectories: Fit on at most this many training trajectories (a seeded subset); None: all.
        rotation_weight: Percent-of-size per degree of rotation error in the loss (0: position only).
        view_point_m: World position (metres) of the camera that measured the trajectories (tracked from video);
            with ``along_view_weight`` the loss weighs the position error along the camera's viewing ray by that
            factor (`grounder.sim.rollout.along_view_weighted`): tracked depth is far noisier than the position
            across the image. None: every direction counts alike (motion capture, simulation).
        along_view_weight: Weight of the along-ray position error, in (0, 1]; used only with ``view_point_m``.
        popsize: Differential-evolution population per parameter (SciPy's ``popsize``).
        generations: Differential-evolution generations (0 skips the global search).
        local_iterations: `mujoco.minimize.least_squares` iterations (0 skips the local refinement).
        fd_step: Finite-difference step in search coordinates (unit box); large, as contact losses are rough.
        interval_level: Two-sided level of the parameter intervals.
        seed: Seed of the global search.
        nthread: Rollout threads; None: the CPU cores this process may use.
        max_batch_mb: Memory cap of one rollout call's recorded states; larger batches are split.
        initial: Start values by parameter name instead of the scene's (the scene's stay the "nominal" ones that
            before/after compare with); with no search budget the result is these values, evaluated.
        robust_scale: Raw mode. None: the objective is the mean of the trajectories' losses. A number k: each
            trajectory's error r = sqrt(loss) enters through the pseudo-Huber function with scale c = k x the median
            r at the start values (quadratic below c, linear above), so one trajectory that cannot be matched (a
            badly tracked impact) weighs like a few, not like all the others together.
        separate_bodies: The bodies never touch each other (objects tossed apart): search each body's parameters on
            its own, one body after another, the others held at their current values. Exact when the loss is a
            sum over bodies that each depend only on their own parameters; each search is then a few dimensions
            instead of all of them, which a small budget covers. Raw mode, per-body parameters (``BODY.*``) only.
    """

    params: tuple[str, ...] = ()
    mode: Literal["raw", "embedding"] = "raw"
    validation_fraction: float = 0.3
    split_seed: int = 0
    max_train_trajectories: int | None = None
    rotation_weight: float = 0.0
    view_point_m: tuple[float, float, float] | None = None
    along_view_weight: float = 1.0
    popsize: int = 8
    generations: int = 20
    local_iterations: int = 10
    fd_step: float = 0.02
    interval_level: float = 0.95
    seed: int = 0
    nthread: int | None = None
    max_batch_mb: float = 256.0
    initial: dict[str, float] = field(default_factory=dict)
    separate_bodies: bool = False
    robust_scale: float | None = None

    def __post_init__(self) -> None:
        # Options come from the CLI, a batch file's settings and Python callers: each field is checked for type and
        # range here, as a NaN weight or a float generation count would otherwise run a calibration that means nothing.
        def bad(name: str, expected: str) -> GrounderError:
            return GrounderError(f"calibrate option {name} must be {expected}, got {shown(getattr(self, name))}")

        def count(name: str, least: int, most: int | None = None, *, optional: bool = False) -> None:
            value = getattr(self, name)
            if optional and value is None:
                return
            if not integer_in(value, least, most):
                rule = f"an integer >= {least}" if most is None else f"an integer in [{least}, {most}]"
                raise bad(name, rule + (" or null" if optional else ""))

        def number(name: str, expected: str, ok: Callable[[float], bool], *, optional: bool = False) -> None:
            value = getattr(self, name)
            if optional and value is None:
                return
            if not (finite_number(value) and ok(float(value))):
                raise bad(name, expected + (" or null" if optional else ""))

        if self.mode not in ("raw", "embedding"):
            raise bad("mode", "'raw' or 'embedding'")
        if isinstance(self.params, str) or not isinstance(self.params, Sequence):
            raise bad("params", "a list of parameter names (NAME or NAME=LOW:HIGH)")
        if not all(isinstance(p, str) for p in self.params):
            raise bad("params", "a list of parameter names (text: NAME or NAME=LOW:HIGH)")
        object.__setattr__(self, "params", tuple(self.params))
        number("validation_fraction", "a number in [0, 1)", lambda v: 0.0 <= v < 1.0)
        count("split_seed", 0, MAX_SEED)
        count("max_train_trajectories", 1, optional=True)
        number("rotation_weight", "a number in [0, 100] (percent of size per degree)", lambda v: 0.0 <= v <= 100.0)
        if self.view_point_m is not None:
            point = self.view_point_m
            if isinstance(point, str) or not isinstance(point, Sequence | np.ndarray) or len(point) != 3:
                raise bad("view_point_m", "3 finite numbers (x, y, z in metres) or null")
            if not all(finite_number(v) for v in point):
                raise bad("view_point_m", "3 finite numbers (x, y, z in metres) or null")
            object.__setattr__(self, "view_point_m", tuple(float(v) for v in point))
        number("along_view_weight", "a number in (0, 1]", lambda v: 0.0 < v <= 1.0)
        count("popsize", 1, 1000)  # per parameter: 1000 x 10 parameters is 10000 rollouts per generation
        count("generations", 0)
        count("local_iterations", 0)
        number("fd_step", "a number in (0, 1) (a step in the unit search box)", lambda v: 0.0 < v < 1.0)
        number("interval_level", "a number in (0, 1)", lambda v: 0.0 < v < 1.0)
        count("seed", 0, MAX_SEED)
        count("nthread", 1, 256, optional=True)  # 1e5 threads hung the run
        number("max_batch_mb", "a finite number > 0 (MiB)", lambda v: v > 0.0)
        if not isinstance(self.initial, Mapping) or not all(
            isinstance(k, str) and finite_number(v) for k, v in self.initial.items()
        ):
            raise bad("initial", "a mapping of parameter names to finite numbers")
        object.__setattr__(self, "initial", {k: float(v) for k, v in self.initial.items()})
        if not isinstance(self.separate_bodies, bool | np.bool_):
            raise bad("separate_bodies", "true or false")
        object.__setattr__(self, "separate_bodies", bool(self.separate_bodies))
        number("robust_scale", "a finite number > 0", lambda v: v > 0.0, optional=True)
        if self.separate_bodies and self.mode != "raw":
            raise GrounderError("separate_bodies applies to raw mode only")
        if self.robust_scale is not None and self.mode != "raw":
            raise GrounderError("robust_scale applies to raw mode only (embedding mode weighs its prior by the misfit)")


@dataclass(frozen=True, kw_only=True)
class ParameterFit:
    """One fitted parameter, physical units.

    Attributes:
        name: Parameter name.
        nominal: The scene's value before calibration.
        value: The calibrated value.
        lower, upper: Search bounds.
        interval_low, interval_high: ``interval_level`` interval (clipped to the bounds).
        unit: Unit.
    """

    name: str
    nominal: float
    value: float
    lower: float
    upper: float
    interval_low: float
    interval_high: float
    unit: str


@dataclass(frozen=True, kw_only=True, eq=False)
class ErrorSummary:
    """Open-loop errors of one model on a set of trajectories (means over free bodies per trajectory).

    Attributes:
        names: Trajectory names.
        position_pct: (N,) time-average position error, percent of the body size.
        rotation_deg: (N,) time-average geodesic rotation error, degrees.
        loss: (N,) the calibration loss per trajectory.
    """

    names: tuple[str, ...]
    position_pct: np.ndarray
    rotation_deg: np.ndarray
    loss: np.ndarray

    def as_dict(self) -> dict[str, Any]:
        def stats(a: np.ndarray) -> dict[str, float]:
            return {"mean": float(np.mean(a)), "std": float(np.std(a))} if len(a) else {"mean": math.nan, "std": 0.0}

        return {
            "count": len(self.names),
            "position_pct_of_size": stats(self.position_pct),
            "rotation_deg": stats(self.rotation_deg),
            "loss": stats(self.loss),
            "per_trajectory": {
                n: {"position_pct": float(p), "rotation_deg": float(r)}
                for n, p, r in zip(self.names, self.position_pct, self.rotation_deg, strict=True)
            },
        }


@dataclass(frozen=True, kw_only=True, eq=False)
class CalibrationResult:
    """What a calibration found.

    Attributes:
        parameters: The fitted parameters, in the order given.
        train_names, validation_names: The split.
        before, after: Errors of the scene as given and as calibrated, per split: keys ``train``, ``validation``.
        model: The calibrated, compiled model.
        spec: The calibrated `MjSpec` (what ``scene.xml`` is written from).
        history: Best training loss after each stage step (DE generations, then least-squares iterations).
        evaluations: Number of (model, trajectory) rollouts simulated.
        steps_per_second: Model steps per second of wall time spent inside `mujoco.rollout` calls.
        eval_steps_per_second: Model steps per second of the whole evaluation (building models, rollout, losses).
        seconds: Wall time of the calibration.
        mode: ``raw`` or ``embedding``.
        out_dir: The calibrated scene folder, when one was written.
    """

    parameters: tuple[ParameterFit, ...]
    train_names: tuple[str, ...]
    validation_names: tuple[str, ...]
    before: dict[str, ErrorSummary]
    after: dict[str, ErrorSummary]
    model: mujoco.MjModel
    spec: mujoco.MjSpec
    history: tuple[float, ...]
    evaluations: int
    steps_per_second: float
    eval_steps_per_second: float
    seconds: float
    mode: str = "raw"
    out_dir: Path | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def values(self) -> dict[str, float]:
        """Calibrated values by parameter name."""
        return {p.name: p.value for p in self.parameters}

    @property
    def intervals(self) -> dict[str, tuple[float, float]]:
        """Intervals by parameter name."""
        return {p.name: (p.interval_low, p.interval_high) for p in self.parameters}

    def to_json(self) -> dict[str, Any]:
        """What ``calibration.json`` holds."""
        return {
            "mode": self.mode,
            "parameters": {
                p.name: {
                    "value": p.value,
                    "nominal": p.nominal,
                    "interval": [p.interval_low, p.interval_high],
                    "bounds": [p.lower, p.upper],
                    "unit": p.unit,
                }
                for p in self.parameters
            },
            "split": {"train": list(self.train_names), "validation": list(self.validation_names)},
            "errors": {
                "before": {k: v.as_dict() for k, v in self.before.items()},
                "after": {k: v.as_dict() for k, v in self.after.items()},
            },
            "history": list(self.history),
            "evaluations": self.evaluations,
            "steps_per_second": self.steps_per_second,
            "eval_steps_per_second": self.eval_steps_per_second,
            "seconds": self.seconds,
            **self.extra,
        }


# ----------------------------------------------------------------------------------------------------------------
# Scene loading and trajectory split


def load_scene(scene: Path) -> tuple[mujoco.MjSpec, mujoco.MjModel]:
    """The scene's `MjSpec` and compiled model.

    Raises:
        GrounderError: missing or unreadable MJCF.
    """
    xml = sim.scene_xml_path(scene)
    try:
        spec = mujoco.MjSpec.from_file(str(xml))
        model = spec.compile()
    except Exception as exc:  # mujoco raises ValueError for parse and compile errors
        raise GrounderError(f"{xml}: MuJoCo cannot load it ({' '.join(str(exc).split())})") from exc
    return spec, model


def split_names(
    names: Sequence[str], validation_fraction: float, seed: int, together: Sequence[Sequence[str]] = ()
) -> tuple[list[str], list[str]]:
    """The documented train/validation split (module docstring, step 1): returns (train, validation). Each group
    in ``together`` (copies of one motion, `grounder.core.repeats.repeated_motions`) stays on one side: the side the
    shuffle put its first member on."""
    ordered = sorted(names, key=_natural_key)
    if len(ordered) < 2 or validation_fraction <= 0:
        return ordered, []
    perm = np.random.default_rng(seed).permutation(len(ordered))
    n_val = min(max(1, round(validation_fraction * len(ordered))), len(ordered) - 1)
    val, train = split_keeping_together([ordered[i] for i in perm], n_val, together)
    return sorted(train, key=_natural_key), sorted(val, key=_natural_key)


def training_subset(train: Sequence[str], max_count: int | None, seed: int) -> list[str]:
    """A seeded subset of at most ``max_count`` training names (all when None)."""
    if max_count is None or max_count >= len(train):
        return list(train)
    pick = np.random.default_rng(seed + 1).choice(len(train), size=max_count, replace=False)
    return sorted((train[i] for i in pick), key=_natural_key)


# ----------------------------------------------------------------------------------------------------------------
# Batched evaluation


@dataclass(frozen=True, kw_only=True)
class _JointError:
    qpos_index: int
    scale: float  # error units per "percent": hinge 0.01 rad, slide 0.001 m


def pseudo_huber_residuals(res: np.ndarray, scale: float) -> np.ndarray:
    """Residuals whose squares are the pseudo-Huber function of `res` with this scale: quadratic below it, linear
    above, so least squares (and sums of squares) over them are robust to a few large residuals."""
    return scale * np.sqrt(2.0 * (np.sqrt(1.0 + (res / scale) ** 2) - 1.0))


class Evaluator:
    """Losses of many candidate parameter vectors on a fixed set of trajectories, each batch one `mujoco.rollout`.

    Trajectories are grouped by length so that short ones are not simulated to the length of the longest.
    """

    def __init__(
        self,
        base: mujoco.MjModel,
        params: Sequence[Parameter],
        trajs: Sequence[Trajectory],
        *,
        rotation_weight: float,
        view_point_m: Sequence[float] | None = None,
        along_view_weight: float = 1.0,
        nthread: int | None = None,
        max_batch_mb: float = 256.0,
        group_size: int = 16,
    ) -> None:
        if not trajs:
            raise GrounderError("no trajectories to evaluate")
        self.base = base
        self.params = list(params)
        self.trajs = list(trajs)
        self.rotation_weight = rotation_weight
        self.view_point_m = None if view_point_m is None else np.asarray(view_point_m, np.float64)
        self.along_view_weight = along_view_weight
        self.nthread = nthread or sim.default_nthread()
        self.max_batch_bytes = max_batch_mb * 2**20
        self._data = mujoco.MjData(base)
        self.qpos_at, _ = sim._offsets(base)
        self.free = sim.free_joints(base)
        self.sizes = [body_size_m(base, mujoco.mj_name2id(base, mujoco.mjtObj.mjOBJ_BODY, fj.body)) for fj in self.free]
        self.scalar: list[_JointError] = []
        for j in range(base.njnt):
            jtype = int(base.jnt_type[j])
            if jtype == mujoco.mjtJoint.mjJNT_HINGE:
                self.scalar.append(_JointError(qpos_index=int(base.jnt_qposadr[j]), scale=0.01))
            elif jtype == mujoco.mjtJoint.mjJNT_SLIDE:
                self.scalar.append(_JointError(qpos_index=int(base.jnt_qposadr[j]), scale=0.001))
        order = sorted(range(len(self.trajs)), key=lambda i: self.trajs[i].num_steps)
        self.groups = [order[i : i + group_size] for i in range(0, len(order), group_size)]
        self.batches = [sim.prepare(base, [self.trajs[i] for i in g]) for g in self.groups]
        self.rollouts = 0
        self.steps = 0
        self.rollout_seconds = 0.0
        self.eval_seconds = 0.0

    def models(self, values: np.ndarray) -> list[mujoco.MjModel]:
        """Models for (K, P) physical parameter vectors."""
        return [apply_to_model(self.base, self.params, row, data=self._data) for row in np.atleast_2d(values)]

    def errors(self, models: Sequence[mujoco.MjModel]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per (model, trajectory): position % of size, rotation degrees, loss; each (K, B)."""
        tick = time.perf_counter()
        k_count, b_count = len(models), len(self.trajs)
        pos = np.zeros((k_count, b_count))
        rot = np.zeros((k_count, b_count))
        joint = np.zeros((k_count, b_count))
        nstate = mujoco.mj_stateSize(self.base, sim.FULLPHYSICS)
        for group, batch in zip(self.groups, self.batches, strict=True):
            per_model_bytes = len(group) * (batch.nstep + 1) * nstate * 8 * 2
            chunk = max(1, int(self.max_batch_bytes // max(per_model_bytes, 1)))
            for start in range(0, k_count, chunk):
                sub = list(models[start : start + chunk])
                t0 = time.perf_counter()
                states = sim.rollout_states(sub, batch, nthread=self.nthread)
                self.rollout_seconds += time.perf_counter() - t0
                self.rollouts += len(sub) * len(group)
                self.steps += len(sub) * len(group) * batch.nstep
                for col, b in enumerate(group):
                    traj = self.trajs[b]
                    rows = states[:, col, batch.sample_steps[col], self.qpos_at : self.qpos_at + self.base.nq]
                    p_err = np.zeros(len(sub))
                    r_err = np.zeros(len(sub))
                    for fj, size in zip(self.free, self.sizes, strict=True):
                        seen_m = traj.qpos[None, :, fj.pos]
                        dpos = np.linalg.norm(
                            sim.along_view_weighted(
                                rows[:, :, fj.pos] - seen_m, seen_m, self.view_point_m, self.along_view_weight
                            ),
                            axis=2,
                        )
                        p_err += 100.0 * dpos.mean(axis=1) / size
                        ang = sim.quat_angle_rad(
                            rows[:, :, fj.quat], np.broadcast_to(traj.qpos[:, fj.quat], rows[:, :, fj.quat].shape)
                        )
                        r_err += np.degrees(ang.mean(axis=1))
                    if self.free:
                        p_err /= len(self.free)
                        r_err /= len(self.free)
                    j_err = np.zeros(len(sub))
                    for je in self.scalar:
                        j_err += (
                            np.abs(rows[:, :, je.qpos_index] - traj.qpos[None, :, je.qpos_index]).mean(1) / je.scale
                        )
                    pos[start : start + len(sub), b] = p_err
                    rot[start : start + len(sub), b] = r_err
                    joint[start : start + len(sub), b] = j_err
        loss = pos + self.rotation_weight * rot + joint
        loss[~np.isfinite(loss)] = 1e6
        self.eval_seconds += time.perf_counter() - tick
        return pos, rot, loss

    def loss_of_values(self, values: np.ndarray) -> np.ndarray:
        """Per (candidate, trajectory) loss (K, B) for (K, P) physical values."""
        _, _, loss = self.errors(self.models(values))
        return loss

    def summary(self, model: mujoco.MjModel) -> ErrorSummary:
        pos, rot, loss = self.errors([model])
        return ErrorSummary(
            names=tuple(t.name for t in self.trajs), position_pct=pos[0], rotation_deg=rot[0], loss=loss[0]
        )


# ----------------------------------------------------------------------------------------------------------------
# Search


def _to_values(params: Sequence[Parameter], unit: np.ndarray) -> np.ndarray:
    """(K, P) unit-box coordinates -> physical values."""
    unit = np.atleast_2d(unit)
    return np.stack([p.from_unit(unit[:, i]) for i, p in enumerate(params)], axis=1)


def _initial_unit(params: Sequence[Parameter], initial: dict[str, float]) -> np.ndarray:
    unknown = sorted(set(initial) - {p.name for p in params})
    if unknown:
        raise GrounderError(f"initial values given for {unknown}, which are not being calibrated")
    unit = _nominal_unit(params)
    for i, p in enumerate(params):
        if p.name in initial:
            unit[i] = float(np.clip(p.to_unit(float(initial[p.name])), 0.0, 1.0))
    return unit


def _nominal_unit(params: Sequence[Parameter]) -> np.ndarray:
    return np.array([float(np.clip(p.to_unit(p.nominal), 0.0, 1.0)) for p in params])


@dataclass(frozen=True, kw_only=True, eq=False)
class _Problem:
    """A search in the unit box: coordinates -> raw parameter values, and the residuals the fit minimises.

    Residuals of a point: ``sqrt(loss_b) / data_scale`` per trajectory, then ``prior(u)`` (embedding mode). The
    objective is their sum of squares divided by the number of trajectories (raw mode: the mean loss).
    """

    ev: Evaluator
    x0: np.ndarray
    values: Callable[[np.ndarray], np.ndarray]
    fixed: tuple[int, ...] = ()
    prior: Callable[[np.ndarray], np.ndarray] | None = None
    data_scale: float = 1.0
    robust_c: float | None = None  # pseudo-Huber scale of the per-trajectory residuals (CalibrateOptions.robust_scale)

    @property
    def free(self) -> list[int]:
        return [i for i in range(len(self.x0)) if i not in self.fixed]

    def residuals(self, u_rows: np.ndarray) -> np.ndarray:
        """(K, n) -> (K, R)."""
        u_rows = np.atleast_2d(u_rows)
        loss = self.ev.loss_of_values(self.values(u_rows))
        res = np.sqrt(np.maximum(loss, 0.0)) / self.data_scale
        if self.robust_c is not None:
            res = pseudo_huber_residuals(res, self.robust_c)
        if self.prior is not None:
            res = np.concatenate([res, self.prior(u_rows)], axis=1)
        return res

    def objective(self, u_rows: np.ndarray) -> np.ndarray:
        return np.sum(self.residuals(u_rows) ** 2, axis=1) / len(self.ev.trajs)


def _global_search(
    prob: _Problem, options: CalibrateOptions, report: ProgressFn, history: list[float]
) -> tuple[np.ndarray, float]:
    from scipy.optimize import differential_evolution

    n = len(prob.x0)
    best: dict[str, Any] = {"u": prob.x0, "loss": math.inf}

    def objective(u_cols: np.ndarray) -> np.ndarray:
        u = np.atleast_2d(u_cols.T) if u_cols.ndim == 2 else u_cols[None]
        loss = prob.objective(u)
        i = int(np.argmin(loss))
        if loss[i] < best["loss"]:
            best["u"], best["loss"] = u[i].copy(), float(loss[i])
        return loss

    generation = {"k": 0}

    def callback(*_args: Any, **_kwargs: Any) -> None:
        generation["k"] += 1
        history.append(best["loss"])
        report("global search (differential evolution)", generation["k"], options.generations)

    report("global search (differential evolution)", 0, options.generations)
    differential_evolution(
        objective,
        [(0.0, 1.0)] * n,
        popsize=options.popsize,
        maxiter=options.generations,
        seed=options.seed,
        x0=prob.x0,
        init="sobol" if n > 1 else "latinhypercube",
        vectorized=True,
        updating="deferred",
        polish=False,
        tol=0.0,
        callback=callback,
    )
    return best["u"], best["loss"]


def _local_refine(
    prob: _Problem, u0: np.ndarray, options: CalibrateOptions, report: ProgressFn, history: list[float]
) -> tuple[np.ndarray, float]:
    """Least squares over the free coordinates from ``u0``; choices (condim, cone) stay as in ``u0``."""
    from mujoco import minimize

    free = prob.free

    def full(cols: np.ndarray) -> np.ndarray:
        u = np.tile(u0, (len(cols), 1))
        u[:, free] = cols
        return u

    def residual(x: np.ndarray) -> np.ndarray:
        cols = np.atleast_2d(x.T)  # minimize passes (n, k): k points
        return prob.residuals(full(cols)).T  # (R, k)

    def on_iter(trace: list[Any]) -> None:
        history.append(float(2.0 * trace[-1].objective / len(prob.ev.trajs)))
        done = min(len(trace), options.local_iterations)
        report("local refinement (mujoco.minimize)", done, options.local_iterations)

    report("local refinement (mujoco.minimize)", 0, options.local_iterations)
    x, _trace = minimize.least_squares(
        u0[free].copy(),
        residual,
        bounds=[np.zeros(len(free)), np.ones(len(free))],
        eps=options.fd_step,
        max_iter=options.local_iterations,
        verbose=minimize.Verbosity.SILENT,
        iter_callback=on_iter,
    )
    u = full(np.asarray(x, dtype=np.float64).reshape(1, -1))[0]
    return u, float(prob.objective(u[None])[0])


def _jacobian(prob: _Problem, u: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (R,) at u and their central finite-difference Jacobian (R, len(free)) in unit coordinates."""
    free = prob.free
    cols = [u]
    steps = np.zeros(len(free))
    for k, i in enumerate(free):
        lo, hi = max(u[i] - step, 0.0), min(u[i] + step, 1.0)
        up, down = u.copy(), u.copy()
        up[i], down[i] = hi, lo
        steps[k] = hi - lo
        cols += [up, down]
    res = prob.residuals(np.stack(cols))  # (1 + 2 len(free), R)
    jac = np.stack([(res[1 + 2 * k] - res[2 + 2 * k]) / max(steps[k], 1e-12) for k in range(len(free))], axis=1)
    return res[0], jac.reshape(res.shape[1], len(free))


def body_groups(params: Sequence[Parameter]) -> list[list[int]]:
    """Parameter indices grouped by the body their name starts with (``BODY.friction.sliding`` -> ``BODY``).

    Raises:
        GrounderError: a parameter is not a body's (``geom:``, ``joint:``, ``actuator:``, ``opt.``).
    """
    groups: dict[str, list[int]] = {}
    for i, p in enumerate(params):
        head = p.name.split(".", 1)[0]
        if ":" in head or head == "opt":
            raise GrounderError(
                f"separate_bodies needs per-body parameters (BODY.*), got {p.name!r}; leave separate_bodies off"
            )
        groups.setdefault(head, []).append(i)
    return list(groups.values())


def _subproblem(prob: _Problem, group: Sequence[int], current: np.ndarray) -> _Problem:
    """The search over the coordinates in ``group`` only, the others held at ``current``."""
    index = list(group)

    def values(u_rows: np.ndarray) -> np.ndarray:
        u_rows = np.atleast_2d(u_rows)
        full = np.tile(current, (len(u_rows), 1))
        full[:, index] = u_rows
        return prob.values(full)

    return _Problem(
        ev=prob.ev,
        x0=current[index].copy(),
        values=values,
        fixed=tuple(k for k, i in enumerate(index) if i in prob.fixed),
        prior=None,
        data_scale=prob.data_scale,
        robust_c=prob.robust_c,
    )


def _search(
    prob: _Problem, options: CalibrateOptions, report: ProgressFn, groups: Sequence[Sequence[int]] | None = None
) -> tuple[np.ndarray, list[float]]:
    """Global then local search from ``prob.x0``; returns the best point and the loss history.

    With ``groups``, the search runs group by group (see ``CalibrateOptions.separate_bodies``).
    """
    if groups is not None and len(groups) > 1:
        current = prob.x0.copy()
        history = [float(prob.objective(current[None])[0])]
        for group in groups:
            sub_u, sub_history = _search(_subproblem(prob, group, current), options, report)
            current[list(group)] = sub_u
            history += sub_history[1:]
        return current, history
    history = [float(prob.objective(prob.x0[None])[0])]
    best_u, best_loss = prob.x0, history[0]
    if options.generations > 0:
        u, loss = _global_search(prob, options, report, history)
        if loss < best_loss:
            best_u, best_loss = u, loss
    if options.local_iterations > 0 and prob.free:
        u, loss = _local_refine(prob, best_u, options, report, history)
        if loss < best_loss:
            best_u, best_loss = u, loss
        history.append(best_loss)
    log.info("calibration: training objective %.3f -> %.3f", history[0], best_loss)
    return best_u, history


def _intervals_unit(residuals: np.ndarray, jac: np.ndarray, level: float) -> np.ndarray:
    """Half-widths (P,) in unit coordinates; inf where the data does not constrain the parameter."""
    from scipy.stats import norm

    dof = max(residuals.size - jac.shape[1], 1)
    s2 = float(residuals @ residuals) / dof
    hess = jac.T @ jac
    lam, vec = np.linalg.eigh(hess)
    lam_max = float(lam.max(initial=0.0))
    half = np.empty(jac.shape[1])
    z = float(norm.ppf(0.5 + level / 2.0))
    for j in range(jac.shape[1]):
        acc = 0.0
        vmax = float(np.max(np.abs(vec[j]))) or 1.0
        for i in range(len(lam)):
            li = lam[i] if lam_max > 0 and lam[i] / lam_max >= 1e-12 else 0.0
            vji = vec[j, i] if abs(vec[j, i] / vmax) >= 1e-8 else 0.0
            if li == 0.0 and vji != 0.0:
                acc = math.inf
                break
            if li != 0.0:
                acc += vji**2 / li
        half[j] = z * math.sqrt(s2 * acc) if math.isfinite(acc) else math.inf
    return half


# ----------------------------------------------------------------------------------------------------------------
# Public entry point


def _raw_fits(
    prob: _Problem, params: Sequence[Parameter], best_u: np.ndarray, options: CalibrateOptions, report: ProgressFn
) -> tuple[np.ndarray, list[ParameterFit]]:
    """Values and intervals (module docstring, step 5) of raw mode at the optimum."""
    report("intervals", 0, 1)
    half = np.zeros(len(params))  # a choice is reported as itself
    if prob.free:
        residuals, jac = _jacobian(prob, best_u, options.fd_step)
        half[prob.free] = _intervals_unit(residuals, jac, options.interval_level)
    values = _to_values(params, best_u[None])[0]
    fits = []
    for i, p in enumerate(params):
        if p.discrete:
            lo = hi = float(values[i])
        else:
            lo = p.lower if not math.isfinite(half[i]) else float(p.from_unit(best_u[i] - half[i]))
            hi = p.upper if not math.isfinite(half[i]) else float(p.from_unit(best_u[i] + half[i]))
        fits.append(
            ParameterFit(
                name=p.name,
                nominal=p.nominal,
                value=float(values[i]),
                lower=p.lower,
                upper=p.upper,
                interval_low=lo,
                interval_high=hi,
                unit=p.unit,
            )
        )
    report("intervals", 1, 1)
    return values, fits


def _fit_embedding(
    scene: Path,
    base: mujoco.MjModel,
    fit_trajs: Sequence[Trajectory],
    options: CalibrateOptions,
    common: dict[str, Any],
    report: ProgressFn,
) -> tuple[list[Parameter], np.ndarray, list[ParameterFit], Evaluator, list[float], dict[str, Any]]:
    """Embedding mode (see grounder.calibration.embedding): MAP embedding, posterior, decoded raw parameters."""
    import grounder.calibration.embedding as emb

    if options.params:
        raise GrounderError("--params does not apply to embedding mode (it fits the property embedding); leave it out")
    space = emb.embedding_space(scene, base)
    params = list(space.params)
    ev = Evaluator(base, params, fit_trajs, **common)
    x0 = emb.to_unit(np.zeros(space.dim))
    prior_loss = ev.loss_of_values(space.values(np.zeros((1, space.dim))))[0]

    def values_of(u: np.ndarray) -> np.ndarray:
        return space.values(emb.from_unit(u))

    # 1. Data only (from the prior mean): the misfit left at its optimum is the noise scale s^2 of the posterior.
    fit_u, history = _search(_Problem(ev=ev, x0=x0, values=values_of), options, report)
    misfit = float(ev.loss_of_values(values_of(fit_u[None]))[0].mean())
    data_scale = math.sqrt(max(misfit, 1e-6))
    # 2. The posterior's mode: least squares on [sqrt(loss_b) / s, w] from the data-only optimum.
    prob = _Problem(ev=ev, x0=x0, values=values_of, prior=emb.from_unit, data_scale=data_scale)
    best_u = fit_u
    if options.local_iterations > 0:
        u, _ = _local_refine(prob, fit_u, options, report, [])
        if prob.objective(u[None])[0] <= prob.objective(fit_u[None])[0]:
            best_u = u
        history.append(float(ev.loss_of_values(values_of(best_u[None]))[0].mean()))
    report("intervals", 0, 1)
    _, jac = _jacobian(prob, best_u, options.fd_step)
    jac_w = jac / (2 * emb.W_BOUND)  # d residual / d w
    cov_w = np.linalg.pinv(jac_w.T @ jac_w)
    w = emb.from_unit(best_u)
    values = space.values(w[None])[0]
    samples = emb.posterior_samples(space, w, cov_w, count=200, seed=options.seed)
    prior_samples = emb.posterior_samples(space, np.zeros(space.dim), np.eye(space.dim), count=200, seed=options.seed)
    alpha = 50.0 * (1.0 - options.interval_level)
    fits = []
    for i, p in enumerate(params):
        fits.append(
            ParameterFit(
                name=p.name,
                nominal=p.nominal,
                value=float(values[i]),
                lower=float(np.percentile(prior_samples[:, i], 0.5)),
                upper=float(np.percentile(prior_samples[:, i], 99.5)),
                interval_low=float(np.percentile(samples[:, i], alpha)),
                interval_high=float(np.percentile(samples[:, i], 100.0 - alpha)),
                unit=p.unit,
            )
        )
    report("intervals", 1, 1)
    w_std = np.sqrt(np.maximum(np.diag(cov_w), 0.0))
    extra = {
        "embedding": emb.summaries(space, w, w_std),
        "embedding_objective": {
            "prior_mean_loss": float(prior_loss.mean()),
            "data_only_loss": misfit,
            "noise_scale_s2": data_scale**2,
        },
    }
    return params, values, fits, ev, history, extra


def _check_trajectories(model: mujoco.MjModel, trajs: Sequence[Trajectory]) -> None:
    if not trajs:
        raise GrounderError("no trajectories to calibrate on; pass a folder with at least one .npz trajectory")
    names = [t.name for t in trajs]
    if len(set(names)) != len(names):
        raise GrounderError("trajectory names must be unique; the split is made by name")
    for t in trajs:
        validate_against_model(t, model)
        sim.step_indices(t.time_s, model.opt.timestep, t.name)


def calibrate(
    scene: Path,
    trajs: Sequence[Trajectory],
    *,
    options: CalibrateOptions | None = None,
    out: Path | None = None,
    progress: ProgressFn | None = None,
) -> CalibrationResult:
    """Fits the scene's physical parameters to recorded trajectories.

    Args:
        scene: An MJCF file, or a scene folder holding ``scene.xml``.
        trajs: Recorded trajectories in the scene's joint order (uniquely named).
        options: Parameters, split, search budget; defaults: the scene kind's parameters (module docstring).
        out: If given, the calibrated scene folder to write (must not exist or be empty): ``scene.xml`` (and the
            source folder's other files and assets), ``calibration.json``, ``report.html``. Written in a temporary
            sibling folder and moved into place at the end.
        progress: ``progress(stage, done, total)`` callback.

    Returns:
        The fitted parameters with intervals, errors before/after on both splits, the calibrated model and spec.

    Raises:
        GrounderError: the scene cannot be loaded, a trajectory does not fit it, a parameter name is unknown, there
            are no trajectories, the output folder is not empty, or embedding mode is asked of a scene without a
            property embedding.
    """
    options = options or CalibrateOptions()
    report: ProgressFn = progress or (lambda _s, _d, _t: None)
    tick = time.perf_counter()
    scene = Path(scene)
    if out is not None:
        out = Path(out)
        if out.exists() and (not out.is_dir() or any(out.iterdir())):
            raise GrounderError(f"{out}: output folder exists and is not empty; choose a new folder")
    spec, base = load_scene(scene)
    if out is not None:
        _check_manifest(scene)
        sim.check_links_stay_inside(scene, NOT_COPIED)
    _check_trajectories(base, trajs)
    by_name = {t.name: t for t in trajs}
    repeats = repeated_motions(trajs, base) if options.validation_fraction > 0 else []  # no split, nothing to keep
    if repeats:
        log.warning(
            "%s; each kept on one side of the split (remove the copies if they are not meant to weigh double)",
            describe_repeats(repeats),
        )
    train_names, val_names = split_names(list(by_name), options.validation_fraction, options.split_seed, repeats)
    fit_names = training_subset(train_names, options.max_train_trajectories, options.split_seed)
    fit_trajs = [by_name[n] for n in fit_names]
    common: dict[str, Any] = {
        "rotation_weight": options.rotation_weight,
        "view_point_m": options.view_point_m,
        "along_view_weight": options.along_view_weight,
        "nthread": options.nthread,
        "max_batch_mb": options.max_batch_mb,
    }
    extra: dict[str, Any] = {}
    if options.mode == "embedding":
        params, values, fits, ev, history, extra = _fit_embedding(scene, base, fit_trajs, options, common, report)
    else:
        params = resolve_parameters(base, options.params)
        ev = Evaluator(base, params, fit_trajs, **common)
        prob = _Problem(
            ev=ev,
            x0=_initial_unit(params, options.initial),
            values=lambda u: _to_values(params, u),
            fixed=tuple(i for i, p in enumerate(params) if p.discrete),
        )
        if options.robust_scale is not None:
            start = np.sqrt(np.maximum(ev.loss_of_values(prob.values(prob.x0[None]))[0], 0.0))
            prob = replace(prob, robust_c=max(options.robust_scale * float(np.median(start)), 1e-9))
        groups = body_groups(params) if options.separate_bodies else None
        best_u, history = _search(prob, options, report, groups)
        values, fits = _raw_fits(prob, params, best_u, options, report)

    calibrated_spec = apply_to_spec(spec, base, params, values)
    try:
        calibrated = calibrated_spec.compile()
    except Exception as exc:
        raise GrounderError(f"the calibrated scene does not compile ({exc})") from exc

    report("validation", 0, 1)
    before: dict[str, ErrorSummary] = {}
    after: dict[str, ErrorSummary] = {}
    for split, names in (("train", train_names), ("validation", val_names)):
        if not names:
            continue
        split_ev = Evaluator(base, params, [by_name[n] for n in names], **common)
        before[split] = split_ev.summary(base)
        after[split] = split_ev.summary(calibrated)
    report("validation", 1, 1)

    result = CalibrationResult(
        parameters=tuple(fits),
        train_names=tuple(train_names),
        validation_names=tuple(val_names),
        before=before,
        after=after,
        model=calibrated,
        spec=calibrated_spec,
        history=tuple(history),
        evaluations=ev.rollouts,
        steps_per_second=ev.steps / max(ev.rollout_seconds, 1e-9),
        eval_steps_per_second=ev.steps / max(ev.eval_seconds, 1e-9),
        seconds=time.perf_counter() - tick,
        mode=options.mode,
        extra={
            **extra,
            "scene": str(scene),
            "fit_trajectories": fit_names,
            "repeated_trajectories": [list(g) for g in repeats],
            "options": {
                k: (list(v) if isinstance(v, tuple) else v) for k, v in options.__dict__.items() if k != "nthread"
            },
        },
    )
    if out is not None:
        report("writing", 0, 1)
        write_calibrated_scene(scene, result, [by_name[n] for n in val_names or train_names], out, base)
        result = CalibrationResult(**{**result.__dict__, "out_dir": out})
        report("writing", 1, 1)
    return result


# ----------------------------------------------------------------------------------------------------------------
# Output


# Not copied from the scene folder: what calibrate writes anew, the large unchanged reconstruction, and a learned
# residual, which was trained against the uncalibrated model and no longer applies.
NOT_COPIED = ("scene.xml", "calibration.json", "report.html", "reconstruction", *RESIDUAL_FILES)


def _check_manifest(scene: Path) -> None:
    """A scene folder's ``scene.json``, which the calibrated folder carries with a note (`_note_in_manifest`), must be
    readable JSON: found before the calibration runs, not after.

    Raises:
        GrounderError: scene.json cannot be read or parsed (including nesting deeper than the parser allows).
    """
    manifest = Path(scene) / "scene.json"
    if not Path(scene).is_dir() or not manifest.is_file():
        return
    read_json_file(manifest, "restore it (re-run `image2sim ground` for this scene) or remove it from the scene folder")


def _note_in_manifest(manifest: Path, result: CalibrationResult) -> None:
    """Records in a copied ``scene.json`` that scene.xml was calibrated, and with which values.

    The file is replaced (a temporary file renamed over it), never written through: a copied link would otherwise
    lead the write to the file it points at, outside the output folder.
    """
    if not manifest.is_file():
        return
    try:
        data = json.loads(manifest.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):  # checked by calibrate() first; changed since: copied as it is
        return
    if isinstance(data, dict):
        data["calibration"] = {
            "file": "calibration.json",
            "mode": result.mode,
            "parameters": result.values,
            "note": "scene.xml holds the calibrated values; per-object entries above are from before calibration",
        }
        write_text_atomic(manifest, json.dumps(data, indent=1) + "\n")


def write_calibrated_scene(
    scene: Path,
    result: CalibrationResult,
    report_trajs: Sequence[Trajectory],
    out: Path,
    base: mujoco.MjModel,
) -> Path:
    """Writes ``out``: calibrated ``scene.xml`` (+ assets), ``calibration.json``, ``report.html``; atomically."""
    from image2sim_common.outdir import staged_output_dir  # here: importing `reconstruction` loads pycolmap

    scene = Path(scene)
    out = Path(out)
    # The claim, the short staging names and the second look at `out` before the move are `staged_output_dir`'s: a
    # folder that appeared at `out` while calibrating is left as it is, and the result kept beside it.
    with staged_output_dir(out, error=GrounderError, inputs=(scene,)) as stage:
        sim.copy_scene_files(scene, stage, skip=NOT_COPIED)
        (stage / "scene.xml").write_text(result.spec.to_xml())
        _note_in_manifest(stage / "scene.json", result)
        # The written MJCF must reproduce the calibrated model: a drifted writer would silently lose the fit.
        reloaded = mujoco.MjModel.from_xml_path(str(stage / "scene.xml"))
        if reloaded.nq != base.nq or reloaded.nv != base.nv:
            raise GrounderError("the written scene.xml does not match the scene's joints")
        (stage / "calibration.json").write_text(json.dumps(result.to_json(), indent=1) + "\n")
        from grounder.calibration.report import write_report

        write_report(stage / "report.html", result, base, report_trajs)
    return out
