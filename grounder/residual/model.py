"""Learned residual dynamics on top of MuJoCo: features, the bounded and gated correction, and its files.

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

Files in a residual scene folder: ``scene.xml`` (+ assets), ``residual.pt`` (torch ``state_dict``: weights and the
normalisation, bounds and coverage statistics; read with ``weights_only=True``), ``residual.json`` (metadata:
period, bodies, feature and output names, gate thresholds, training summary) and ``residual.onnx`` (the same
features -> gated correction function, for use outside Python).
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

import mujoco
import numpy as np

from grounder.core.json_files import read_json_file
from grounder.core.torch_files import load_weights_file, tensor_problem
from grounder.errors import GrounderError, shown
from image2sim_common.rotations import quat_conj, quat_mul, quat_to_mat, quat_to_rotvec, rotvec_to_quat

if TYPE_CHECKING:
    from grounder.residual.joint import NumpyJointResidual

RESIDUAL_FORMAT = "image2sim-residual"
RESIDUAL_VERSION = 1
WEIGHTS_FILE = "residual.pt"
META_FILE = "residual.json"
ONNX_FILE = "residual.onnx"
RESIDUAL_FILES = (WEIGHTS_FILE, META_FILE, ONNX_FILE)  # what makes a scene folder a residual scene

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
        scene_files_sha256: Hash of each file that scene.xml includes or loads (meshes, textures, ...), by its path
            relative to the scene's folder (:func:`scene_files_sha256`); None for a residual written before this
            field, whose included files are then not checked.
        training: Free-form training summary (data, seeds, errors), for provenance.
        space: ``free`` (body-frame corrections of free bodies, this module) or ``joint`` (hinge and slide joints,
            ``grounder.residual.joint``; ``bodies`` then names the joints).
        feature_names, output_names: The network's inputs and outputs (fixed for ``free``, per scene for ``joint``).
    """

    period_steps: int
    timestep_s: float
    bodies: tuple[str, ...]
    hidden: int
    layers: int
    gate: GateOptions
    scene_xml_sha256: str
    training: dict[str, Any]
    space: str = "free"
    scene_files_sha256: dict[str, str] | None = None
    feature_names: tuple[str, ...] = FEATURE_NAMES
    output_names: tuple[str, ...] = OUTPUT_NAMES

    @property
    def period_s(self) -> float:
        return self.period_steps * self.timestep_s

    def to_json(self) -> dict[str, Any]:
        return {
            "format": RESIDUAL_FORMAT,
            "version": RESIDUAL_VERSION,
            "kind": (
                "body-frame state correction at the data rate, bounded and gated"
                if self.space == "free"
                else "joint-space state correction at the data rate, bounded and gated"
            ),
            "space": self.space,
            "period_steps": self.period_steps,
            "timestep_s": self.timestep_s,
            "period_s": self.period_s,
            "bodies": list(self.bodies),
            "features": list(self.feature_names),
            "outputs": list(self.output_names),
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
            **({} if self.scene_files_sha256 is None else {"scene_files_sha256": dict(self.scene_files_sha256)}),
            "files": {"weights": WEIGHTS_FILE, "onnx": ONNX_FILE},
            "training": self.training,
        }

    @staticmethod
    def from_json(raw: Any, where: Path) -> ResidualMeta:
        """The metadata from ``residual.json``'s parsed content, an untrusted file: every field's type and range is
        checked here, so that the residual and :class:`grounder.Simulator` can use them as they are.

        Raises:
            GrounderError: one line naming the field, its value and what it must be.
        """
        if not isinstance(raw, dict):
            raise GrounderError(f"{where}: expected a JSON object, got a JSON {_json_type(raw)}; {_RETRAIN}")
        if raw.get("format") != RESIDUAL_FORMAT or raw.get("version") != RESIDUAL_VERSION:
            raise GrounderError(
                f"{where}: not an {RESIDUAL_FORMAT} v{RESIDUAL_VERSION} file (format={shown(raw.get('format'))}, "
                f"version={shown(raw.get('version'))}); {_RETRAIN}"
            )
        space = raw.get("space", "free")
        if space not in ("free", "joint"):
            raise GrounderError(f"{where}: unknown residual space {shown(space)}; {_RETRAIN}")
        field = _MetaFields(raw, where)
        features, outputs = field.names("features"), field.names("outputs")
        if space == "free" and (features != FEATURE_NAMES or outputs != OUTPUT_NAMES):
            raise GrounderError(f"{where}: features or outputs differ from this version's; {_RETRAIN}")
        gate = _MetaFields(field.value("gate", dict, "an object"), where, "gate.")
        training = raw.get("training", {})
        if not isinstance(training, dict):
            raise GrounderError(f"{where}: training is a JSON {_json_type(training)}, expected an object; {_RETRAIN}")
        sha256 = field.value("scene_xml_sha256", str, "the scene.xml's sha256 (64 hex digits)")
        if re.fullmatch(r"[0-9a-f]{64}", sha256) is None:
            raise field.bad("scene_xml_sha256", sha256, "the scene.xml's sha256 (64 lowercase hex digits)")
        files_sha256 = None
        if "scene_files_sha256" in raw:  # absent in residuals written before it
            expected = "an object of file path -> sha256 (64 lowercase hex digits)"
            files_sha256 = field.value("scene_files_sha256", dict, expected)
            if len(files_sha256) > MAX_SCENE_FILES or not all(
                isinstance(v, str) and re.fullmatch(r"[0-9a-f]{64}", v) is not None for v in files_sha256.values()
            ):
                raise field.bad("scene_files_sha256", files_sha256, expected)
        return ResidualMeta(
            period_steps=field.integer("period_steps", 1, MAX_PERIOD_STEPS),
            timestep_s=field.number("timestep_s", lambda x: x > 0.0, "a number > 0"),
            bodies=field.names("bodies", nonempty=True),
            hidden=field.integer("hidden", 1),
            layers=field.integer("layers", 1),
            gate=GateOptions(
                rest_speed_m_s=gate.pair("rest_speed_m_s", lowest=0.0),
                air_clearance_m=gate.pair("air_clearance_m"),
                range_margin=gate.number("range_margin", lambda x: x >= 0.0, "a number >= 0"),
                coverage_centres=gate.integer("coverage_centres", 1),
                coverage_quantile=gate.number("coverage_quantile", lambda x: 0.0 < x <= 1.0, "a number in (0, 1]"),
                energy_restore_fraction=gate.number(
                    "energy_restore_fraction", lambda x: 0.0 <= x <= 1.0, "a number in [0, 1]"
                ),
            ),
            scene_xml_sha256=sha256,
            training=dict(training),
            space=space,
            feature_names=features,
            output_names=outputs,
            scene_files_sha256=None if files_sha256 is None else dict(files_sha256),
        )


_RETRAIN = "retrain with `image2sim residual train`"

MAX_SCENE_FILES = 100_000
"""Most entries ``scene_files_sha256`` may hold (a scene's meshes, textures and includes)."""

MAX_PERIOD_STEPS = 100_000
"""Most model steps one period may span: far beyond any data rate (1 Hz at a 10 us timestep), while a rollout's
buffers, which grow with the period whatever the data, stay small."""


def _json_type(value: Any) -> str:
    names = {dict: "object", list: "array", str: "string", bool: "boolean", int: "number", float: "number"}
    return "null" if value is None else names.get(type(value), type(value).__name__)


class _MetaFields:
    """Typed reads of one JSON object of ``residual.json``; each failure is one GrounderError line naming the field."""

    def __init__(self, raw: dict[str, Any], where: Path, prefix: str = ""):
        self.raw, self.where, self.prefix = raw, where, prefix

    def bad(self, key: str, value: Any, expected: str) -> GrounderError:
        return GrounderError(f"{self.where}: {self.prefix}{key} is {shown(value)}, expected {expected}; {_RETRAIN}")

    def value(self, key: str, kind: type | tuple[type, ...], expected: str) -> Any:
        if key not in self.raw:
            raise GrounderError(f"{self.where}: {self.prefix}{key} is missing, expected {expected}; {_RETRAIN}")
        value = self.raw[key]
        if not isinstance(value, kind) or isinstance(value, bool) is not (kind is bool):
            raise self.bad(key, value, expected)
        return value

    def integer(self, key: str, lowest: int, highest: int | None = None) -> int:
        expected = f"an integer >= {lowest}" if highest is None else f"an integer in [{lowest}, {highest}]"
        value = self.value(key, int, expected)  # not a float: 8.7 steps must not become 8
        if value < lowest or (highest is not None and value > highest):
            raise self.bad(key, value, expected)
        return int(value)

    def number(self, key: str, ok: Callable[[float], bool], expected: str) -> float:
        return self._finite(key, self.value(key, (int, float), expected), ok, expected)

    def _finite(self, key: str, value: int | float, ok: Callable[[float], bool], expected: str) -> float:
        try:
            number = float(value)
        except OverflowError:  # an integer beyond float range
            number = math.inf
        if not math.isfinite(number) or not ok(number):
            raise self.bad(key, value, expected)
        return number

    def pair(self, key: str, lowest: float = -math.inf) -> tuple[float, float]:
        """(off, on) thresholds: finite, off >= lowest, on > off (the gate divides by on - off)."""
        expected = "[off, on], finite numbers with on > off"
        expected += "" if lowest == -math.inf else f" and off >= {lowest:g}"
        value = self.value(key, list, expected)
        if len(value) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            raise self.bad(key, value, expected)
        try:
            off = self._finite(key, value[0], lambda x: x >= lowest, expected)
            on = self._finite(key, value[1], lambda x: x > off, expected)
        except GrounderError:
            raise self.bad(key, value, expected) from None  # the pair, not one number of it
        return off, on

    def names(self, key: str, *, nonempty: bool = False) -> tuple[str, ...]:
        expected = "a non-empty list of names" if nonempty else "a list of names"
        value = self.value(key, list, expected)
        if not all(isinstance(v, str) for v in value) or (nonempty and not value):
            raise self.bad(key, value, expected)
        return tuple(value)


class CoverageStats(Protocol):
    """What :func:`coverage_gate` reads: the training statistics a numpy residual holds (see ``NumpyResidual``)."""

    range_lo: np.ndarray  # (B, F)
    range_hi: np.ndarray
    feat_mean: np.ndarray
    feat_std: np.ndarray
    centres: np.ndarray  # (B, K, F), standardised
    coverage_dist: np.ndarray  # (B,)
    meta: ResidualMeta


def coverage_gate(stats: CoverageStats, feats: np.ndarray) -> np.ndarray:
    """(N, B, F) -> (N, B): inside the training ranges (fading over ``range_margin`` of each range) times near the
    training states (distance to the nearest k-means centre, fading from ``coverage_dist`` to twice that)."""
    margin = stats.meta.gate.range_margin * (stats.range_hi - stats.range_lo) + 1e-9
    outside = np.maximum(np.maximum(stats.range_lo - feats, feats - stats.range_hi), 0.0) / margin
    in_range = np.prod(1.0 - smoothstep(outside), axis=-1)
    z = (feats - stats.feat_mean) / stats.feat_std
    # squared distances to every centre: |z|^2 - 2 z.c + |c|^2
    centre_sq = np.sum(stats.centres**2, axis=-1)
    d2 = np.sum(z * z, axis=-1)[..., None] - 2.0 * np.einsum("nbf,bkf->nbk", z, stats.centres) + centre_sq
    dist = np.sqrt(np.maximum(np.min(d2, axis=-1), 0.0))
    return in_range * (1.0 - smoothstep(dist / stats.coverage_dist - 1.0))


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


def fade_ranges(range_lo: np.ndarray, range_hi: np.ndarray, range_margin: float) -> np.ndarray:
    """(..., 3, F): each feature's training range, low and high, and 1 / the margin the gate fades over beyond it
    (:func:`coverage_gate`'s), as the compiled single-state path takes them."""
    inv_margin = 1.0 / (range_margin * (range_hi - range_lo) + 1e-9)
    return np.ascontiguousarray(np.stack([range_lo, range_hi, inv_margin], axis=-2), dtype=np.float64)


def network_layers(
    layers: list[tuple[np.ndarray, np.ndarray]],
    feat_mean: np.ndarray,
    feat_std: np.ndarray,
    out_scale: np.ndarray,
    out_bound: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One network as the compiled single-state path takes it (``grounder.residual.kernel._gated_network``):
    ``(first (F + 1, H + F), mids (L, H + 1, H), last (H + 2, O))`` from its layers ``(weight (in, out), bias
    (out,))``, the feature standardisation (F,) and the output's scale and bound (O,).

    Every layer takes ``[x, 1]`` (its bias is its last row; the output layer's is times scale / bound, and the
    bound follows as one more row). The first one works on the raw features: it gives the first layer's
    pre-activations and the standardised features z (both linear in the raw features, as z = (f - mean) / std),
    from which the coverage check measures distances.
    """
    inv_std = 1.0 / feat_std
    standardise = np.vstack([np.diag(inv_std), -feat_mean * inv_std])  # (F + 1, F)
    w1, b1 = layers[0]
    first_layer = standardise @ w1
    first_layer[-1] += b1
    first = np.hstack([first_layer, standardise])
    hidden = w1.shape[1]
    mids = np.array([np.vstack([w, bias]) for w, bias in layers[1:-1]], dtype=np.float64).reshape(
        -1, hidden + 1, hidden
    )
    w_out, b_out = layers[-1]
    last = np.vstack([np.vstack([w_out, b_out]) * (out_scale / out_bound), out_bound])
    return np.ascontiguousarray(first), np.ascontiguousarray(mids), np.ascontiguousarray(last, dtype=np.float64)


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
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def scene_files_sha256(xml: Path) -> dict[str, str]:
    """sha256 of each file ``xml`` includes or loads (`grounder.sim.rollout.scene_files`), keyed by its path relative
    to the MJCF's folder (POSIX separators); files the MJCF names but that do not exist are left out (MuJoCo then
    fails to load the scene anyway)."""
    from grounder.sim.rollout import scene_files

    hashes = {}
    for rel in scene_files(xml):
        path = xml.parent / rel
        if path.is_file():
            hashes[rel.as_posix()] = file_sha256(path)
    return dict(sorted(hashes.items()))


def _changed_scene_file(xml: Path, trained: dict[str, str]) -> str | None:
    """The first file of the scene that differs from the one the residual was trained with (as a phrase), or None."""
    now = scene_files_sha256(xml)
    for name in sorted(set(now) | set(trained)):
        if name not in now:
            return f"{name} is gone"
        if name not in trained:
            return f"{name} is new"
        if now[name] != trained[name]:
            return f"{name} changed (sha256 {now[name][:12]}..., the residual was trained with {trained[name][:12]}...)"
    return None


def has_residual_files(scene_dir: Path) -> bool:
    scene_dir = Path(scene_dir)
    return scene_dir.is_dir() and (scene_dir / META_FILE).is_file() and (scene_dir / WEIGHTS_FILE).is_file()


def check_residual_pair(scene_dir: Path) -> None:
    """Refuses a scene folder that holds one of ``residual.json`` and ``residual.pt`` without the other.

    Such a folder would otherwise be simulated without its residual, silently.

    Raises:
        GrounderError: one line naming the file that is there and the one that is missing, and what to do.
    """
    scene_dir = Path(scene_dir)
    if not scene_dir.is_dir():
        return
    there = [name for name in (META_FILE, WEIGHTS_FILE) if (scene_dir / name).exists()]
    if len(there) == 1:
        missing = WEIGHTS_FILE if there[0] == META_FILE else META_FILE
        raise GrounderError(
            f"{scene_dir / there[0]} has no {missing} beside it: the residual is incomplete; copy the whole scene "
            "folder again, retrain it (image2sim residual train), or run without it (--no-residual)"
        )


def _checked_state(state: Any, meta: ResidualMeta, where: Path) -> dict[str, np.ndarray]:
    """``residual.pt``'s tensors as float64 arrays, each checked against the metadata first.

    Every tensor must be dense, of a real floating-point dtype (``speed_columns`` of a joint-space residual:
    integer), of the shape that ``residual.json`` implies (bodies, features, outputs, ``hidden``, ``layers``,
    ``gate.coverage_centres``) and finite; the ones the residual divides by positive (``feat_std``, ``out_bound``,
    ``coverage_dist``), ``out_gain`` >= 0 and ``range_lo`` <= ``range_hi``. No tensor may be missing or extra.

    Raises:
        GrounderError: one line naming the file, the tensor and the problem.
    """
    import torch

    if not isinstance(state, dict) or not all(isinstance(k, str) for k in state):
        raise GrounderError(
            f"{where}: expected a state_dict (names -> tensors), not a {type(state).__name__}; {_RETRAIN}"
        )
    if len(state) < 2 * (meta.layers + 1):  # before listing the layers' tensors: a huge count must not build a list
        raise GrounderError(
            f"{where}: holds {len(state)} tensors, too few for the {meta.layers} hidden layers in {META_FILE}; "
            f"{_RETRAIN}"
        )
    num_b = 1 if meta.space == "joint" else len(meta.bodies)
    num_f, num_o = len(meta.feature_names), len(meta.output_names)
    expected: dict[str, tuple[int, ...]] = {
        "feat_mean": (num_b, num_f),
        "feat_std": (num_b, num_f),
        "out_scale": (num_b, num_o),
        "out_bound": (num_b, num_o),
        "range_lo": (num_b, num_f),
        "range_hi": (num_b, num_f),
        "centres": (num_b, meta.gate.coverage_centres, num_f),
        "coverage_dist": (num_b,),
        "out_gain": (num_b,),
        "radius_m": (num_b,),
    }
    if meta.space == "joint":
        expected["speed_columns"] = (len(meta.bodies),)
    widths = (num_f, *([meta.hidden] * meta.layers), num_o)
    for b in range(num_b):
        for i in range(meta.layers + 1):
            expected[f"nets.{b}.{2 * i}.weight"] = (widths[i + 1], widths[i])
            expected[f"nets.{b}.{2 * i}.bias"] = (widths[i + 1],)
    sizes = (
        f"{len(meta.bodies)} {'joints' if meta.space == 'joint' else 'bodies'}, {num_f} features, {num_o} outputs, "
        f"hidden={meta.hidden}, layers={meta.layers}, gate.coverage_centres={meta.gate.coverage_centres}"
    )
    missing = [name for name in expected if name not in state]
    if missing:
        raise GrounderError(f"{where}: missing tensor {shown(missing[0])} ({META_FILE}: {sizes}); {_RETRAIN}")
    extra = [name for name in state if name not in expected]
    if extra:
        raise GrounderError(f"{where}: unexpected tensor {shown(extra[0])} ({META_FILE}: {sizes}); {_RETRAIN}")
    arrays: dict[str, np.ndarray] = {}
    for name, shape in expected.items():
        tensor = state[name]
        problem = tensor_problem(tensor)
        if problem is None and tensor.dtype.is_floating_point == (name == "speed_columns"):
            wanted = "an integer" if name == "speed_columns" else "a floating-point"
            problem = f"has dtype {tensor.dtype}, expected {wanted} one"
        if problem is None and tuple(tensor.shape) != shape:
            problem = f"has shape {tuple(tensor.shape)}, expected {shape} ({META_FILE}: {sizes})"
        if problem is None:
            try:
                array = tensor.detach().resolve_conj().resolve_neg().to(torch.float64).numpy()
            except (RuntimeError, TypeError) as exc:
                raise GrounderError(
                    f"{where}: tensor {name!r} cannot be read as numbers ({type(exc).__name__}); {_RETRAIN}"
                ) from exc
            if not np.isfinite(array).all():
                problem = "holds NaN or infinite values"
            elif name in ("feat_std", "out_bound", "coverage_dist") and not (array > 0.0).all():
                problem = "holds values <= 0 (the residual divides by them)"
            elif name == "out_gain" and not (array >= 0.0).all():
                problem = "holds a negative output gain"
            elif name == "range_hi" and not (array >= arrays["range_lo"]).all():
                problem = "is below range_lo somewhere"
            arrays[name] = array
        if problem is not None:
            raise GrounderError(f"{where}: tensor {name!r} {problem}; {_RETRAIN}")
    return arrays


def load_residual(
    scene_dir: Path, model: mujoco.MjModel, *, scene_xml: Path | None = None, check_scene_xml: bool = True
) -> NumpyResidual | NumpyJointResidual:
    """Reads ``residual.json`` and ``residual.pt`` from a scene folder, checked against the scene's model.

    Both files are untrusted input: the metadata's fields and every tensor are checked (types, ranges, shapes
    against the metadata, finite values) before anything uses them.

    Args:
        scene_dir: The residual scene folder.
        model: The scene's compiled model.
        scene_xml: The MJCF ``model`` was compiled from (default ``scene_dir/scene.xml``); its sha256 must be the
            one in ``residual.json``, so that a residual is never applied to a scene edited since training.
        check_scene_xml: Check that hash (off for a caller that only reads the period and never applies the
            residual, such as training a new residual on an edited residual scene).

    Returns:
        The free-body residual, or the joint-space one (``grounder.residual.joint``) for an articulated scene.

    Raises:
        GrounderError: missing or malformed files, a residual trained for other bodies or another timestep, or a
            scene.xml that changed since training.
    """
    from grounder.residual.joint import JOINT_SPACE, NumpyJointResidual, check_joint_meta, history_of, joint_space

    scene_dir = Path(scene_dir)
    meta_path, weights_path = scene_dir / META_FILE, scene_dir / WEIGHTS_FILE
    raw = read_json_file(meta_path, _RETRAIN)
    meta = ResidualMeta.from_json(raw, meta_path)
    if meta.space == JOINT_SPACE:
        try:
            space = joint_space(model, history_of(meta.feature_names))
        except GrounderError as exc:  # a scene of other joints: name the residual it does not fit
            raise GrounderError(f"{meta_path}: a joint-space residual, not for this scene ({exc}); retrain it") from exc
        check_joint_meta(meta, space, str(meta_path))
        if meta.output_names != space.output_names:
            raise GrounderError(
                f"{meta_path}: outputs {shown(list(meta.output_names))} are not the scene's joints' "
                f"{shown(list(space.output_names))}; retrain it on this scene"
            )
        bodies: list[FreeBody] = []
    else:
        try:
            bodies = free_bodies(model)
        except GrounderError as exc:  # a scene of hinges and slides: name the residual it does not fit
            raise GrounderError(
                f"{meta_path}: a residual of free bodies {list(meta.bodies)}, not for this scene ({exc}); retrain it "
                "on this scene, or run without it (--no-residual)"
            ) from exc
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
    if check_scene_xml:
        xml = Path(scene_xml) if scene_xml is not None else scene_dir / "scene.xml"
        try:
            digest = file_sha256(xml)
        except OSError as exc:
            raise GrounderError(f"{xml}: could not be read ({exc.strerror or type(exc).__name__})") from exc
        if digest != meta.scene_xml_sha256:
            raise GrounderError(
                f"{xml}: {xml.name} changed since the residual was trained (sha256 {digest[:12]}..., "
                f"{META_FILE} has {meta.scene_xml_sha256[:12]}...); retrain with `image2sim residual train` "
                "or restore the scene"
            )
        if meta.scene_files_sha256 is not None:
            try:
                changed = _changed_scene_file(xml, meta.scene_files_sha256)
            except OSError as exc:
                raise GrounderError(
                    f"{xml}: a file it uses could not be read ({exc.strerror or type(exc).__name__})"
                ) from exc
            if changed is not None:
                raise GrounderError(
                    f"{xml}: {changed} since the residual was trained; retrain with `image2sim residual train` "
                    "or restore the scene"
                )
    arrays = _checked_state(load_weights_file(weights_path, _RETRAIN), meta, weights_path)
    if meta.space == JOINT_SPACE:
        return NumpyJointResidual(arrays, meta, space)
    return NumpyResidual(arrays, meta, bodies, model.opt.gravity)


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
