"""Training the residual: one-step targets from recorded motion, then rounds of data aggregation along rollouts.

Round 0 fits the correction that takes MuJoCo's one-period prediction from each recorded state to the next
recorded state. A model trained on one-step targets only sees recorded states, but in a rollout it is fed its own
predictions, which drift; so each further round rolls the current hybrid model out from recorded states for
``dagger_horizon`` periods and adds, for every state it visits, the correction back to the recorded next state
("data as demonstrator", Venkatraman et al., AAAI 2015; DAgger for dynamics models). States that drifted too far
(``dagger_max_pos_error_m``, ``dagger_max_rot_error_deg``) are left out: there the recorded next state is no
longer a learnable target. The gate statistics (ranges, k-means centres) are recomputed on all states seen.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from grounder.core.repeats import describe_repeated_indices, repeated_motion_indices, split_keeping_together
from grounder.core.trajectory import Trajectory, validate_against_model
from grounder.errors import GrounderError
from grounder.residual.files import file_sha256, scene_files_sha256
from grounder.residual.free_body import (
    FreeBody,
    NumpyResidual,
    body_features,
    correction_targets,
    free_bodies,
    smooth_free_bodies,
)
from grounder.residual.joint import (
    JOINT_SPACE,
    JointSpace,
    NumpyJointResidual,
    joint_features,
    joint_space,
    joint_targets,
)
from grounder.residual.meta import (
    META_FILE,
    NUM_OUTPUTS,
    ONNX_FILE,
    OUTPUT_NAMES,
    RESIDUAL_FILES,
    WEIGHTS_FILE,
    GateOptions,
    ResidualMeta,
)
from grounder.residual.options import ResidualOptions, ResidualTrainResult
from grounder.residual.report import ResidualReport, RolloutErrors, rollout_errors, write_residual_report
from grounder.residual.simulator import Simulator
from grounder.sim.rollout import free_joints, quat_angle_rad, step_indices
from grounder.sim.scene_files import SCENE_XML, check_links_stay_inside, copy_scene_files, scene_xml_path
from image2sim_common.progress import ProgressFn
from reconstruction import check_output_dir, staged_output_dir

log = logging.getLogger(__name__)

REPORT_FILE = "report.html"  # the residual's HTML report, beside residual.pt/.json/.onnx
_FREE_RMS = ("position, m", "rotation, rad", "velocity, m/s", "angular velocity, rad/s")  # one-step RMS groups


@dataclass(frozen=True, kw_only=True)
class _Transitions:
    feats: np.ndarray  # (N, B, F)
    targets: np.ndarray  # (N, B, 12)
    groups: np.ndarray  # (N,) the recorded segment each sample comes from


def _period_steps(model: mujoco.MjModel, trajs: Sequence[Trajectory]) -> int:
    gaps = np.concatenate([np.diff(step_indices(t.time_s, model.opt.timestep, t.name)) for t in trajs])
    values, counts = np.unique(gaps, return_counts=True)
    return int(values[np.argmax(counts)])


def _group_rms(err: np.ndarray, joint: bool = False) -> tuple[float, float, float, float]:
    """(N, B, 12) -> RMS norm of each 3-vector group; joint corrections (N, 1, 2J) -> (position, 0, velocity, 0)."""
    if joint:
        half = err.shape[-1] // 2
        pos = float(np.sqrt(np.mean(np.sum(err[..., :half] ** 2, axis=-1))))
        vel = float(np.sqrt(np.mean(np.sum(err[..., half:] ** 2, axis=-1))))
        return (pos, 0.0, vel, 0.0)
    groups = err.reshape(*err.shape[:-1], 4, 3)
    rms = np.sqrt(np.mean(np.sum(groups**2, axis=-1), axis=tuple(range(groups.ndim - 2))))
    return (float(rms[0]), float(rms[1]), float(rms[2]), float(rms[3]))


class _Trainer:
    def __init__(self, sim: Simulator, trajs: Sequence[Trajectory], options: ResidualOptions):
        """``sim``: the scene as MuJoCo alone (`Simulator(..., use_residual=False)`), loaded once per training."""
        self.options = options
        self.sim = sim
        self.model = self.sim.model
        for traj in trajs:
            validate_against_model(traj, self.model)
        self.period = _period_steps(self.model, trajs)
        self.sim.period_steps = self.period
        # free bodies get the body-frame residual; a scene of hinge and slide joints the joint-space one, which
        # also sees the controls of the last ctrl_history_s
        self.space: JointSpace | None = None
        if not free_joints(self.model):
            period_s = self.period * float(self.model.opt.timestep)
            self.space = joint_space(self.model, math.ceil(options.ctrl_history_s / period_s - 1e-9))
        self.bodies: list[FreeBody] = free_bodies(self.model) if self.space is None else []
        if self.space is not None and (options.smooth_window or options.dagger_rounds):
            raise GrounderError(
                "smoothing and aggregation rounds are for free bodies; train a jointed scene with smooth_window=0 "
                "and dagger_rounds=0 (--rounds 0)"
            )
        nq, nv = self.model.nq, self.model.nv
        # Recorded segments: per trajectory the runs of samples spaced exactly one period apart.
        self.qpos: list[np.ndarray] = []
        self.qvel: list[np.ndarray] = []
        self.ctrl: list[np.ndarray | None] = []
        for traj in trajs:
            steps = step_indices(traj.time_s, self.model.opt.timestep, traj.name)
            breaks = np.flatnonzero(np.diff(steps) != self.period) + 1
            for seg in np.split(np.arange(len(steps)), breaks):
                if len(seg) >= 2:
                    qpos, qvel = traj.qpos[seg].reshape(-1, nq), traj.qvel[seg].reshape(-1, nv)
                    if options.smooth_window:
                        qpos, qvel = smooth_free_bodies(
                            traj.time_s[seg], qpos, qvel, self.bodies, options.smooth_window
                        )
                    self.qpos.append(qpos)
                    self.qvel.append(qvel)
                    self.ctrl.append(None if traj.ctrl is None else traj.ctrl[seg])
        if not self.qpos:
            raise GrounderError("no two consecutive samples are one period apart; nothing to train on")

    def _controls(self, ctrl_rows: np.ndarray | None) -> np.ndarray | None:
        if not self.model.nu:
            return None
        held = np.zeros((0, self.model.nu)) if ctrl_rows is None else ctrl_rows
        return np.repeat(held[:, None, :], self.period, axis=1)

    def _one_period(self, qpos: np.ndarray, qvel: np.ndarray, ctrl: np.ndarray | None) -> tuple[np.ndarray, ...]:
        """MuJoCo only, one period from each state: (qpos, qvel) after it."""
        states = self.sim._states(qpos, qvel)
        nctrl = None
        if self.model.nu:
            nctrl = self._controls(np.zeros((len(qpos), self.model.nu)) if ctrl is None else ctrl)
        end = self.sim._physics(states, nctrl, self.period)[:, -1]
        qa, va = self.sim._qpos_at, self.sim._qvel_at
        return end[:, qa : qa + self.model.nq], end[:, va : va + self.model.nv]

    def one_step(self) -> _Transitions:
        q0 = np.concatenate([q[:-1] for q in self.qpos])
        v0 = np.concatenate([v[:-1] for v in self.qvel])
        q1 = np.concatenate([q[1:] for q in self.qpos])
        v1 = np.concatenate([v[1:] for v in self.qvel])
        ctrl = None
        if self.model.nu:
            ctrl = np.concatenate(
                [
                    np.zeros((len(q) - 1, self.model.nu)) if c is None else c[:-1]
                    for q, c in zip(self.qpos, self.ctrl, strict=True)
                ]
            )
        qs, vs = self._one_period(q0, v0, ctrl)
        groups = np.concatenate([np.full(len(q) - 1, i) for i, q in enumerate(self.qpos)])
        if self.space is not None:
            prev = None
            if self.space.history:  # the controls of the periods before each sample (the first one held)
                rows = [np.arange(len(q) - 1)[:, None] - np.arange(1, self.space.history + 1)[None] for q in self.qpos]
                nu = self.model.nu
                prev = np.concatenate(
                    [
                        np.zeros((*r.shape, nu)) if c is None else c[np.maximum(r, 0)]
                        for r, c in zip(rows, self.ctrl, strict=True)
                    ]
                )
            feats = joint_features(q0, v0, ctrl, self.space, prev)
            return _Transitions(feats=feats, targets=joint_targets(qs, vs, q1, v1, self.space), groups=groups)
        feats, rots = body_features(q0, v0, self.bodies)
        return _Transitions(feats=feats, targets=correction_targets(qs, vs, q1, v1, rots, self.bodies), groups=groups)

    def aggregate(self, residual: NumpyResidual) -> _Transitions:
        """Rolls the hybrid model out from every ``dagger_stride``-th recorded state; targets back to the recording."""
        opt = self.options
        starts = [(s, i) for s, q in enumerate(self.qpos) for i in range(0, len(q) - 1, opt.dagger_stride)]
        seg = np.array([s for s, _ in starts])
        idx = np.array([i for _, i in starts])
        qpos = np.stack([self.qpos[s][i] for s, i in starts])
        qvel = np.stack([self.qvel[s][i] for s, i in starts])
        lengths = np.array([len(self.qpos[s]) for s in seg])
        self.sim._set_residual(residual)
        feats_out, targets_out, groups_out = [], [], []
        max_rot = np.radians(opt.dagger_max_rot_error_deg)
        for k in range(opt.dagger_horizon):
            alive = idx + k + 1 < lengths
            if not alive.any():
                break
            seg, idx, qpos, qvel, lengths = seg[alive], idx[alive], qpos[alive], qvel[alive], lengths[alive]
            true_q = np.stack([self.qpos[s][i + k] for s, i in zip(seg, idx, strict=True)])
            true_v = np.stack([self.qvel[s][i + k] for s, i in zip(seg, idx, strict=True)])
            true_q1 = np.stack([self.qpos[s][i + k + 1] for s, i in zip(seg, idx, strict=True)])
            true_v1 = np.stack([self.qvel[s][i + k + 1] for s, i in zip(seg, idx, strict=True)])
            ctrl = None
            if self.model.nu:
                ctrl = np.stack(
                    [
                        np.zeros(self.model.nu) if self.ctrl[s] is None else self.ctrl[s][i + k]
                        for s, i in zip(seg, idx, strict=True)
                    ]
                )
            qs, vs = self._one_period(qpos, qvel, ctrl)
            feats, rots = body_features(qpos, qvel, self.bodies)
            if k > 0:  # k == 0 is the recorded state itself, already in the one-step data
                close = np.ones(len(qpos), dtype=bool)
                for body in self.bodies:
                    p = body.qpos_adr
                    close &= np.linalg.norm(qpos[:, p : p + 3] - true_q[:, p : p + 3], axis=1) <= (
                        opt.dagger_max_pos_error_m
                    )
                    close &= quat_angle_rad(qpos[:, p + 3 : p + 7], true_q[:, p + 3 : p + 7]) <= max_rot
                targets = correction_targets(qs, vs, true_q1, true_v1, rots, self.bodies)
                if opt.dagger_pull < 1.0:  # keep part of the drift: match the recorded increment instead
                    drift = correction_targets(qpos, qvel, true_q, true_v, rots, self.bodies)
                    targets = targets - (1.0 - opt.dagger_pull) * drift
                feats_out.append(feats[close])
                targets_out.append(targets[close])
                groups_out.append(seg[close])
            qpos, qvel = residual.correct(qpos, qvel, qs, vs)
        self.sim._set_residual(None)
        if not feats_out:
            return _Transitions(
                feats=np.zeros((0, len(self.bodies), residual.feat_mean.shape[1])),
                targets=np.zeros((0, len(self.bodies), NUM_OUTPUTS)),
                groups=np.zeros(0, dtype=np.int64),
            )
        return _Transitions(
            feats=np.concatenate(feats_out), targets=np.concatenate(targets_out), groups=np.concatenate(groups_out)
        )


def _kmeans(z: np.ndarray, k: int, seed: int) -> np.ndarray:
    from scipy.cluster.vq import kmeans2

    rng = np.random.default_rng(seed)
    sample = z[rng.choice(len(z), size=min(len(z), 20000), replace=False)]
    k_eff = min(k, len(sample))
    cent, _ = kmeans2(sample, k_eff, seed=np.random.default_rng(seed), minit="++", iter=20)
    if k_eff < k:  # pad by repeating a centre (the nearest distance is unchanged)
        cent = np.concatenate([cent, np.repeat(cent[:1], k - k_eff, axis=0)])
    return cent


def _nearest(z: np.ndarray, cent: np.ndarray) -> np.ndarray:
    d2 = np.sum(z * z, 1)[:, None] - 2 * z @ cent.T + np.sum(cent**2, 1)[None]
    return np.sqrt(np.maximum(d2.min(axis=1), 0.0))


def _coverage_stats(feats: np.ndarray, groups: np.ndarray, gate: GateOptions, seed: int) -> dict[str, np.ndarray]:
    """Normalisation and coverage statistics of training features (N, B, F), per body.

    The distance scale is calibrated on held-out trajectories: centres fitted on the even-numbered trajectories
    (``groups``), distances measured from the odd-numbered ones. A new recording of the same kind of motion is
    then inside the coverage about as often as ``coverage_quantile``, which distances of the training states to
    centres fitted on themselves would badly overstate in 11 dimensions.
    """
    num_b = feats.shape[1]
    mean = feats.mean(axis=0)
    std = feats.std(axis=0) + 1e-6
    lo = np.quantile(feats, 0.001, axis=0)
    hi = np.quantile(feats, 0.999, axis=0)
    centres = np.zeros((num_b, gate.coverage_centres, feats.shape[2]))
    dist = np.ones(num_b)
    fit_half = groups % 2 == 0
    for b in range(num_b):
        z = (feats[:, b] - mean[b]) / std[b]
        centres[b] = _kmeans(z, gate.coverage_centres, seed + b)
        if fit_half.any() and (~fit_half).any():
            nearest = _nearest(z[~fit_half], _kmeans(z[fit_half], gate.coverage_centres, seed + b))
        else:
            nearest = _nearest(z, centres[b])
        dist[b] = max(float(np.quantile(nearest, gate.coverage_quantile)), 1e-3)
    return {
        "feat_mean": mean,
        "feat_std": std,
        "range_lo": lo,
        "range_hi": hi,
        "centres": centres,
        "coverage_dist": dist,
    }


def _output_stats(targets: np.ndarray, quantile: float) -> dict[str, np.ndarray]:
    scale = targets.std(axis=0) + 1e-9
    bound = np.maximum(np.quantile(np.abs(targets), quantile, axis=0), scale)
    return {"out_scale": scale, "out_bound": bound}


def _fit(torch_model: Any, data: _Transitions, options: ResidualOptions, round_index: int) -> None:
    import torch

    # The gate does not depend on the weights: compute it once.
    feats = torch.as_tensor(data.feats)
    targets = torch.as_tensor(data.targets)
    with torch.no_grad():
        gate = torch_model.gate(feats).unsqueeze(-1)
    scale = torch_model.out_scale
    keep = gate.squeeze(-1).amax(dim=1) > 0  # samples with no active body teach nothing
    feats, targets, gate = feats[keep], targets[keep], gate[keep]
    generator = torch.Generator().manual_seed(options.seed * 1000 + round_index)
    optim = torch.optim.AdamW(
        torch_model.nets.parameters(), lr=options.learning_rate, weight_decay=options.weight_decay
    )
    num = len(feats)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(optim, T_max=options.steps, eta_min=0.05 * options.learning_rate)
    torch_model.train()
    order = torch.randperm(num, generator=generator)
    cursor = 0
    for _step in range(options.steps):
        if cursor + options.batch_size > num:
            order, cursor = torch.randperm(num, generator=generator), 0
        batch = order[cursor : cursor + options.batch_size]
        cursor += options.batch_size
        pred = torch_model.raw(feats[batch]) * gate[batch]
        loss = torch.nn.functional.huber_loss(pred / scale, targets[batch] * gate[batch] / scale, delta=1.0)
        optim.zero_grad()
        loss.backward()
        optim.step()
        sched.step()
    torch_model.eval()


def _numpy_residual(
    torch_model: Any, meta: ResidualMeta, trainer: _Trainer, spread_model: Any = None
) -> NumpyResidual | NumpyJointResidual:
    state = {k: v.detach().numpy().copy() for k, v in _state_dict(torch_model, spread_model).items()}
    if trainer.space is not None:
        return NumpyJointResidual(state, meta, trainer.space)
    return NumpyResidual(state, meta, trainer.bodies, trainer.model.opt.gravity)


def _state_dict(torch_model: Any, spread_model: Any) -> dict[str, Any]:
    """``residual.pt``'s tensors: the mean's, and the spread's under ``spread.`` when there is one."""
    from grounder.residual.spread import spread_state

    state = {k: v.detach().clone() for k, v in torch_model.state_dict().items()}
    return state if spread_model is None else {**state, **spread_state(spread_model)}


def _train_spread(
    torch_model: Any,
    meta: ResidualMeta,
    trainer: _Trainer,
    data: _Transitions,
    gain: float,
    scene: Path,
    trajs: Sequence[Trajectory],
    select_trajs: Sequence[Trajectory],
    options: ResidualOptions,
) -> tuple[Any, ResidualMeta, NumpyResidual | NumpyJointResidual, dict[str, Any]]:
    """The learned spread (``grounder.residual.spread``) around the mean at its chosen gain, and its gain chosen on
    sampled rollouts of the held-out trajectories: each start perturbed by the start noise, and the parameters drawn
    from the scene folder's ``distribution.json`` when it has one (as ``rollout --samples`` draws them)."""
    import torch

    from grounder.calibration.distribution import DISTRIBUTION_FILE, read_distribution
    from grounder.residual.spread import fit_spread, select_spread_gain
    from grounder.sim.start_noise import measure_start_noise

    spread_model = fit_spread(
        torch_model,
        data.feats,
        data.targets,
        gain,
        hidden=options.spread_hidden,
        steps=options.spread_steps,
        seed=options.seed,
    )
    meta = replace(meta, spread_hidden=options.spread_hidden)
    residual = _numpy_residual(torch_model, meta, trainer, spread_model)
    residual.out_gain[:] = gain
    scene_dir = scene if scene.is_dir() else scene.parent
    model = trainer.sim.model
    models = None
    if (scene_dir / DISTRIBUTION_FILE).is_file():
        dist = read_distribution(scene_dir / DISTRIBUTION_FILE, model.nv)
        models = dist.draw_models(model, options.spread_samples, np.random.default_rng(options.seed))
        noise = dist.start_noise
    else:
        noise = measure_start_noise(model, trajs)
    spread_gain, scores = select_spread_gain(
        trainer.sim,
        residual,
        select_trajs,
        options.spread_gains,
        samples=options.spread_samples,
        seed=options.seed,
        noise=noise,
        models=models,
    )
    with torch.no_grad():
        spread_model.gain.fill_(spread_gain)
    record = {
        "gain": spread_gain,
        "energy_score_by_gain": {str(g): v for g, v in scores.items()},
        "samples": options.spread_samples,
        "parameters_from": DISTRIBUTION_FILE if models is not None else "the scene's values",
    }
    log.info("held-out energy score per spread gain: %s", scores)
    return spread_model, meta, residual, record


def train_residual(
    scene: Path,
    trajs: Sequence[Trajectory],
    out: Path,
    options: ResidualOptions | None = None,
    *,
    overwrite: bool = False,
    progress: ProgressFn | None = None,
) -> ResidualTrainResult:
    """Trains a residual on recorded trajectories and writes a residual scene folder.

    Args:
        scene: A (calibrated) scene folder with ``scene.xml``, or an MJCF file; the scene's folder is copied.
        trajs: Recorded trajectories of the scene (the project's trajectory format).
        out: Output folder, created; it must be new or empty unless ``overwrite``.
        options: Training options.
        overwrite: Replace a non-empty ``out`` once the result is ready.
        progress: Called as ``progress(stage, done, total)``.

    Returns:
        Where it wrote and one-step errors before and after.

    Raises:
        GrounderError: bad scene, trajectories that do not fit it, or an output folder in the way.
    """
    import torch

    from grounder.residual.torch_model import residual_model

    options = options or ResidualOptions()
    started = time.perf_counter()
    out = Path(out)
    check_output_dir(out, overwrite=overwrite, error=GrounderError, inputs=(scene,))
    if not trajs:
        raise GrounderError("no trajectories to train on; pass a folder of .npz trajectories")
    scene_xml = scene_xml_path(Path(scene))
    check_links_stay_inside(Path(scene), (*RESIDUAL_FILES, SCENE_XML))  # before the training, not at the copy
    report = progress or (lambda _s, _d, _t: None)
    prev_threads = torch.get_num_threads()
    torch.set_num_threads(options.num_threads)
    try:
        torch.manual_seed(options.seed)
        trainer, fit_trajs, select_trajs = _trainer_and_split(scene_xml, trajs, options)
        report("residual: one-step targets", 0, 1)
        base = trainer.one_step()
        report("residual: one-step targets", 1, 1)
        meta = _untrained_meta(trainer, options, scene_xml)
        space = trainer.space
        torch_model = residual_model(meta, space=space, radius_m=np.array([b.radius_m for b in trainer.bodies]))
        data = _train_rounds(torch_model, meta, trainer, base, options, report)
        residual = _numpy_residual(torch_model, meta, trainer)
        before = _group_rms(base.targets, joint=space is not None)
        after = _group_rms(base.targets - residual(base.feats), joint=space is not None)  # gain 1, before choosing
        held_rms, held_gate = _held_out_one_step(trainer.sim, select_trajs, options, residual, joint=space is not None)
        report("residual: gain on held-out rollouts", 0, 1)
        gain, scores, preds_by_gain, errors_by_gain = _select_gain(trainer.sim, residual, select_trajs, options.gains)
        report("residual: gain on held-out rollouts", 1, 1)
        with torch.no_grad():
            torch_model.out_gain.fill_(gain)
        residual.out_gain[:] = gain
        if gain == 0.0:
            log.warning(
                "the residual did not improve multi-step rollouts of the held-out trajectories at any gain; "
                "it is saved with gain 0 (MuJoCo alone)"
            )
        spread_model, spread_record = None, None
        if options.spread and space is None and select_trajs:
            report("residual: spread", 0, 1)
            spread_model, meta, residual, spread_record = _train_spread(
                torch_model, meta, trainer, data, gain, Path(scene), trajs, select_trajs, options
            )
            report("residual: spread", 1, 1)
        seconds = time.perf_counter() - started
        meta = replace(
            meta,
            training=_training_record(
                trajs,
                fit_trajs,
                select_trajs,
                options,
                num_samples=len(data.feats),
                scores=scores,
                gain=gain,
                before=before,
                after=after,
                seconds=seconds,
                joint=space is not None,
            )
            | ({"spread": spread_record} if spread_record is not None else {}),
        )
        with staged_output_dir(out, overwrite=overwrite, error=GrounderError, inputs=(scene,)) as staging:
            _write_residual_files(staging, Path(scene), scene_xml, torch_model, meta, spread_model)
            write_residual_report(
                staging / REPORT_FILE,
                _residual_report(
                    trainer,
                    meta,
                    residual,
                    num_fit=len(fit_trajs),
                    held_out=select_trajs,
                    num_samples=len(data.feats),
                    seconds=seconds,
                    gain=gain,
                    preds_by_gain=preds_by_gain,
                    errors_by_gain=errors_by_gain,
                    before=before,
                    after=after,
                    held_rms=held_rms,
                    held_gate=held_gate,
                ),
            )
    finally:
        torch.set_num_threads(prev_threads)
    return ResidualTrainResult(
        out=out,
        gain=gain,
        gain_scores=scores,
        num_trajectories=len(trajs),
        num_samples=len(data.feats),
        one_step_rms_before=before,
        one_step_rms_after=after,
        seconds=seconds,
        space="free" if space is None else JOINT_SPACE,
    )


def _trainer_and_split(
    scene_xml: Path, trajs: Sequence[Trajectory], options: ResidualOptions
) -> tuple[_Trainer, list[Trajectory], list[Trajectory]]:
    """Loads the scene as MuJoCo alone, checks the trajectories against it and splits them into those the residual
    is fitted on and those its output gain is chosen on: ``(trainer of the fit ones, fit, gain selection)``."""
    sim = Simulator(scene_xml, use_residual=False)
    for traj in trajs:
        validate_against_model(traj, sim.model)
    fit_trajs, select_trajs = _selection_split(trajs, options, sim.model)
    if not select_trajs:
        log.warning(
            "no trajectory held out to check the residual's output gain (%d trajectories; it takes 5): the "
            "residual ships at gain 1 unchecked",
            len(trajs),
        )
    return _Trainer(sim, fit_trajs, options), fit_trajs, select_trajs


def _untrained_meta(trainer: _Trainer, options: ResidualOptions, scene_xml: Path) -> ResidualMeta:
    """The metadata of the residual about to be trained (no training summary yet): period, bodies or joints,
    network size, gate and the hashes of the scene's files."""
    meta = ResidualMeta(
        period_steps=trainer.period,
        timestep_s=float(trainer.model.opt.timestep),
        bodies=tuple(b.name for b in trainer.bodies),
        hidden=options.hidden,
        layers=options.layers,
        gate=options.gate,
        scene_xml_sha256=file_sha256(scene_xml),
        scene_files_sha256=scene_files_sha256(scene_xml),
        training={},
    )
    space = trainer.space
    if space is not None:
        meta = replace(
            meta,
            bodies=space.names,
            space=JOINT_SPACE,
            feature_names=space.feature_names,
            output_names=space.output_names,
        )
    return meta


def _train_rounds(
    torch_model: Any,
    meta: ResidualMeta,
    trainer: _Trainer,
    base: _Transitions,
    options: ResidualOptions,
    report: ProgressFn,
) -> _Transitions:
    """Fits ``torch_model`` in ``dagger_rounds + 1`` rounds: the one-step targets ``base``, then each round also the
    targets aggregated along rollouts of the previous round's residual; the statistics (normalisation, coverage,
    output bounds) are recomputed on each round's data first. Returns the last round's data."""
    import torch

    data = base
    rounds = options.dagger_rounds + 1
    for r in range(rounds):
        report("residual: training rounds", r, rounds)
        stats = _coverage_stats(data.feats, data.groups, options.gate, options.seed) | _output_stats(
            base.targets, options.bound_quantile
        )
        with torch.no_grad():
            for name, value in stats.items():
                getattr(torch_model, name).copy_(torch.as_tensor(value))
        _fit(torch_model, data, options, r)
        log.info("round %d: %d samples", r, len(data.feats))
        if r + 1 < rounds:
            free_residual = _numpy_residual(torch_model, meta, trainer)
            assert isinstance(free_residual, NumpyResidual)  # aggregation rounds are refused for joints
            extra = trainer.aggregate(free_residual)
            data = _Transitions(
                feats=np.concatenate([base.feats, extra.feats]),
                targets=np.concatenate([base.targets, extra.targets]),
                groups=np.concatenate([base.groups, extra.groups]),
            )
    report("residual: training rounds", rounds, rounds)
    return data


def _training_record(
    trajs: Sequence[Trajectory],
    fit_trajs: Sequence[Trajectory],
    select_trajs: Sequence[Trajectory],
    options: ResidualOptions,
    *,
    num_samples: int,
    scores: dict[float, float],
    gain: float,
    before: tuple[float, float, float, float],
    after: tuple[float, float, float, float],
    seconds: float,
    joint: bool,
) -> dict[str, Any]:
    """``residual.json``'s training summary: the data and its split, the gain chosen, one-step errors, options and
    versions, for provenance."""
    import torch

    rms_keys = ("pos_m", "rot_rad", "vel_m_s", "omega_rad_s") if not joint else ("joint_pos", "joint_vel")
    return {
        "num_trajectories": len(trajs),
        "trajectory_names": [t.name for t in trajs],
        "num_samples_last_round": num_samples,
        "fit_trajectories": [t.name for t in fit_trajs],
        "gain_selection_trajectories": [t.name for t in select_trajs],
        "gain_scores": {f"{g:g}": v for g, v in scores.items()},
        "selected_gain": gain,
        "one_step_rms_before": dict(zip(rms_keys, before if not joint else before[::2], strict=True)),
        "one_step_rms_after": dict(zip(rms_keys, after if not joint else after[::2], strict=True)),
        "options": _options_json(options),
        "seconds": seconds,
        "torch_version": torch.__version__,
        "mujoco_version": mujoco.__version__,
    }


def _write_residual_files(
    staging: Path, scene: Path, scene_xml: Path, torch_model: Any, meta: ResidualMeta, spread_model: Any = None
) -> None:
    """Writes the residual scene folder's files into ``staging``: the scene's files (without any old residual; the
    MJCF as ``scene.xml``), the weights, the metadata and the ONNX export."""
    import torch

    from grounder.residual.torch_model import export_onnx

    # the scene's files without any old residual; the MJCF as scene.xml
    copy_scene_files(scene, staging, skip=(*RESIDUAL_FILES, SCENE_XML))
    shutil.copy2(scene_xml, staging / SCENE_XML)
    torch.save(_state_dict(torch_model, spread_model), staging / WEIGHTS_FILE)
    (staging / META_FILE).write_text(json.dumps(meta.to_json(), indent=2) + "\n")
    export_onnx(torch_model, staging / ONNX_FILE)


def _residual_report(
    trainer: _Trainer,
    meta: ResidualMeta,
    residual: NumpyResidual | NumpyJointResidual,
    *,
    num_fit: int,
    held_out: list[Trajectory],
    num_samples: int,
    seconds: float,
    gain: float,
    preds_by_gain: dict[float, list[Trajectory]],
    errors_by_gain: dict[float, RolloutErrors],
    before: tuple[float, float, float, float],
    after: tuple[float, float, float, float],
    held_rms: tuple[tuple[float, ...], tuple[float, ...]],
    held_gate: np.ndarray,
) -> ResidualReport:
    """What the training's HTML report shows: the held-out rollouts per gain and the one-step errors per output
    group (on the fit and the held-out trajectories, MuJoCo alone and with the residual)."""
    space = trainer.space
    labels = ("joint position, rad or m", "joint velocity, rad/s or m/s") if space is not None else _FREE_RMS
    groups = (0, 2) if space is not None else (0, 1, 2, 3)
    return ResidualReport(
        model=trainer.model,
        space="free" if space is None else JOINT_SPACE,
        num_fit=num_fit,
        held_out=held_out,
        num_samples=num_samples,
        seconds=seconds,
        period_steps=trainer.period,
        gain=gain,
        preds_by_gain=preds_by_gain,
        errors_by_gain=errors_by_gain,
        one_step_rms=[
            (label, before[g], after[g], held_rms[0][g], held_rms[1][g])
            for label, g in zip(labels, groups, strict=True)
        ],
        output_names=meta.output_names if space is not None else OUTPUT_NAMES,
        output_bound=np.asarray(residual.out_bound),
        held_out_gate=held_gate,
    )


def _held_out_one_step(
    sim: Simulator,
    trajs: Sequence[Trajectory],
    options: ResidualOptions,
    residual: NumpyResidual | NumpyJointResidual,
    *,
    joint: bool,
) -> tuple[tuple[tuple[float, ...], tuple[float, ...]], np.ndarray]:
    """One-step RMS on the held-out trajectories (MuJoCo alone, with the residual at its present gain) and the gate
    at their recorded states; NaNs and an empty gate where there are none, or no two samples one period apart."""
    nan = (float("nan"),) * 4
    if not trajs:
        return (nan, nan), np.empty(0)
    try:
        held = _Trainer(sim, trajs, options).one_step()  # the same MuJoCo-only simulator, loaded once
    except GrounderError:
        return (nan, nan), np.empty(0)
    before = _group_rms(held.targets, joint=joint)
    after = _group_rms(held.targets - residual(held.feats), joint=joint)
    return (before, after), residual.gate(held.feats)


def _selection_split(
    trajs: Sequence[Trajectory], options: ResidualOptions, model: mujoco.MjModel
) -> tuple[list[Trajectory], list[Trajectory]]:
    """Seeded split of the trajectories (which fit ``model``) into (fit, gain selection); all fit when there are
    fewer than 5. Copies of one motion (`grounder.core.repeats`) stay on one side, and a warning names them."""
    count = round(options.selection_fraction * len(trajs))
    if len(trajs) < 5 or count < 1 or not options.gains:
        return list(trajs), []
    repeats = repeated_motion_indices(trajs, model)
    if repeats:
        named = describe_repeated_indices(trajs, repeats)
        log.warning("%s; each kept on one side of the fit / gain-check split", named)
    perm = np.random.default_rng(options.seed + 7919).permutation(len(trajs)).tolist()
    chosen_list, _ = split_keeping_together(perm, count, repeats)
    chosen = set(chosen_list)
    return [t for i, t in enumerate(trajs) if i not in chosen], [t for i, t in enumerate(trajs) if i in chosen]


def rollout_score(model: mujoco.MjModel, preds: Sequence[Trajectory], real: Sequence[Trajectory]) -> float:
    """Mean over trajectories and free bodies of time-averaged position error / body size + rotation error / 100 deg.

    Body size: twice the largest distance of a collision point from the body origin, scaled by 1/sqrt(3) (a
    cube's edge; for the cube tosses exactly the cube width). A scene without free bodies: the mean over
    trajectories and joints of the time-averaged joint error (rad for hinges, m for slides).
    """
    return float(np.mean(rollout_errors(model, preds, real).scores()))


def _select_gain(
    sim: Simulator, residual: NumpyResidual | NumpyJointResidual, trajs: Sequence[Trajectory], gains: Sequence[float]
) -> tuple[float, dict[float, float], dict[float, list[Trajectory]], dict[float, RolloutErrors]]:
    """The gain whose held-out rollouts score lowest (ties to the smaller); every gain's score, rollouts and errors."""
    if not trajs:
        return 1.0, {}, {}, {}
    preds: dict[float, list[Trajectory]] = {}
    errors: dict[float, RolloutErrors] = {}
    for gain in sorted(set(gains)):
        residual.out_gain[:] = gain
        sim._set_residual(residual)
        preds[gain] = sim.rollout(trajs)
        errors[gain] = rollout_errors(sim.model, preds[gain], trajs)
    sim._set_residual(None)
    scores = {gain: float(np.mean(e.scores())) for gain, e in errors.items()}  # as rollout_score
    best = min(scores, key=lambda g: (scores[g], g))
    log.info("held-out rollout score per gain: %s", scores)
    return best, scores, preds, errors


def _options_json(options: ResidualOptions) -> dict[str, Any]:
    from dataclasses import asdict

    return asdict(options)
