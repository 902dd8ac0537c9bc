"""Identifiability: which parameters the clip constrains. `screen_parameters` asks, per parameter, whether moving it
by -/+20% from where the rollouts match the tracks best changes its object's rollouts by more than tracking resolves
(`step_visible`, also applied where a fit lands); `indistinguishable_range` gives a calibrated value's resolution
range.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from grounder.core.trajectory import Trajectory
from grounder.interaction.options import SCREEN_MIN_POSITION_M, SCREEN_MIN_ROTATION_DEG


@dataclass(frozen=True, kw_only=True)
class ParameterScreen:
    """How much one parameter's value shows in the clip.

    Attributes:
        name: the calibration parameter name (`BODY.friction.sliding`, ...).
        body: the free body whose motion is compared (the name's first part).
        nominal: the scene's (prior) value.
        lower, upper: the search bounds.
        best: the grid value whose rollout matches the tracked motion best (others at their grid best).
        change_down, change_up: (mean position change m, mean rotation change deg) of the body's rollout when the
            parameter moves from `best` to `best * (1 - relative_change)` / `best * (1 + relative_change)`.
        constrained: both changes exceed the thresholds: the clip tells the parameter to within `relative_change`.
        curve: (value, mean position error m, mean rotation error deg) against the tracked motion along the grid.
    """

    name: str
    body: str
    nominal: float
    lower: float
    upper: float
    best: float
    change_down: tuple[float, float]
    change_up: tuple[float, float]
    constrained: bool
    curve: tuple[tuple[float, float, float], ...]

    def as_dict(self) -> dict[str, Any]:
        return {
            "constrained": self.constrained,
            "grid_best": round(self.best, 5),
            "change_down_mm_deg": [round(1e3 * self.change_down[0], 3), round(self.change_down[1], 3)],
            "change_up_mm_deg": [round(1e3 * self.change_up[0], 3), round(self.change_up[1], 3)],
            "curve": [[round(v, 5), round(1e3 * p, 3), round(r, 3)] for v, p, r in self.curve],
        }


def screen_parameters(
    scene_xml: Path,
    trajs: Sequence[Trajectory],
    params: Sequence[str],
    *,
    relative_change: float = 0.2,
    min_position_m: float = SCREEN_MIN_POSITION_M,
    min_rotation_deg: float = SCREEN_MIN_ROTATION_DEG,
    grid_points: int = 13,
    passes: int = 2,
    nthread: int | None = 1,
) -> list[ParameterScreen]:
    """Which parameters the tracked motion constrains to within `relative_change`.

    Each trajectory is rolled out open loop from its first state (as calibration does). Coordinate-wise grid search
    (`passes` sweeps over `grid_points` values across each parameter's bounds, in its search coordinate, every other
    parameter at its current grid best) finds where the rollouts match the tracks best; there each parameter is
    moved by -/+ `relative_change`, and it counts as constrained only if the moved body's rollout changes by at
    least `min_position_m` (root mean square over the frames) or `min_rotation_deg` in both directions: a smaller
    change is below what tracking resolves (a parameter of an object that never slides, or never bounces, leaves no
    trace).

    Contact parameters are applied as calibration applies them (the body's geoms get top priority), so on a scene
    whose contacts mix parameters (MuJoCo: the larger friction, the solmix-weighted solref) the values found are the
    contact's effective ones.
    """
    import mujoco

    from grounder.calibration.parameters import apply_to_model, resolve_parameters
    from grounder.sim.rollout import simulate

    base = mujoco.MjModel.from_xml_path(str(scene_xml))
    resolved = resolve_parameters(base, list(params))
    data = mujoco.MjData(base)
    trajs = list(trajs)
    current = np.array([p.nominal for p in resolved], float)

    def run(rows: np.ndarray) -> list[tuple[Any, list[Trajectory]]]:
        models = [apply_to_model(base, resolved, row, data=data) for row in rows]
        preds = simulate(models, trajs, nthread=nthread)
        return list(zip(models, preds, strict=True))  # type: ignore[arg-type]

    curves: list[list[tuple[float, float, float]]] = [[] for _ in resolved]
    for _ in range(passes):
        for i, p in enumerate(resolved):
            values = [float(v) for v in p.from_unit(np.linspace(0.0, 1.0, grid_points))]
            rows = np.repeat(current[None], len(values), axis=0)
            rows[:, i] = values
            body = _body_of(p.name)
            curve = []
            for v, (model, preds) in zip(values, run(rows), strict=True):
                pos_m, rot_deg = _body_errors(model, preds, trajs, body)
                curve.append((v, pos_m, rot_deg))
            score = [pos / min_position_m + rot / min_rotation_deg for _, pos, rot in curve]
            current[i] = curve[int(np.argmin(score))][0]
            curves[i] = curve
    out = []
    for i, p in enumerate(resolved):
        change_down, change_up, constrained = step_visible(
            base, resolved, current, i, trajs, relative_change, min_position_m, min_rotation_deg, nthread=nthread
        )
        out.append(
            ParameterScreen(
                name=p.name,
                body=_body_of(p.name) or "",
                nominal=p.nominal,
                lower=p.lower,
                upper=p.upper,
                best=float(current[i]),
                change_down=change_down,
                change_up=change_up,
                constrained=constrained,
                curve=tuple(curves[i]),
            )
        )
    return out


def _body_errors(
    model: Any, preds: Sequence[Trajectory], reals: Sequence[Trajectory], body: str | None, *, rms: bool = False
) -> tuple[float, float]:
    """Position error (m) and rotation error (deg) of one free body (None: the worst body) over trajectories: the
    mean over all samples, or with `rms` the root mean square (a change confined to a bounce counts fully)."""
    from grounder.sim.rollout import free_body_errors

    per: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for pred, real in zip(preds, reals, strict=True):
        for name, (pos, rot) in free_body_errors(model, pred, real).items():
            per.setdefault(name, []).append((pos, rot))

    def reduce(values: np.ndarray) -> float:
        return float(np.sqrt(np.mean(values**2))) if rms else float(np.mean(values))

    stats = {
        name: (
            reduce(np.concatenate([p for p, _ in errs])),
            float(np.rad2deg(reduce(np.concatenate([r for _, r in errs])))),
        )
        for name, errs in per.items()
    }
    if body is not None and body in stats:
        return stats[body]
    return max(stats.values(), key=lambda s: s[0])


def _body_of(name: str) -> str | None:
    """The free body whose motion shows a parameter (`BODY.field`), or None for a pair parameter (`A:B.field`)."""
    head = name.split(".", 1)[0]
    return None if ":" in head else head


def step_visible(
    base: Any,
    resolved: Sequence[Any],
    values: np.ndarray,
    index: int,
    trajs: Sequence[Trajectory],
    relative_change: float,
    min_position_m: float,
    min_rotation_deg: float,
    *,
    nthread: int | None = 1,
) -> tuple[tuple[float, float], tuple[float, float], bool]:
    """Moves parameter `index` from `values[index]` by -/+ `relative_change` (the others at `values`) and returns the
    changes of its body's rollouts, (position m, rotation deg) root mean square each way, and whether both are at
    least `min_position_m` or `min_rotation_deg`. A bound hit counts as no change in that direction: the clip may not
    rule out the bound's far side."""
    import mujoco

    from grounder.calibration.parameters import apply_to_model
    from grounder.sim.rollout import simulate

    p = resolved[index]
    centre = float(values[index])
    rows = np.repeat(np.asarray(values, float)[None], 3, axis=0)
    rows[1, index] = float(np.clip(centre * (1.0 - relative_change), p.lower, p.upper))
    rows[2, index] = float(np.clip(centre * (1.0 + relative_change), p.lower, p.upper))
    data = mujoco.MjData(base)
    models = [apply_to_model(base, resolved, row, data=data) for row in rows]
    ref, down, up = simulate(models, list(trajs), nthread=nthread)
    body = _body_of(p.name)
    change_down = _body_errors(models[1], down, ref, body, rms=True)  # type: ignore[arg-type]
    change_up = _body_errors(models[2], up, ref, body, rms=True)  # type: ignore[arg-type]

    def visible(change: tuple[float, float]) -> bool:
        return change[0] >= min_position_m or change[1] >= min_rotation_deg

    down_ok = visible(change_down) and rows[1, index] < centre
    up_ok = visible(change_up) and rows[2, index] > centre
    return change_down, change_up, bool(down_ok and up_ok)


def indistinguishable_range(
    scene_xml: Path,
    trajs: Sequence[Trajectory],
    params: Sequence[str],
    values: np.ndarray,
    index: int,
    *,
    min_position_m: float,
    min_rotation_deg: float,
    max_factor: float = 2.0,
    points: int = 41,
    nthread: int | None = 1,
) -> list[float]:
    """The range of `params[index]` outside which the tracks tell a rollout from the one at `values[index]`.

    The parameter is scanned over `values[index]` times [1 / max_factor, max_factor] (log spaced, within its bounds),
    the others held at `values`; a value is distinguishable when the body's rollout moves by at least
    `min_position_m` or `min_rotation_deg` (means over the frames) from the calibrated one. The range runs from the
    nearest distinguishable value below to the nearest above (an outer bound of the indistinguishable values); a
    side with none is open: the parameter's bound.

    A resolution interval, not a statistical one: the Laplace interval of the calibration needs many independent
    trajectories and a smooth loss; a single toss gives one of each object and a kinked loss.
    """
    import mujoco

    from grounder.calibration.parameters import apply_to_model, resolve_parameters
    from grounder.sim.rollout import simulate

    base = mujoco.MjModel.from_xml_path(str(scene_xml))
    resolved = resolve_parameters(base, list(params))
    p = resolved[index]
    centre = float(values[index])
    scan = np.unique(np.clip(centre * np.geomspace(1.0 / max_factor, max_factor, points), p.lower, p.upper))
    rows = np.repeat(np.asarray(values, float)[None], len(scan) + 1, axis=0)
    rows[1:, index] = scan
    data = mujoco.MjData(base)
    models = [apply_to_model(base, resolved, row, data=data) for row in rows]
    preds = simulate(models, list(trajs), nthread=nthread)
    body = _body_of(p.name)
    ref = preds[0]
    same = []
    for model, pred in zip(models[1:], preds[1:], strict=True):
        pos_m, rot_deg = _body_errors(model, pred, ref, body, rms=True)  # type: ignore[arg-type]
        same.append(pos_m < min_position_m and rot_deg < min_rotation_deg)
    below = [v for v, ok in zip(scan, same, strict=True) if v < centre and not ok]
    above = [v for v, ok in zip(scan, same, strict=True) if v > centre and not ok]
    return [float(max(below)) if below else p.lower, float(min(above)) if above else p.upper]
