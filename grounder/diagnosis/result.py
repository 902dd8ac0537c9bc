"""What a diagnosis found: :class:`Diagnosis` (``diagnosis.json``'s content, via ``to_json``) and the
:class:`EffectResult` of each library effect, with the one-sentence finding written from them."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from grounder.diagnosis.effects import AppliedEffect
from grounder.diagnosis.targets import ALL, Layout, Target


@dataclass(frozen=True, kw_only=True)
class EffectResult:
    """One effect fitted on the training trajectories and scored on the held-out ones."""

    effect: str
    kind: str  # recalibration | new_effect | measurement
    params: dict[str, float]
    nominal_params: dict[str, float]
    train_gap_after: float
    heldout_gap_before: float
    heldout_gap_after: float
    heldout_reduction: float
    ci: tuple[float, float]
    score: float  # reduction minus the complexity penalty
    per_traj_after: np.ndarray = field(repr=False)
    heldout_by_phase: dict[str, dict[str, float]] = field(default_factory=dict)
    heldout_by_body: dict[str, dict[str, float]] = field(default_factory=dict)
    target: Target = ALL

    @property
    def key(self) -> str:
        """``effect``, or ``effect@body`` / ``effect@a|b`` when localised (as in ``Diagnosis.selected``)."""
        return self.target.key(self.effect)


@dataclass(frozen=True, kw_only=True)
class Diagnosis:
    """The diagnosis; ``to_json()`` is the content of ``diagnosis.json``."""

    gap_metric: str
    gap: dict[str, Any]
    effects: list[EffectResult]
    selected: list[str]
    steps: list[dict[str, Any]]
    heldout: dict[str, float]
    unexplained_fraction: float
    split: dict[str, list[str]]
    applied: list[AppliedEffect] = field(repr=False)
    noise: dict[str, float] = field(default_factory=dict)
    measurement_check: dict[str, Any] = field(default_factory=dict)
    figures: dict[str, Any] = field(repr=False, default_factory=dict)
    seconds: float = 0.0
    layout: Layout | None = None
    unexplained_by_body: dict[str, dict[str, float]] = field(default_factory=dict)
    model: mujoco.MjModel | None = field(repr=False, default=None)  # the model diagnosed (explicit pairs, if any)

    def to_json(self) -> dict[str, Any]:
        best = self.effects[0] if self.effects else None
        runner_up = self.effects[1] if len(self.effects) > 1 else None
        return {
            "gap_metric": self.gap_metric,
            "gap": self.gap,
            "effects": [
                {
                    "effect": e.effect,
                    "key": e.key,
                    "target": e.target.to_json(),
                    "kind": e.kind,
                    "meaning": _meaning(e),
                    "params": e.params,
                    "nominal_params": e.nominal_params,
                    "heldout_gap_before": e.heldout_gap_before,
                    "heldout_gap_after": e.heldout_gap_after,
                    "heldout_reduction": e.heldout_reduction,
                    "ci": list(e.ci),
                    "score": e.score,
                    "train_gap_after": e.train_gap_after,
                    "heldout_by_phase": e.heldout_by_phase,
                    "heldout_by_body": e.heldout_by_body,
                }
                for e in self.effects
            ],
            "selected": self.selected,
            "steps": self.steps,
            "heldout": self.heldout,
            "unexplained_fraction": self.unexplained_fraction,
            "finding": _finding(self),
            "top_separated_from_runner_up": (
                None if best is None or runner_up is None else bool(best.ci[0] > runner_up.heldout_reduction)
            ),
            "split": self.split,
            "noise": self.noise,
            "measurement_check": self.measurement_check,
            "seconds": self.seconds,
            "layout": None
            if self.layout is None
            else {
                "bodies": list(self.layout.bodies),
                "contact_pairs": ["|".join(p) for p in self.layout.pairs],
                "contact_pair_samples": {"|".join(p): n for p, n in self.layout.pair_samples.items()},
                "pairs_with_own_parameters": self.layout.explicit,
                "air_drag_per_body": self.layout.fluid_per_body,
            },
            "unexplained_by_body": self.unexplained_by_body,
        }


def _meaning(e: EffectResult) -> str:
    if e.kind == "recalibration":
        return "miscalibrated existing parameter"
    if e.kind == "measurement":
        return "measurement bias of the recording"
    return "missing effect"


def _finding(diag: Diagnosis) -> str:
    text = _finding_main(diag)
    bodies = diag.unexplained_by_body
    if len(bodies) > 1:
        worst = max(v["before"] for v in bodies.values())
        left = [
            f"{b} ({v['unexplained_fraction']:.0%} remains)"
            for b, v in bodies.items()
            # Largely unexplained, a large share of the gap, and above what the recording's noise leaves there.
            if v["unexplained_fraction"] > 0.5
            and v["before"] >= 0.5 * worst
            and v["after"] > 1.25 * v.get("noise_floor", 0)
        ]
        if left:
            text += f"; largely unexplained on body {', '.join(left)}"
    check = diag.measurement_check
    if check.get("selected"):
        named = ", ".join(
            f"{e['effect']} ({', '.join(f'{k}={v:.4g}' for k, v in e['params'].items())})" for e in check["selected"]
        )
        text += (
            f"; recording bias suspected: {named}, together {check['heldout_reduction']:.0%} of the held-out gap "
            f"in free flight and at rest"
        )
    return text


def _finding_main(diag: Diagnosis) -> str:
    if not diag.selected:
        if diag.heldout["gap_before"] <= 1.25 * diag.heldout.get("noise_floor", 0.0):
            return "the nominal model already matches the recordings to their noise floor"
        return (
            "no effect in the library explains the gap on held-out data (largely unexplained: "
            f"{diag.unexplained_fraction:.0%} remains)"
        )
    parts = f"the selected effect(s) {', '.join(diag.selected)}"
    floor = diag.heldout.get("noise_floor", 0.0)
    if diag.heldout["gap_after"] <= 1.25 * floor:
        return (
            f"{parts} explain {1 - diag.unexplained_fraction:.0%} of the held-out gap; what remains is at the "
            f"recording's noise floor ({floor:.4g})"
        )
    if diag.unexplained_fraction > 0.5:
        return f"largely unexplained: {parts} explain only {1 - diag.unexplained_fraction:.0%} of the held-out gap"
    return f"{parts} explain {1 - diag.unexplained_fraction:.0%} of the held-out gap"
