"""The residual for articulated scenes: a bounded, gated correction of hinge and slide joints at the data rate.

Scenes whose moving parts hang on hinge and slide joints (a pendulum, an arm) have no free body for the
body-frame residual of ``grounder/residual/free_body.py``. Here one MLP sees the whole joint space and corrects it after
every period of ``period_steps`` model steps, like the free-body residual:

    q[t+1], qdot[t+1] = mujoco^P(q[t], qdot[t], u[t]) + gain * gate * bound * tanh(mlp(features) * scale / bound)

Features (in this order): per hinge joint sin q and cos q, per slide joint q (metres); every joint's velocity
(rad/s or m/s); every actuator's control over the period; then the controls of the ``history`` periods before
(most recent first; ``ResidualOptions.ctrl_history_s``, 50 ms by default), from which an actuator's delay or lag
can be learnt. Outputs: per joint a position correction (rad or m) then per joint a velocity correction.

Safety, as for free bodies: every output is capped at the ``bound`` quantile of the training corrections; the gate
is exactly 0 when every joint is slower than ``rest_speed_m_s[0]`` (read as rad/s, or m/s for slide joints), so a
mechanism at rest is never pushed; it fades to 0 outside the training ranges and k-means coverage; the output gain
is chosen on held-out multi-step rollouts (0: MuJoCo alone). There is no energy cap: a driven mechanism's energy
is not bounded by its start, and a passive one at rest is already held by the rest gate.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import mujoco
import numpy as np

from grounder.errors import GrounderError
from grounder.residual.meta import ResidualMeta, coverage_gate, fade_ranges, network_layers, smoothstep

JOINT_SPACE = "joint"


@dataclass(frozen=True, kw_only=True)
class JointSpace:
    """The hinge and slide joints a joint-space residual corrects, in joint order.

    Attributes:
        names: Joint names.
        qpos_adr: (J,) qpos address of each joint.
        dof_adr: (J,) qvel address of each joint.
        hinge: (J,) True for hinge joints (angles; features sin and cos), False for slide joints.
        nu: Number of actuators (controls are features).
        history: Periods of earlier controls that are features too (most recent first), so that an actuator's
            delay or lag can be learnt; ``ctrl_prev`` arguments carry them as (N, history, nu).
    """

    names: tuple[str, ...]
    qpos_adr: np.ndarray
    dof_adr: np.ndarray
    hinge: np.ndarray
    nu: int
    history: int = 0

    @property
    def num_joints(self) -> int:
        return len(self.names)

    @property
    def feature_names(self) -> tuple[str, ...]:
        out: list[str] = []
        for name, is_hinge in zip(self.names, self.hinge, strict=True):
            out += [f"sin_{name}", f"cos_{name}"] if is_hinge else [f"pos_{name}_m"]
        out += [f"vel_{n}" for n in self.names]
        out += [f"ctrl_{i}" for i in range(self.nu)]
        return (*out, *(f"ctrl_{i}_prev{k}" for k in range(1, self.history + 1) for i in range(self.nu)))

    @property
    def output_names(self) -> tuple[str, ...]:
        return (*(f"dpos_{n}" for n in self.names), *(f"dvel_{n}" for n in self.names))

    @property
    def speed_columns(self) -> list[int]:
        start = int(2 * self.hinge.sum() + (~self.hinge).sum())
        return list(range(start, start + self.num_joints))


def joint_space(model: mujoco.MjModel, history: int = 0) -> JointSpace:
    """The model's hinge and slide joints (``history``: periods of earlier controls as features, if it has actuators).

    Raises:
        GrounderError: the model has a free or ball joint (use the free-body residual), or no joint at all.
    """
    kinds = [int(t) for t in model.jnt_type]
    if any(k in (mujoco.mjtJoint.mjJNT_FREE, mujoco.mjtJoint.mjJNT_BALL) for k in kinds):
        raise GrounderError("the joint-space residual corrects hinge and slide joints only; this scene has others")
    if not kinds:
        raise GrounderError("the scene has no joint; there is nothing for a residual to correct")
    names = tuple(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}" for j in range(model.njnt))
    return JointSpace(
        names=names,
        qpos_adr=np.array(model.jnt_qposadr, dtype=np.int64),
        dof_adr=np.array(model.jnt_dofadr, dtype=np.int64),
        hinge=np.array([k == mujoco.mjtJoint.mjJNT_HINGE for k in kinds]),
        nu=int(model.nu),
        history=history if model.nu else 0,
    )


def history_of(feature_names: tuple[str, ...]) -> int:
    """The ``history`` of a joint space from its feature names (as stored in ``residual.json``)."""
    return sum(1 for name in feature_names if name.startswith("ctrl_0_prev"))


def joint_features(
    qpos: np.ndarray,
    qvel: np.ndarray,
    ctrl: np.ndarray | None,
    space: JointSpace,
    ctrl_prev: np.ndarray | None = None,
) -> np.ndarray:
    """(N, nq), (N, nv), (N, nu) or None, (N, history, nu) or None -> features (N, 1, F) in the order of
    ``space.feature_names``. Without ``ctrl_prev`` the earlier controls are taken as the present one (held)."""
    q = qpos[:, space.qpos_adr]
    cols: list[np.ndarray] = []
    for j, is_hinge in enumerate(space.hinge):
        cols += [np.sin(q[:, j]), np.cos(q[:, j])] if is_hinge else [q[:, j]]
    cols += [qvel[:, d] for d in space.dof_adr]
    if space.nu:
        held = np.zeros((len(qpos), space.nu)) if ctrl is None else np.asarray(ctrl, dtype=np.float64)
        cols += [held[:, i] for i in range(space.nu)]
        if space.history:
            prev = np.repeat(held[:, None], space.history, axis=1) if ctrl_prev is None else np.asarray(ctrl_prev)
            cols += [prev[:, k, i] for k in range(space.history) for i in range(space.nu)]
    return np.stack(cols, axis=1)[:, None, :]


def joint_error(qpos_a: np.ndarray, qpos_b: np.ndarray, space: JointSpace) -> np.ndarray:
    """(N, nq) x 2 -> (N, J) joint positions a - b, hinge angles wrapped to (-pi, pi] (a full turn is no error)."""
    diff = qpos_a[:, space.qpos_adr] - qpos_b[:, space.qpos_adr]
    diff[:, space.hinge] = np.angle(np.exp(1j * diff[:, space.hinge]))
    return diff


def joint_targets(
    qpos_sim: np.ndarray, qvel_sim: np.ndarray, qpos_true: np.ndarray, qvel_true: np.ndarray, space: JointSpace
) -> np.ndarray:
    """The correction (N, 1, 2J) that turns the simulated into the true joint states (angles wrapped to +-pi)."""
    dq = joint_error(qpos_true, qpos_sim, space)
    dv = qvel_true[:, space.dof_adr] - qvel_sim[:, space.dof_adr]
    return np.concatenate([dq, dv], axis=1)[:, None, :]


def apply_joint_correction(
    qpos: np.ndarray, qvel: np.ndarray, correction: np.ndarray, space: JointSpace
) -> tuple[np.ndarray, np.ndarray]:
    """Adds a correction (N, 1, 2J) to states after MuJoCo stepped; returns new (qpos, qvel), inputs untouched."""
    qpos, qvel = qpos.copy(), qvel.copy()
    j = space.num_joints
    qpos[:, space.qpos_adr] += correction[:, 0, :j]
    qvel[:, space.dof_adr] += correction[:, 0, j:]
    return qpos, qvel


class JointKernelArgs(NamedTuple):
    """The joint-space residual's constants for ``grounder.residual.kernel.correct_joints`` (J joints, other
    sizes as in ``grounder.residual.free_body.FreeKernelArgs``). Few arrays on purpose: numba's dispatch of a call with
    more than 15 arguments took twice as long here (3.5 against 1.7 us)."""

    joints: np.ndarray  # (J, 3) int64: qpos address, dof address, 1 for a hinge (features sin, cos) else 0
    consts: np.ndarray  # (3,): rest speed off, on - off; coverage distance
    out_gain: np.ndarray  # (1,) the residual's own out_gain (the same array: setting its values in place applies)
    ranges: np.ndarray  # (3, F)
    first: np.ndarray  # (F + 1, H + F)
    mids: np.ndarray  # (L, H + 1, H)
    last: np.ndarray  # (H + 2, 2 J): the output layer, then the bound
    centres: np.ndarray  # (F, K)
    ints: np.ndarray  # (2,) int64: periods of earlier controls among the features; the coverage hint (written)


class NumpyJointResidual:
    """The joint-space residual evaluated with numpy from a ``state_dict`` (same function as the torch model)."""

    def __init__(self, state: dict[str, np.ndarray], meta: ResidualMeta, space: JointSpace):
        self.meta = meta
        self.space = space
        self.bodies: list = []  # no free body (the Simulator's ``bodies``)
        self.feat_mean = state["feat_mean"]  # (1, F)
        self.feat_std = state["feat_std"]
        self.out_scale = state["out_scale"]  # (1, O)
        self.out_bound = state["out_bound"]
        # (1,); set it in place (``out_gain[:] = g``): the compiled single-state path reads this array
        self.out_gain = np.array(state["out_gain"], dtype=np.float64)
        self.range_lo = state["range_lo"]
        self.range_hi = state["range_hi"]
        self.centres = state["centres"]  # (1, K, F)
        self.coverage_dist = state["coverage_dist"]
        self.layers = [
            (np.ascontiguousarray(state[f"nets.0.{2 * i}.weight"].T), state[f"nets.0.{2 * i}.bias"])
            for i in range(meta.layers + 1)
        ]
        self._speed = np.array(space.speed_columns, dtype=np.int64)
        g = meta.gate
        first, mids, last = network_layers(
            self.layers, self.feat_mean[0], self.feat_std[0], self.out_scale[0], self.out_bound[0]
        )
        self.kernel_args = JointKernelArgs(
            joints=np.column_stack([space.qpos_adr, space.dof_adr, space.hinge]).astype(np.int64),
            consts=np.array(
                [
                    g.rest_speed_m_s[0],
                    g.rest_speed_m_s[1] - g.rest_speed_m_s[0],
                    self.coverage_dist[0],
                ],
                dtype=np.float64,
            ),
            out_gain=self.out_gain,
            ranges=fade_ranges(self.range_lo[0], self.range_hi[0], g.range_margin),
            first=first,
            mids=mids,
            last=last,
            centres=np.ascontiguousarray(self.centres[0].T, dtype=np.float64),
            ints=np.array([space.history, 0], dtype=np.int64),
        )
        self._no_ctrl, self._not_given = np.zeros(space.nu), np.zeros(0)
        self._kernel: Callable[..., None] | None = None

    def gate(self, feats: np.ndarray) -> np.ndarray:
        """(N, 1, F) -> (N, 1) in [0, 1]: moving x inside the training ranges x near the training states."""
        g = self.meta.gate
        speed = np.max(np.abs(feats[..., self._speed]), axis=-1)
        moving = smoothstep((speed - g.rest_speed_m_s[0]) / (g.rest_speed_m_s[1] - g.rest_speed_m_s[0]))
        return moving * coverage_gate(self, feats)

    def raw(self, feats: np.ndarray) -> np.ndarray:
        """(N, 1, F) -> (N, 1, O) bounded correction before the gate."""
        h = (feats[:, 0] - self.feat_mean[0]) / self.feat_std[0]
        for weight, bias in self.layers[:-1]:
            h = np.tanh(h @ weight + bias)
        u = h @ self.layers[-1][0] + self.layers[-1][1]
        return (self.out_bound[0] * np.tanh(u * self.out_scale[0] / self.out_bound[0]))[:, None, :]

    def __call__(self, feats: np.ndarray) -> np.ndarray:
        return self.raw(feats) * (self.gate(feats) * self.out_gain)[..., None]

    def correct_one(
        self,
        qpos0: np.ndarray,
        qvel0: np.ndarray,
        qpos: np.ndarray,
        qvel: np.ndarray,
        ctrl: np.ndarray | None,
        ctrl_prev: np.ndarray | None = None,
    ) -> None:
        """:meth:`correct` for one state ((nq,), (nv,), (nu,) or None: zeros; ``ctrl_prev`` (history, nu) or None:
        ``ctrl`` held), in place on ``qpos``/``qvel``, compiled (``grounder.residual.kernel.correct_joints``: a
        small arm steps in microseconds); it stops as soon as the gate is 0, so a still mechanism costs a test."""
        space = self.space
        held = self._no_ctrl if ctrl is None or not space.nu else np.asarray(ctrl, dtype=np.float64)
        if ctrl_prev is None or not space.history:
            prev = self._not_given  # the kernel holds ``held`` through the history
        else:
            prev = np.ascontiguousarray(ctrl_prev, dtype=np.float64).ravel()
        kernel = self._kernel
        if kernel is None:  # numba: imported on first use (and compiled on the first use on a machine)
            from grounder.residual.kernel import correct_joints

            kernel = self._kernel = correct_joints
        kernel(qpos0, qvel0, qpos, qvel, held, prev, *self.kernel_args)

    def correct(
        self,
        qpos0: np.ndarray,
        qvel0: np.ndarray,
        qpos_sim: np.ndarray,
        qvel_sim: np.ndarray,
        ctrl: np.ndarray | None = None,
        ctrl_prev: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """States after one period: MuJoCo's ``(qpos_sim, qvel_sim)`` from ``(qpos0, qvel0)`` under ``ctrl``,
        corrected. All (N, nq) / (N, nv) / (N, nu); ``ctrl_prev`` (N, history, nu) the earlier controls."""
        feats = joint_features(qpos0, qvel0, ctrl, self.space, ctrl_prev)
        return apply_joint_correction(qpos_sim, qvel_sim, self(feats), self.space)


def check_joint_meta(meta: ResidualMeta, space: JointSpace, where: str) -> None:
    """Raises GrounderError when a joint-space residual was trained on other joints or actuators."""
    if tuple(meta.bodies) != space.names or tuple(meta.feature_names) != space.feature_names:
        raise GrounderError(
            f"{where}: the residual corrects joints {list(meta.bodies)} with features {list(meta.feature_names)}, "
            f"but the scene has {list(space.names)} and {list(space.feature_names)}; retrain it on this scene"
        )
