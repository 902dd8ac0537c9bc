"""Learned residual dynamics on top of MuJoCo: features, the bounded and gated correction, and its files.

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
- an output gain chosen by multi-step rollouts of held-out trajectories (``grounder._residual_train``): a residual
  that does not improve rollouts gets gain 0, i.e. exactly MuJoCo.

Files in a residual scene folder: ``scene.xml`` (+ assets), ``residual.pt`` (torch ``state_dict``: weights and the
normalisation, bounds and coverage statistics; read with ``weights_only=True``), ``residual.json`` (metadata:
period, bodies, feature and output names, gate thresholds, training summary) and ``residual.onnx`` (the same
features -> gated correction function, for use outside Python).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from grounder.errors import GrounderError

RESIDUAL_FORMAT = "image2sim-residual"
RESIDUAL_VERSION = 1
WEIGHTS_FILE = "residual.pt"
META_FILE = "residual.json"
ONNX_FILE = "residual.onnx"

FEATURE_NAMES = (
    "clearance_m",
    "height_m",
    "up_body_x",
    "up_body_y",
    "up_body_z",
    "vel_body_x_m_s",
    "vel_body_y_m_s",
    "vel_body_z_m_s",
    "omega_body_x_rad_s",
    "omega_body_y_rad_s",
    "omega_body_z_rad_s",
)
OUTPUT_NAMES = (
    "dpos_body_x_m",
    "dpos_body_y_m",
    "dpos_body_z_m",
    "drot_body_x_rad",
    "drot_body_y_rad",
    "drot_body_z_rad",
    "dvel_body_x_m_s",
    "dvel_body_y_m_s",
    "dvel_body_z_m_s",
    "domega_body_x_rad_s",
    "domega_body_y_rad_s",
    "domega_body_z_rad_s",
)
NUM_FEATURES = len(FEATURE_NAMES)
NUM_OUTPUTS = len(OUTPUT_NAMES)


# --- quaternions (w first), batched over leading axes ----------------------------------------------------------


def quat_to_mat(quat_wxyz: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions -> (..., 3, 3) rotation matrices (body -> world)."""
    w, x, y, z = np.moveaxis(quat_wxyz, -1, 0)
    out = np.empty((*quat_wxyz.shape[:-1], 3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - w * z)
    out[..., 0, 2] = 2 * (x * z + w * y)
    out[..., 1, 0] = 2 * (x * y + w * z)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - w * x)
    out[..., 2, 0] = 2 * (x * z - w * y)
    out[..., 2, 1] = 2 * (y * z + w * x)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def quat_mul(a_wxyz: np.ndarray, b_wxyz: np.ndarray) -> np.ndarray:
    """Hamilton product a * b, (..., 4)."""
    aw, ax, ay, az = np.moveaxis(a_wxyz, -1, 0)
    bw, bx, by, bz = np.moveaxis(b_wxyz, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conj(quat_wxyz: np.ndarray) -> np.ndarray:
    return quat_wxyz * np.array([1.0, -1.0, -1.0, -1.0])


def rotvec_to_quat(rotvec: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors (radians) -> (..., 4) unit quaternions."""
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(a/2)/a -> 1/2 as a -> 0; the series keeps full precision for tiny corrections.
    small = angle < 1e-6
    scale = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / np.where(small, 1.0, angle))
    return np.concatenate([np.cos(half), rotvec * scale], axis=-1)


def quat_to_rotvec(quat_wxyz: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions -> (..., 3) rotation vectors, angle in [0, pi] (q and -q give the same)."""
    q = np.where(quat_wxyz[..., :1] < 0, -quat_wxyz, quat_wxyz)
    sin_half = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sin_half, q[..., :1])
    small = sin_half < 1e-9
    scale = np.where(small, 2.0, angle / np.where(small, 1.0, sin_half))
    return q[..., 1:] * scale


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


# --- gate and network, numpy evaluation ------------------------------------------------------------------------


def _smoothstep1(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


def _rotate(rows: tuple[float, ...], x: float, y: float, z: float) -> tuple[float, float, float]:
    return (
        rows[0] * x + rows[1] * y + rows[2] * z,
        rows[3] * x + rows[4] * y + rows[5] * z,
        rows[6] * x + rows[7] * y + rows[8] * z,
    )


def _energy_py(
    mass: float,
    inertia: list[list[float]],
    gravity: tuple[float, float, float],
    p3: list[float],
    v3: list[float],
    w3: list[float],
) -> float:
    iw = [inertia[k][0] * w3[0] + inertia[k][1] * w3[1] + inertia[k][2] * w3[2] for k in range(3)]
    kinetic = 0.5 * mass * (v3[0] ** 2 + v3[1] ** 2 + v3[2] ** 2) + 0.5 * (
        w3[0] * iw[0] + w3[1] * iw[1] + w3[2] * iw[2]
    )
    return kinetic - mass * (p3[0] * gravity[0] + p3[1] * gravity[1] + p3[2] * gravity[2])


def smoothstep(x: np.ndarray) -> np.ndarray:
    """0 for x <= 0, 1 for x >= 1, C1 in between (3x^2 - 2x^3)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


@dataclass(frozen=True, kw_only=True)
class GateOptions:
    """Where the correction is switched on; see the module docstring.

    Attributes:
        rest_speed_m_s: (off, on) speed of the fastest point, ``|v| + radius |omega|``: below ``off`` a body in
            contact gets exactly zero correction.
        air_clearance_m: (off, on) clearance of the lowest point above z = 0: above ``on`` a body is in flight and
            is corrected whatever its speed (at the top of a toss).
        range_margin: Fraction of each feature's training range over which the correction fades out beyond it.
        coverage_centres: k-means centres summarising the training states for the distance check.
        coverage_quantile: Quantile of the training states' distances to their nearest centre where fading starts;
            the correction reaches 0 at twice that distance.
        energy_restore_fraction: The corrected state's energy may exceed MuJoCo's by at most this fraction of
            what MuJoCo dissipated over the period, and never the energy at its start (see ``cap_energy``).
    """

    rest_speed_m_s: tuple[float, float] = (0.01, 0.05)
    air_clearance_m: tuple[float, float] = (0.005, 0.02)
    range_margin: float = 0.1
    coverage_centres: int = 256
    coverage_quantile: float = 0.99
    energy_restore_fraction: float = 0.5


@dataclass(frozen=True, kw_only=True)
class ResidualMeta:
    """The metadata in ``residual.json``.

    Attributes:
        period_steps: Model steps between corrections (one data sample interval).
        timestep_s: The model timestep the residual was trained with.
        bodies: Names of the corrected free bodies, in joint order.
        hidden: Width of the MLP's hidden layers.
        layers: Number of hidden layers.
        gate: The gate thresholds.
        scene_xml_sha256: Hash of the scene.xml the residual was trained on.
        training: Free-form training summary (data, seeds, errors), for provenance.
    """

    period_steps: int
    timestep_s: float
    bodies: tuple[str, ...]
    hidden: int
    layers: int
    gate: GateOptions
    scene_xml_sha256: str
    training: dict[str, Any]

    @property
    def period_s(self) -> float:
        return self.period_steps * self.timestep_s

    def to_json(self) -> dict[str, Any]:
        return {
            "format": RESIDUAL_FORMAT,
            "version": RESIDUAL_VERSION,
            "kind": "body-frame state correction at the data rate, bounded and gated",
            "period_steps": self.period_steps,
            "timestep_s": self.timestep_s,
            "period_s": self.period_s,
            "bodies": list(self.bodies),
            "features": list(FEATURE_NAMES),
            "outputs": list(OUTPUT_NAMES),
            "hidden": self.hidden,
            "layers": self.layers,
            "gate": {
                "rest_speed_m_s": list(self.gate.rest_speed_m_s),
                "air_clearance_m": list(self.gate.air_clearance_m),
                "range_margin": self.gate.range_margin,
                "coverage_centres": self.gate.coverage_centres,
                "coverage_quantile": self.gate.coverage_quantile,
                "energy_restore_fraction": self.gate.energy_restore_fraction,
            },
            "scene_xml_sha256": self.scene_xml_sha256,
            "files": {"weights": WEIGHTS_FILE, "onnx": ONNX_FILE},
            "training": self.training,
        }

    @staticmethod
    def from_json(raw: dict[str, Any], where: Path) -> ResidualMeta:
        if raw.get("format") != RESIDUAL_FORMAT or raw.get("version") != RESIDUAL_VERSION:
            raise GrounderError(
                f"{where}: not an {RESIDUAL_FORMAT} v{RESIDUAL_VERSION} file (format={raw.get('format')!r}, "
                f"version={raw.get('version')!r}); retrain with `image2sim residual train`"
            )
        if list(raw.get("features", [])) != list(FEATURE_NAMES) or list(raw.get("outputs", [])) != list(OUTPUT_NAMES):
            raise GrounderError(f"{where}: features or outputs differ from this version's; retrain the residual")
        try:
            gate = raw["gate"]
            return ResidualMeta(
                period_steps=int(raw["period_steps"]),
                timestep_s=float(raw["timestep_s"]),
                bodies=tuple(str(b) for b in raw["bodies"]),
                hidden=int(raw["hidden"]),
                layers=int(raw["layers"]),
                gate=GateOptions(
                    rest_speed_m_s=(float(gate["rest_speed_m_s"][0]), float(gate["rest_speed_m_s"][1])),
                    air_clearance_m=(float(gate["air_clearance_m"][0]), float(gate["air_clearance_m"][1])),
                    range_margin=float(gate["range_margin"]),
                    coverage_centres=int(gate["coverage_centres"]),
                    coverage_quantile=float(gate["coverage_quantile"]),
                    energy_restore_fraction=float(gate["energy_restore_fraction"]),
                ),
                scene_xml_sha256=str(raw.get("scene_xml_sha256", "")),
                training=dict(raw.get("training", {})),
            )
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise GrounderError(f"{where}: malformed residual metadata ({type(exc).__name__}: {exc})") from exc


class NumpyResidual:
    """The residual evaluated with numpy from a ``state_dict``: features (N, B, 11) -> gated correction (N, B, 12).

    Same function as the torch model (``grounder._residual_torch.ResidualModel``) and its ONNX export; numpy
    because a single simulation's step is a few microseconds of MuJoCo, where torch's per-call overhead (tens of
    microseconds) would dominate.
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
        self.out_gain = np.array(state["out_gain"], dtype=np.float64)  # (B,), chosen on held-out rollouts
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
        self._margin = meta.gate.range_margin * (self.range_hi - self.range_lo) + 1e-9
        self._centre_sq = np.sum(self.centres**2, axis=-1)  # (B, K)
        self._scale_over_bound = self.out_scale / self.out_bound
        self._inv_std = 1.0 / self.feat_std
        self._inv_margin = 1.0 / self._margin
        # plain-Python copies for correct_one
        self._lo_list = self.range_lo.tolist()
        self._hi_list = self.range_hi.tolist()
        self._inv_margin_list = self._inv_margin.tolist()
        self._coverage_list = self.coverage_dist.tolist()
        self._inertia_list = [b.inertia_body.tolist() for b in bodies]
        self._gravity_list = self.gravity.tolist()
        self._points_list = [b.points_body_m.tolist() if len(b.points_body_m) <= 16 else None for b in bodies]
        # correct_one folds the standardisation into one stacked matrix: first-layer pre-activations and the
        # distances to the coverage centres come from a single matrix-vector product with the raw features.
        hidden = self.layers[0][0][0].shape[1]
        self._hidden = hidden
        self._stacked, self._bias1, self._centre_const = [], [], []
        for b in range(num_b):
            w1, b1 = self.layers[b][0]  # (F, H), (H,)
            mean, inv_std = self.feat_mean[b], self._inv_std[b]
            centres_raw = mean + self.feat_std[b] * self.centres[b]  # (K, F)
            self._stacked.append(np.concatenate([(w1 * inv_std[:, None]).T, centres_raw * inv_std**2]))
            self._bias1.append(b1 - (mean * inv_std) @ w1)
            self._centre_const.append(np.sum((centres_raw * inv_std) ** 2, axis=1))
        self._inv_std_sq = self._inv_std**2

    def gate(self, feats: np.ndarray) -> np.ndarray:
        """(N, B, F) raw features -> (N, B) gate in [0, 1] (the output gain not included)."""
        g = self.meta.gate
        speed = np.linalg.norm(feats[..., 5:8], axis=-1) + self.radius_m * np.linalg.norm(feats[..., 8:11], axis=-1)
        moving = smoothstep((speed - g.rest_speed_m_s[0]) / (g.rest_speed_m_s[1] - g.rest_speed_m_s[0]))
        flying = smoothstep((feats[..., 0] - g.air_clearance_m[0]) / (g.air_clearance_m[1] - g.air_clearance_m[0]))
        active = 1.0 - (1.0 - moving) * (1.0 - flying)
        outside = np.maximum(np.maximum(self.range_lo - feats, feats - self.range_hi), 0.0) / self._margin
        in_range = np.prod(1.0 - smoothstep(outside), axis=-1)
        z = (feats - self.feat_mean) / self.feat_std
        # squared distances to every centre: |z|^2 - 2 z.c + |c|^2
        d2 = np.sum(z * z, axis=-1)[..., None] - 2.0 * np.einsum("nbf,bkf->nbk", z, self.centres) + self._centre_sq
        dist = np.sqrt(np.maximum(np.min(d2, axis=-1), 0.0))
        near = 1.0 - smoothstep(dist / self.coverage_dist - 1.0)
        return active * in_range * near

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

    def correct_one(
        self, qpos0: np.ndarray, qvel0: np.ndarray, qpos: np.ndarray, qvel: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`correct` for one state ((nq,), (nv,)), written for speed: ``qpos``/``qvel`` are modified in place.

        A single simulation steps MuJoCo in microseconds, where numpy's per-call overhead on 3-vectors would
        dominate: the 3-vector algebra is plain Python floats, numpy is used for the MLP and the coverage check.
        Same arithmetic as :meth:`correct` (checked by the tests).
        """
        g = self.meta.gate
        rest_lo, rest_span = g.rest_speed_m_s[0], g.rest_speed_m_s[1] - g.rest_speed_m_s[0]
        air_lo, air_span = g.air_clearance_m[0], g.air_clearance_m[1] - g.air_clearance_m[0]
        gx, gy, gz = self._gravity_list
        for b, body in enumerate(self.bodies):
            p, d = body.qpos_adr, body.dof_adr
            px, py, pz, qw, qx, qy, qz = qpos0[p : p + 7].tolist()
            vx, vy, vz, wx, wy, wz = qvel0[d : d + 6].tolist()
            # rotation matrix rows (body -> world)
            r00, r01, r02 = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)
            r10, r11, r12 = 2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)
            r20, r21, r22 = 2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)
            ubx, uby, ubz = r20, r21, r22
            vbx = r00 * vx + r10 * vy + r20 * vz
            vby = r01 * vx + r11 * vy + r21 * vz
            vbz = r02 * vx + r12 * vy + r22 * vz
            points = self._points_list[b]
            if points is None:
                clearance = pz + float((body.points_body_m @ np.array((ubx, uby, ubz))).min())
            else:
                clearance = pz + min(x * ubx + y * uby + zz * ubz for x, y, zz in points)
            speed = math.sqrt(vx * vx + vy * vy + vz * vz) + body.radius_m * math.sqrt(wx * wx + wy * wy + wz * wz)
            moving = _smoothstep1((speed - rest_lo) / rest_span)
            flying = _smoothstep1((clearance - air_lo) / air_span)
            gate = (1.0 - (1.0 - moving) * (1.0 - flying)) * float(self.out_gain[b])
            if gate == 0.0:  # at rest (or switched off): exactly no correction
                continue
            feats = (clearance, pz, ubx, uby, ubz, vbx, vby, vbz, wx, wy, wz)
            for f, lo, hi, inv in zip(feats, self._lo_list[b], self._hi_list[b], self._inv_margin_list[b], strict=True):
                if f < lo:
                    gate *= 1.0 - _smoothstep1((lo - f) * inv)
                elif f > hi:
                    gate *= 1.0 - _smoothstep1((f - hi) * inv)
            f = np.array(feats)
            y = self._stacked[b] @ f
            d2 = float((self._centre_const[b] - 2.0 * y[self._hidden :]).min() + (f * f) @ self._inv_std_sq[b])
            gate *= 1.0 - _smoothstep1(math.sqrt(max(d2, 0.0)) / self._coverage_list[b] - 1.0)
            if gate == 0.0:
                continue
            layers = self.layers[b]
            h = np.tanh(y[: self._hidden] + self._bias1[b])
            for weight, bias in layers[1:-1]:
                h = np.tanh(h @ weight + bias)
            u = h @ layers[-1][0] + layers[-1][1]
            c = ((gate * self.out_bound[b]) * np.tanh(u * self._scale_over_bound[b])).tolist()
            mass, inertia = body.mass_kg, self._inertia_list[b]

            grav = (gx, gy, gz)
            e_start = _energy_py(mass, inertia, grav, [px, py, pz], [vx, vy, vz], [wx, wy, wz])
            sx, sy, sz, sw, sqx, sqy, sqz = qpos[p : p + 7].tolist()
            svx, svy, svz, swx, swy, swz = qvel[d : d + 6].tolist()
            e_sim = _energy_py(mass, inertia, grav, [sx, sy, sz], [svx, svy, svz], [swx, swy, swz])

            rows = (r00, r01, r02, r10, r11, r12, r20, r21, r22)
            dpx, dpy, dpz = _rotate(rows, c[0], c[1], c[2])
            ax, ay, az = _rotate(rows, c[3], c[4], c[5])
            dvx, dvy, dvz = _rotate(rows, c[6], c[7], c[8])
            pos = [sx + dpx, sy + dpy, sz + dpz]
            vel = [svx + dvx, svy + dvy, svz + dvz]
            omg = [swx + c[9], swy + c[10], swz + c[11]]
            angle = math.sqrt(ax * ax + ay * ay + az * az)
            half_sin = 0.5 - angle * angle / 48.0 if angle < 1e-6 else math.sin(0.5 * angle) / angle
            dw, dx, dy, dz = math.cos(0.5 * angle), ax * half_sin, ay * half_sin, az * half_sin
            nw = dw * sw - dx * sqx - dy * sqy - dz * sqz
            nx = dw * sqx + dx * sw + dy * sqz - dz * sqy
            ny = dw * sqy - dx * sqz + dy * sw + dz * sqx
            nz = dw * sqz + dx * sqy - dy * sqx + dz * sw
            norm = math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
            fraction = g.energy_restore_fraction
            cap = max(e_sim, min(e_start, e_sim + fraction * max(e_start - e_sim, 0.0)))
            e_new = _energy_py(mass, inertia, grav, pos, vel, omg)
            if e_new > cap + 1e-12:
                potential = -mass * (pos[0] * gx + pos[1] * gy + pos[2] * gz)
                k = math.sqrt(max(cap - potential, 0.0) / max(e_new - potential, 1e-300))
                vel, omg = [k * x for x in vel], [k * x for x in omg]
            qpos[p : p + 7] = (*pos, nw / norm, nx / norm, ny / norm, nz / norm)
            qvel[d : d + 6] = (*vel, *omg)
        return qpos, qvel

    def correct(
        self, qpos0: np.ndarray, qvel0: np.ndarray, qpos_sim: np.ndarray, qvel_sim: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """States after one period: MuJoCo's ``(qpos_sim, qvel_sim)`` from ``(qpos0, qvel0)``, corrected.

        All (N, nq) / (N, nv). Applies the gated correction of the starting state, then the energy cap.
        """
        feats, rots = body_features(qpos0, qvel0, self.bodies)
        qpos, qvel = apply_correction(qpos_sim, qvel_sim, self(feats), rots, self.bodies)
        fraction = self.meta.gate.energy_restore_fraction
        start = [body_energy(qpos0, qvel0, b, self.gravity) for b in self.bodies]
        sim = [body_energy(qpos_sim, qvel_sim, b, self.gravity) for b in self.bodies]
        cap_energy(start, sim, qpos, qvel, self.bodies, self.gravity, fraction)
        return qpos, qvel


# --- files -----------------------------------------------------------------------------------------------------


def file_sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def has_residual_files(scene_dir: Path) -> bool:
    scene_dir = Path(scene_dir)
    return scene_dir.is_dir() and (scene_dir / META_FILE).is_file() and (scene_dir / WEIGHTS_FILE).is_file()


def load_residual(scene_dir: Path, model: mujoco.MjModel) -> NumpyResidual:
    """Reads ``residual.json`` and ``residual.pt`` from a scene folder, checked against the scene's model.

    Raises:
        GrounderError: missing or malformed files, or a residual trained for other bodies or another timestep.
    """
    import torch

    scene_dir = Path(scene_dir)
    meta_path, weights_path = scene_dir / META_FILE, scene_dir / WEIGHTS_FILE
    try:
        meta = ResidualMeta.from_json(json.loads(meta_path.read_text()), meta_path)
    except (OSError, json.JSONDecodeError) as exc:
        raise GrounderError(f"{meta_path}: could not be read ({type(exc).__name__}: {exc})") from exc
    bodies = free_bodies(model)
    if tuple(b.name for b in bodies) != meta.bodies:
        raise GrounderError(
            f"{meta_path}: the residual corrects bodies {list(meta.bodies)} but the scene's free bodies are "
            f"{[b.name for b in bodies]}; retrain it on this scene"
        )
    if not np.isclose(meta.timestep_s, model.opt.timestep, rtol=1e-9, atol=0.0):
        raise GrounderError(
            f"{meta_path}: trained with timestep {meta.timestep_s:.6g} s but the scene has {model.opt.timestep:.6g} s; "
            "retrain the residual on this scene"
        )
    try:
        state = torch.load(weights_path, weights_only=True, map_location="cpu")
    except Exception as exc:  # torch raises many types for corrupt or unsafe files
        raise GrounderError(f"{weights_path}: could not be read ({type(exc).__name__}: {exc})") from exc
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise GrounderError(f"{weights_path}: expected a state_dict of tensors")
    arrays = {k: v.detach().to(torch.float64).numpy() for k, v in state.items()}
    try:
        return NumpyResidual(arrays, meta, bodies, model.opt.gravity)
    except KeyError as exc:
        raise GrounderError(f"{weights_path}: missing tensor {exc}; retrain the residual") from exc


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
