"""Learned residual dynamics on top of MuJoCo for free bodies: features, the bounded and gated correction.

This module is the residual of free bodies; scenes of hinge and slide joints only get the joint-space residual of
``grounder/residual/joint.py`` (same files, ``"space": "joint"`` in ``residual.json``).

What the residual is. Every ``period_steps`` model steps (one sample interval of the training data, 1/148 s for the
cube tosses) each free body's state is corrected after MuJoCo has stepped:

    x[t+1] = cap(mujoco^P(x[t]) (+) gain * gate(x[t]) * bound * tanh(mlp(features(x[t])) * scale / bound))

The correction has 12 components per body, expressed in the body frame of ``x[t]`` so that the model is invariant
to where on the plane and which way round a toss happens: position (3, metres), rotation vector (3, radians,
applied on the left in the world frame), linear velocity (3, m/s), angular velocity (3, rad/s, body frame like the
free joint's qvel). Features (11 per body, also body-frame): clearance of the lowest collision point above the
z = 0 support plane, height of the body origin, the world "up" axis in the body frame, the linear velocity in the
body frame and the body angular velocity.

Safety, by construction:

- ``bound * tanh(...)`` caps every component at the ``bound`` quantile of what training needed;
- the gate is exactly 0 for a body that is slow (speed of its fastest point below ``rest_speed_m_s[0]``) *and*
  near the support (clearance below ``air_clearance_m[0]``): an object at rest gets no correction at all, so it
  stays exactly where MuJoCo keeps it;
- the gate fades smoothly to 0 outside the states seen in training: per-feature ranges (0.1-99.9 percentiles,
  fading over a margin of 10% of the range) times a distance-to-training-states check (distance in standardised
  feature space to the nearest of K k-means centres of the training states, fading from the training distances'
  99th percentile to twice that; the scale is measured on trajectories held out of the centres' fit);
- an energy cap (``cap_energy``): after the correction a free body's kinetic plus potential energy may not exceed
  its energy at the start of the period, nor MuJoCo's prediction by more than half of what MuJoCo dissipated in
  it, so the residual cannot sustain motion that friction stops;
- an output gain chosen by multi-step rollouts of held-out trajectories (``grounder.residual.train``): a residual
  that does not improve rollouts gets gain 0, i.e. exactly MuJoCo.

The files a residual is stored in are read and checked by ``grounder.residual.files``; its metadata and the
parts of the gate it shares with the joint-space residual are in ``grounder.residual.meta``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import mujoco
import numpy as np

from grounder.errors import GrounderError
from grounder.residual.meta import (
    NUM_FEATURES,
    NUM_OUTPUTS,
    ResidualMeta,
    coverage_gate,
    fade_ranges,
    network_layers,
    smoothstep,
)
from image2sim_common.rotations import quat_conj, quat_mul, quat_to_mat, quat_to_rotvec, rotvec_to_quat

# --- the bodies the residual corrects --------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class FreeBody:
    """A free-joint body the residual corrects.

    Attributes:
        name: Body name in the model.
        qpos_adr: Where its qpos (position 3, quaternion w-first 4) starts.
        dof_adr: Where its qvel (world linear velocity 3, body angular velocity 3) starts.
        points_body_m: (V, 3) collision points in the body frame (box corners, mesh vertices, or the corners of
            the geom's bounding box for other shapes), for the clearance feature.
        radius_m: Largest distance of a collision point from the body origin (speed of the fastest point).
        mass_kg: Mass of the body (with its subtree), for the energy cap.
        inertia_body: (3, 3) rotational inertia about the body origin in the body frame (kg m^2), for the
            energy cap (the free joint's angular velocity is in the body frame; the centre of mass is assumed at
            the origin, as the data's positions are the body centre's).
    """

    name: str
    qpos_adr: int
    dof_adr: int
    points_body_m: np.ndarray
    radius_m: float
    mass_kg: float
    inertia_body: np.ndarray


_BOX_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)


def _geom_points_body(model: mujoco.MjModel, geom_id: int) -> np.ndarray:
    """Points on (or bounding) one collision geom, in its body's frame."""
    if model.geom_type[geom_id] == mujoco.mjtGeom.mjGEOM_MESH:
        mesh_id = int(model.geom_dataid[geom_id])
        start, count = int(model.mesh_vertadr[mesh_id]), int(model.mesh_vertnum[mesh_id])
        local = np.asarray(model.mesh_vert[start : start + count], dtype=np.float64)
    else:
        aabb = np.asarray(model.geom_aabb[geom_id], dtype=np.float64)  # centre (3), half-size (3) in the geom frame
        local = aabb[:3] + _BOX_CORNERS * aabb[3:]
    rot = np.asarray(model.geom_quat[geom_id], dtype=np.float64)
    return local @ quat_to_mat(rot).T + np.asarray(model.geom_pos[geom_id], dtype=np.float64)


def free_bodies(model: mujoco.MjModel) -> list[FreeBody]:
    """The model's free-joint bodies with their collision points, in joint order.

    Raises:
        GrounderError: the model has no free joint, or a free body has no collision geom.
    """
    out = []
    for joint in range(model.njnt):
        if model.jnt_type[joint] != mujoco.mjtJoint.mjJNT_FREE:
            continue
        body = int(model.jnt_bodyid[joint])
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body) or f"body{body}"
        geoms = [
            g
            for g in range(model.ngeom)
            if model.geom_bodyid[g] == body and (model.geom_contype[g] or model.geom_conaffinity[g])
        ]
        if not geoms:
            raise GrounderError(f"free body '{name}' has no collision geom; the residual needs its shape for contact")
        points = np.concatenate([_geom_points_body(model, g) for g in geoms])
        if len(points) > 256:  # only extreme points matter for the lowest one; a hull keeps them
            from scipy.spatial import ConvexHull

            points = points[ConvexHull(points).vertices]
        principal = quat_to_mat(np.asarray(model.body_iquat[body], dtype=np.float64))
        out.append(
            FreeBody(
                name=name,
                qpos_adr=int(model.jnt_qposadr[joint]),
                dof_adr=int(model.jnt_dofadr[joint]),
                points_body_m=points,
                radius_m=float(np.max(np.linalg.norm(points, axis=1))),
                mass_kg=float(model.body_subtreemass[body]),
                inertia_body=principal @ np.diag(model.body_inertia[body]) @ principal.T,
            )
        )
    if not out:
        raise GrounderError("the scene has no free-joint body; the residual corrects free bodies only")
    return out


# --- features, corrections, training targets -------------------------------------------------------------------


def body_features(qpos: np.ndarray, qvel: np.ndarray, bodies: list[FreeBody]) -> tuple[np.ndarray, np.ndarray]:
    """Features of each free body and its orientation.

    Args:
        qpos: (N, nq) generalised positions.
        qvel: (N, nv) generalised velocities.
        bodies: The bodies, from :func:`free_bodies`.

    Returns:
        ``features`` (N, B, 11) in the order of ``FEATURE_NAMES`` and ``world_from_body`` (N, B, 3, 3).
    """
    n = qpos.shape[0]
    feats = np.empty((n, len(bodies), NUM_FEATURES))
    rots = np.empty((n, len(bodies), 3, 3))
    for b, body in enumerate(bodies):
        pos = qpos[:, body.qpos_adr : body.qpos_adr + 3]
        rot = quat_to_mat(qpos[:, body.qpos_adr + 3 : body.qpos_adr + 7])
        up_body = rot[:, 2, :]  # R^T e_z: the world's up axis seen from the body
        feats[:, b, 0] = pos[:, 2] + np.min(up_body @ body.points_body_m.T, axis=1)
        feats[:, b, 1] = pos[:, 2]
        feats[:, b, 2:5] = up_body
        feats[:, b, 5:8] = np.einsum("nji,nj->ni", rot, qvel[:, body.dof_adr : body.dof_adr + 3])
        feats[:, b, 8:11] = qvel[:, body.dof_adr + 3 : body.dof_adr + 6]
        rots[:, b] = rot
    return feats, rots


def apply_correction(
    qpos: np.ndarray, qvel: np.ndarray, correction: np.ndarray, world_from_body: np.ndarray, bodies: list[FreeBody]
) -> tuple[np.ndarray, np.ndarray]:
    """Adds a correction (N, B, 12) to states after MuJoCo stepped; returns new (qpos, qvel), inputs untouched.

    ``world_from_body`` (N, B, 3, 3) is the orientation at the *start* of the period, the frame the correction is
    expressed in.
    """
    qpos, qvel = qpos.copy(), qvel.copy()
    for b, body in enumerate(bodies):
        rot = world_from_body[:, b]
        corr = correction[:, b]
        p, d = body.qpos_adr, body.dof_adr
        qpos[:, p : p + 3] += np.einsum("nij,nj->ni", rot, corr[:, 0:3])
        dquat = rotvec_to_quat(np.einsum("nij,nj->ni", rot, corr[:, 3:6]))
        quat = quat_mul(dquat, qpos[:, p + 3 : p + 7])
        qpos[:, p + 3 : p + 7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
        qvel[:, d : d + 3] += np.einsum("nij,nj->ni", rot, corr[:, 6:9])
        qvel[:, d + 3 : d + 6] += corr[:, 9:12]
    return qpos, qvel


def body_energy(qpos: np.ndarray, qvel: np.ndarray, body: FreeBody, gravity: np.ndarray) -> np.ndarray:
    """(N,) kinetic plus gravitational potential energy of one free body, joules."""
    p, d = body.qpos_adr, body.dof_adr
    v, omega = qvel[:, d : d + 3], qvel[:, d + 3 : d + 6]
    kinetic = 0.5 * body.mass_kg * np.sum(v * v, axis=1) + 0.5 * np.einsum(
        "ni,ij,nj->n", omega, body.inertia_body, omega
    )
    return kinetic - body.mass_kg * qpos[:, p : p + 3] @ gravity


def cap_energy(
    energy_start: list[np.ndarray],
    energy_sim: list[np.ndarray],
    qpos: np.ndarray,
    qvel: np.ndarray,
    bodies: list[FreeBody],
    gravity: np.ndarray,
    restore_fraction: float,
) -> np.ndarray:
    """Scales corrected free-body velocities (in place) so that the residual cannot create energy.

    Per body the energy after the correction is capped at ``max(E_sim, min(E_start, E_sim + restore_fraction *
    (E_start - E_sim)))``: never above the energy at the start of the period (unless MuJoCo itself went above it),
    and restoring at most that fraction of what MuJoCo dissipated during it. A passive object therefore keeps
    losing energy whenever MuJoCo says it does, and a learned correction cannot sustain motion that friction would
    stop (a tracker's velocity noise at rest would otherwise teach the residual to cancel friction at low speed).
    Returns ``qvel``.
    """
    for b, body in enumerate(bodies):
        start, sim = energy_start[b], energy_sim[b]
        # never below MuJoCo's own energy: the cap limits what the residual adds, not what MuJoCo does
        cap = np.maximum(sim, np.minimum(start, sim + restore_fraction * np.maximum(start - sim, 0.0)))
        energy = body_energy(qpos, qvel, body, gravity)
        over = energy > cap + 1e-12
        if not over.any():
            continue
        d = body.dof_adr
        potential = body_energy(qpos, np.zeros_like(qvel), body, gravity)
        kinetic = energy - potential
        allowed = np.clip(cap - potential, 0.0, None)
        scale = np.sqrt(np.where(over, allowed / np.maximum(kinetic, 1e-300), 1.0))
        qvel[:, d : d + 6] *= np.minimum(scale, 1.0)[:, None]
    return qvel


def correction_targets(
    qpos_sim: np.ndarray,
    qvel_sim: np.ndarray,
    qpos_true: np.ndarray,
    qvel_true: np.ndarray,
    world_from_body: np.ndarray,
    bodies: list[FreeBody],
) -> np.ndarray:
    """The correction (N, B, 12) that :func:`apply_correction` needs to turn the simulated into the true states."""
    out = np.empty((qpos_sim.shape[0], len(bodies), NUM_OUTPUTS))
    for b, body in enumerate(bodies):
        rot_t = np.swapaxes(world_from_body[:, b], 1, 2)
        p, d = body.qpos_adr, body.dof_adr
        out[:, b, 0:3] = np.einsum("nij,nj->ni", rot_t, qpos_true[:, p : p + 3] - qpos_sim[:, p : p + 3])
        dquat = quat_mul(qpos_true[:, p + 3 : p + 7], quat_conj(qpos_sim[:, p + 3 : p + 7]))
        out[:, b, 3:6] = np.einsum("nij,nj->ni", rot_t, quat_to_rotvec(dquat))
        out[:, b, 6:9] = np.einsum("nij,nj->ni", rot_t, qvel_true[:, d : d + 3] - qvel_sim[:, d : d + 3])
        out[:, b, 9:12] = qvel_true[:, d + 3 : d + 6] - qvel_sim[:, d + 3 : d + 6]
    return out


# --- numpy evaluation ----------------------------------------------------------------------------------------


class FreeKernelArgs(NamedTuple):
    """The residual's constants for ``grounder.residual.kernel.correct_free_bodies``, packed once per residual
    (B bodies, F = 11 features, H hidden units, L hidden-to-hidden layers, K coverage centres, P collision points
    at most)."""

    body_i: np.ndarray  # (B, 3) int64: qpos address, dof address, number of collision points
    body_f: np.ndarray  # (B, 13): radius (m), coverage distance, mass / 2, mass (kg), inertia / 2 (9, kg m^2)
    out_gain: np.ndarray  # (B,) the residual's own out_gain (the same array: setting its values in place applies)
    ranges: np.ndarray  # (B, 3, F): feature range low, high, 1 / fade margin
    points: np.ndarray  # (B, P, 3) collision points in the body frame, m
    first: np.ndarray  # (B, F + 1, H + F): [f, 1] @ first -> first layer's pre-activations, standardised features
    mids: np.ndarray  # (B, L, H + 1, H): hidden layers, [a, 1] @ mids[b, l] (weights, then the bias as a row)
    last: np.ndarray  # (B, H + 2, 12): output layer, [a, 1] @ last[b, :-1] (times scale / bound); the bound last
    centres: np.ndarray  # (B, F, K) coverage centres, standardised (one column per centre)
    consts: np.ndarray  # (8,): rest speed off, on - off; clearance off, on - off; energy restore fraction; gravity
    hints: np.ndarray  # (B,) int64, written by the kernel: per body the coverage centre nearest to the last state


class NumpyResidual:
    """The residual evaluated with numpy from a ``state_dict``: features (N, B, 11) -> gated correction (N, B, 12).

    Same function as the torch model (``grounder.residual.torch_model.ResidualModel``) and its ONNX export; numpy
    because a single simulation's step is a few microseconds of MuJoCo, where torch's per-call overhead (tens of
    microseconds) would dominate. Batches go through :meth:`correct` (vectorised); one state at a time, what
    ``grounder.Simulator.step`` does, through :meth:`correct_one`, compiled (``grounder.residual.kernel``), since
    numpy's per-call overhead on so few numbers would dominate there in turn.
    """

    def __init__(self, state: dict[str, np.ndarray], meta: ResidualMeta, bodies: list[FreeBody], gravity: np.ndarray):
        self.meta = meta
        self.bodies = bodies
        self.gravity = np.asarray(gravity, dtype=np.float64).copy()
        num_b = len(bodies)
        self.feat_mean = state["feat_mean"]  # (B, F)
        self.feat_std = state["feat_std"]
        self.out_scale = state["out_scale"]  # (B, 12)
        self.out_bound = state["out_bound"]
        # (B,), chosen on held-out rollouts; set it in place (``out_gain[:] = g``): the compiled path reads this array
        self.out_gain = np.array(state["out_gain"], dtype=np.float64)
        self.range_lo = state["range_lo"]  # (B, F)
        self.range_hi = state["range_hi"]
        self.centres = state["centres"]  # (B, K, F), standardised
        self.coverage_dist = state["coverage_dist"]  # (B,)
        self.radius_m = np.array([b.radius_m for b in bodies])
        self.layers: list[list[tuple[np.ndarray, np.ndarray]]] = []
        for b in range(num_b):
            layers = []
            for i in range(meta.layers + 1):
                weight = state[f"nets.{b}.{2 * i}.weight"]
                layers.append((np.ascontiguousarray(weight.T), state[f"nets.{b}.{2 * i}.bias"]))
            self.layers.append(layers)
        self.kernel_args = self._kernel_args()
        self._kernel: Callable[..., None] | None = None
        from grounder.residual.spread import NumpySpread

        # the learned spread (grounder.residual.spread), used only by sampled steps (`correct` with an rng)
        self.spread = NumpySpread(state, num_b) if meta.spread_hidden else None

    def _kernel_args(self) -> FreeKernelArgs:
        """The constants of :func:`grounder.residual.kernel.correct_free_bodies` (see :meth:`correct_one`)."""
        num_b = len(self.bodies)
        most_points = max(len(b.points_body_m) for b in self.bodies)
        body_i = np.zeros((num_b, 3), dtype=np.int64)
        body_f = np.zeros((num_b, 13))
        points = np.zeros((num_b, most_points, 3))
        networks = []
        for b, (body, layers) in enumerate(zip(self.bodies, self.layers, strict=True)):
            body_i[b] = body.qpos_adr, body.dof_adr, len(body.points_body_m)
            body_f[b, :4] = body.radius_m, self.coverage_dist[b], 0.5 * body.mass_kg, body.mass_kg
            body_f[b, 4:] = 0.5 * body.inertia_body.ravel()
            points[b, : len(body.points_body_m)] = body.points_body_m
            networks.append(
                network_layers(layers, self.feat_mean[b], self.feat_std[b], self.out_scale[b], self.out_bound[b])
            )
        first, mids, last = (np.ascontiguousarray(np.stack(m)) for m in zip(*networks, strict=True))
        g = self.meta.gate
        return FreeKernelArgs(
            body_i=body_i,
            body_f=body_f,
            out_gain=self.out_gain,
            ranges=fade_ranges(self.range_lo, self.range_hi, g.range_margin),
            points=points,
            first=first,
            mids=mids,
            last=last,
            centres=np.ascontiguousarray(np.swapaxes(self.centres, 1, 2), dtype=np.float64),
            consts=np.array(
                [
                    g.rest_speed_m_s[0],
                    g.rest_speed_m_s[1] - g.rest_speed_m_s[0],
                    g.air_clearance_m[0],
                    g.air_clearance_m[1] - g.air_clearance_m[0],
                    g.energy_restore_fraction,
                    *self.gravity.tolist(),
                ]
            ),
            hints=np.zeros(num_b, dtype=np.int64),
        )

    def gate(self, feats: np.ndarray) -> np.ndarray:
        """(N, B, F) raw features -> (N, B) gate in [0, 1] (the output gain not included)."""
        g = self.meta.gate
        speed = np.linalg.norm(feats[..., 5:8], axis=-1) + self.radius_m * np.linalg.norm(feats[..., 8:11], axis=-1)
        moving = smoothstep((speed - g.rest_speed_m_s[0]) / (g.rest_speed_m_s[1] - g.rest_speed_m_s[0]))
        flying = smoothstep((feats[..., 0] - g.air_clearance_m[0]) / (g.air_clearance_m[1] - g.air_clearance_m[0]))
        active = 1.0 - (1.0 - moving) * (1.0 - flying)
        return active * coverage_gate(self, feats)

    def raw(self, feats: np.ndarray) -> np.ndarray:
        """(N, B, F) -> (N, B, 12) bounded correction before the gate."""
        out = np.empty((*feats.shape[:2], NUM_OUTPUTS))
        z = (feats - self.feat_mean) / self.feat_std
        for b, layers in enumerate(self.layers):
            h = z[:, b]
            for weight, bias in layers[:-1]:
                h = np.tanh(h @ weight + bias)
            u = h @ layers[-1][0] + layers[-1][1]
            out[:, b] = self.out_bound[b] * np.tanh(u * self.out_scale[b] / self.out_bound[b])
        return out

    def __call__(self, feats: np.ndarray) -> np.ndarray:
        gate = self.gate(feats) * self.out_gain
        return self.raw(feats) * gate[..., None]

    def correct_one(self, qpos0: np.ndarray, qvel0: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """:meth:`correct` for one state, compiled (``grounder.residual.kernel``): ``qpos``/``qvel`` (MuJoCo's
        prediction after one period from ``qpos0`` (nq,), ``qvel0`` (nv,); all float64 arrays) are corrected in
        place.

        The same function as :meth:`correct` up to rounding (the tests check it), except that where the gate is
        exactly 0 the state is left exactly as MuJoCo made it (:meth:`correct` still renormalises the quaternion,
        a change of about 1e-16).
        """
        kernel = self._kernel
        if kernel is None:  # numba: imported on first use (and compiled on the first use on a machine)
            from grounder.residual.kernel import correct_free_bodies

            kernel = self._kernel = correct_free_bodies
        kernel(qpos0, qvel0, qpos, qvel, *self.kernel_args)

    def correct(
        self,
        qpos0: np.ndarray,
        qvel0: np.ndarray,
        qpos_sim: np.ndarray,
        qvel_sim: np.ndarray,
        rng: np.random.Generator | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """States after one period: MuJoCo's ``(qpos_sim, qvel_sim)`` from ``(qpos0, qvel0)``, corrected.

        All (N, nq) / (N, nv). Applies the gated correction of the starting state, then the energy cap. With
        ``rng`` and a learned spread, a draw of the spread (its standard deviations times standard normals) is then
        added the same way.
        """
        feats, rots = body_features(qpos0, qvel0, self.bodies)
        gate = self.gate(feats)
        correction = self.raw(feats) * (gate * self.out_gain)[..., None]  # self(feats), keeping the gate for below
        qpos, qvel = apply_correction(qpos_sim, qvel_sim, correction, rots, self.bodies)
        fraction = self.meta.gate.energy_restore_fraction
        start = [body_energy(qpos0, qvel0, b, self.gravity) for b in self.bodies]
        sim = [body_energy(qpos_sim, qvel_sim, b, self.gravity) for b in self.bodies]
        cap_energy(start, sim, qpos, qvel, self.bodies, self.gravity, fraction)
        if rng is not None and self.spread is not None:
            # the drawn part after the cap: the cap keeps the mean from adding energy, and applied to zero-mean
            # draws it would only ever take energy away (a bias, not a spread)
            z = (feats - self.feat_mean) / self.feat_std
            sd = self.spread.std(z, gate)
            if np.any(sd > 0.0):
                qpos, qvel = apply_correction(qpos, qvel, sd * rng.normal(size=sd.shape), rots, self.bodies)
        return qpos, qvel


# --- smoothing the recorded motion ---------------------------------------------------------------------------


def smooth_free_bodies(
    time_s: np.ndarray, qpos: np.ndarray, qvel: np.ndarray, bodies: list[FreeBody], window: int
) -> tuple[np.ndarray, np.ndarray]:
    """Free-body poses smoothed and velocities re-estimated from them, ``(qpos (T, nq), qvel (T, nv))``.

    Trackers record noisy poses and velocities as filtered backward differences of them (late by about half a
    frame). Fed to the residual as inputs, that noise teaches it to pull every velocity towards the average
    (regression dilution): damping that does not exist. So training uses a Savitzky-Golay fit (quadratic, over
    ``window`` samples, which must be odd; <= 2 keeps the poses) of the positions and of the sign-aligned
    quaternions, and velocities are central differences of the smoothed poses, the velocities that carry one pose
    into the next under MuJoCo's integration to second order (one-sided at the ends). Other joints are unchanged.
    """
    from scipy.signal import savgol_filter

    qpos = np.array(qpos, dtype=np.float64, copy=True)
    out = np.array(qvel, dtype=np.float64, copy=True)
    num = len(time_s)
    if num < 3:
        return qpos, out
    window = min(window, num if num % 2 else num - 1)
    for body in bodies:
        p = body.qpos_adr
        quat = qpos[:, p + 3 : p + 7].copy()
        flips = np.cumprod(np.r_[1.0, np.sign(np.sum(quat[1:] * quat[:-1], axis=1) + 1e-300)])
        quat *= flips[:, None]
        if window >= 3:
            qpos[:, p : p + 3] = savgol_filter(qpos[:, p : p + 3], window, 2, axis=0)
            quat = savgol_filter(quat, window, 2, axis=0)
        qpos[:, p + 3 : p + 7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    prev = np.r_[0, np.arange(num - 1)]
    nxt = np.r_[np.arange(1, num), num - 1]
    span = (time_s[nxt] - time_s[prev])[:, None]
    for body in bodies:
        p, d = body.qpos_adr, body.dof_adr
        out[:, d : d + 3] = (qpos[nxt, p : p + 3] - qpos[prev, p : p + 3]) / span
        quat = qpos[:, p + 3 : p + 7]
        # body-frame angular velocity: q[next] = q[prev] * exp(omega_body * span)
        out[:, d + 3 : d + 6] = quat_to_rotvec(quat_mul(quat_conj(quat[prev]), quat[nxt])) / span
    return qpos, out
