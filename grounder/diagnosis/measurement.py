"""The measurement check: recording biases (length and time scale, velocity lag) fitted and scored on the quiet
stretches of the recordings (free flight, resting), where contact modelling cannot absorb them.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from grounder.diagnosis.effects import (
    AppliedEffect,
    Effect,
)
from grounder.diagnosis.engine import (
    DiagnoseOptions,
    Engine,
    bootstrap_reduction,
    lower_bound,
)
from grounder.diagnosis.gap import (
    rms,
)
from grounder.diagnosis.phases import detect_phases, window_labels

QUIET_PHASES = ("free_flight", "resting")
"""Phases whose physics the nominal model gets right when its geometry is right (gravity; static contact): the
measurement check fits the recording biases on these samples only, so contact modelling cannot absorb them."""
MEASUREMENT_NAMES = ("length_scale", "time_scale", "velocity_lag")


def measurement_check(
    engine: Engine,
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
        lo, hi = bootstrap_reduction(before, after, rng, options.n_bootstrap)
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
        if gain < options.min_gain or lower_bound(current, after, rng, options.n_bootstrap) <= 0:
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
