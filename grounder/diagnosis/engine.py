"""The diagnosis's setting (:class:`DiagnoseOptions`) and its engine: batched evaluation of candidate models on fixed
window sets, the parameter search, and the scores an effect gets (held-out reduction, bootstrap interval, penalty).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from grounder.core.trajectory import Trajectory
from grounder.diagnosis.effects import (
    AppliedEffect,
    Effect,
    apply_effects,
)
from grounder.diagnosis.gap import (
    Group,
    Scores,
    Windows,
    coordinate_groups,
    make_windows,
    predict,
    rms,
    score,
)
from grounder.diagnosis.result import EffectResult
from grounder.sim.rollout import default_nthread


@dataclass(frozen=True, kw_only=True)
class DiagnoseOptions:
    """The one setting of the diagnosis (used unchanged for every case of the withheld-effect benchmark).

    Attributes:
        effects: effect names to test; None = every library effect that can act on the model.
        holdout_fraction: share of trajectories held out for scoring (at least 2 held out, 2 for training).
        seed: seeds the split and the bootstrap.
        horizon_s: length of the short-horizon windows (re-started from the recorded state).
        robust_scale: ``c`` of the gap metric's Cauchy function (None: plain RMS); see :mod:`grounder.diagnosis.gap`.
        max_effects: at most this many effects are selected.
        min_gain: an effect is added only if it cuts the current held-out gap by at least this fraction (after
            the complexity penalty).
        complexity_penalty: subtracted from a held-out reduction per fitted parameter.
        search_rounds: refinement rounds of the batched parameter search after the initial grid (two fewer for
            a single parameter, whose rounds shrink four-fold from the grid's spacing).
        n_bootstrap: bootstrap resamples of the held-out trajectories.
        noise_stop_ratio: no effect is added after the first once the held-out gap is within this factor of the
            noise floor (the gap a perfect model shows at the recording's estimated noise level).
        shortlist: effects re-fitted in each greedy step after the first (best of the first ranking).
        localise: in a scene of several bodies or contact pairs, also fit each contact and body effect on the
            bodies and contact pairs where the gap is largest (``local_bodies`` and ``local_pairs`` of them); a
            localised variant pays ``complexity_penalty`` once more than the global one (the choice of where).
        velocity_smoothing_frames: the recorded velocities are a Savitzky-Golay derivative of the positions over
            this many frames (tracked video; set from ``track.json`` by `diagnose_files`): the noise floor then
            counts the position noise that derivative carries into them (`grounder.diagnosis.noise`).
        nthread: rollout threads (default: the CPU cores this process may use).
    """

    effects: tuple[str, ...] | None = None
    holdout_fraction: float = 0.3
    seed: int = 0
    horizon_s: float = 0.25
    robust_scale: float | None = 1.0
    max_effects: int = 3
    min_gain: float = 0.1
    complexity_penalty: float = 0.02
    search_rounds: int = 5
    n_bootstrap: int = 1000
    noise_stop_ratio: float = 1.3
    shortlist: int = 5
    localise: bool = True
    local_bodies: int = 1
    local_pairs: int = 1
    velocity_smoothing_frames: int | None = None
    nthread: int | None = None


class Engine:
    """Batched evaluation of candidate models on fixed window sets."""

    def __init__(
        self, model: mujoco.MjModel, train: list[Trajectory], held: list[Trajectory], options: DiagnoseOptions
    ):
        from mujoco import rollout as mj_rollout

        self.model = model
        self.options = options
        self.groups: list[Group] = coordinate_groups(model)
        self.nthread = options.nthread or default_nthread()
        self.runner = mj_rollout.Rollout(nthread=self.nthread)
        self.train, self.held = train, held
        self.train_w = make_windows(model, train, options.horizon_s)
        self.held_w = make_windows(model, held, options.horizon_s)
        self.evaluations = 0

    def close(self) -> None:
        self.runner.close()

    def scores(self, applied_sets: Sequence[list[AppliedEffect]], windows: Windows, n_traj: int) -> Scores:
        cands = [apply_effects(self.model, a) for a in applied_sets]
        self.evaluations += len(cands)
        pred = predict(cands, windows, self.runner, self.nthread)
        return score(pred, windows, self.groups, n_traj, self.options.robust_scale)

    def per_traj(self, applied_sets: Sequence[list[AppliedEffect]], windows: Windows, n_traj: int) -> np.ndarray:
        return self.scores(applied_sets, windows, n_traj).per_traj

    def count(self, windows: Windows, n_traj: int) -> np.ndarray:
        out = np.zeros(n_traj)
        np.add.at(out, windows.traj_index, windows.mask.sum(axis=1))
        return out

    def fit(
        self,
        base: list[AppliedEffect],
        effects: list[Effect],
        init: list[dict[str, float]] | None = None,
        slot_mask: np.ndarray | None = None,
    ) -> tuple[list[AppliedEffect], float]:
        """Fits the parameters of ``effects`` jointly on top of ``base`` (fixed) on the training windows.

        A batched shrinking search in the unit box of the parameters: a grid (or Sobol points) over the whole box
        with the nominal point, then rounds of points around the best so far (``search_rounds`` halving ones; for
        one parameter ``search_rounds - 2`` quartering ones), each round one ``mujoco.rollout`` call.
        """
        params = [(e, p) for e in effects for p in e.params_of(self.model)]
        dim = len(params)
        start = np.array(
            [p.to_unit((init[effects.index(e)] if init else e.nominal_of(self.model))[p.name]) for e, p in params]
        )
        count = self.count(self.train_w, len(self.train))

        def unpack(u: np.ndarray) -> list[AppliedEffect]:
            out = list(base)
            k = 0
            for e in effects:
                values = {}
                for p in e.params_of(self.model):
                    values[p.name] = float(p.from_unit(np.array(u[k])))
                    k += 1
                out.append(AppliedEffect(effect=e, values=values))
            return out

        def losses(points: np.ndarray) -> np.ndarray:
            if slot_mask is not None:
                sq = self.scores([unpack(u) for u in points], self.train_w, len(self.train)).sq.mean(axis=-1)
                return (sq * slot_mask[None]).sum(axis=(1, 2)) / max(int(slot_mask.sum()), 1)
            per = self.per_traj([unpack(u) for u in points], self.train_w, len(self.train))
            return per.sum(axis=1) / max(count.sum(), 1)

        rng = np.random.default_rng(self.options.seed)
        if init is not None:
            points = np.vstack([start, np.clip(start + rng.uniform(-0.1, 0.1, (4 * dim, dim)), 0, 1)])
            radii = [0.05, 0.02][: self.options.search_rounds]
        else:
            if dim == 1:
                grid = np.linspace(0.0, 1.0, 9)[:, None]
            else:
                from scipy.stats import qmc

                grid = qmc.Sobol(dim, scramble=True, seed=self.options.seed).random_base2(
                    int(np.ceil(np.log2(8 * dim)))
                )
                grid = np.vstack([grid, np.full((1, dim), 0.5)])
            points = np.vstack([start[None], grid])
            if dim == 1:
                # The grid's spacing is 1/8, so the best grid point is within 1/16 of the optimum: each round looks
                # at +-r and +-r/2 and the next r is a quarter (resolution 1/512 after three rounds).
                radii = [0.0625 / 4**k for k in range(max(1, self.options.search_rounds - 2))]
            else:
                radii = [1.5 * 0.25 / 2**k for k in range(self.options.search_rounds)]
        vals = losses(points)
        best_u, best = points[int(np.argmin(vals))], float(np.min(vals))
        for r in radii:
            if dim == 1:
                offsets = np.array([-1.0, -0.5, 0.5, 1.0])[:, None] * r
            else:
                offsets = rng.uniform(-r, r, (4 * dim, dim))
            pts = np.clip(best_u[None] + offsets, 0.0, 1.0)
            vals = losses(pts)
            if float(np.min(vals)) < best:
                best_u, best = pts[int(np.argmin(vals))], float(np.min(vals))
        return unpack(best_u), float(np.sqrt(best))


def _resampled_reductions(before: np.ndarray, after: np.ndarray, rng: np.random.Generator, n_boot: int) -> np.ndarray:
    """(n_boot,) 1 - sqrt(sum after / sum before) over trajectories resampled with replacement."""
    n = len(before)
    idx = rng.integers(0, n, (n_boot, n))
    return 1.0 - np.sqrt(after[idx].sum(axis=1) / np.maximum(before[idx].sum(axis=1), 1e-300))


def bootstrap_reduction(
    before: np.ndarray, after: np.ndarray, rng: np.random.Generator, n_boot: int
) -> tuple[float, float]:
    """95% interval of the held-out reduction (`_resampled_reductions`)."""
    red = _resampled_reductions(before, after, rng, n_boot)
    return float(np.percentile(red, 2.5)), float(np.percentile(red, 97.5))


def lower_bound(before: np.ndarray, after: np.ndarray, rng: np.random.Generator, n_boot: int) -> float:
    """One-sided 5% lower bound of the held-out reduction (`_resampled_reductions`)."""
    return float(np.percentile(_resampled_reductions(before, after, rng, n_boot), 5.0))


def penalty_of(effect: Effect, model: mujoco.MjModel, options: DiagnoseOptions) -> float:
    """Complexity penalty: per fitted parameter, and once more for a localised effect (where it acts is a choice)."""
    return options.complexity_penalty * (len(effect.params_of(model)) + (effect.target.kind != "all"))


def effect_result(
    effect: Effect,
    fitted: AppliedEffect,
    model: mujoco.MjModel,
    train_gap: float,
    before: np.ndarray,
    after: np.ndarray,
    count: np.ndarray,
    options: DiagnoseOptions,
    rng: np.random.Generator,
) -> EffectResult:
    g0, g1 = rms(before, count), rms(after, count)
    reduction = 1.0 - g1 / max(g0, 1e-300)
    return EffectResult(
        effect=effect.name,
        target=effect.target,
        kind=effect.kind_of(model),
        params=fitted.values,
        nominal_params=effect.nominal_of(model),
        train_gap_after=train_gap,
        heldout_gap_before=g0,
        heldout_gap_after=g1,
        heldout_reduction=reduction,
        ci=bootstrap_reduction(before, after, rng, options.n_bootstrap),
        score=reduction - penalty_of(effect, model, options),
        per_traj_after=after,
    )
