"""Where the gap lies: its breakdown by body, contact pair, coordinate, phase and time, and the bodies and contact
pairs where localised effects are tried (`grounder.diagnosis.targets`).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any

import mujoco
import numpy as np

from grounder.core.trajectory import Trajectory
from grounder.diagnosis.effects import (
    AppliedEffect,
    Effect,
    apply_effects,
)
from grounder.diagnosis.engine import (
    Engine,
)
from grounder.diagnosis.gap import (
    Group,
    Windows,
    make_windows,
    predict,
    score,
)
from grounder.diagnosis.phases import PHASES, detect_phases
from grounder.diagnosis.result import EffectResult
from grounder.diagnosis.targets import Layout, Target, body_target, pair_target

LOCALISE_MIN_REDUCTION = 0.02
"""An effect family is tried on a contact pair (and, beyond `CHEAP_LOCAL`, on a body) when a variant already fitted
cuts the held-out gap by at least this much, overall or on one of the place's bodies (a change on one body also
shows, diluted, as a change on all)."""


def breakdown(
    engine: Engine,
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
        entry["by_body"] = body_gaps(engine.groups, mask, sq)
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


def where_targets(
    engine: Engine, layout: Layout, contacts_train: Sequence[list[frozenset[tuple[str, str]]]]
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


def localised(
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
            if not helps:
                continue
            local = effect.at(target)
            if local.applicable(model):
                out.append(local)
    return out


def gap_summary(gap_all: dict[str, Any], gap_diag: dict[str, Any]) -> dict[str, Any]:
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
