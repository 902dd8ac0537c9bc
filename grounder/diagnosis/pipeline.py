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

import logging
import math
from collections.abc import Sequence
from dataclasses import replace
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
from grounder.diagnosis.engine import (
    DiagnoseOptions,
    Engine,
    effect_result,
    lower_bound,
    penalty_of,
)
from grounder.diagnosis.gap import (
    GAP_METRIC,
    GAP_METRIC_PLAIN,
    Scores,
    make_windows,
    predict,
    rms,
    score,
)
from grounder.diagnosis.measurement import measurement_check
from grounder.diagnosis.noise import add_noise, estimate_noise
from grounder.diagnosis.outputs import write_outputs
from grounder.diagnosis.phases import detect_phases, phase_reductions, window_labels
from grounder.diagnosis.result import Diagnosis, EffectResult
from grounder.diagnosis.targets import Layout, contacts_at_samples, prepare
from grounder.diagnosis.tracked import MIN_SEGMENT_SAMPLES, read_track_folder
from grounder.diagnosis.where import body_gaps, body_reductions, breakdown, gap_summary, localised, where_targets
from grounder.errors import GrounderError
from grounder.sim.scene_files import load_scene_model
from image2sim_common.progress import ProgressFn, no_progress
from reconstruction import check_output_dir

log = logging.getLogger(__name__)


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
    model, layout = prepare(model, spec, trajs, contacts)
    effects = resolve_effects(list(options.effects) if options.effects is not None else None, model)
    _check_localised(effects, model, layout)
    rng = np.random.default_rng(options.seed)
    held_idx, train_idx = _holdout_split(model, trajs, rng.permutation(len(trajs)).tolist(), options)
    held = [trajs[i] for i in sorted(held_idx)]
    train = [trajs[i] for i in sorted(train_idx)]
    engine = Engine(model, train, held, options)
    try:
        held_count = engine.count(engine.held_w, len(held))
        held_phases = window_labels(engine.held_w, [detect_phases(model, t) for t in held])
        base_scores = engine.scores([[]], engine.held_w, len(held))
        base_held = base_scores.per_traj[0]
        gap_before = rms(base_held, held_count)
        results = _rank_effects(engine, effects, base_scores, held_count, held_phases, gap_before, rng, report)
        if options.effects is None:
            # Where the gap is largest: the cheap one-parameter effects on the body, then on the contact pair each
            # family that helped globally or on a body (`localised`).
            targets = where_targets(engine, layout, [contacts[i] for i in sorted(train_idx)])
            for kind in ("body", "pair"):  # pairs after bodies: a pair is tried where its body's variant helped
                local = localised(effects, [t for t in targets if t.kind == kind], model, results)
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
        measurement = measurement_check(engine, effects, held_phases, options, rng)
        noise = estimate_noise(model, trajs, options.velocity_smoothing_frames)
        floor_nominal, _ = _noise_floor(engine, held, [], noise, options.seed)
        applied, current, steps = _select_effects(
            engine, results, base_held, held_count, floor_nominal, rng, report, by_key
        )
        applied, current = _refine_jointly(engine, applied, current, held_count)
        _step_reductions_by_body(engine, applied, steps)
        gap_after = rms(current, held_count)
        floor, floor_by_body = _noise_floor(engine, held, applied, noise, options.seed)
        after_sq = engine.scores([applied], engine.held_w, len(held)).sq[0] if applied else base_scores.sq[0]
        held_by_body = [body_gaps(engine.groups, engine.held_w.mask, sq) for sq in (base_scores.sq[0], after_sq)]
        report("breaking the gap down", 0, 2)
        gap_all = breakdown(engine, trajs, [], contacts, layout)
        gap_diag = breakdown(engine, trajs, applied, contacts, layout)
        report("breaking the gap down", 2, 2)
        figures = _figure_data(engine, held, applied)
    finally:
        engine.close()
    held_ol_before = gap_all["open_loop"]["total"]
    reduction = 1.0 - gap_after / max(gap_before, 1e-300)
    by_body = {
        b: {
            "before": held_by_body[0][b],
            "after": held_by_body[1][b],
            "unexplained_fraction": float(min(1.0, held_by_body[1][b] / max(held_by_body[0][b], 1e-300))),
            "noise_floor": floor_by_body.get(b, 0.0),
        }
        for b in held_by_body[0]
    }
    return Diagnosis(
        gap_metric=_metric_text(options),
        gap=gap_summary(gap_all, gap_diag),
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
        if e.target.kind == "pair" and layout.explicit and tuple(e.target.parties) not in layout.pairs:
            raise GrounderError(
                f"effect '{e.key}': {' and '.join(e.target.parties)} never touch in the recordings; contact pairs "
                f"that do: {', '.join('|'.join(p) for p in layout.pairs) or 'none'}"
            )
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


def _step_reductions_by_body(engine: Engine, applied: list[AppliedEffect], steps: list[dict[str, Any]]) -> None:
    """Adds to each accepted step its held-out gap by body before and after it (after the joint refinement)."""
    accepted = [s for s in steps if s.get("accepted")]
    if not accepted or len(accepted) != len(applied):
        return
    prefixes = [applied[:k] for k in range(len(applied) + 1)]
    sq = engine.scores(prefixes, engine.held_w, len(engine.held)).sq
    for k, step in enumerate(accepted):
        step["heldout_by_body"] = body_reductions(engine.groups, engine.held_w.mask, sq[k], sq[k + 1])


def _rank_effects(
    engine: Engine,
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
        result = effect_result(effect, fitted[-1], model, train_gap, base_held, after, held_count, options, rng)
        by_phase = phase_reductions(base_scores, after_scores, engine.held_w, held_phases)
        by_body = body_reductions(engine.groups, engine.held_w.mask, base_scores.sq[0], after_scores.sq[0])
        results.append(replace(result, heldout_by_phase=by_phase, heldout_by_body=by_body))
        log.info("%s: held-out %.4f -> %.4f", effect.key, gap_before, results[-1].heldout_gap_after)
    report(stage, len(effects), len(effects))
    results.sort(key=lambda r: -r.score)
    return results


def _select_effects(
    engine: Engine,
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
        lower = lower_bound(current, after, rng, options.n_bootstrap)
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
    engine: Engine, applied: list[AppliedEffect], current: np.ndarray, held_count: np.ndarray
) -> tuple[list[AppliedEffect], np.ndarray]:
    """Joint refinement of everything selected (small local search on the training windows), kept when it does not
    make the held-out gap worse: ``(applied, held-out per-trajectory gap)``."""
    if len(applied) > 1:
        refined, _ = engine.fit([], [a.effect for a in applied], init=[a.values for a in applied])
        per = engine.per_traj([refined], engine.held_w, len(engine.held))[0]
        if rms(per, held_count) <= rms(current, held_count):
            applied, current = refined, per
    return applied, current


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
    engine: Engine, held: list[Trajectory], applied: list[AppliedEffect], noise: dict[str, float], seed: int
) -> tuple[float, dict[str, float]]:
    """Short-horizon gap of the diagnosed model against its own simulations of the held-out starts, plus noise; and
    the same by body."""
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
    return float(sc.gap[0]), body_gaps(engine.groups, windows.mask, sc.sq[0])


def _figure_data(engine: Engine, held: list[Trajectory], applied: list[AppliedEffect]) -> dict[str, Any]:
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
    tracked = read_track_folder(traj_dir)
    if tracked is not None and not tracked.segments:
        shares = ", ".join(f"{k} {v:.0%}" for k, v in sorted(tracked.tracked_fraction.items(), key=lambda kv: kv[1]))
        raise GrounderError(
            f"{traj_dir}: image2sim track found no run of frames long enough with every object tracked at once, so it "
            f"wrote no trajectory{f' (tracked: {shares})' if shares else ''}; the diagnosis simulates every body "
            "together: film again with every "
            "object in view and textured where the camera sees it, or ground a scene without the objects it never "
            "found"
        )
    trajs = load_trajectories(traj_dir, model)
    options = options or DiagnoseOptions()
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
