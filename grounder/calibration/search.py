"""The search of a calibration in the unit box of its parameters (the `grounder.calibration.fit` module docstring,
steps 3 to 5): `_Problem` (coordinates -> values -> residuals), differential evolution, `mujoco.minimize` least
squares, the finite-difference Jacobian, the search body by body (``separate_bodies``) and the Gauss-Newton
intervals in unit coordinates.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from grounder.calibration.evaluator import Evaluator, pseudo_huber_residuals
from grounder.calibration.options import CalibrateOptions
from grounder.calibration.parameters import Parameter
from grounder.errors import GrounderError
from image2sim_common.progress import ProgressFn

log = logging.getLogger(__name__)


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


LOCAL_MU_FACTOR = 10.0**0.5


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
        # A rejected step raises the damping by 10^0.5 (mujoco.minimize: 10^0.1). The contact losses are rough and
        # most trial steps fail at first; each failure costs a rollout of every trajectory, one candidate at a time:
        # on the 280 real training tosses 47 evaluations per iteration at 10^0.1.
        mu_factor=LOCAL_MU_FACTOR,
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
    prob: _Problem,
    options: CalibrateOptions,
    report: ProgressFn,
    groups: Sequence[Sequence[int]] | None = None,
    global_prob: _Problem | None = None,
) -> tuple[np.ndarray, list[float]]:
    """Global then local search from ``prob.x0``; returns the best point and the loss history.

    With ``groups``, the search runs group by group (see ``CalibrateOptions.separate_bodies``). With ``global_prob``
    (the same search on a subset of the trajectories, `CalibrateOptions.global_search_trajectories`), the global
    search scores its candidates there; its best is scored again on ``prob``, which the local refinement minimises.
    """
    if groups is not None and len(groups) > 1:
        current = prob.x0.copy()
        history = [float(prob.objective(current[None])[0])]
        for group in groups:
            sub_global = None if global_prob is None else _subproblem(global_prob, group, current)
            sub_u, sub_history = _search(_subproblem(prob, group, current), options, report, global_prob=sub_global)
            current[list(group)] = sub_u
            history += sub_history[1:]
        return current, history
    history = [float(prob.objective(prob.x0[None])[0])]
    best_u, best_loss = prob.x0, history[0]
    if options.generations > 0:
        u, loss = _global_search(global_prob or prob, options, report, history)
        if global_prob is not None:
            loss = float(prob.objective(u[None])[0])
            history.append(loss)
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
