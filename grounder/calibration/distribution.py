"""A fitted distribution over a scene's calibrated parameters (``image2sim calibrate --distribution``).

What it models: every recorded trajectory ran with its own parameters theta_i (the board is a little stickier here,
that impact a little softer), drawn from one population N(mean, cov) in the search coordinates (raw mode: each
parameter's unit box, log scale where the search uses it; embedding mode: the property embedding), and started from
a state the tracker saw with error (`grounder.sim.start_noise`). The fit maximises the likelihood of the recorded
trajectories under the sampled simulations, ``sum_i log integral p(y_i | theta, start) N(theta; mean, cov) dtheta``:
the population-level likelihood that DROPO (Tiboni et al., 2023) maximises, here over whole trajectories rather than
one-step transitions, as what a user samples are whole rollouts.

How (Monte Carlo expectation-maximisation for a hierarchical Gaussian):

1. Cut every trajectory into windows of ``horizon`` sample intervals (5; one starting every ``stride`` samples), as
   DROPO compares short transitions: a whole toss is chaotic (a cube landing on another face), so the likelihood of a
   whole trajectory under a handful of samples is all or nothing, while a short window's outcome is a smooth
   function of the parameters.
2. Draw M parameter vectors from a proposal (the current N(mean, cov) widened by `PROPOSAL_WIDTH`; the importance
   ratio enters the weights) and, per window, M starts: its recorded first state perturbed by the start noise.
   Simulate every window M times in batched `mujoco.rollout` calls (`grounder.sim.sampled`).
3. Per trajectory and sample, the observation likelihood: independent Gaussians on each window's error at its last
   sample (free bodies: the position error as a fraction of the body's size and the rotation error as a rotation
   vector in radians, each group with its own scale; hinge and slide joints: the joint error), summed over the
   trajectory's windows (one parameter vector per trajectory). The scales are fitted too: their maximum-likelihood
   values given the weights, alternated with the weights a few times.
4. Each trajectory's samples get weights proportional to likelihood x importance ratio (the trajectory's posterior
   over theta). New mean: the average over trajectories of each posterior mean (with ``CalibrateOptions.
   distribution_centre = "point"`` the calibrated values, kept); new covariance: the average over trajectories of
   each posterior's second moment about the mean. Repeat ``iterations`` times.

5. Finally the measured start noise gets one scale factor, fitted on whole trajectories by the energy score
   (`fit_start_noise_scale`; the measure is a lower bound of how uncertain a recorded start is).

The mean is fitted by default: centred on a point calibrated with a small budget, the covariance absorbs the point's
own error (on the known case of `grounder.calibration.known_case`, seed 102: a point 16% off gave a spread 47% too
wide, against 9% with the mean fitted).

Parameters the data says nothing about keep their spread (their posterior is the population), so the fit narrows
only what the recordings constrain. Choices (condim, cone) are held at the point estimate. The samples are drawn
seeded: the same call gives the same distribution.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from grounder.calibration.evaluator import scalar_joint_errors
from grounder.calibration.parameters import Parameter, apply_to_model, body_size_m, resolve_parameters
from grounder.core.trajectory import Trajectory
from grounder.errors import GrounderError
from grounder.sim.rollout import free_joints
from grounder.sim.sampled import rollout_samples
from grounder.sim.start_noise import StartNoise, perturbed_starts
from image2sim_common.progress import ProgressFn, no_progress
from image2sim_common.rotations import quat_conj, quat_mul, quat_to_rotvec

log = logging.getLogger(__name__)

DISTRIBUTION_FILE = "distribution.json"
FORMAT = "image2sim-distribution"
VERSION = 1
METHOD = "monte-carlo-em"
INITIAL_STD_UNIT = 0.1  # raw mode's starting spread: a tenth of each parameter's search range
MIN_VARIANCE_UNIT = 1e-8  # a floor on the covariance's diagonal (a parameter never collapses to exactly one value)
_SCALE_ROUNDS = 5  # alternations of weights and observation scales per iteration
PROPOSAL_WIDTH = 1.5  # the proposal's spread over the population's


@dataclass(frozen=True, kw_only=True, eq=False)
class FittedDistribution:
    """A Gaussian over parameters in their search coordinates, with how it was fitted.

    Attributes:
        names: The parameters it draws, in order.
        specs: ``NAME=LOW:HIGH`` of each: re-resolving them on the scene gives the same coordinates.
        log_scale: Per parameter, whether its coordinate is logarithmic.
        units: Per parameter, its unit.
        point: (P,) the calibrated point, in the unit coordinates.
        mean, cov: (P,), (P, P) the Gaussian, in the unit coordinates (draws are clipped to [0, 1]).
        start_noise: The measured error of the recorded first states (drawn with the parameters).
        mode: ``raw`` or ``embedding`` (then ``embedding`` holds the fitted Gaussian over the embedding, and
            ``mean``/``cov`` are its moments in the decoded parameters' coordinates).
        method: How it was fitted (module docstring).
        fit: The fit's record: samples, iterations, observation scales, per-iteration log-likelihood and
            effective sample size, trajectories.
        embedding: Embedding mode: the Gaussian over the embedding (``mean``, ``cov``) and the prior it narrowed.
    """

    names: tuple[str, ...]
    specs: tuple[str, ...]
    log_scale: tuple[bool, ...]
    units: tuple[str, ...]
    point: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    start_noise: StartNoise
    mode: str = "raw"
    method: str = METHOD
    fit: dict[str, Any] = field(default_factory=dict)
    embedding: dict[str, Any] | None = None

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diag(self.cov), 0.0))

    def draw_unit(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """(count, P) draws in the unit coordinates, clipped to [0, 1]."""
        chol = _cholesky(self.cov)
        return np.clip(self.mean + rng.normal(size=(count, len(self.mean))) @ chol.T, 0.0, 1.0)

    def parameters(self, model: mujoco.MjModel) -> list[Parameter]:
        """The parameters resolved on ``model`` (the calibrated scene) with the stored bounds.

        Raises:
            GrounderError: a name does not resolve on this scene, or its coordinate differs from the stored one.
        """
        params = resolve_parameters(model, list(self.specs))
        for p, log_scale in zip(params, self.log_scale, strict=True):
            if p.log_scale != log_scale:
                raise GrounderError(
                    f"{DISTRIBUTION_FILE}: parameter {p.name} is searched on a {'log' if p.log_scale else 'linear'} "
                    "scale in this scene, not as the file says; re-run `image2sim calibrate --distribution`"
                )
        return params

    def draw_values(self, params: Sequence[Parameter], count: int, rng: np.random.Generator) -> np.ndarray:
        """(count, P) parameter values in physical units."""
        unit = self.draw_unit(count, rng)
        return np.stack([p.from_unit(unit[:, i]) for i, p in enumerate(params)], axis=1)

    def draw_models(self, model: mujoco.MjModel, count: int, rng: np.random.Generator) -> list[mujoco.MjModel]:
        """``count`` copies of ``model`` (the scene the file belongs to), each with one draw of the parameters."""
        params = self.parameters(model)
        return [apply_to_model(model, params, row) for row in self.draw_values(params, count, rng)]

    def summary(self, params: Sequence[Parameter], count: int = 4000, seed: int = 0) -> list[dict[str, Any]]:
        """Per parameter: the point value and the distribution's mean, std, 5th and 95th percentile (physical)."""
        values = self.draw_values(params, count, np.random.default_rng(seed))
        rows = []
        for i, p in enumerate(params):
            rows.append(
                {
                    "name": p.name,
                    "unit": p.unit,
                    "value": float(p.from_unit(self.point[i])),
                    "mean": float(values[:, i].mean()),
                    "std": float(values[:, i].std()),
                    "p05": float(np.percentile(values[:, i], 5)),
                    "p95": float(np.percentile(values[:, i], 95)),
                }
            )
        return rows

    def to_json(self, params: Sequence[Parameter] | None = None) -> dict[str, Any]:
        out: dict[str, Any] = {
            "format": FORMAT,
            "version": VERSION,
            "method": self.method,
            "mode": self.mode,
            "coordinates": "each parameter's unit search coordinate (log where log_scale); draws clipped to [0, 1]",
            "parameters": [
                {"name": n, "spec": s, "log_scale": ls, "unit": u}
                for n, s, ls, u in zip(self.names, self.specs, self.log_scale, self.units, strict=True)
            ],
            "point_unit": [float(v) for v in self.point],
            "mean_unit": [float(v) for v in self.mean],
            "cov_unit": [[float(v) for v in row] for row in self.cov],
            "start_noise": self.start_noise.to_json(),
            "fit": self.fit,
        }
        if self.embedding is not None:
            out["embedding"] = self.embedding
        if params is not None:
            out["summary"] = self.summary(params)
        return out


def _cholesky(cov: np.ndarray) -> np.ndarray:
    cov = 0.5 * (cov + cov.T)
    for ridge in (0.0, 1e-12, 1e-10, 1e-8, 1e-6):
        try:
            return np.linalg.cholesky(cov + ridge * np.eye(len(cov)))
        except np.linalg.LinAlgError:
            continue
    w, v = np.linalg.eigh(cov)
    return v * np.sqrt(np.maximum(w, 0.0))


# ----------------------------------------------------------------------------------------------------------------
# Reading distribution.json (an untrusted file: every field checked)


def _numbers(value: Any, shape: tuple[int, ...], where: str, key: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != shape or not np.all(np.isfinite(arr)):
        raise GrounderError(f"{where}: {key} must be finite numbers of shape {shape}; re-run calibrate --distribution")
    return arr


def read_distribution(path: Path, nv: int) -> FittedDistribution:
    """Reads ``distribution.json`` (written by `write_distribution`), checking every field.

    Raises:
        GrounderError: the file is missing, not JSON, of another format, or a field is malformed.
    """
    from grounder.core.json_files import read_json_file

    where = str(path)
    data = read_json_file(path, "re-run `image2sim calibrate --distribution` to write it")
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise GrounderError(f"{where}: not an image2sim distribution file (format {FORMAT!r} expected)")
    if data.get("version") != VERSION:
        raise GrounderError(
            f"{where}: version {data.get('version')!r} is not {VERSION}; re-run `image2sim calibrate --distribution`"
        )
    rows = data.get("parameters")
    if not isinstance(rows, list) or not rows:
        raise GrounderError(f"{where}: parameters must be a non-empty list")
    names, specs, logs, units = [], [], [], []
    for row in rows:
        if not (
            isinstance(row, dict)
            and isinstance(row.get("name"), str)
            and isinstance(row.get("spec"), str)
            and isinstance(row.get("log_scale"), bool)
            and isinstance(row.get("unit", ""), str)
        ):
            raise GrounderError(f"{where}: each parameter needs a name, a spec (NAME=LOW:HIGH) and log_scale")
        names.append(row["name"])
        specs.append(row["spec"])
        logs.append(row["log_scale"])
        units.append(row.get("unit", ""))
    p = len(names)
    point = _numbers(data.get("point_unit"), (p,), where, "point_unit")
    mean = _numbers(data.get("mean_unit"), (p,), where, "mean_unit")
    cov = _numbers(data.get("cov_unit"), (p, p), where, "cov_unit")
    if not np.allclose(cov, cov.T, atol=1e-9) or np.min(np.linalg.eigvalsh(cov)) < -1e-9:
        raise GrounderError(f"{where}: cov_unit must be a symmetric positive semi-definite matrix")
    noise = StartNoise.from_json(data.get("start_noise", {}), nv, where)
    mode = data.get("mode", "raw")
    if mode not in ("raw", "embedding"):
        raise GrounderError(f"{where}: mode must be raw or embedding")
    fit = data.get("fit", {})
    return FittedDistribution(
        names=tuple(names),
        specs=tuple(specs),
        log_scale=tuple(logs),
        units=tuple(units),
        point=point,
        mean=mean,
        cov=cov,
        start_noise=noise,
        mode=mode,
        method=str(data.get("method", METHOD)),
        fit=fit if isinstance(fit, dict) else {},
        embedding=data.get("embedding") if isinstance(data.get("embedding"), dict) else None,
    )


def read_scene_distribution(scene_dir: Path, nv: int, instead: str) -> FittedDistribution:
    """A scene folder's ``distribution.json`` (`read_distribution`).

    Args:
        instead: What else the user may do, appended to the complaint when the folder has none.

    Raises:
        GrounderError: the folder has no distribution.json, or it is malformed.
    """
    path = Path(scene_dir) / DISTRIBUTION_FILE
    if not path.is_file():
        raise GrounderError(
            f"{scene_dir} has no {DISTRIBUTION_FILE} to draw from; calibrate it with `image2sim calibrate "
            f"--distribution` {instead}"
        )
    return read_distribution(path, nv)


def write_distribution(path: Path, dist: FittedDistribution, params: Sequence[Parameter]) -> None:
    path.write_text(json.dumps(dist.to_json(params), indent=1) + "\n", encoding="utf-8")


def spec_of(p: Parameter) -> str:
    """``NAME=LOW:HIGH``, exact (repr) so that re-resolving gives the same coordinates."""
    return f"{p.name}={p.lower!r}:{p.upper!r}"


# ----------------------------------------------------------------------------------------------------------------
# The observation model


@dataclass(frozen=True, kw_only=True)
class _Window:
    """A piece of one recorded trajectory: simulated from its first recorded sample, compared at its last."""

    traj: int  # which trajectory
    piece: Trajectory  # samples k .. k + horizon


def windows_of(trajs: Sequence[Trajectory], horizon: int, stride: int) -> list[_Window]:
    """Every trajectory cut into pieces of ``horizon`` sample intervals, one starting every ``stride`` samples."""
    out = []
    for b, t in enumerate(trajs):
        h = min(horizon, t.num_steps - 1)
        for k in range(0, t.num_steps - h, stride):
            out.append(
                _Window(
                    traj=b,
                    piece=Trajectory(
                        time_s=t.time_s[k : k + h + 1],
                        qpos=t.qpos[k : k + h + 1],
                        qvel=t.qvel[k : k + h + 1],
                        ctrl=None if t.ctrl is None else t.ctrl[k : k + h + 1],
                        name=f"{t.name}@{k}",
                    ),
                )
            )
    return out


class _Likelihood:
    """Squared, scaled errors of sampled window rollouts at each window's last sample (module docstring, step 2)."""

    def __init__(self, model: mujoco.MjModel) -> None:
        self.free = free_joints(model)
        self.sizes = [
            body_size_m(model, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, fj.body)) for fj in self.free
        ]
        self.scalar = [(je.qpos_index, je.scale) for je in scalar_joint_errors(model)]  # the calibration loss's scales
        if not self.free and not self.scalar:
            raise GrounderError("the scene has no free body, hinge or slide joint: nothing to fit a distribution to")

    def squared(self, recorded: np.ndarray, simulated: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Recorded qpos (nq,) against M simulated ones (M, nq): the sum of squared scaled errors of each group
        (position, rotation, joint) (M, 3), and how many numbers each group summed (3,)."""
        m = len(simulated)
        sq = np.zeros((m, 3))
        counts = np.zeros(3)
        for fj, size in zip(self.free, self.sizes, strict=True):
            d = (simulated[:, fj.pos] - recorded[None, fj.pos]) / size
            sq[:, 0] += np.sum(d**2, axis=1)
            rel = quat_mul(np.broadcast_to(quat_conj(recorded[fj.quat]), (m, 4)), simulated[:, fj.quat])
            sq[:, 1] += np.sum(quat_to_rotvec(rel) ** 2, axis=1)
            counts[:2] += 3
        for adr, scale in self.scalar:
            sq[:, 2] += ((simulated[:, adr] - recorded[adr]) / scale) ** 2
            counts[2] += 1
        return sq, counts


def _weights_and_scales(
    sq: np.ndarray, counts: np.ndarray, scales: np.ndarray | None, log_ratio: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Alternates the trajectories' sample weights and the observation scales (module docstring, steps 2-3).

    Args:
        sq: (N, M, 3) squared errors per trajectory, sample and group; counts: (N, 3) numbers summed.
        log_ratio: (M,) log of population density over proposal density of each sample (importance correction).

    Returns:
        weights (N, M), scales (3,), log-likelihood (N, M).
    """
    used = counts.sum(axis=0) > 0
    if scales is None:  # start from the plain average over samples
        scales = np.sqrt(np.where(used, sq.mean(axis=1).sum(axis=0) / np.maximum(counts.sum(axis=0), 1), 1.0))
    scales = np.maximum(scales, 1e-9)
    shift = np.zeros(sq.shape[1]) if log_ratio is None else log_ratio

    def log_likelihood(scales: np.ndarray) -> np.ndarray:  # (N, M), with the importance correction
        loglik = -0.5 * np.sum(sq / scales**2, axis=2) - np.sum(counts * np.log(scales), axis=1)[:, None]
        return np.where(np.isfinite(loglik), loglik + shift[None], -np.inf)

    for _ in range(_SCALE_ROUNDS):
        loglik = log_likelihood(scales)
        top = loglik.max(axis=1, keepdims=True)
        top = np.where(np.isfinite(top), top, 0.0)
        w = np.exp(loglik - top)
        w = w / np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
        w = np.where(np.isfinite(w).all(axis=1, keepdims=True), w, 1.0 / sq.shape[1])
        total = np.einsum("nm,nmg->g", w, np.where(np.isfinite(sq), sq, 0.0))
        scales = np.where(used, np.sqrt(total / np.maximum(counts.sum(axis=0), 1)), 1.0)
        scales = np.maximum(scales, 1e-9)
    return w, scales, log_likelihood(scales)


# ----------------------------------------------------------------------------------------------------------------
# The fit


@dataclass(frozen=True, kw_only=True)
class EMSettings:
    """The fit's budget: ``samples`` draws per iteration, ``iterations``; windows of ``horizon`` sample intervals
    starting every ``stride`` samples; ``fixed_mean``: keep the mean where it starts (fit the covariance only)."""

    samples: int = 64
    iterations: int = 8
    horizon: int = 5
    stride: int = 5
    seed: int = 0
    nthread: int | None = None
    max_batch_mb: float = 256.0
    fixed_mean: bool = False


def fit_population(
    base: mujoco.MjModel,
    params: Sequence[Parameter],
    values_of: Callable[[np.ndarray], np.ndarray],
    mean0: np.ndarray,
    cov0: np.ndarray,
    trajs: Sequence[Trajectory],
    noise: StartNoise,
    settings: EMSettings,
    progress: ProgressFn = no_progress,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Monte Carlo EM (module docstring) from N(mean0, cov0) in the search coordinates.

    Args:
        params: Every parameter the models set; ``values_of`` maps (M, D) coordinates to (M, len(params)) values.

    Returns:
        mean (D,), cov (D, D), and the fit's record.
    """
    rng = np.random.default_rng(settings.seed)
    like = _Likelihood(base)
    windows = windows_of(trajs, settings.horizon, settings.stride)
    pieces = [w.piece for w in windows]
    owner = np.array([w.traj for w in windows])
    units = len(trajs)
    mean = np.asarray(mean0, np.float64).copy()
    cov = np.asarray(cov0, np.float64).copy()
    data = mujoco.MjData(base)
    history: list[dict[str, Any]] = []
    scales = None
    for it in range(settings.iterations):
        progress("distribution", it, settings.iterations)
        # The proposal is the population widened (its tails are where the extreme trajectories' posteriors lie);
        # each sample's weight carries the ratio of the population's density to the proposal's.
        normal = rng.normal(size=(settings.samples, len(mean)))
        z = mean + PROPOSAL_WIDTH * normal @ _cholesky(cov).T
        log_ratio = -0.5 * np.sum(normal**2, axis=1) * (PROPOSAL_WIDTH**2 - 1.0)
        models = [apply_to_model(base, params, row, data=data) for row in values_of(z)]
        starts = [perturbed_starts(base, p.qpos[0], p.qvel[0], noise, settings.samples, rng) for p in pieces]
        sims = rollout_samples(models, pieces, starts, nthread=settings.nthread, max_batch_mb=settings.max_batch_mb)
        sq = np.zeros((units, settings.samples, 3))
        counts = np.zeros((units, 3))
        for piece, b, (qpos, _) in zip(pieces, owner, sims, strict=True):
            sq_w, count_w = like.squared(piece.qpos[-1], qpos[:, -1])
            sq[b] += sq_w
            counts[b] += count_w
        w, scales, loglik = _weights_and_scales(sq, counts, scales, log_ratio)
        post_mean = w @ z  # (N, D)
        if not settings.fixed_mean:
            mean = post_mean.mean(axis=0)
        dev = z - mean  # (M, D)
        cov = np.einsum("nm,mi,mj->ij", w, dev, dev) / units
        cov = 0.5 * (cov + cov.T) + MIN_VARIANCE_UNIT * np.eye(len(mean))
        top = loglik.max(axis=1)
        marginal = float(np.sum(top + np.log(np.mean(np.exp(loglik - top[:, None]), axis=1))))
        ess = 1.0 / np.sum(w**2, axis=1)
        history.append(
            {
                "iteration": it + 1,
                "log_likelihood": marginal,
                "median_effective_samples": float(np.median(ess)),
                "std_unit": [float(v) for v in np.sqrt(np.diag(cov))],
            }
        )
        log.info("distribution EM %d: log-likelihood %.1f, median ESS %.1f", it + 1, marginal, np.median(ess))
    progress("distribution", settings.iterations, settings.iterations)
    record = {
        "samples_per_iteration": settings.samples,
        "iterations": settings.iterations,
        "window_horizon_samples": settings.horizon,
        "window_stride_samples": settings.stride,
        "windows": len(windows),
        "seed": settings.seed,
        "trajectories": len(trajs),
        "observation_scales": {
            "position_fraction_of_size": float(scales[0]) if scales is not None else math.nan,
            "rotation_rad": float(scales[1]) if scales is not None else math.nan,
            "joint_scaled": float(scales[2]) if scales is not None else math.nan,
        },
        "history": history,
    }
    return mean, cov, record


def fit_raw_distribution(
    base: mujoco.MjModel,
    params: Sequence[Parameter],
    values: np.ndarray,
    trajs: Sequence[Trajectory],
    noise: StartNoise,
    settings: EMSettings,
    progress: ProgressFn = no_progress,
) -> FittedDistribution:
    """Raw mode: a Gaussian over the continuous parameters' unit coordinates, around the calibrated ``values``.

    Args:
        params: The calibrated parameters; ``values`` their calibrated values.
            Choices (condim, cone) stay at their values.
    """
    chosen = [i for i, p in enumerate(params) if not p.discrete]
    if not chosen:
        raise GrounderError("no continuous parameter to fit a distribution over (choices such as condim are held)")
    point = np.array([params[i].to_unit(values[i]) for i in chosen], np.float64).clip(0.0, 1.0)

    def values_of(z: np.ndarray) -> np.ndarray:
        out = np.tile(np.asarray(values, np.float64), (len(z), 1))
        for col, i in enumerate(chosen):
            out[:, i] = params[i].from_unit(z[:, col])
        return out

    cov0 = np.eye(len(chosen)) * INITIAL_STD_UNIT**2
    mean, cov, record = fit_population(base, params, values_of, point, cov0, trajs, noise, settings, progress)
    sel = [params[i] for i in chosen]
    return FittedDistribution(
        names=tuple(p.name for p in sel),
        specs=tuple(spec_of(p) for p in sel),
        log_scale=tuple(p.log_scale for p in sel),
        units=tuple(p.unit for p in sel),
        point=point,
        mean=mean,
        cov=cov,
        start_noise=noise,
        mode="raw",
        fit=record,
    )


def fit_embedding_distribution(
    base: mujoco.MjModel,
    space: Any,
    w_point: np.ndarray,
    trajs: Sequence[Trajectory],
    noise: StartNoise,
    settings: EMSettings,
    progress: ProgressFn = no_progress,
) -> FittedDistribution:
    """Embedding mode: the population starts as the property model's prior, N(0, I) over the embedding, and the fit
    narrows it; the result is also stored as its moments in the decoded parameters' unit coordinates, which is what
    `rollout --samples` and `randomize` draw from (no property model needed there)."""
    params = list(space.params)
    dim = int(space.dim)

    from grounder.calibration.embedding import W_BOUND

    def values_of(z: np.ndarray) -> np.ndarray:  # the search's box, as in the MAP fit
        return np.asarray(space.values(np.clip(np.asarray(z), -W_BOUND, W_BOUND)), np.float64)

    mean, cov, record = fit_population(
        base, params, values_of, np.zeros(dim), np.eye(dim), trajs, noise, settings, progress
    )
    draws = np.random.default_rng(settings.seed).normal(size=(4000, dim)) @ _cholesky(cov).T + mean
    vals = values_of(draws)
    unit = np.stack([np.clip(p.to_unit(vals[:, i]), 0.0, 1.0) for i, p in enumerate(params)], axis=1)
    point_vals = values_of(np.asarray(w_point, np.float64)[None])[0]
    return FittedDistribution(
        names=tuple(p.name for p in params),
        specs=tuple(spec_of(p) for p in params),
        log_scale=tuple(p.log_scale for p in params),
        units=tuple(p.unit for p in params),
        point=np.array([np.clip(p.to_unit(point_vals[i]), 0.0, 1.0) for i, p in enumerate(params)], np.float64),
        mean=unit.mean(axis=0),
        cov=np.atleast_2d(np.cov(unit, rowvar=False)) + MIN_VARIANCE_UNIT * np.eye(len(params)),
        start_noise=noise,
        mode="embedding",
        fit=record,
        embedding={
            "mean": [float(v) for v in mean],
            "cov": [[float(v) for v in row] for row in cov],
            "prior": {"mean": [0.0] * dim, "cov": "identity"},
            "map": [float(v) for v in w_point],
        },
    )


_RELATIVE = (".size_scale", "opt.gravity_scale")  # factors on the scene's own value: 1 in a calibrated scene


def settings_of(options: Any) -> EMSettings:
    """The fit's settings from `CalibrateOptions`."""
    return EMSettings(
        samples=options.distribution_samples,
        iterations=options.distribution_iterations,
        seed=options.seed,
        nthread=options.nthread,
        max_batch_mb=options.max_batch_mb,
        fixed_mean=options.mode == "raw" and options.distribution_centre == "point",
    )


def check_names(params: Sequence[Parameter], names: Sequence[str]) -> None:
    """``--distribution-params`` must name calibrated continuous parameters (checked before any search runs).

    Raises:
        GrounderError: naming the others and the choices.
    """
    unknown = set(names) - {p.name for p in params if not p.discrete}
    if unknown:
        raise GrounderError(
            f"--distribution-params names {', '.join(sorted(unknown))}, which calibration does not fit as a "
            f"continuous parameter; choose among {', '.join(p.name for p in params if not p.discrete)}"
        )


def calibrated_raw_distribution(
    calibrated: mujoco.MjModel,
    params: Sequence[Parameter],
    trajs: Sequence[Trajectory],
    noise: StartNoise,
    settings: EMSettings,
    names: Sequence[str] = (),
    progress: ProgressFn = no_progress,
) -> FittedDistribution:
    """Raw mode's distribution in the calibrated scene's own terms: each calibrated parameter re-resolved on the
    calibrated model with the calibration's bounds (factors such as ``size_scale`` around that scene's 1), so that
    ``rollout --samples`` and ``randomize`` apply draws to the written scene.xml exactly as the fit did."""
    check_names(params, names)
    chosen = [p for p in params if not p.discrete and (not names or p.name in names)]
    if not chosen:
        raise GrounderError("no continuous parameter to fit a distribution over (choices such as condim are held)")
    specs = [p.name if p.name.endswith(_RELATIVE) else spec_of(p) for p in chosen]
    on_calibrated = resolve_parameters(calibrated, specs)
    values = np.array([p.nominal for p in on_calibrated], np.float64)
    return fit_raw_distribution(calibrated, on_calibrated, values, trajs, noise, settings, progress=progress)


START_NOISE_SCALES = (1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0)
SCALE_SAMPLES = 16
SCALE_TRAJECTORIES = 200


def fit_start_noise_scale(
    model: mujoco.MjModel,
    dist: FittedDistribution,
    trajs: Sequence[Trajectory],
    settings: EMSettings,
    scales: Sequence[float] = START_NOISE_SCALES,
    progress: ProgressFn = no_progress,
) -> FittedDistribution:
    """The distribution with its start noise scaled by the factor whose whole-trajectory sampled rollouts score best.

    The measured start noise (`grounder.sim.start_noise`) is a lower bound of how uncertain a rollout's start is:
    a quadratic through a smooth tracker's first frames sees its jitter, not what the tracker's filtering hides (on
    the real cube tosses the velocities are median-filtered backward differences). So, as ensemble forecasts are
    recalibrated (their spread inflated by a factor fitted to past cases under a proper score), one factor is fitted
    on the fitting trajectories (at most `SCALE_TRAJECTORIES`): each simulated `SCALE_SAMPLES` times from starts
    perturbed by factor x the measured noise, parameters from the fitted distribution (the same draws for every
    factor), whole trajectories scored by the energy score (`grounder.sim.sample_scores`); the lowest wins, 1 among
    the candidates. Without measured start noise there is nothing to scale.
    """
    from dataclasses import replace

    from grounder.sim.sample_scores import score_samples

    if dist.start_noise.trajectories == 0 or not trajs or not free_joints(model):
        return dist
    use = list(trajs)[:SCALE_TRAJECTORIES]
    models = dist.draw_models(model, SCALE_SAMPLES, np.random.default_rng(settings.seed + 1))
    scores: dict[float, float] = {}
    for i, scale in enumerate(scales):
        progress("start noise scale", i, len(scales))
        noise = dist.start_noise.scaled(scale)
        rng = np.random.default_rng(settings.seed + 2)
        starts = [perturbed_starts(model, t.qpos[0], t.qvel[0], noise, SCALE_SAMPLES, rng) for t in use]
        fans = rollout_samples(models, use, starts, nthread=settings.nthread, max_batch_mb=settings.max_batch_mb)
        scores[scale] = float(
            np.mean([score_samples(model, t, q, v).energy for t, (q, v) in zip(use, fans, strict=True)])
        )
    progress("start noise scale", len(scales), len(scales))
    best = min(scores, key=lambda s: (scores[s], s))
    log.info("energy score by start noise scale: %s", scores)
    fit = {
        **dist.fit,
        "start_noise_scale": {
            "chosen": best,
            "energy_score_by_scale": {str(k): v for k, v in scores.items()},
            "trajectories": len(use),
            "samples": SCALE_SAMPLES,
            "measured": dist.start_noise.to_json(),
        },
    }
    return replace(dist, start_noise=dist.start_noise.scaled(best), fit=fit)
