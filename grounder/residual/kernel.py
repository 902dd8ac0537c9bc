"""The residuals' single-state corrections, compiled (numba): what ``grounder.Simulator.step`` runs.

``correct_free_bodies`` for the free-body residual (``grounder.residual.free_body``), ``correct_joints`` for the
joint-space one (``grounder.residual.joint``); both evaluate the gate and network with ``_gated_network``.

A single simulation steps MuJoCo in microseconds per model step. Evaluated from Python, the residual's correction
(features, gate, a 64-wide network, the energy cap) cost 14-60 us per period depending on the machine, most of it
the interpreter and numpy's per-call overhead, which took it over the issue's 50% of a single simulation's step
time on slower machines. Compiled, the same function is a few microseconds.

Each is the same function as its vectorised numpy reference (``NumpyResidual.correct``, which the tests check it
against to 1e-12 m and 1e-10 m/s; ``NumpyJointResidual.correct``). For free bodies: the correction of the period's
starting state ``(qpos0, qvel0)``, applied to MuJoCo's prediction ``(qpos, qvel)`` in place, then the energy cap.
The network is not evaluated where the gate is already exactly 0 (at rest, outside the feature ranges, or far from
the training states), and there the state is left exactly as MuJoCo made it (the reference renormalises the
quaternion, a change of about 1e-16).

Compiled on first use and cached on disk (numba's ``cache=True``: next to this file, or in the user's cache
directory where that is not writable), so only the first use on a machine pays the compilation (seconds). Where
neither is writable, each process compiles on its first use instead.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numba
import numpy as np


def _jit(func: Callable[..., Any]) -> Any:
    """numba's ``njit`` (no Python objects, the GIL released, numpy's rules for division by 0), cached on disk
    where numba finds a writable folder for it; where it finds none (a read-only install and user cache, which
    numba reports by raising ``RuntimeError`` when the function is defined) compiled anew in each process."""
    try:
        return numba.njit(cache=True, nogil=True, error_model="numpy")(func)
    except RuntimeError:
        return numba.njit(nogil=True, error_model="numpy")(func)


# order of grounder.residual.free_body.FreeKernelArgs.body_f's columns
BODY_F_RADIUS, BODY_F_COVERAGE, BODY_F_HALF_MASS, BODY_F_MASS, BODY_F_INERTIA = 0, 1, 2, 3, 4
# order of grounder.residual.free_body.FreeKernelArgs.consts
CONST_REST_LO, CONST_REST_SPAN, CONST_AIR_LO, CONST_AIR_SPAN, CONST_FRACTION, CONST_GRAVITY = 0, 1, 2, 3, 4, 5


@_jit
def _smoothstep(x: float) -> float:
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    return x * x * (3.0 - 2.0 * x)


@_jit
def _tanh(x: float) -> float:
    """tanh from one exp: a third of libm's tanh time here (the network's ~140 tanh were a third of its cost),
    within 2.3e-16 of it in absolute terms (checked from 1e-300 to 1e4 either side of 0)."""
    e = math.exp(-2.0 * abs(x))
    return math.copysign((1.0 - e) / (1.0 + e), x)


@_jit
def _energy(
    vx: float,
    vy: float,
    vz: float,
    wx: float,
    wy: float,
    wz: float,
    px: float,
    py: float,
    pz: float,
    body_f: np.ndarray,
    consts: np.ndarray,
) -> tuple[float, float]:
    """(kinetic, potential) energy of a free body, joules (body_f: one row of FreeKernelArgs.body_f)."""
    i = BODY_F_INERTIA
    rotational = (
        wx * (body_f[i] * wx + body_f[i + 1] * wy + body_f[i + 2] * wz)
        + wy * (body_f[i + 3] * wx + body_f[i + 4] * wy + body_f[i + 5] * wz)
        + wz * (body_f[i + 6] * wx + body_f[i + 7] * wy + body_f[i + 8] * wz)
    )
    kinetic = body_f[BODY_F_HALF_MASS] * (vx * vx + vy * vy + vz * vz) + rotational
    g = CONST_GRAVITY
    potential = -body_f[BODY_F_MASS] * (px * consts[g] + py * consts[g + 1] + pz * consts[g + 2])
    return kinetic, potential


@_jit
def _gated_network(
    feats: np.ndarray,
    gate: float,
    ranges: np.ndarray,
    first: np.ndarray,
    mids: np.ndarray,
    last: np.ndarray,
    centres: np.ndarray,
    coverage_dist: float,
    hint: np.ndarray,
    out: np.ndarray,
) -> float:
    """The gate times its coverage fades, and the bounded network output of one state.

    ``feats`` (F + 1,): the raw features and a trailing 1; ``gate``: the gate so far (at rest, output gain);
    ``ranges`` (3, F): feature range low, high, 1 / fade margin; ``first`` (F + 1, H + F), ``mids`` (L, H + 1, H),
    ``last`` (H + 2, O): the layers as ``[x, 1] @ layer`` (``first`` also gives the standardised features z;
    ``last``'s final row is the output's bound); ``centres`` (F, K): the coverage centres, standardised; ``hint``
    (1,) int64: the centre nearest to the last state that needed the search, updated here (for speed only: results
    never depend on it). Returns the gate faded outside the feature ranges and far from the training states; where
    that is exactly 0 the network is not evaluated and ``out`` (O,) is left as it was, else ``out`` is the bounded
    output ``bound * tanh(...)`` (the gate not applied).
    """
    num_feats = ranges.shape[1]
    for f in range(num_feats):  # fading over the margin beyond each feature's training range
        if feats[f] < ranges[0, f]:
            gate *= 1.0 - _smoothstep((ranges[0, f] - feats[f]) * ranges[2, f])
        elif feats[f] > ranges[1, f]:
            gate *= 1.0 - _smoothstep((feats[f] - ranges[1, f]) * ranges[2, f])
    if gate == 0.0:
        return 0.0
    # Matrix-vector products as sums of scaled rows (x @ W, W row-major): every output accumulates in its own
    # lane, so the inner loops vectorise without reordering any sum. The first one, with [f, 1], gives the first
    # layer's pre-activations and the standardised features z.
    hidden = first.shape[1] - num_feats
    pre = np.zeros(first.shape[1])
    for c in range(num_feats + 1):
        x = feats[c]
        for r in range(pre.shape[0]):
            pre[r] += x * first[c, r]
    # Distance to the nearest coverage centre (standardised units). The fade is exactly 1 within coverage_dist,
    # so when the centre nearest to the last state seen (``hint``) is that close no other is needed.
    nearest_sq = 0.0
    for f in range(num_feats):
        diff = pre[hidden + f] - centres[f, hint[0]]
        nearest_sq += diff * diff
    if nearest_sq > coverage_dist * coverage_dist:
        dist_sq = np.zeros(centres.shape[1])
        for f in range(num_feats):
            z = pre[hidden + f]
            for k in range(dist_sq.shape[0]):
                diff = z - centres[f, k]
                dist_sq[k] += diff * diff
        nearest = 0
        for k in range(1, dist_sq.shape[0]):
            if dist_sq[k] < dist_sq[nearest]:
                nearest = k
        hint[0] = nearest
        nearest_sq = dist_sq[nearest]
    gate *= 1.0 - _smoothstep(math.sqrt(nearest_sq) / coverage_dist - 1.0)
    if gate == 0.0:
        return 0.0
    act = np.empty(hidden)
    for r in range(hidden):
        act[r] = _tanh(pre[r])
    act_next = np.empty(hidden)
    for layer in range(mids.shape[0]):
        for r in range(hidden):
            act_next[r] = mids[layer, hidden, r]
        for c in range(hidden):
            x = act[c]
            for r in range(hidden):
                act_next[r] += x * mids[layer, c, r]
        for r in range(hidden):
            act[r] = _tanh(act_next[r])
    for r in range(out.shape[0]):
        out[r] = last[hidden, r]
    for c in range(hidden):
        x = act[c]
        for r in range(out.shape[0]):
            out[r] += x * last[c, r]
    for r in range(out.shape[0]):
        out[r] = last[hidden + 1, r] * _tanh(out[r])
    return gate


@_jit
def correct_free_bodies(
    qpos0: np.ndarray,
    qvel0: np.ndarray,
    qpos: np.ndarray,
    qvel: np.ndarray,
    body_i: np.ndarray,
    body_f: np.ndarray,
    out_gain: np.ndarray,
    ranges: np.ndarray,
    points: np.ndarray,
    first: np.ndarray,
    mids: np.ndarray,
    last: np.ndarray,
    centres: np.ndarray,
    consts: np.ndarray,
    hints: np.ndarray,
) -> None:
    """Corrects MuJoCo's prediction ``(qpos (nq,), qvel (nv,))`` after one period from ``(qpos0, qvel0)`` in place
    (the other arguments: the fields of ``grounder.residual.free_body.FreeKernelArgs``, in order)."""
    feats = np.empty(ranges.shape[2] + 1)
    feats[-1] = 1.0
    out = np.empty(last.shape[2])
    for b in range(body_i.shape[0]):
        p, d, num_points = body_i[b, 0], body_i[b, 1], body_i[b, 2]
        bf = body_f[b]
        px, py, pz = qpos0[p], qpos0[p + 1], qpos0[p + 2]
        qw, qx, qy, qz = qpos0[p + 3], qpos0[p + 4], qpos0[p + 5], qpos0[p + 6]
        vx, vy, vz, wx, wy, wz = qvel0[d], qvel0[d + 1], qvel0[d + 2], qvel0[d + 3], qvel0[d + 4], qvel0[d + 5]
        # rotation matrix (body -> world)
        r00, r01, r02 = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)
        r10, r11, r12 = 2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)
        r20, r21, r22 = 2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)
        lowest = np.inf
        for k in range(num_points):
            lowest = min(lowest, points[b, k, 0] * r20 + points[b, k, 1] * r21 + points[b, k, 2] * r22)
        clearance = pz + lowest
        # at-rest gate: exactly 0 for a slow body near the support
        speed = math.sqrt(vx * vx + vy * vy + vz * vz) + bf[BODY_F_RADIUS] * math.sqrt(wx * wx + wy * wy + wz * wz)
        moving = _smoothstep((speed - consts[CONST_REST_LO]) / consts[CONST_REST_SPAN])
        flying = _smoothstep((clearance - consts[CONST_AIR_LO]) / consts[CONST_AIR_SPAN])
        gate = (1.0 - (1.0 - moving) * (1.0 - flying)) * out_gain[b]
        if gate == 0.0:  # at rest (or switched off): exactly no correction
            continue
        feats[0], feats[1], feats[2], feats[3], feats[4] = clearance, pz, r20, r21, r22
        feats[5] = r00 * vx + r10 * vy + r20 * vz
        feats[6] = r01 * vx + r11 * vy + r21 * vz
        feats[7] = r02 * vx + r12 * vy + r22 * vz
        feats[8], feats[9], feats[10] = wx, wy, wz
        gate = _gated_network(
            feats,
            gate,
            ranges[b],
            first[b],
            mids[b],
            last[b],
            centres[b],
            bf[BODY_F_COVERAGE],
            hints[b : b + 1],
            out,
        )
        if gate == 0.0:
            continue
        c0, c1, c2, c3, c4, c5 = out[0], out[1], out[2], out[3], out[4], out[5]
        c6, c7, c8, c9, c10, c11 = out[6], out[7], out[8], out[9], out[10], out[11]

        kinetic, potential = _energy(vx, vy, vz, wx, wy, wz, px, py, pz, bf, consts)
        e_start = kinetic + potential
        sx, sy, sz = qpos[p], qpos[p + 1], qpos[p + 2]
        sw, sqx, sqy, sqz = qpos[p + 3], qpos[p + 4], qpos[p + 5], qpos[p + 6]
        vx, vy, vz, wx, wy, wz = qvel[d], qvel[d + 1], qvel[d + 2], qvel[d + 3], qvel[d + 4], qvel[d + 5]
        kinetic, potential = _energy(vx, vy, vz, wx, wy, wz, sx, sy, sz, bf, consts)
        e_sim = kinetic + potential
        # the gated correction, rotated to the world by the starting orientation
        sx += gate * (r00 * c0 + r01 * c1 + r02 * c2)
        sy += gate * (r10 * c0 + r11 * c1 + r12 * c2)
        sz += gate * (r20 * c0 + r21 * c1 + r22 * c2)
        ax = gate * (r00 * c3 + r01 * c4 + r02 * c5)
        ay = gate * (r10 * c3 + r11 * c4 + r12 * c5)
        az = gate * (r20 * c3 + r21 * c4 + r22 * c5)
        vx += gate * (r00 * c6 + r01 * c7 + r02 * c8)
        vy += gate * (r10 * c6 + r11 * c7 + r12 * c8)
        vz += gate * (r20 * c6 + r21 * c7 + r22 * c8)
        wx += gate * c9
        wy += gate * c10
        wz += gate * c11
        angle = math.sqrt(ax * ax + ay * ay + az * az)
        half_sin = 0.5 - angle * angle / 48.0 if angle < 1e-6 else math.sin(0.5 * angle) / angle
        dw, dx, dy, dz = math.cos(0.5 * angle), ax * half_sin, ay * half_sin, az * half_sin
        nw = dw * sw - dx * sqx - dy * sqy - dz * sqz
        nx = dw * sqx + dx * sw + dy * sqz - dz * sqy
        ny = dw * sqy - dx * sqz + dy * sw + dz * sqx
        nz = dw * sqz + dx * sqy - dy * sqx + dz * sw
        norm = math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
        # energy cap (grounder.residual.free_body.cap_energy)
        fraction = consts[CONST_FRACTION]
        cap = max(e_sim, min(e_start, e_sim + fraction * max(e_start - e_sim, 0.0)))
        kinetic, potential = _energy(vx, vy, vz, wx, wy, wz, sx, sy, sz, bf, consts)
        if kinetic + potential > cap + 1e-12:
            scale = math.sqrt(max(cap - potential, 0.0) / max(kinetic, 1e-300))
            vx, vy, vz, wx, wy, wz = scale * vx, scale * vy, scale * vz, scale * wx, scale * wy, scale * wz
        qpos[p], qpos[p + 1], qpos[p + 2] = sx, sy, sz
        qpos[p + 3], qpos[p + 4], qpos[p + 5], qpos[p + 6] = nw / norm, nx / norm, ny / norm, nz / norm
        qvel[d], qvel[d + 1], qvel[d + 2], qvel[d + 3], qvel[d + 4], qvel[d + 5] = vx, vy, vz, wx, wy, wz


@_jit
def correct_joints(
    qpos0: np.ndarray,
    qvel0: np.ndarray,
    qpos: np.ndarray,
    qvel: np.ndarray,
    ctrl: np.ndarray,
    ctrl_prev: np.ndarray,
    joints: np.ndarray,
    consts: np.ndarray,
    out_gain: np.ndarray,
    ranges: np.ndarray,
    first: np.ndarray,
    mids: np.ndarray,
    last: np.ndarray,
    centres: np.ndarray,
    ints: np.ndarray,
) -> None:
    """The joint-space residual's correction of MuJoCo's prediction ``(qpos, qvel)`` after one period from
    ``(qpos0, qvel0)`` under the control ``ctrl`` (nu,), the earlier periods' controls ``ctrl_prev`` (history * nu,
    most recent first; empty: ``ctrl`` held) (in place; the other arguments: the fields of
    ``grounder.residual.joint.JointKernelArgs``, in order).

    Same function as ``grounder.residual.joint.NumpyJointResidual.correct``; it stops where the gate is 0, so a
    mechanism at rest costs one test.
    """
    num_joints = joints.shape[0]
    speed = 0.0
    for j in range(num_joints):
        speed = max(speed, abs(qvel0[joints[j, 1]]))
    gate = out_gain[0] * _smoothstep((speed - consts[0]) / consts[1])
    if gate == 0.0:  # every joint slower than the rest threshold (or switched off): exactly no correction
        return
    feats = np.empty(ranges.shape[1] + 1)
    feats[-1] = 1.0
    i = 0
    for j in range(num_joints):
        q = qpos0[joints[j, 0]]
        if joints[j, 2]:
            feats[i], feats[i + 1] = math.sin(q), math.cos(q)
            i += 2
        else:
            feats[i] = q
            i += 1
    for j in range(num_joints):
        feats[i + j] = qvel0[joints[j, 1]]
    i += num_joints
    for u in range(ctrl.shape[0]):
        feats[i + u] = ctrl[u]
    i += ctrl.shape[0]
    if ctrl_prev.shape[0] == 0:  # not given: this period's control, held through the history as well
        for k in range(ints[0]):
            for u in range(ctrl.shape[0]):
                feats[i + k * ctrl.shape[0] + u] = ctrl[u]
    else:
        for u in range(ctrl_prev.shape[0]):
            feats[i + u] = ctrl_prev[u]
    out = np.empty(last.shape[1])
    gate = _gated_network(feats, gate, ranges, first, mids, last, centres, consts[2], ints[1:2], out)
    if gate == 0.0:
        return
    for j in range(num_joints):
        qpos[joints[j, 0]] += gate * out[j]
        qvel[joints[j, 1]] += gate * out[num_joints + j]
