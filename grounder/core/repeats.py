"""Trajectories that record the same motion twice, and train/validation splits that keep such copies together.

A copy on both sides of a split lets a model that memorises its training data look better on validation than it
is. The real cube tosses hold 18 such pairs (`docs/residual_cube.md`, "Twin tosses"): a toss stored a second time
turned about the vertical, moved along the board and with the cube's faces relabelled. So a copy is recognised by
what such a change leaves alone, on a level floor (the plane normal to the model's gravity):

- every free body's height above it (its centre, metres), vertical velocity and horizontal speed (m/s);
- every other joint's position and velocity, and the controls, as they are (they have no such symmetry);
- the sample times from the first.

Two trajectories are copies when they have the same number of samples at the same times, their free bodies'
heights differ by at most ``height_tol_m`` and velocities by at most ``speed_tol_m_s`` (root mean square over
the samples), and everything else agrees within ``other_tol`` (largest difference). The defaults take the tosses'
copies, which agree to rounding, and a copy with 0.1 mm of noise on its positions, while different tosses stay
apart: the nearest two differ in height by 1.4 mm and in speed by 28 mm/s (root mean square). Bodies at rest at the
same height for the same time, wherever they stand, are the same motion too, and are grouped as such.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from typing import TypeVar

import mujoco
import numpy as np
from scipy.spatial import cKDTree

from grounder.core.trajectory import Trajectory, _natural_key

HEIGHT_TOL_M = 2e-4
SPEED_TOL_M_S = 5e-3
OTHER_TOL = 1e-9

H = TypeVar("H", bound=Hashable)


def _up_unit(model: mujoco.MjModel) -> np.ndarray:
    g = np.asarray(model.opt.gravity, dtype=np.float64)
    norm = float(np.linalg.norm(g))
    return -g / norm if norm > 0 else np.array([0.0, 0.0, 1.0])


def _signature(traj: Trajectory, model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(heights (T, F) m, free-body velocities (T, 2F) m/s, everything else (T, K)) of one trajectory."""
    up = _up_unit(model)
    heights, speeds, others = [], [], []
    free_q: set[int] = set()
    free_v: set[int] = set()
    for j in range(model.njnt):
        if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE:
            continue
        qa, va = int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j])
        free_q.update(range(qa, qa + 7))
        free_v.update(range(va, va + 6))
        v_m_s = traj.qvel[:, va : va + 3]
        v_up = v_m_s @ up
        heights.append(traj.qpos[:, qa : qa + 3] @ up)
        speeds += [v_up, np.linalg.norm(v_m_s - v_up[:, None] * up, axis=1)]
    others += [traj.qpos[:, i] for i in range(traj.nq) if i not in free_q]
    others += [traj.qvel[:, i] for i in range(traj.nv) if i not in free_v]
    if traj.ctrl is not None:
        others += list(traj.ctrl.T)
    others.append(traj.time_s - traj.time_s[0])
    t = traj.num_steps

    def stack(cols: list[np.ndarray]) -> np.ndarray:
        return np.stack(cols, axis=1) if cols else np.zeros((t, 0))

    return stack(heights), stack(speeds), stack(others)


def repeated_motions(trajs: Sequence[Trajectory], model: mujoco.MjModel) -> list[tuple[str, ...]]:
    """Groups of two or more trajectory names that record the same motion (module docstring; default tolerances),
    each in natural order, the groups in the natural order of their first names. Trajectories must fit ``model``
    (same nq, nv)."""
    found = [tuple(sorted((trajs[i].name for i in g), key=_natural_key)) for g in repeated_motion_indices(trajs, model)]
    return sorted(found, key=lambda g: _natural_key(g[0]))


def repeated_motion_indices(
    trajs: Sequence[Trajectory],
    model: mujoco.MjModel,
    *,
    height_tol_m: float = HEIGHT_TOL_M,
    speed_tol_m_s: float = SPEED_TOL_M_S,
    other_tol: float = OTHER_TOL,
) -> list[tuple[int, ...]]:
    """`repeated_motions` by position in ``trajs`` (names need not be unique): groups in ascending order."""
    sigs = [_signature(t, model) for t in trajs]
    parent = list(range(len(trajs)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    by_length: dict[tuple[int, int, int], list[int]] = {}
    for i, (h, _, o) in enumerate(sigs):
        by_length.setdefault((h.shape[0], h.shape[1], o.shape[1]), []).append(i)
    for members in by_length.values():
        if len(members) < 2:
            continue
        # A copy's per-column means differ by no more than its tolerances (|mean d| <= rms d <= max |d|): a
        # k-d tree over the means, scaled by them, finds the candidates without comparing every pair.
        keys = np.stack(
            [
                np.concatenate(
                    [
                        sigs[i][0].mean(axis=0) / height_tol_m,
                        sigs[i][1].mean(axis=0) / speed_tol_m_s,
                        sigs[i][2].mean(axis=0) / max(other_tol, 1e-300),
                    ]
                )
                for i in members
            ]
        )
        candidates = cKDTree(keys).query_pairs(1.0 + 1e-9, p=np.inf)  # keys hold at least the times' column
        for a, b in sorted(candidates):
            (ha, sa, oa), (hb, sb, ob) = sigs[members[a]], sigs[members[b]]
            same = (
                (ha.size == 0 or float(np.sqrt(np.mean((ha - hb) ** 2, axis=0)).max()) <= height_tol_m)
                and (sa.size == 0 or float(np.sqrt(np.mean((sa - sb) ** 2, axis=0)).max()) <= speed_tol_m_s)
                and (oa.size == 0 or float(np.abs(oa - ob).max()) <= other_tol)
            )
            if same:
                parent[root(members[a])] = root(members[b])
    groups: dict[int, list[int]] = {}
    for i in range(len(trajs)):
        groups.setdefault(root(i), []).append(i)
    return sorted(tuple(g) for g in groups.values() if len(g) > 1)


def split_keeping_together(
    ordered: Sequence[H], count: int, together: Sequence[Sequence[H]] = ()
) -> tuple[list[H], list[H]]:
    """(first, rest): the first ``count`` of ``ordered`` (a shuffled order), except that each group in ``together``
    goes whole to the side the shuffle put its first member (as the group lists them) on: as likely the one side as
    the other, where following whichever member comes first in ``ordered`` would favour ``first``. When that leaves
    a side empty though there are at least two units (groups and lone names), the unit that comes last on the full
    side moves over, so both sides keep at least one; a single unit goes to ``rest``. Each side keeps the order of
    ``ordered``."""
    position = {name: i for i, name in enumerate(ordered)}
    unit_of = {name: name for name in ordered}
    for group in together:
        members = [n for n in group if n in position]
        if members:
            lead = members[0]
            for n in members:
                unit_of[n] = lead
    first_side = {unit_of[n] for n in ordered if position[unit_of[n]] < count}
    units = list(dict.fromkeys(unit_of[n] for n in ordered))
    if len(units) < 2:
        first_side = set()  # one motion only: nothing to hold out, all of it on the rest side
    elif len(first_side) in (0, len(units)):
        # Both sides must keep one: move the last unit of the full side over.
        if first_side:
            first_side.discard(units[-1])
        else:
            first_side.add(units[-1])
    first = [n for n in ordered if unit_of[n] in first_side]
    rest = [n for n in ordered if unit_of[n] not in first_side]
    return first, rest


def describe_repeats(groups: Sequence[Sequence[str]]) -> str:
    """The start of one line naming the copies: ``N groups of trajectories record the same motion (...): 41=505,
    43=507, ...`` (the first ten groups); the caller says what it did with them."""
    listed = ", ".join("=".join(g) for g in groups[:10]) + (f" and {len(groups) - 10} more" if len(groups) > 10 else "")
    return (
        f"{len(groups)} {'group' if len(groups) == 1 else 'groups'} of trajectories record the same motion (up to a "
        f"turn about the vertical and a shift): {listed}"
    )


def describe_repeated_indices(trajs: Sequence[Trajectory], groups: Sequence[Sequence[int]]) -> str:
    """`describe_repeats` for groups of indices into ``trajs`` (an unnamed trajectory shows as ``#i``)."""
    return describe_repeats([[trajs[i].name or f"#{i}" for i in g] for g in groups])
