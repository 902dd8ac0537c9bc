"""Sim-to-real gap diagnosis: where the gap lies, which unmodelled effect causes it, how far it shrinks.

Steps (one fixed setting for every input; see :class:`DiagnoseOptions`):

1. **Split** the trajectories into training and held-out ones (seeded shuffle; copies of one motion,
   `grounder.core.repeats`, kept on one side).
2. **Where.** Re-simulate every trajectory with the nominal model, short-horizon (re-started from the recorded
   state every ``horizon_s``) and open-loop, and break the normalised gap (:data:`grounder.diagnosis.gap.GAP_METRIC`)
   down by body, coordinate group, phase (free flight, impact, sliding, rolling, resting, actuated, free motion;
   detected from the recorded motion and the nominal model's contacts at the recorded states) and time.
3. **Which.** Fit each library effect's few parameters on the training trajectories by a batched shrinking search
   (every round simulates all candidate models x training windows in one ``mujoco.rollout`` call), score it on the
   held-out trajectories, bootstrap the held-out reduction over trajectories, and rank by reduction minus a
   complexity penalty per parameter.
4. **How far.** Add effects greedily, each re-fitted on top of those already selected, while the held-out gap keeps
   falling by at least ``min_gain`` (relative, after the penalty) with a bootstrap lower bound above zero.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from grounder.core.repeats import describe_repeated_indices, repeated_motion_indices, split_keeping_together
from grounder.core.trajectory import Trajectory, load_trajectories, validate_against_model
from grounder.diagnosis.effects import (
    AppliedEffect,
    Effect,
    apply_effects,
    resolve_effects,
)
from grounder.diagnosis.gap import (
    GAP_METRIC,
    GAP_METRIC_PLAIN,
    Group,
    Scores,
    Windows,
    coordinate_groups,
    make_windows,
    predict,
    rms,
    score,
)
from grounder.diagnosis.noise import add_noise, estimate_noise
from grounder.diagnosis.outputs import write_outputs
from grounder.diagnosis.phases import PHASES, detect_phases, phase_reductions, window_labels
from grounder.diagnosis.result import Diagnosis, EffectResult
from grounder.diagnosis.targets import Layout, Target, body_target, contacts_at_samples, pair_target, prepare
from grounder.errors import GrounderError
from grounder.sim.rollout import default_nthread
from grounder.sim.scene_files import load_scene_model
from image2sim_common.progress import ProgressFn, no_progress
from reconstruction import check_output_dir

log = logging.getLogger(__name__)

LOCALISE_MIN_REDUCTION = 0.02
"""An effect family is tried on single bodies and contact pairs when its global variant cuts the held-out gap by at
least this much (a change on one body also shows, diluted, as a change on all)."""


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


# ------------------------------------------------------------------------------------------------------- validation
def check_inputs(model: mujoco.MjModel, trajs: Sequence[Trajectory], options: DiagnoseOptions) -> None:
    """Fails before any work on input the diagnosis cannot use.

    Raises:
        GrounderError: dimension mismatch, bad quaternions, unknown effect names, a bad hold-out fraction, or too
            few trajectories for a held-out split.
    """
    for traj in trajs:
        validate_against_model(traj, model)
    if not 0.0 < options.holdout_fraction < 1.0:
        raise GrounderError(f"--holdout must be between 0 and 1 (exclusive), got {options.holdout_fraction}")
    n_hold = _n_holdout(len(trajs), options.holdout_fraction)
    if n_hold < 2 or len(trajs) - n_hold < 2:
        raise GrounderError(
            f"{len(trajs)} trajectories with --holdout {options.holdout_fraction:g} leave {len(trajs) - n_hold} for "
            f"training and {n_hold} held out; the diagnosis needs at least 2 of each: record more trajectories "
            f"(8 or more recommended)"
        )
    sample_s = max(float(np.median(np.diff(t.time_s))) for t in trajs)
    if not (math.isfinite(options.horizon_s) and options.horizon_s >= sample_s):
        raise GrounderError(
            f"--horizon {options.horizon_s:g} s is shorter than the recordings' sample interval ({sample_s:.4g} s) "
            "or not finite: a window needs two samples; pass a horizon of a few samples or more"
        )
    resolve_effects(list(options.effects) if options.effects is not None else None, model)
    if model.nu and any(t.ctrl is None for t in trajs):
        raise GrounderError("the model has actuators but the trajectories carry no 'ctrl'; record the controls")


def _n_holdout(n: int, fraction: float) -> int:
    return round(n * fraction)


def _holdout_split(
    model: mujoco.MjModel, trajs: Sequence[Trajectory], order: list[int], options: DiagnoseOptions
) -> tuple[list[int], list[int]]:
    """(held-out, training) indices: the first ``_n_holdout`` of the shuffled ``order``, copies of one motion
    (`grounder.core.repeats`) kept on one side, unless that would leave fewer than 2 on a side (then as shuffled)."""
    n_hold = _n_holdout(len(trajs), options.holdout_fraction)
    repeats = repeated_motion_indices(trajs, model)
    held, train = split_keeping_together(order, n_hold, repeats)
    if repeats:
        named = describe_repeated_indices(trajs, repeats)
        if len(held) < 2 or len(train) < 2:
            log.warning(
                "%s; too few trajectories to keep each on one side of the held-out split, so held-out scores may "
                "count copies of training trajectories",
                named,
            )
            return order[:n_hold], order[n_hold:]
        log.warning("%s; each kept on one side of the held-out split", named)
    return held, train


# ------------------------------------------------------------------------------------------------------------- phases
# ------------------------------------------------------------------------------------------------------- the engine
class _Engine:
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


def _bootstrap_reduction(
    before: np.ndarray, after: np.ndarray, rng: np.random.Generator, n_boot: int
) -> tuple[float, float]:
    """95% interval of 1 - sqrt(sum after / sum before) over trajectories resampled with replacement."""
    n = len(before)
    idx = rng.integers(0, n, (n_boot, n))
    b = before[idx].sum(axis=1)
    a = after[idx].sum(axis=1)
    red = 1.0 - np.sqrt(a / np.maximum(b, 1e-300))
    return float(np.percentile(red, 2.5)), float(np.percentile(red, 97.5))


def _lower_bound(before: np.ndarray, after: np.ndarray, rng: np.random.Generator, n_boot: int) -> float:
    n = len(before)
    idx = rng.integers(0, n, (n_boot, n))
    red = 1.0 - np.sqrt(after[idx].sum(axis=1) / np.maximum(before[idx].sum(axis=1), 1e-300))
    return float(np.percentile(red, 5.0))


# ----------------------------------------------------------------------------------------------------- breakdowns
def _breakdown(
    engine: _Engine,
    trajs: list[Trajectory],
    applied: list[AppliedEffect],
    contacts: Sequence[list[frozenset[tuple[str, str]]]],
    layout: Layout,
) -> dict[str, Any]:
    """Gap of a model on trajectories: total, by body, by contact pair, by coordinate group, by phase, over time;
    both measures."""
    model = engine.model
    out: dict[str, Any] = {}
    phases = [detect_phases(model, t) for t in trajs]
    for name, horizon in (("short_horizon", engine.options.horizon_s), ("open_loop", None)):
        windows = make_windows(model, trajs, horizon)
        cand = apply_effects(model, applied)
        pred = predict([cand], windows, engine.runner, engine.nthread)
        sc = score(pred, windows, engine.groups, len(trajs), engine.options.robust_scale)
        sq = sc.sq[0]  # (W, S, G)
        mask = windows.mask
        n = max(int(mask.sum()), 1)
        entry: dict[str, Any] = {"total": float(np.sqrt(sq.mean(axis=-1)[mask].sum() / n))}
        by_group = {g.label: float(np.sqrt(sq[..., k][mask].mean())) for k, g in enumerate(engine.groups)}
        bodies: dict[str, list[int]] = {}
        for k, g in enumerate(engine.groups):
            bodies.setdefault(g.body, []).append(k)
        entry["by_body"] = {b: float(np.sqrt(sq[..., ks].mean(axis=-1)[mask].mean())) for b, ks in bodies.items()}
        entry["by_pair"] = pair_gaps(engine.groups, mask, sq, window_contacts(windows, contacts), layout.pairs)
        entry["by_coordinate"] = by_group
        per_sample = sq.mean(axis=-1)
        labels = np.empty(mask.shape, dtype=object)
        times = np.zeros(mask.shape)
        for w in range(len(windows.traj_index)):
            ti = windows.traj_index[w]
            labels[w] = phases[ti][windows.sample_index[w]]
            times[w] = trajs[ti].time_s[windows.sample_index[w]] - trajs[ti].time_s[0]
        by_phase = {}
        phase_share = {}
        for p in PHASES:
            sel = mask & (labels == p)
            if sel.any():
                by_phase[p] = float(np.sqrt(per_sample[sel].mean()))
                phase_share[p] = float(sel.sum() / n)
        entry["by_phase"] = by_phase
        entry["phase_share"] = phase_share
        t_max = float(times[mask].max()) if mask.any() else 1.0
        edges = np.linspace(0.0, t_max + 1e-9, 11)
        by_time = []
        for lo, hi in itertools.pairwise(edges):
            sel = mask & (times >= lo) & (times < hi)
            if sel.any():
                by_time.append({"t_s": float(0.5 * (lo + hi)), "gap": float(np.sqrt(per_sample[sel].mean()))})
        entry["by_time"] = by_time
        out[name] = entry
    return out


# ------------------------------------------------------------------------------------------------------------ where
def body_gaps(groups: Sequence[Group], mask: np.ndarray, sq: np.ndarray) -> dict[str, float]:
    """RMS gap per body over the scored slots (``sq``: (W, S, G) squared errors of one model)."""
    bodies: dict[str, list[int]] = {}
    for k, g in enumerate(groups):
        bodies.setdefault(g.body, []).append(k)
    return {
        b: float(np.sqrt(sq[..., ks].mean(axis=-1)[mask].mean())) if mask.any() else 0.0 for b, ks in bodies.items()
    }


def body_reductions(
    groups: Sequence[Group], mask: np.ndarray, before: np.ndarray, after: np.ndarray
) -> dict[str, dict[str, float]]:
    """Per body: gap before and after a change, and the reduction (``before``, ``after``: (W, S, G))."""
    b0, b1 = body_gaps(groups, mask, before), body_gaps(groups, mask, after)
    return {b: {"before": b0[b], "after": b1[b], "reduction": 1.0 - b1[b] / max(b0[b], 1e-300)} for b in b0}


def window_contacts(windows: Windows, contacts: Sequence[list[frozenset[tuple[str, str]]]]) -> np.ndarray:
    """(W, S) the contact pairs touching at each window slot's recorded state."""
    out = np.empty(windows.mask.shape, dtype=object)
    for w in range(len(windows.traj_index)):
        per = contacts[int(windows.traj_index[w])]
        for k, sample in enumerate(windows.sample_index[w]):
            out[w, k] = per[int(sample)]
    return out


def pair_gaps(
    groups: Sequence[Group],
    mask: np.ndarray,
    sq: np.ndarray,
    labels: np.ndarray,
    pairs: Sequence[tuple[str, str]],
) -> dict[str, dict[str, float]]:
    """Per contact pair "a|b": the RMS gap of its moving bodies' coordinates over the slots where the pair touches
    at the recorded state, and the share of scored slots that is."""
    n = max(int(mask.sum()), 1)
    out = {}
    for pair in pairs:
        ks = [k for k, g in enumerate(groups) if g.body in pair]
        if not ks:
            continue
        touching = np.vectorize(lambda c, p=pair: p in c, otypes=[bool])(labels) & mask
        if touching.any():
            out["|".join(pair)] = {
                "gap": float(np.sqrt(sq[..., ks].mean(axis=-1)[touching].mean())),
                "share": float(touching.sum() / n),
            }
    return out


def _where_targets(
    engine: _Engine, layout: Layout, contacts_train: Sequence[list[frozenset[tuple[str, str]]]]
) -> list[Target]:
    """Bodies and contact pairs where the nominal model's training gap is largest (what localised effects try)."""
    options = engine.options
    if not (options.localise and layout.localised):
        return []
    sq = engine.scores([[]], engine.train_w, len(engine.train)).sq[0]
    mask = engine.train_w.mask
    targets: list[Target] = []
    if len(layout.bodies) > 1:
        gaps = body_gaps(engine.groups, mask, sq)
        ranked = sorted((b for b in layout.bodies if b in gaps), key=lambda b: -gaps[b])
        targets += [body_target(b) for b in ranked[: options.local_bodies]]
    if layout.explicit and len(layout.pairs) > 1:
        labels = window_contacts(engine.train_w, contacts_train)
        gaps_p = pair_gaps(engine.groups, mask, sq, labels, layout.pairs)

        def same_as_a_body(pair: str) -> bool:  # the only contact pair of a body tried already: the same place
            return any([p for p in layout.pairs if t.parties[0] in p] == [tuple(pair.split("|"))] for t in targets)

        ranked_p = sorted((p for p in gaps_p if not same_as_a_body(p)), key=lambda p: -gaps_p[p]["gap"])
        targets += [pair_target(*p.split("|")) for p in ranked_p[: options.local_pairs]]
    return targets


CHEAP_LOCAL = ("sliding_friction", "torsional_friction", "rolling_friction", "restitution", "contact_stiffness", "mass")
"""One-parameter effects tried on the body with the largest gap whatever their global variant showed: a change on
one body, made everywhere, also changes the bodies the model already gets right, so the global fit may show nothing
(scaling every mass alike leaves free bodies' motion as it is)."""


def _localised(
    effects: Sequence[Effect], targets: Sequence[Target], model: mujoco.MjModel, fitted: Sequence[EffectResult]
) -> list[Effect]:
    """Each effect that can act on one body or pair, at each target, when it is cheap (`CHEAP_LOCAL`, bodies only)
    or when a variant already fitted shows it might help there: it cuts the held-out gap by
    ``LOCALISE_MIN_REDUCTION`` overall, or on one of the target's bodies."""
    out = []
    for effect in effects:
        if effect.target.kind != "all":
            continue
        tried = [r for r in fitted if r.effect == effect.name]
        for target in targets:
            if target.kind not in effect.scopes:
                continue
            helps = (target.kind == "body" and effect.name in CHEAP_LOCAL) or any(
                r.heldout_reduction >= LOCALISE_MIN_REDUCTION
                or any(
                    r.heldout_by_body.get(b, {}).get("reduction", 0.0) >= LOCALISE_MIN_REDUCTION for b in target.parties
                )
                for r in tried
            )
            local = effect.at(target)
            if helps and local.applicable(model):
                out.append(local)
    return out


# -------------------------------------------------------------------------------------------------------- diagnose
def diagnose(
    model: mujoco.MjModel,
    trajs: Sequence[Trajectory],
    options: DiagnoseOptions | None = None,
    progress: ProgressFn | None = None,
    *,
    spec: mujoco.MjSpec | None = None,
) -> Diagnosis:
    """Diagnoses the gap between ``model`` and recorded ``trajs`` (see the module docstring).

    Args:
        model: the nominal model (its timestep must not exceed the sample interval).
        trajs: recorded trajectories in the model's joint order.
        options: the setting; defaults to :class:`DiagnoseOptions`.
        progress: optional callback ``(stage, done, total)``.
        spec: the model's MjSpec (from its MJCF). With it, a scene of several bodies or contact pairs is prepared
            so that each contact pair can carry its own parameters (`grounder.diagnosis.targets`); without it,
            effects are localised to bodies only.

    Raises:
        GrounderError: see :func:`check_inputs`; a contact-pair effect named without ``spec``.
    """
    import time

    t0 = time.perf_counter()
    options = options or DiagnoseOptions()
    trajs = list(trajs)
    check_inputs(model, trajs, options)
    report = progress or no_progress
    contacts = [contacts_at_samples(model, t) for t in trajs]
    nominal = model
    model, layout, _ = prepare(nominal, spec, trajs, contacts)
    effects = resolve_effects(list(options.effects) if options.effects is not None else None, model)
    _check_localised(effects, model, layout)
    rng = np.random.default_rng(options.seed)
    held_idx, train_idx = _holdout_split(model, trajs, rng.permutation(len(trajs)).tolist(), options)
    held = [trajs[i] for i in sorted(held_idx)]
    train = [trajs[i] for i in sorted(train_idx)]
    engine = _Engine(model, train, held, options)
    try:
        held_count = engine.count(engine.held_w, len(held))
        held_phases = window_labels(engine.held_w, [detect_phases(model, t) for t in held])
        base_scores = engine.scores([[]], engine.held_w, len(held))
        base_held = base_scores.per_traj[0]
        gap_before = rms(base_held, held_count)
        results = _rank_effects(engine, effects, base_scores, held_count, held_phases, gap_before, rng, report)
        if options.effects is None:
            # Where the gap is largest, each effect family that explains some of it as a global change (or whose
            # global change cannot show: scaling every mass alike leaves free bodies' motion as it is).
            targets = _where_targets(engine, layout, [contacts[i] for i in sorted(train_idx)])
            for kind in ("body", "pair"):  # pairs after bodies: a pair is tried where its body's variant helped
                local = _localised(effects, [t for t in targets if t.kind == kind], model, results)
                results += _rank_effects(
                    engine,
                    local,
                    base_scores,
                    held_count,
                    held_phases,
                    gap_before,
                    rng,
                    report,
                    f"fitting {kind} effects",
                )
                effects = effects + local
            results.sort(key=lambda r: -r.score)
        by_key = {e.key: e for e in effects}
        measurement = _measurement_check(engine, effects, held_phases, options, rng)
        noise = estimate_noise(model, trajs, options.velocity_smoothing_frames)
        floor_nominal = _noise_floor(engine, held, [], noise, options.seed)
        applied, current, steps = _select_effects(
            engine, results, base_held, held_count, floor_nominal, rng, report, by_key
        )
        applied, current = _refine_jointly(engine, applied, current, held_count)
        _step_reductions_by_body(engine, applied, steps)
        gap_after = rms(current, held_count)
        floor = _noise_floor(engine, held, applied, noise, options.seed)
        report("breaking the gap down", 0, 2)
        gap_all = _breakdown(engine, trajs, [], contacts, layout)
        gap_diag = _breakdown(engine, trajs, applied, contacts, layout)
        report("breaking the gap down", 2, 2)
        figures = _figure_data(engine, held, applied)
    finally:
        engine.close()
    held_ol_before = gap_all["open_loop"]["total"]
    reduction = 1.0 - gap_after / max(gap_before, 1e-300)
    by_body = {
        b: {
            "before": gap_all["short_horizon"]["by_body"][b],
            "after": gap_diag["short_horizon"]["by_body"][b],
            "unexplained_fraction": float(
                min(1.0, gap_diag["short_horizon"]["by_body"][b] / max(gap_all["short_horizon"]["by_body"][b], 1e-300))
            ),
        }
        for b in gap_all["short_horizon"]["by_body"]
    }
    return Diagnosis(
        gap_metric=_metric_text(options),
        gap=_gap_summary(gap_all, gap_diag),
        effects=results,
        selected=[a.effect.key for a in applied],
        steps=steps,
        heldout={
            "gap_before": gap_before,
            "gap_after": gap_after,
            "reduction": reduction,
            "noise_floor": floor,
            "reduction_above_noise": _above_noise(gap_before, gap_after, floor),
            "open_loop_all_before": held_ol_before,
            "open_loop_all_after": gap_diag["open_loop"]["total"],
        },
        unexplained_fraction=float(max(0.0, 1.0 - reduction)),
        split={"train": [t.name for t in train], "heldout": [t.name for t in held]},
        noise=noise,
        measurement_check=measurement,
        applied=applied,
        figures=figures,
        seconds=time.perf_counter() - t0,
        layout=layout,
        unexplained_by_body=by_body,
        model=model,
    )


def _check_localised(effects: Sequence[Effect], model: mujoco.MjModel, layout: Layout) -> None:
    """Named localised effects that the prepared model cannot carry.

    Raises:
        GrounderError: a contact-pair effect without explicit pairs, or air drag on one body without the
            ellipsoid fluid model.
    """
    for e in effects:
        if e.target.kind == "pair" and not layout.explicit:
            raise GrounderError(
                f"effect '{e.key}' needs contact pairs with their own parameters: pass the scene's MJCF (the CLI "
                "does), and a scene whose pair touches in the recordings"
            )
        if e.target.kind == "body" and e.name == "air_drag" and not layout.fluid_per_body:
            raise GrounderError(
                f"effect '{e.key}' needs the ellipsoid fluid model per body: pass the scene's MJCF and a still medium "
                "(density and viscosity 0)"
            )


def _step_reductions_by_body(engine: _Engine, applied: list[AppliedEffect], steps: list[dict[str, Any]]) -> None:
    """Adds to each accepted step its held-out gap by body before and after it (after the joint refinement)."""
    accepted = [s for s in steps if s.get("accepted")]
    if not accepted or len(accepted) != len(applied):
        return
    prefixes = [applied[:k] for k in range(len(applied) + 1)]
    sq = engine.scores(prefixes, engine.held_w, len(engine.held)).sq
    for k, step in enumerate(accepted):
        step["heldout_by_body"] = body_reductions(engine.groups, engine.held_w.mask, sq[k], sq[k + 1])


def _rank_effects(
    engine: _Engine,
    effects: list[Effect],
    base_scores: Scores,
    held_count: np.ndarray,
    held_phases: np.ndarray,
    gap_before: float,
    rng: np.random.Generator,
    report: ProgressFn,
    stage: str = "fitting effects",
) -> list[EffectResult]:
    """Which: every effect alone on the nominal model, fitted on the training windows and scored on the held-out
    ones (``base_scores``: the nominal model's held-out scores), best score first."""
    model, options, held = engine.model, engine.options, engine.held
    base_held = base_scores.per_traj[0]
    results: list[EffectResult] = []
    for i, effect in enumerate(effects):
        report(stage, i, len(effects))
        fitted, train_gap = engine.fit([], [effect])
        after_scores = engine.scores([fitted], engine.held_w, len(held))
        after = after_scores.per_traj[0]
        result = _result(effect, fitted[-1], model, train_gap, base_held, after, held_count, options, rng)
        by_phase = phase_reductions(base_scores, after_scores, engine.held_w, held_phases)
        by_body = body_reductions(engine.groups, engine.held_w.mask, base_scores.sq[0], after_scores.sq[0])
        results.append(replace(result, heldout_by_phase=by_phase, heldout_by_body=by_body))
        log.info("%s: held-out %.4f -> %.4f", effect.key, gap_before, results[-1].heldout_gap_after)
    report(stage, len(effects), len(effects))
    results.sort(key=lambda r: -r.score)
    return results


def _select_effects(
    engine: _Engine,
    results: list[EffectResult],
    base_held: np.ndarray,
    held_count: np.ndarray,
    floor_nominal: float,
    rng: np.random.Generator,
    report: ProgressFn,
    by_key: dict[str, Effect],
) -> tuple[list[AppliedEffect], np.ndarray, list[dict[str, Any]]]:
    """How far: greedy forward selection from the nominal model (held-out per-trajectory gap ``base_held``), each
    step's effect re-fitted on top of those already selected, while the held-out gap keeps falling by ``min_gain``
    with a bootstrap lower bound above zero and stays above the noise floor.

    Returns:
        The selected effects as fitted, their held-out per-trajectory gap, and one record per step tried.
    """
    model, options, held = engine.model, engine.options, engine.held
    applied: list[AppliedEffect] = []
    current = base_held
    steps: list[dict[str, Any]] = []
    candidates = {r.key: r for r in results}
    for step in range(options.max_effects):
        report("selecting effects", step, options.max_effects)
        if step > 0 and rms(current, held_count) <= options.noise_stop_ratio * floor_nominal:
            steps.append(
                {"stopped": "the held-out gap is at the recording's noise floor", "noise_floor": floor_nominal}
            )
            break
        if step == 0:
            best_name = results[0].key if results else None
            trial = [AppliedEffect(effect=by_key[best_name], values=candidates[best_name].params)] if best_name else []
            after = candidates[best_name].per_traj_after if best_name else current
        else:
            taken = {a.effect.name for a in applied}
            pool = [r.key for r in results if r.effect not in taken]
            pool = pool[: options.shortlist]
            best_name, trial, after = None, [], current
            best_score = -np.inf
            for name in pool:
                fitted, _ = engine.fit(applied, [by_key[name]])
                per = engine.per_traj([fitted], engine.held_w, len(held))[0]
                gain = 1.0 - rms(per, held_count) / max(rms(current, held_count), 1e-300)
                s = gain - penalty_of(by_key[name], model, options)
                if s > best_score:
                    best_score, best_name, trial, after = s, name, fitted, per
        if best_name is None:
            break
        gap_cur, gap_new = rms(current, held_count), rms(after, held_count)
        gain = 1.0 - gap_new / max(gap_cur, 1e-300)
        penalty = penalty_of(by_key[best_name], model, options)
        lower = _lower_bound(current, after, rng, options.n_bootstrap)
        accepted = gain - penalty >= options.min_gain and lower > 0
        steps.append(
            {
                "effect": best_name,
                "target": by_key[best_name].target.to_json(),
                "params": trial[-1].values if trial else {},
                "heldout_gap_before": gap_cur,
                "heldout_gap_after": gap_new,
                "relative_gain": gain,
                "gain_lower_5pct": lower,
                "accepted": bool(accepted),
            }
        )
        if not accepted:
            break
        applied, current = trial, after
    report("selecting effects", options.max_effects, options.max_effects)
    return applied, current, steps


def _refine_jointly(
    engine: _Engine, applied: list[AppliedEffect], current: np.ndarray, held_count: np.ndarray
) -> tuple[list[AppliedEffect], np.ndarray]:
    """Joint refinement of everything selected (small local search on the training windows), kept when it does not
    make the held-out gap worse: ``(applied, held-out per-trajectory gap)``."""
    if len(applied) > 1:
        refined, _ = engine.fit([], [a.effect for a in applied], init=[a.values for a in applied])
        per = engine.per_traj([refined], engine.held_w, len(engine.held))[0]
        if rms(per, held_count) <= rms(current, held_count):
            applied, current = refined, per
    return applied, current


def _gap_summary(gap_all: dict[str, Any], gap_diag: dict[str, Any]) -> dict[str, Any]:
    """``Diagnosis.gap``: the nominal model's short-horizon breakdown, its open-loop one, and the diagnosed model's."""
    short = gap_all["short_horizon"]
    return {
        "total": short["total"],
        "by_body": short["by_body"],
        "by_pair": short["by_pair"],
        "by_phase": short["by_phase"],
        "by_coordinate": short["by_coordinate"],
        "by_time": short["by_time"],
        "phase_share": short["phase_share"],
        "open_loop": gap_all["open_loop"],
        "after_selected": gap_diag,
    }


def penalty_of(effect: Effect, model: mujoco.MjModel, options: DiagnoseOptions) -> float:
    """Complexity penalty: per fitted parameter, and once more for a localised effect (where it acts is a choice)."""
    return options.complexity_penalty * (len(effect.params_of(model)) + (effect.target.kind != "all"))


def _result(
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
        ci=_bootstrap_reduction(before, after, rng, options.n_bootstrap),
        score=reduction - penalty_of(effect, model, options),
        per_traj_after=after,
    )


QUIET_PHASES = ("free_flight", "resting")
"""Phases whose physics the nominal model gets right when its geometry is right (gravity; static contact): the
measurement check fits the recording biases on these samples only, so contact modelling cannot absorb them."""
MEASUREMENT_NAMES = ("length_scale", "time_scale", "velocity_lag")


def _measurement_check(
    engine: _Engine,
    effects: list[Effect],
    held_phases: np.ndarray,
    options: DiagnoseOptions,
    rng: np.random.Generator,
) -> dict[str, Any]:
    """Recording biases fitted and scored on quiet stretches only (free flight, resting since the window start)."""
    candidates = [e for e in effects if e.name in MEASUREMENT_NAMES]
    if not candidates:
        return {}
    model = engine.model
    train_labels = window_labels(engine.train_w, [detect_phases(model, t) for t in engine.train])
    # Only slots whose whole window up to them is quiet: an impact earlier in the window would leak into them.
    train_mask = engine.train_w.mask & np.logical_and.accumulate(np.isin(train_labels, QUIET_PHASES), axis=1)
    held_mask = engine.held_w.mask & np.logical_and.accumulate(np.isin(held_phases, QUIET_PHASES), axis=1)
    if train_mask.sum() < 20 or held_mask.sum() < 20:
        return {"skipped": "fewer than 20 free-flight or resting samples in the training or held-out set"}
    n_held = len(engine.held)

    def masked_per_traj(sq: np.ndarray) -> np.ndarray:
        per = np.zeros(n_held)
        np.add.at(per, engine.held_w.traj_index, (sq.mean(axis=-1) * held_mask).sum(axis=-1))
        return per

    count = np.zeros(n_held)
    np.add.at(count, engine.held_w.traj_index, held_mask.sum(axis=1))
    before = masked_per_traj(engine.scores([[]], engine.held_w, n_held).sq[0])
    out: list[dict[str, Any]] = []
    alone: dict[str, tuple[list[AppliedEffect], np.ndarray]] = {}
    for effect in candidates:
        fitted, _ = engine.fit([], [effect], slot_mask=train_mask)
        after = masked_per_traj(engine.scores([fitted], engine.held_w, n_held).sq[0])
        alone[effect.key] = (fitted, after)
        g0, g1 = rms(before, count), rms(after, count)
        lo, hi = _bootstrap_reduction(before, after, rng, options.n_bootstrap)
        out.append(
            {
                "effect": effect.name,
                "params": fitted[-1].values,
                "heldout_gap_before": g0,
                "heldout_gap_after": g1,
                "heldout_reduction": 1.0 - g1 / max(g0, 1e-300),
                "ci": [lo, hi],
                "significant": bool(lo > 0 and 1.0 - g1 / max(g0, 1e-300) >= options.min_gain),
            }
        )
    out.sort(key=lambda e: -float(e["heldout_reduction"]))
    # Biases confound each other (a velocity lag looks like a gravity or scale error in free flight): add them
    # greedily, each re-fitted on top of those already accepted.
    applied: list[AppliedEffect] = []
    current = before
    selected = []
    remaining = list(candidates)
    while remaining:
        trials = []
        for effect in remaining:
            if applied:
                fitted, _ = engine.fit(applied, [effect], slot_mask=train_mask)
                after = masked_per_traj(engine.scores([fitted], engine.held_w, n_held).sq[0])
            else:  # the first round is each bias alone, fitted above
                fitted, after = alone[effect.key]
            trials.append((rms(after, count), effect, fitted, after))
        gap_new, effect, fitted, after = min(trials, key=lambda t: t[0])
        gain = 1.0 - gap_new / max(rms(current, count), 1e-300)
        if gain < options.min_gain or _lower_bound(current, after, rng, options.n_bootstrap) <= 0:
            break
        applied, current = fitted, after
        remaining.remove(effect)
        selected.append({"effect": effect.name, "params": fitted[-1].values, "heldout_gap_after": gap_new})
    for item, final in zip(selected, applied, strict=True):
        item["params"] = final.values
    return {
        "phases": list(QUIET_PHASES),
        "heldout_samples": int(held_mask.sum()),
        "effects": out,
        "selected": selected,
        "heldout_gap_before": rms(before, count),
        "heldout_gap_after": rms(current, count),
        "heldout_reduction": 1.0 - rms(current, count) / max(rms(before, count), 1e-300),
    }


def _metric_text(options: DiagnoseOptions) -> str:
    if options.robust_scale:
        return GAP_METRIC.format(horizon_s=options.horizon_s, robust=options.robust_scale)
    return GAP_METRIC_PLAIN.format(horizon_s=options.horizon_s)


def _above_noise(before: float, after: float, floor: float) -> float:
    """Reduction of the part of the gap above the noise floor (squared gaps subtract)."""
    excess_before = max(before**2 - floor**2, 0.0)
    if excess_before <= 0.0:
        return 0.0
    return float(1.0 - np.sqrt(max(after**2 - floor**2, 0.0) / excess_before))


def _noise_floor(
    engine: _Engine, held: list[Trajectory], applied: list[AppliedEffect], noise: dict[str, float], seed: int
) -> float:
    """Short-horizon gap of the diagnosed model against its own simulations of the held-out starts, plus noise."""
    from grounder.diagnosis.effects import Transforms
    from grounder.sim.rollout import simulate

    floor_model, _ = apply_effects(engine.model, applied)
    clean = simulate(floor_model, held, nthread=engine.nthread)
    assert isinstance(clean[0], Trajectory)
    rng = np.random.default_rng(seed + 1)
    noisy = [add_noise(engine.model, t, noise, rng) for t in clean if isinstance(t, Trajectory)]
    windows = make_windows(floor_model, noisy, engine.options.horizon_s)
    pred = predict([(floor_model, Transforms())], windows, engine.runner, engine.nthread)
    sc = score(pred, windows, engine.groups, len(noisy), engine.options.robust_scale)
    return float(sc.gap[0])


def _figure_data(engine: _Engine, held: list[Trajectory], applied: list[AppliedEffect]) -> dict[str, Any]:
    """Open-loop real vs simulated (before, after) for the first two held-out trajectories."""
    trajs = held[:2]
    windows = make_windows(engine.model, trajs, None)
    cands = [apply_effects(engine.model, []), apply_effects(engine.model, applied)]
    pred = predict(cands, windows, engine.runner, engine.nthread)
    out = []
    for w, traj in enumerate(trajs):
        k = int(windows.mask[w].sum()) + 1
        out.append(
            {
                "name": traj.name,
                "time_s": traj.time_s[:k] - traj.time_s[0],
                "real": windows.real_qpos[w, :k],
                "before": pred[0, w, :k],
                "after": pred[1, w, :k],
            }
        )
    return {"trajectories": out, "groups": engine.groups}


# ------------------------------------------------------------------------------------------------------------ output
MIN_SEGMENT_SAMPLES = 3
"""Tracked segments shorter than this (frames) are left out: a window needs a start and a sample to score, and the
noise estimate third differences."""


@dataclass(frozen=True, kw_only=True)
class TrackedInput:
    """What ``track.json`` says about a folder `image2sim track` wrote: its frame rate, the tracker's velocity
    smoothing window, the fraction of frames each object was tracked in, and the segments it cut."""

    fps: float
    smoothing_frames: int
    tracked_fraction: dict[str, float]
    segments: tuple[str, ...]


def read_track_folder(traj_dir: Path) -> TrackedInput | None:
    """``traj_dir``'s ``track.json`` (None when there is none: trajectories recorded some other way).

    Raises:
        GrounderError: a ``track.json`` that is not one `image2sim track` wrote.
    """
    import json

    from grounder.tracking.options import TRACK_JSON

    path = Path(traj_dir) / TRACK_JSON
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
        if doc.get("format") != "image2sim.track/1":
            raise ValueError(f"format {doc.get('format')!r}")
        smoothing = doc.get("options", {}).get("smoothing", {})
        return TrackedInput(
            fps=float(doc["fps"]),
            smoothing_frames=int(smoothing.get("window_frames", 7)),
            tracked_fraction={k: float(v["tracked_fraction"]) for k, v in doc.get("objects", {}).items()},
            segments=tuple(str(seg["name"]) for seg in doc.get("segments", [])),
        )
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise GrounderError(
            f"{path}: not a track.json that image2sim track wrote ({exc}); pass the folder track wrote, or remove "
            "the file to use the trajectories as recorded"
        ) from exc


def diagnose_files(
    scene_xml: Path,
    traj_dir: Path,
    out_dir: Path,
    options: DiagnoseOptions | None = None,
    *,
    overwrite: bool = False,
    progress: ProgressFn | None = None,
) -> Diagnosis:
    """Loads the scene (an MJCF or a scene folder such as `ground` writes) and the trajectories (a folder of
    ``.npz``, or the folder `image2sim track` wrote: its segments, with the tracker's smoothing counted in the noise
    floor), diagnoses, and writes ``out_dir`` (the CLI's ``diagnose``)."""
    scene_xml, model = load_scene_model(scene_xml)
    trajs = load_trajectories(traj_dir, model)
    options = options or DiagnoseOptions()
    tracked = read_track_folder(traj_dir)
    if tracked is not None:
        short = [t.name for t in trajs if t.num_steps < MIN_SEGMENT_SAMPLES]
        if short:
            log.warning(
                "%d tracked segment(s) shorter than %d frames left out (%s): the objects were lost around them",
                len(short),
                MIN_SEGMENT_SAMPLES,
                ", ".join(short[:5]) + (" ..." if len(short) > 5 else ""),
            )
        trajs = [t for t in trajs if t.num_steps >= MIN_SEGMENT_SAMPLES]
        if options.velocity_smoothing_frames is None:
            options = replace(options, velocity_smoothing_frames=tracked.smoothing_frames)
        lost = {k: 1.0 - v for k, v in tracked.tracked_fraction.items() if v < 1.0}
        if lost:
            log.info("frames lost by the tracker (left out): %s", ", ".join(f"{k} {v:.0%}" for k, v in lost.items()))
    out_dir = Path(out_dir)
    check_output_dir(out_dir, overwrite=overwrite, error=GrounderError, inputs=(scene_xml, traj_dir))
    diag = diagnose(model, trajs, options, progress, spec=mujoco.MjSpec.from_file(str(scene_xml)))
    if tracked is not None:
        diag = replace(
            diag,
            noise={**diag.noise, "velocity_smoothing_frames": float(options.velocity_smoothing_frames or 0)},
            split={**diag.split, "tracked_segments_used": [t.name for t in trajs]},
        )
    write_outputs(diag, scene_xml, model, out_dir, overwrite=overwrite)
    return diag
