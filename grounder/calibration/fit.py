"""Calibration: fit a scene's physical parameters to recorded trajectories, with intervals and a validation split.

Parameter names (``box.mass``, ``box.friction.sliding``, ``box.solref.timeconst``, ``geom:NAME.friction.sliding``,
``joint:NAME.damping``, ``actuator:NAME.gain``, ``opt.gravity_scale``, ...) and their defaults are documented in
:mod:`grounder.calibration.parameters`; in short:

- ``BODY.mass``, ``BODY.com.x|y|z``, ``BODY.friction.sliding|torsional|rolling``, ``BODY.solref.timeconst|dampratio``,
  ``BODY.solimp.dmin|dmax|width|midpoint|power``, ``BODY.size_scale`` (contact parameters apply to every collision
  geom of the body, whose priority is raised so that its values govern its contacts);
- ``geom:NAME.<same contact fields>``, ``joint:NAME.damping|frictionloss|armature|stiffness``,
  ``actuator:NAME.gain|kp|kv``, ``opt.gravity_scale`` (compensates a timing/length bias of the measurement),
  ``opt.impratio``.

How it fits (raw mode):

1. The trajectories are split once, reproducibly: the names in natural order are shuffled with
   ``numpy.random.default_rng(split_seed)``; the first ``round(validation_fraction * N)`` are validation, the rest
   training (at least one of each when N >= 2). Trajectories that record the same motion twice
   (`grounder.core.repeats`: e.g. one toss stored again, turned and shifted) stay together, on the side the shuffle
   put the first of them (in natural order) on, and a warning names them. Optionally a seeded subset of the
   training split is used.
2. Loss of a trajectory: re-simulated open loop from its first recorded state (:mod:`grounder.sim.rollout`), for each
   free body the time-average of the position error as a percentage of the body's size (largest extent of its
   collision geoms: the cube's width) plus ``rotation_weight`` times the time-average geodesic rotation error in
   degrees, averaged over free bodies; plus, for hinge/slide joints, the time-average joint error (rad, or m as a
   percentage of 0.1 m). The objective is the mean over training trajectories: exactly the metric of Acosta, Yang
   & Posa (RA-L 2022) when ``rotation_weight = 0``.
3. Global search (contact losses have many local minima): SciPy's differential evolution in the unit box (log scale
   for time constants, masses, gains), seeded, with the scene's own values in the first population. Each
   generation is one batched `mujoco.rollout` call over (candidate models x training trajectories), on a seeded
   subset of at most ``global_search_trajectories`` of them (it only has to find the basin).
4. Local refinement on every fitting trajectory: `mujoco.minimize.least_squares` from the best candidate (scored
   again on all of them), residual per trajectory
   ``sqrt(loss)`` (so the sum of squares is the objective), finite differences batched in one rollout per
   Jacobian. The better of the two is kept.
5. Intervals: Gauss-Newton (Laplace) approximation at the optimum, as in ``mujoco.sysid.calculate_intervals``:
   ``cov = s^2 (J^T J)^-1`` with ``s^2`` the residual variance, a z-interval in search coordinates mapped back to
   physical units and clipped to the bounds. A parameter the data does not constrain gets its whole bounds.

Embedding mode fits the objects' property embeddings instead (prior: the grounded scene's ``scene.json``
``properties.embedding`` / ``embedding_std``), decoded to density/friction/solref by the property model; see
:func:`calibrate`.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

import grounder.sim.rollout as sim
from grounder.calibration.evaluator import Evaluator
from grounder.calibration.options import CalibrateOptions
from grounder.calibration.parameters import Parameter, apply_to_spec, resolve_parameters
from grounder.calibration.result import CalibrationResult, ErrorSummary, ParameterFit
from grounder.calibration.scene_output import NOT_COPIED, _check_manifest, write_calibrated_scene
from grounder.calibration.search import (
    _initial_unit,
    _intervals_unit,
    _jacobian,
    _local_refine,
    _Problem,
    _search,
    _to_values,
    body_groups,
)
from grounder.core.repeats import describe_repeats, repeated_motions, split_keeping_together
from grounder.core.trajectory import Trajectory, _natural_key, validate_against_model
from grounder.errors import GrounderError
from grounder.sim.scene_files import check_links_stay_inside, load_scene_spec
from image2sim_common.progress import ProgressFn

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------------------------
# Trajectory split


def split_names(
    names: Sequence[str], validation_fraction: float, seed: int, together: Sequence[Sequence[str]] = ()
) -> tuple[list[str], list[str]]:
    """The documented train/validation split (module docstring, step 1): returns (train, validation). Each group
    in ``together`` (copies of one motion, `grounder.core.repeats.repeated_motions`) stays on one side: the side the
    shuffle put its first member on."""
    ordered = sorted(names, key=_natural_key)
    if len(ordered) < 2 or validation_fraction <= 0:
        return ordered, []
    perm = np.random.default_rng(seed).permutation(len(ordered))
    n_val = min(max(1, round(validation_fraction * len(ordered))), len(ordered) - 1)
    val, train = split_keeping_together([ordered[i] for i in perm], n_val, together)
    return sorted(train, key=_natural_key), sorted(val, key=_natural_key)


def training_subset(train: Sequence[str], max_count: int | None, seed: int) -> list[str]:
    """A seeded subset of at most ``max_count`` training names (all when None)."""
    if max_count is None or max_count >= len(train):
        return list(train)
    pick = np.random.default_rng(seed + 1).choice(len(train), size=max_count, replace=False)
    return sorted((train[i] for i in pick), key=_natural_key)


# ----------------------------------------------------------------------------------------------------------------
# Public entry point


def _raw_fits(
    prob: _Problem, params: Sequence[Parameter], best_u: np.ndarray, options: CalibrateOptions, report: ProgressFn
) -> tuple[np.ndarray, list[ParameterFit]]:
    """Values and intervals (module docstring, step 5) of raw mode at the optimum."""
    report("intervals", 0, 1)
    half = np.zeros(len(params))  # a choice is reported as itself
    if prob.free:
        residuals, jac = _jacobian(prob, best_u, options.fd_step)
        half[prob.free] = _intervals_unit(residuals, jac, options.interval_level)
    values = _to_values(params, best_u[None])[0]
    fits = []
    for i, p in enumerate(params):
        if p.discrete:
            lo = hi = float(values[i])
        else:
            lo = p.lower if not math.isfinite(half[i]) else float(p.from_unit(best_u[i] - half[i]))
            hi = p.upper if not math.isfinite(half[i]) else float(p.from_unit(best_u[i] + half[i]))
        fits.append(
            ParameterFit(
                name=p.name,
                nominal=p.nominal,
                value=float(values[i]),
                lower=p.lower,
                upper=p.upper,
                interval_low=lo,
                interval_high=hi,
                unit=p.unit,
            )
        )
    report("intervals", 1, 1)
    return values, fits


def _fit_embedding(
    scene: Path,
    base: mujoco.MjModel,
    fit_trajs: Sequence[Trajectory],
    options: CalibrateOptions,
    common: dict[str, Any],
    report: ProgressFn,
) -> tuple[list[Parameter], np.ndarray, list[ParameterFit], Evaluator, list[float], dict[str, Any]]:
    """Embedding mode (see grounder.calibration.embedding): MAP embedding, posterior, decoded raw parameters."""
    import grounder.calibration.embedding as emb

    if options.params:
        raise GrounderError("--params does not apply to embedding mode (it fits the property embedding); leave it out")
    space = emb.embedding_space(scene, base)
    params = list(space.params)
    ev = Evaluator(base, params, fit_trajs, **common)
    x0 = emb.to_unit(np.zeros(space.dim))
    prior_loss = ev.loss_of_values(space.values(np.zeros((1, space.dim))))[0]

    def values_of(u: np.ndarray) -> np.ndarray:
        return space.values(emb.from_unit(u))

    # 1. Data only (from the prior mean): the misfit left at its optimum is the noise scale s^2 of the posterior.
    fit_u, history = _search(_Problem(ev=ev, x0=x0, values=values_of), options, report)
    misfit = float(ev.loss_of_values(values_of(fit_u[None]))[0].mean())
    data_scale = math.sqrt(max(misfit, 1e-6))
    # 2. The posterior's mode: least squares on [sqrt(loss_b) / s, w] from the data-only optimum.
    prob = _Problem(ev=ev, x0=x0, values=values_of, prior=emb.from_unit, data_scale=data_scale)
    best_u = fit_u
    if options.local_iterations > 0:
        u, _ = _local_refine(prob, fit_u, options, report, [])
        if prob.objective(u[None])[0] <= prob.objective(fit_u[None])[0]:
            best_u = u
        history.append(float(ev.loss_of_values(values_of(best_u[None]))[0].mean()))
    report("intervals", 0, 1)
    _, jac = _jacobian(prob, best_u, options.fd_step)
    jac_w = jac / (2 * emb.W_BOUND)  # d residual / d w
    cov_w = np.linalg.pinv(jac_w.T @ jac_w)
    w = emb.from_unit(best_u)
    values = space.values(w[None])[0]
    samples = emb.posterior_samples(space, w, cov_w, count=200, seed=options.seed)
    prior_samples = emb.posterior_samples(space, np.zeros(space.dim), np.eye(space.dim), count=200, seed=options.seed)
    alpha = 50.0 * (1.0 - options.interval_level)
    fits = []
    for i, p in enumerate(params):
        fits.append(
            ParameterFit(
                name=p.name,
                nominal=p.nominal,
                value=float(values[i]),
                lower=float(np.percentile(prior_samples[:, i], 0.5)),
                upper=float(np.percentile(prior_samples[:, i], 99.5)),
                interval_low=float(np.percentile(samples[:, i], alpha)),
                interval_high=float(np.percentile(samples[:, i], 100.0 - alpha)),
                unit=p.unit,
            )
        )
    report("intervals", 1, 1)
    w_std = np.sqrt(np.maximum(np.diag(cov_w), 0.0))
    extra: dict[str, Any] = {
        "embedding": emb.summaries(space, w, w_std),
        "embedding_objective": {
            "prior_mean_loss": float(prior_loss.mean()),
            "data_only_loss": misfit,
            "noise_scale_s2": data_scale**2,
        },
        "_space": space,  # for the distribution fit; not written
        "_w": w,
    }
    return params, values, fits, ev, history, extra


def _fit_distribution(
    base: mujoco.MjModel,
    calibrated: mujoco.MjModel,
    params: Sequence[Parameter],
    fit_trajs: Sequence[Trajectory],
    options: CalibrateOptions,
    extra: dict[str, Any],
    report: ProgressFn,
) -> Any:
    """``--distribution``: the start noise of the fitted trajectories, the population fit, then the start noise's
    scale (`grounder.calibration.distribution`)."""
    import grounder.calibration.distribution as dist
    from grounder.sim.start_noise import measure_start_noise

    noise = measure_start_noise(base, fit_trajs)
    settings = dist.settings_of(options)
    if options.mode == "embedding":
        fitted = dist.fit_embedding_distribution(base, extra["_space"], extra["_w"], fit_trajs, noise, settings, report)
    else:
        fitted = dist.calibrated_raw_distribution(
            calibrated, params, fit_trajs, noise, settings, options.distribution_params, report
        )
    return dist.fit_start_noise_scale(calibrated, fitted, fit_trajs, settings, progress=report)


def _check_trajectories(model: mujoco.MjModel, trajs: Sequence[Trajectory]) -> None:
    if not trajs:
        raise GrounderError("no trajectories to calibrate on; pass a folder with at least one .npz trajectory")
    names = [t.name for t in trajs]
    if len(set(names)) != len(names):
        raise GrounderError("trajectory names must be unique; the split is made by name")
    for t in trajs:
        validate_against_model(t, model)
        sim.step_indices(t.time_s, model.opt.timestep, t.name)


def calibrate(
    scene: Path,
    trajs: Sequence[Trajectory],
    *,
    options: CalibrateOptions | None = None,
    out: Path | None = None,
    progress: ProgressFn | None = None,
) -> CalibrationResult:
    """Fits the scene's physical parameters to recorded trajectories.

    Args:
        scene: An MJCF file, or a scene folder holding ``scene.xml``.
        trajs: Recorded trajectories in the scene's joint order (uniquely named).
        options: Parameters, split, search budget; defaults: the scene kind's parameters (module docstring).
        out: If given, the calibrated scene folder to write (must not exist or be empty): ``scene.xml`` (and the
            source folder's other files and assets), ``calibration.json``, ``report.html``. Written in a temporary
            sibling folder and moved into place at the end.
        progress: ``progress(stage, done, total)`` callback.

    Returns:
        The fitted parameters with intervals, errors before/after on both splits, the calibrated model and spec.

    Raises:
        GrounderError: the scene cannot be loaded, a trajectory does not fit it, a parameter name is unknown, there
            are no trajectories, the output folder is not empty, or embedding mode is asked of a scene without a
            property embedding.
    """
    options = options or CalibrateOptions()
    report: ProgressFn = progress or (lambda _s, _d, _t: None)
    tick = time.perf_counter()
    scene = Path(scene)
    if out is not None:
        out = Path(out)
        if out.exists() and (not out.is_dir() or any(out.iterdir())):
            raise GrounderError(f"{out}: output folder exists and is not empty; choose a new folder")
    spec, base = load_scene_spec(scene)
    if out is not None:
        _check_manifest(scene)
        check_links_stay_inside(scene, NOT_COPIED)
    _check_trajectories(base, trajs)
    by_name = {t.name: t for t in trajs}
    repeats = repeated_motions(trajs, base) if options.validation_fraction > 0 else []  # no split, nothing to keep
    if repeats:
        log.warning(
            "%s; each kept on one side of the split (remove the copies if they are not meant to weigh double)",
            describe_repeats(repeats),
        )
    train_names, val_names = split_names(list(by_name), options.validation_fraction, options.split_seed, repeats)
    fit_names = training_subset(train_names, options.max_train_trajectories, options.split_seed)
    fit_trajs = [by_name[n] for n in fit_names]
    common: dict[str, Any] = {
        "rotation_weight": options.rotation_weight,
        "view_point_m": options.view_point_m,
        "along_view_weight": options.along_view_weight,
        "nthread": options.nthread,
        "max_batch_mb": options.max_batch_mb,
    }
    extra: dict[str, Any] = {}
    if options.mode == "embedding":
        params, values, fits, ev, history, extra = _fit_embedding(scene, base, fit_trajs, options, common, report)
    else:
        params = resolve_parameters(base, options.params)
        if options.distribution:
            from grounder.calibration.distribution import check_names

            check_names(params, options.distribution_params)  # before the search, not after it
        ev = Evaluator(base, params, fit_trajs, **common)
        prob = _Problem(
            ev=ev,
            x0=_initial_unit(params, options.initial),
            values=lambda u: _to_values(params, u),
            fixed=tuple(i for i, p in enumerate(params) if p.discrete),
        )
        if options.robust_scale is not None:
            start = np.sqrt(np.maximum(ev.loss_of_values(prob.values(prob.x0[None]))[0], 0.0))
            prob = replace(prob, robust_c=max(options.robust_scale * float(np.median(start)), 1e-9))
        groups = body_groups(params) if options.separate_bodies else None
        global_prob = None
        limit = options.global_search_trajectories
        if limit is not None and limit < len(fit_trajs) and options.generations > 0:
            few = set(training_subset(fit_names, limit, options.seed))
            global_ev = Evaluator(base, params, [t for t in fit_trajs if t.name in few], **common)
            global_prob = replace(prob, ev=global_ev)
            extra["global_search_trajectories"] = sorted(few, key=_natural_key)
        best_u, history = _search(prob, options, report, groups, global_prob)
        if global_prob is not None:
            ev.absorb_counts(global_prob.ev)
        values, fits = _raw_fits(prob, params, best_u, options, report)

    calibrated_spec = apply_to_spec(spec, base, params, values)
    try:
        calibrated = calibrated_spec.compile()
    except Exception as exc:
        raise GrounderError(f"the calibrated scene does not compile ({exc})") from exc

    distribution = None
    if options.distribution:
        # on every training trajectory: max_train_trajectories bounds the point search, and a population is
        # estimated better from more of its members
        train_trajs = [by_name[n] for n in train_names]
        distribution = _fit_distribution(base, calibrated, params, train_trajs, options, extra, report)
    extra = {k: v for k, v in extra.items() if not k.startswith("_")}

    report("validation", 0, 1)
    before: dict[str, ErrorSummary] = {}
    after: dict[str, ErrorSummary] = {}
    for split, names in (("train", train_names), ("validation", val_names)):
        if not names:
            continue
        split_ev = Evaluator(base, params, [by_name[n] for n in names], **common)
        before[split] = split_ev.summary(base)
        after[split] = split_ev.summary(calibrated)
    report("validation", 1, 1)

    result = CalibrationResult(
        parameters=tuple(fits),
        train_names=tuple(train_names),
        validation_names=tuple(val_names),
        before=before,
        after=after,
        model=calibrated,
        spec=calibrated_spec,
        history=tuple(history),
        evaluations=ev.rollouts,
        steps_per_second=ev.steps / max(ev.rollout_seconds, 1e-9),
        eval_steps_per_second=ev.steps / max(ev.eval_seconds, 1e-9),
        seconds=time.perf_counter() - tick,
        mode=options.mode,
        distribution=distribution,
        extra={
            **extra,
            "scene": str(scene),
            "fit_trajectories": fit_names,
            "repeated_trajectories": [list(g) for g in repeats],
            "options": {
                k: (list(v) if isinstance(v, tuple) else v) for k, v in options.__dict__.items() if k != "nthread"
            },
        },
    )
    if out is not None:
        report("writing", 0, 1)
        write_calibrated_scene(scene, result, [by_name[n] for n in val_names or train_names], out, base)
        result = CalibrationResult(**{**result.__dict__, "out_dir": out})
        report("writing", 1, 1)
    return result
