"""The windowed calibration (`InteractionOptions.calibration` "windows", and what the impacts leave unresolved):
tracked motion cut into short windows (`windows`) that start where a tracked state is well measured
(`reliable_starts`, `object_windows`), each rolled out open loop from its first state; the parameters the clip
constrains (`grounder.interaction.screen`) calibrated on them (`calibrate_constrained`), with each value's range
under tracking-sized start errors (`start_error_ranges`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from grounder.core.trajectory import Trajectory
from grounder.interaction.options import CALIBRATE_SETTINGS, InteractionOptions
from grounder.interaction.record import prior_record
from grounder.interaction.screen import ParameterScreen, indistinguishable_range, screen_parameters, step_visible
from grounder.tracking.smooth import SmoothingOptions
from image2sim_common.progress import ProgressFn


def reliable_starts(traj: Trajectory, smoothing: SmoothingOptions | None = None) -> np.ndarray:
    """(T,) mask of the samples of a tracked trajectory whose state a rollout can start from.

    A tracked state is only as good as its velocity, which comes from a fit over a piece of smooth motion between
    impacts (`grounder.tracking.smooth.impact_pieces`). A sample is a good start for one free body when it lies in
    a piece of at least 3 samples (a free flight's velocity from the ballistic fit, another's from the smoothing
    fit), and is not next to an impact: impacts are only resolved to a frame, so the last sample before a detected
    impact may already be past it and the first sample after one may still be mid-bounce (nor is the first sample
    of a segment that begins in contact a start: what came before it is unknown). On `samples/toss` those samples
    carried 6-38 cm/s of velocity error against under 3 cm/s elsewhere, and the calibration absorbed it into
    friction and damping. A start must be good for every free body of the trajectory (all are simulated from it).
    """
    from grounder.tracking.smooth import impact_pieces

    num = len(traj.time_s)
    good = np.ones(num, bool)
    dt_s = float(np.median(np.diff(traj.time_s))) if num > 1 else None
    for body in range(traj.qvel.shape[1] // 6):
        body_good = np.zeros(num, bool)
        pieces = impact_pieces(traj.qpos[:, 7 * body : 7 * body + 3], smoothing, dt_s)
        for k, (first, last, flight) in enumerate(pieces):
            # Two samples fix a velocity by their difference alone: no redundancy against the poses' noise. On
            # two scans of `samples/tabletop` (SfM on 120 / 100 frames) the box's first flight was such a piece,
            # and the windows started there missed by 10-13 mm at any value (its damping ratio came out +43%).
            if last - first + 1 >= 3:
                start = first + (1 if k > 0 or not flight else 0)
                stop = last if k == len(pieces) - 1 else last - 1
                body_good[start : stop + 1] = True
        good &= body_good
    return good


def windows(
    trajs: Sequence[Trajectory],
    window_s: float | None,
    stride_s: float,
    min_motion_m_s: float,
    *,
    starts: Sequence[np.ndarray] | None = None,
) -> list[Trajectory]:
    """Cuts trajectories into overlapping windows (each at least 3 samples); drops windows where nothing moves.

    With `starts` ((T,) masks, one per trajectory, e.g. from `reliable_starts`), a window begins at the first
    allowed sample at or after its nominal start and keeps its length; a window with no allowed start is dropped.
    """
    out: list[Trajectory] = []
    for index, traj in enumerate(trajs):
        spans: list[tuple[int, int]] = []
        allowed = None if starts is None else np.asarray(starts[index], bool)
        if window_s is None:
            spans = [(0, len(traj.time_s))]
        else:
            t0 = float(traj.time_s[0])
            start = 0.0
            while True:
                first = int(np.searchsorted(traj.time_s, t0 + start - 1e-9))
                if allowed is not None:
                    later = np.nonzero(allowed[first:])[0]
                    first = first + int(later[0]) if len(later) else len(traj.time_s)
                if first < len(traj.time_s):
                    t_first = float(traj.time_s[first])
                    rows = np.nonzero((traj.time_s >= t_first - 1e-9) & (traj.time_s <= t_first + window_s + 1e-9))[0]
                    if len(rows) >= 3 and (int(rows[0]), int(rows[-1]) + 1) not in spans:
                        spans.append((int(rows[0]), int(rows[-1]) + 1))
                if t0 + start + window_s >= traj.time_s[-1] - 1e-9:
                    break
                start += stride_s
        for k, (a, b) in enumerate(spans):
            qvel = traj.qvel[a:b]
            speeds = [np.linalg.norm(qvel[:, d : d + 3], axis=1).max() for d in range(0, qvel.shape[1] - 5, 6)]
            if max(speeds, default=0.0) < min_motion_m_s:
                continue
            out.append(
                Trajectory(
                    time_s=traj.time_s[a:b],
                    qpos=traj.qpos[a:b],
                    qvel=traj.qvel[a:b],
                    ctrl=None if traj.ctrl is None else traj.ctrl[a:b],
                    name=f"{traj.name}_w{k:02d}" if len(spans) > 1 else traj.name,
                )
            )
    return out


def object_windows(body_trajs: Sequence[Trajectory], options: InteractionOptions) -> list[Trajectory]:
    """One object's calibration windows: cut from its single-body trajectories, starting only where its state is
    well measured (`reliable_starts`)."""
    return windows(
        body_trajs,
        options.window_s,
        options.window_stride_s,
        options.min_motion_m_s,
        starts=[reliable_starts(t, options.track.smoothing) for t in body_trajs],
    )


def calibrate_constrained(
    scene_xml: Path,
    trajs: Sequence[Trajectory],
    params: Sequence[str],
    options: InteractionOptions,
    *,
    view_point_m: Sequence[float] | None = None,
    out: Path | None = None,
    progress: ProgressFn | None = None,
) -> dict[str, Any]:
    """Screens `params` on `trajs` (unless `options.identify` is off) and calibrates only the constrained ones; then
    `options.start_rounds` times refits the windows' start states with the calibrated values
    (`grounder.interaction.starts`) and screens and calibrates again on the refitted windows.

    Args:
        view_point_m: the camera centre (world, metres) the trajectories were tracked from: position errors along
            its rays count `options.along_view_weight` as much (None: all directions alike).

    Returns the report's `calibration` entry: `status`; per parameter (all of `params`) `nominal`, `value`,
    `interval`, `bounds`, `unit`, `constrained` and the screen's figures; unconstrained parameters keep the prior
    (`value` = `nominal`, `interval` = `bounds`); `start_refinement`: per round, what each window's start moved.
    Writes the calibrated scene to `out` only if something was calibrated (in the last round).
    """
    import mujoco

    from grounder.calibration.parameters import apply_to_model, resolve_parameters
    from grounder.interaction.starts import refine_window_starts

    windows_now = list(trajs)
    rounds: list[dict[str, Any]] = []
    entry: dict[str, Any] = {}
    for round_index in range(options.start_rounds + 1):
        last = round_index == options.start_rounds
        if round_index:
            base = mujoco.MjModel.from_xml_path(str(scene_xml))
            resolved = resolve_parameters(base, list(entry["parameters"]))
            model = apply_to_model(base, resolved, [entry["parameters"][p.name]["value"] for p in resolved])
            windows_now, fits = refine_window_starts(
                model,
                windows_now,
                rotation_weight=options.rotation_weight,
                view_point_m=view_point_m,
                along_view_weight=options.along_view_weight,
            )
            rounds.append({"round": round_index, "windows": [f.as_dict() for f in fits]})
        entry = _screen_and_calibrate(
            scene_xml,
            windows_now,
            params,
            options,
            view_point_m=view_point_m,
            out=out if last else None,
            progress=progress,
        )
        if not any(r.get("constrained") for r in entry["parameters"].values()):
            break
    entry["start_refinement"] = rounds
    return entry


def _screen_and_calibrate(
    scene_xml: Path,
    trajs: Sequence[Trajectory],
    params: Sequence[str],
    options: InteractionOptions,
    *,
    view_point_m: Sequence[float] | None,
    out: Path | None,
    progress: ProgressFn | None,
) -> dict[str, Any]:
    """One round of `calibrate_constrained`: screen, then calibrate the constrained parameters on `trajs`; a value
    that is not resolved where the fit lands (`_unresolved_at`) keeps the prior and the rest is fitted again."""
    import mujoco

    from grounder.calibration.fit import calibrate
    from grounder.calibration.options import CalibrateOptions
    from grounder.calibration.parameters import resolve_parameters
    from grounder.calibration.scene_output import write_calibrated_scene

    base = mujoco.MjModel.from_xml_path(str(scene_xml))
    resolved = {p.name: p for p in resolve_parameters(base, list(params))}
    screens: dict[str, ParameterScreen] = {}
    if options.identify:
        for screen in screen_parameters(
            scene_xml,
            trajs,
            params,
            relative_change=options.identify_relative_change,
            min_position_m=options.identify_min_position_m,
            min_rotation_deg=options.identify_min_rotation_deg,
        ):
            screens[screen.name] = screen
    fit = [n for n in resolved if not options.identify or screens[n].constrained or _paired(n, resolved, screens)]
    entry: dict[str, Any] = {"parameters": {}}
    for name, p in resolved.items():
        entry["parameters"][name] = {
            **prior_record(p),
            "constrained": name in fit,
            **({"screen": screens[name].as_dict()} if name in screens else {}),
        }
    settings = {
        # Windows cut from one clip overlap and share its errors: holding some out would not test anything new.
        "validation_fraction": 0.0,
        "rotation_weight": options.rotation_weight,
        **view_settings(options, view_point_m),
        **CALIBRATE_SETTINGS,
        **options.calibrate_settings,
    }
    scene = scene_xml.parent if scene_xml.name == "scene.xml" else scene_xml
    while fit:
        result = calibrate(scene, trajs, options=CalibrateOptions(params=tuple(fit), **settings), progress=progress)
        values = np.array([f.value for f in result.parameters])
        # The screen looked at its grid best; the answer must be resolved where it landed, by the same rule (a
        # -/+ step visible both ways). Where it is not, the fit's number says nothing the clip measured: the prior
        # stands and the rest is fitted again without it. A time constant stays with its fitted damping ratio
        # (`_paired`): held at a wrong prior it biases the damping ratio, resolved or not.
        unresolved = [
            name
            for name in (_unresolved_at(base, trajs, fit, values, options) if options.identify else [])
            if _damping_partner(name) not in fit
        ]
        if not unresolved:
            break
        for name in unresolved:
            entry["parameters"][name].update(constrained=False, unresolved_fit=float(values[fit.index(name)]))
        fit = [n for n in fit if n not in unresolved]
    if not fit:
        entry["status"] = "skipped: the clip constrains none of the parameters (prior kept)"
        return entry
    start_ranges = start_error_ranges(base, trajs, [f.name for f in result.parameters], values, options, view_point_m)
    for i, fitted in enumerate(result.parameters):
        if fitted.name in start_ranges:
            lo, hi = start_ranges[fitted.name]
            entry["parameters"][fitted.name].update(
                start_error_range=[lo, hi],
                start_sensitive=bool(
                    lo < fitted.value * (1.0 - options.identify_relative_change)
                    or hi > fitted.value * (1.0 + options.identify_relative_change)
                ),
            )
        entry["parameters"][fitted.name].update(
            value=fitted.value,
            interval=[fitted.interval_low, fitted.interval_high],
            indistinguishable=indistinguishable_range(
                scene_xml,
                trajs,
                [f.name for f in result.parameters],
                values,
                i,
                min_position_m=options.identify_min_position_m,
                min_rotation_deg=options.identify_min_rotation_deg,
            ),
        )
    if out is not None:
        write_calibrated_scene(scene, result, list(trajs), out, base)
    unconstrained = [n for n in resolved if n not in fit]
    entry["status"] = "calibrated" + (
        f"; unconstrained by the clip, prior kept: {unconstrained}" if unconstrained else ""
    )
    entry.update(
        train=list(result.train_names),
        validation=list(result.validation_names),
        before={k: v.as_dict() for k, v in result.before.items()},
        after={k: v.as_dict() for k, v in result.after.items()},
    )
    return entry


def _unresolved_at(
    base: Any, trajs: Sequence[Trajectory], fit: Sequence[str], values: np.ndarray, options: InteractionOptions
) -> list[str]:
    """The fitted parameters whose -/+ `identify_relative_change` step, taken at the fitted `values` in the scene
    model `base`, does not show in their body's rollouts both ways (`step_visible`, the screen's rule)."""
    from grounder.calibration.parameters import resolve_parameters

    resolved = resolve_parameters(base, list(fit))
    return [
        p.name
        for i, p in enumerate(resolved)
        if not step_visible(
            base,
            resolved,
            values,
            i,
            trajs,
            options.identify_relative_change,
            options.identify_min_position_m,
            options.identify_min_rotation_deg,
        )[2]
    ]


def start_error_ranges(
    base: Any,
    trajs: Sequence[Trajectory],
    fit: Sequence[str],
    values: np.ndarray,
    options: InteractionOptions,
    view_point_m: Sequence[float] | None = None,
) -> dict[str, list[float]]:
    """Per fitted parameter, the range of its best value when every window's start is off by a tracking-sized
    error (the fitted value included): how far such a start error moves the answer. Empty when
    `start_speed_error_m_s` is 0.

    Each window is rolled out from its tracked start. A slide's length trades friction against the start speed: on
    `samples/toss` (scan D) the bowl's tracked start speeds were off by 0.002-0.07 m/s (median about 0.03), its
    friction came out -45%, and rollouts from the true starts of the same windows fit best at the rendered value.
    So each parameter is profiled again with the starts moved along their velocity by `start_speed_error_m_s`,
    both ways, and then under `start_state_draws` random errors of the whole start (position, orientation, linear
    and angular velocity; see `InteractionOptions`), which a landing turns on (the other parameters held at the
    fit; the calibration's loss over the windows, through the same pseudo-Huber function, its scale taken from the
    windows' errors at the fit rather than at the prior). A range wider than the screen's step
    (`identify_relative_change`) says the value rests on the starts' accuracy.
    """
    import mujoco

    from grounder.calibration.evaluator import Evaluator, pseudo_huber_residuals
    from grounder.calibration.parameters import resolve_parameters

    if options.start_speed_error_m_s <= 0.0 or not fit:
        return {}
    resolved = resolve_parameters(base, list(fit))
    free = [j for j in range(base.njnt) if base.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
    settings = {"rotation_weight": options.rotation_weight, **view_settings(options, view_point_m), "nthread": 1}
    at_fit = Evaluator(base, resolved, list(trajs), **settings).loss_of_values(values[None])[0]
    robust = {**CALIBRATE_SETTINGS, **options.calibrate_settings}.get("robust_scale")
    c = None if robust is None else max(robust * float(np.median(np.sqrt(np.maximum(at_fit, 0.0)))), 1e-9)

    def objective(loss: np.ndarray) -> np.ndarray:
        r = np.sqrt(np.maximum(loss, 0.0))
        return np.sum((r if c is None else pseudo_huber_residuals(r, c)) ** 2, axis=1)

    scan = np.geomspace(0.5, 2.0, 29)
    ranges = {p.name: [float(values[i]), float(values[i])] for i, p in enumerate(resolved)}

    def profile(shifted: list[Trajectory]) -> None:
        ev = Evaluator(base, resolved, shifted, **settings)
        for i, p in enumerate(resolved):
            rows = np.repeat(values[None], len(scan), axis=0)
            rows[:, i] = np.clip(values[i] * scan, p.lower, p.upper)
            best = float(rows[int(np.argmin(objective(ev.loss_of_values(rows)))), i])
            ranges[p.name] = [min(ranges[p.name][0], best), max(ranges[p.name][1], best)]

    for sign in (-1.0, 1.0):
        shifted = []
        for traj in trajs:
            qvel = np.array(traj.qvel, dtype=np.float64, copy=True)
            for j in free:
                d = int(base.jnt_dofadr[j])
                speed = float(np.linalg.norm(qvel[0, d : d + 3]))
                if speed > 1e-9:
                    qvel[0, d : d + 3] *= max(0.0, 1.0 + sign * options.start_speed_error_m_s / speed)
            shifted.append(replace(traj, qvel=qvel))
        profile(shifted)
    rng = np.random.default_rng(0)
    for _ in range(options.start_state_draws):
        shifted = []
        for traj in trajs:
            qpos = np.array(traj.qpos, dtype=np.float64, copy=True)
            qvel = np.array(traj.qvel, dtype=np.float64, copy=True)
            for j in free:
                a, d = int(base.jnt_qposadr[j]), int(base.jnt_dofadr[j])
                qpos[0, a : a + 3] += rng.normal(0.0, options.start_position_error_m, 3)
                # a small rotation in the body frame, its vector drawn per axis
                tilt_rad = rng.normal(0.0, np.deg2rad(options.start_rotation_error_deg), 3)
                mujoco.mju_quatIntegrate(qpos[0, a + 3 : a + 7], tilt_rad, 1.0)
                qvel[0, d : d + 3] += rng.normal(0.0, options.start_speed_error_m_s, 3)
                qvel[0, d + 3 : d + 6] += rng.normal(0.0, options.start_spin_error_rad_s, 3)
            shifted.append(replace(traj, qpos=qpos, qvel=qvel))
        profile(shifted)
    return ranges


def _paired(name: str, resolved: Mapping[str, Any], screens: Mapping[str, ParameterScreen]) -> bool:
    """A contact time constant is fitted wherever its body's damping ratio is, whatever its own screen says: a bounce
    fixes a combination of the two, and a time constant held at a wrong prior moves the damping ratio instead
    (`InteractionOptions.calibrate_params`)."""
    partner = _damping_partner(name)
    return partner is not None and partner in resolved and screens[partner].constrained


def _damping_partner(name: str) -> str | None:
    """The damping ratio a contact time constant (`….solref.timeconst`) is fitted with, or None for other names."""
    return name.removesuffix("timeconst") + "dampratio" if name.endswith(".solref.timeconst") else None


def view_settings(options: InteractionOptions, view_point_m: Sequence[float] | None) -> dict[str, Any]:
    """`CalibrateOptions` fields that weigh tracked depth less (none without a camera centre)."""
    if view_point_m is None:
        return {}
    return {
        "view_point_m": tuple(float(v) for v in view_point_m),
        "along_view_weight": options.along_view_weight,
    }
