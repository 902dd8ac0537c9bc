"""MuJoCo plus the learned residual: one simulation or a batch. See ``grounder/residual/free_body.py`` for the residual.

A scene folder holds ``scene.xml``; a residual scene also holds ``residual.json``, ``residual.pt`` and
``residual.onnx`` (written by ``image2sim residual train``). :class:`Simulator` advances in periods of
``period_steps`` model steps (the data's sample interval the residual was trained at; 1 step without a residual):
MuJoCo steps, then the residual corrects each free body from the state at the start of the period.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

from grounder.core.trajectory import Trajectory
from grounder.errors import GrounderError
from grounder.residual.files import check_residual_pair, has_residual_files, load_residual
from grounder.residual.free_body import FreeBody, NumpyResidual
from grounder.residual.joint import NumpyJointResidual
from grounder.sim.rollout import (
    FULLPHYSICS,
    _offsets,
    check_stable,
    default_nthread,
    mujoco_warnings,
    prepare,
    simulate,
)
from grounder.sim.scene_files import load_scene_model

log = logging.getLogger(__name__)


def has_residual(scene_dir: Path) -> bool:
    """True when a scene folder holds a trained residual (``residual.json`` and ``residual.pt``)."""
    return has_residual_files(Path(scene_dir))


class Simulator:
    """Steps a scene's MuJoCo model plus its residual (when the folder has one and ``use_residual``).

    Args:
        scene: A scene folder with ``scene.xml`` (and optionally a residual), or an MJCF file.
        use_residual: Apply the residual when the folder has one. Without it, :meth:`rollout` is exactly
            :func:`grounder.sim.rollout.simulate`.
        nthread: Threads for batched stepping (default: the CPU cores this process may use).

    Attributes:
        model: The MuJoCo model.
        residual: The residual, or None.
        period_steps: Model steps per :meth:`step` (the residual's period; 1 without a residual file).
    """

    def __init__(self, scene: Path, *, use_residual: bool = True, nthread: int | None = None):
        xml, self.model = load_scene_model(Path(scene))
        self.nthread = nthread or default_nthread()
        scene_dir = xml.parent
        # The metadata (period_steps included) comes checked from load_residual. Without use_residual the residual
        # is never applied, so neither a scene.xml edited since training nor a broken or incomplete residual is a
        # reason to refuse: training a new residual on that scene is the way to bring them back in line.
        residual: NumpyResidual | NumpyJointResidual | None = None
        if use_residual:
            check_residual_pair(scene_dir)
            if has_residual(scene_dir):
                residual = load_residual(scene_dir, self.model, scene_xml=xml)
        elif has_residual(scene_dir):
            try:
                residual = load_residual(scene_dir, self.model, scene_xml=xml, check_scene_xml=False)
            except GrounderError as exc:
                log.warning("not using the residual in %s (%s)", scene_dir, exc)
        self.period_steps = residual.meta.period_steps if residual is not None else 1
        self.residual: NumpyResidual | NumpyJointResidual | None = residual if use_residual else None
        self._data = mujoco.MjData(self.model)
        self._datas: list[mujoco.MjData] = []
        template = mujoco.MjData(self.model)
        mujoco.mj_resetData(self.model, template)
        self._template = np.empty(mujoco.mj_stateSize(self.model, FULLPHYSICS))
        mujoco.mj_getState(self.model, template, self._template, FULLPHYSICS)
        self._qpos_at, self._qvel_at = _offsets(self.model)

    @property
    def bodies(self) -> list[FreeBody]:
        return [] if self.residual is None else self.residual.bodies

    @property
    def dt_s(self) -> float:
        """Seconds per :meth:`step`."""
        return self.period_steps * float(self.model.opt.timestep)

    def _set_residual(self, residual: NumpyResidual | NumpyJointResidual | None) -> None:
        """Swaps the residual (training evaluates candidates with it)."""
        if residual is not None:
            self.period_steps = residual.meta.period_steps
        self.residual = residual

    # --- one simulation ------------------------------------------------------------------------------------------

    def step(
        self,
        qpos: np.ndarray,
        qvel: np.ndarray,
        ctrl: np.ndarray | None = None,
        ctrl_prev: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Advances one state by one period (``period_steps`` model steps, then the residual).

        Args:
            qpos: (nq,) generalised positions.
            qvel: (nv,) generalised velocities.
            ctrl: (nu,) control held over the period, or None for zeros.
            ctrl_prev: (history, nu) the controls of the periods before, most recent first, for a joint-space
                residual that learnt from them (``residual.space.history``); None: ``ctrl`` was held throughout.

        Returns:
            The new ``(qpos (nq,), qvel (nv,))``.
        """
        m, d = self.model, self._data
        d.qpos[:] = qpos
        d.qvel[:] = qvel
        if m.nu:
            d.ctrl[:] = 0.0 if ctrl is None else ctrl
        residual = self.residual
        if residual is None:
            for _ in range(self.period_steps):
                mujoco.mj_step(m, d)
            return d.qpos.copy(), d.qvel.copy()
        q0, v0 = d.qpos.copy(), d.qvel.copy()
        for _ in range(self.period_steps):
            mujoco.mj_step(m, d)
        # the next call sets _data's state from its arguments, so _data keeps MuJoCo's own prediction (what carries
        # over, warm starts, is the same either way)
        qpos1, qvel1 = d.qpos.copy(), d.qvel.copy()
        if isinstance(residual, NumpyJointResidual):
            residual.correct_one(q0, v0, qpos1, qvel1, ctrl, ctrl_prev)
        else:
            residual.correct_one(q0, v0, qpos1, qvel1)
        return qpos1, qvel1

    # --- batches -------------------------------------------------------------------------------------------------

    def _states(self, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        states = np.tile(self._template, (qpos.shape[0], 1))
        states[:, self._qpos_at : self._qpos_at + self.model.nq] = qpos
        states[:, self._qvel_at : self._qvel_at + self.model.nv] = qvel
        return states

    def _physics(
        self,
        states: np.ndarray,
        controls: np.ndarray | None,
        nstep: int,
        models: Sequence[mujoco.MjModel] | None = None,
    ) -> np.ndarray:
        """MuJoCo only: (N, nstate) -> (N, nstep, nstate), batched over threads with `mujoco.rollout`; ``models``:
        one model per row (parameters drawn per sample), else the scene's."""
        count = min(self.nthread, len(states))
        while len(self._datas) < count:
            self._datas.append(mujoco.MjData(self.model))
        out, _ = mj_rollout.rollout(
            self.model if models is None else list(models),
            self._datas[:count],
            states,
            controls if self.model.nu else None,
            nstep=nstep,
        )
        return out

    def _correct(
        self,
        states0: np.ndarray,
        states1: np.ndarray,
        ctrl: np.ndarray | None = None,
        ctrl_prev: np.ndarray | None = None,
        rng: np.random.Generator | None = None,
    ) -> np.ndarray:
        """Applies the residual to states after one period; ``states0`` are the period's starting states,
        ``ctrl`` (N, nu) the controls held over it and ``ctrl_prev`` (N, history, nu) the earlier ones (the
        joint-space residual sees them); ``rng``: draw the correction from the learned spread."""
        residual = self.residual
        if residual is None:
            return states1
        nq, nv = self.model.nq, self.model.nv
        qa, va = self._qpos_at, self._qvel_at
        args = (states0[:, qa : qa + nq], states0[:, va : va + nv], states1[:, qa : qa + nq], states1[:, va : va + nv])
        if isinstance(residual, NumpyJointResidual):
            qpos, qvel = residual.correct(*args, ctrl, ctrl_prev)
        else:
            qpos, qvel = residual.correct(*args, rng=rng)
        out = states1.copy()
        out[:, qa : qa + nq] = qpos
        out[:, va : va + nv] = qvel
        return out

    def step_batch(
        self,
        qpos: np.ndarray,
        qvel: np.ndarray,
        ctrl: np.ndarray | None = None,
        ctrl_prev: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Advances N states by one period each (MuJoCo batched over threads, the residual vectorised).

        Args:
            qpos: (N, nq) generalised positions.
            qvel: (N, nv) generalised velocities.
            ctrl: (N, nu) controls held over the period, or None for zeros.
            ctrl_prev: (N, history, nu) the earlier periods' controls (see :meth:`step`).

        Returns:
            The new ``(qpos (N, nq), qvel (N, nv))``.
        """
        qpos, qvel = np.atleast_2d(np.asarray(qpos, np.float64)), np.atleast_2d(np.asarray(qvel, np.float64))
        if qpos.shape[1] != self.model.nq or qvel.shape[1] != self.model.nv or len(qpos) != len(qvel):
            raise GrounderError(
                f"{qpos.shape=} and {qvel.shape=} but expected (N, {self.model.nq}) and (N, {self.model.nv})"
            )
        controls = None
        if self.model.nu:
            held = np.zeros((len(qpos), self.model.nu)) if ctrl is None else np.asarray(ctrl, np.float64)
            controls = np.repeat(held[:, None, :], self.period_steps, axis=1)
        states0 = self._states(qpos, qvel)
        held_ctrl = None if controls is None else controls[:, 0]
        states1 = self._correct(
            states0, self._physics(states0, controls, self.period_steps)[:, -1], held_ctrl, ctrl_prev
        )
        nq, nv = self.model.nq, self.model.nv
        return (
            states1[:, self._qpos_at : self._qpos_at + nq].copy(),
            states1[:, self._qvel_at : self._qvel_at + nv].copy(),
        )

    def rollout(self, trajs: Sequence[Trajectory], *, stable: bool = False) -> list[Trajectory]:
        """Re-simulates each trajectory from its first state with its controls; predictions at the recorded times.

        The same contract as :func:`grounder.sim.rollout.simulate` (which it is, without a residual): every
        trajectory runs in one batch, period by period, and is read back at its recorded times rounded to model
        steps. ``stable``: raise when MuJoCo stops a rollout as unstable (`grounder.sim.rollout.check_stable`).
        """
        if self.residual is None:
            out = simulate(self.model, trajs, nthread=self.nthread, stable=stable)
            assert isinstance(out, list)
            return out  # type: ignore[return-value]
        with mujoco_warnings(stable) as warnings:
            states = self._rollout_states(trajs)
        if stable:
            check_stable(states, trajs, self.model, warnings)
        batch_steps = [s for s in prepare(self.model, trajs).sample_steps]
        nq, nv = self.model.nq, self.model.nv
        preds = []
        for b, traj in enumerate(trajs):
            rows = states[b, batch_steps[b]]
            preds.append(
                Trajectory(
                    time_s=traj.time_s.copy(),
                    qpos=rows[:, self._qpos_at : self._qpos_at + nq].copy(),
                    qvel=rows[:, self._qvel_at : self._qvel_at + nv].copy(),
                    ctrl=None if traj.ctrl is None else traj.ctrl.copy(),
                    name=traj.name,
                )
            )
        return preds

    def sample(
        self,
        trajs: Sequence[Trajectory],
        starts: Sequence[tuple[np.ndarray, np.ndarray]],
        rng: np.random.Generator,
        *,
        models: Sequence[mujoco.MjModel] | None = None,
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """K sampled rollouts per trajectory: sample k from ``starts[b][0][k], starts[b][1][k]``, with ``models[k]``
        (default: the scene's), corrections drawn from the residual's learned spread (none without one).

        Returns:
            Per trajectory, (qpos (K, T, nq), qvel (K, T, nv)) at its recorded times.
        """
        count = len(starts[0][0])
        if self.residual is None:  # MuJoCo alone: every model step in one batched call
            from grounder.sim.sampled import rollout_samples

            return rollout_samples(models or [self.model] * count, trajs, starts, nthread=self.nthread)
        rows = [t for t in trajs for _ in range(count)]
        batch = prepare(self.model, rows)
        states0 = np.concatenate([self._states(q, v) for q, v in starts])
        row_models = None if models is None else [m for _ in trajs for m in models]
        states = self._rollout_states(rows, states0=states0, models=row_models, rng=rng)
        nq, nv = self.model.nq, self.model.nv
        out = []
        for b in range(len(trajs)):
            picked = states[b * count : (b + 1) * count][:, batch.sample_steps[b * count]]
            out.append(
                (
                    picked[:, :, self._qpos_at : self._qpos_at + nq].copy(),
                    picked[:, :, self._qvel_at : self._qvel_at + nv].copy(),
                )
            )
        return out

    def _rollout_states(
        self,
        trajs: Sequence[Trajectory],
        *,
        states0: np.ndarray | None = None,
        models: Sequence[mujoco.MjModel] | None = None,
        rng: np.random.Generator | None = None,
    ) -> np.ndarray:
        """(B, nstep + 1, nstate) states of the hybrid rollout of each trajectory, row 0 the initial state
        (``states0`` instead of the recorded first states; ``models`` one per row; ``rng``: sampled corrections)."""
        batch = prepare(self.model, trajs)
        if states0 is not None:
            batch = replace(batch, states0=states0)
        period = self.period_steps
        num_periods = -(-batch.nstep // period)
        total = num_periods * period
        controls = None
        if self.model.nu:
            controls = np.concatenate(
                [batch.controls, np.repeat(batch.controls[:, -1:], total - batch.nstep, axis=1)], axis=1
            )
        out = np.empty((len(trajs), total + 1, batch.states0.shape[1]))
        out[:, 0] = batch.states0
        state = batch.states0
        history = self.residual.space.history if isinstance(self.residual, NumpyJointResidual) else 0
        for k in range(num_periods):
            ctrl = None if controls is None else controls[:, k * period : (k + 1) * period]
            prev = None
            if controls is not None and history:  # earlier periods' controls, the first one held before the start
                prev = np.stack([controls[:, max(k - j, 0) * period] for j in range(1, history + 1)], axis=1)
            block = self._physics(state, ctrl, period, models)
            block[:, -1] = self._correct(state, block[:, -1], None if ctrl is None else ctrl[:, 0], prev, rng)
            out[:, k * period + 1 : (k + 1) * period + 1] = block
            state = block[:, -1]
        return out[:, : batch.nstep + 1]
