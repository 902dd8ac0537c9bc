"""What a calibration returns: `CalibrationResult` (the fitted parameters, the split, errors before and after, the
calibrated model and spec; ``calibration.json`` is its `CalibrationResult.to_json`), with `ParameterFit` (one
parameter's value and interval) and `ErrorSummary` (one model's open-loop errors on a set of trajectories).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np


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
        distribution: With ``CalibrateOptions.distribution``: the fitted parameter distribution
            (`grounder.calibration.distribution.FittedDistribution`, in the calibrated scene's coordinates).
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
    distribution: Any = None

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
