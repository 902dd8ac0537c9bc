"""The alignment behind `benchmarks/residual.py --twins`: a cube toss turned about the vertical, moved along the board
and with its faces relabelled is a motion MuJoCo also produces (level board, elliptic friction cone), and the
alignment finds the turn and relabelling back from the two starts alone."""

from __future__ import annotations

import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest

from grounder.calibration.fit import split_names
from grounder.core.importers import load_dair_pll_cube
from grounder.core.repeats import repeated_motion_indices, repeated_motions
from grounder.core.trajectory import Trajectory
from grounder.sim.rollout import simulate
from image2sim_common.rotations import quat_from_matrix, quat_to_mat

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from residual import _aligned, _alignment, _cube_rotations, _motion_distance, _yaw_m

# The nominal model of the real cube tosses, with the elliptic friction cone the calibration fits (a pyramidal
# cone's facets are fixed in the world, so a turned toss is not quite the same motion there).
NOMINAL_CUBE_XML = Path(__file__).resolve().parents[2] / "samples" / "cube_toss" / "cube.xml"
SHARED_CUBE = Path(__file__).resolve().parents[3] / "shared" / "data" / "cube_toss"


def _cube_model() -> mujoco.MjModel:
    spec = mujoco.MjSpec.from_file(str(NOMINAL_CUBE_XML))
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    return spec.compile()


def _toss(model: mujoco.MjModel, qpos0: np.ndarray, qvel0: np.ndarray, name: str) -> Trajectory:
    """Rolled out from the given start: 0.6 s at 148 Hz (a flight, a landing on an edge, a tumble)."""
    frames = 90
    start = Trajectory(
        time_s=np.arange(frames) / 148.0,
        qpos=np.tile(qpos0, (frames, 1)),
        qvel=np.tile(qvel0, (frames, 1)),
        name=name,
    )
    (rolled,) = simulate(model, [start])
    assert isinstance(rolled, Trajectory)
    return rolled


def _turned(
    qpos0: np.ndarray, qvel0: np.ndarray, yaw: np.ndarray, faces: np.ndarray, to_xy_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The start turned by `yaw` about the vertical through it, moved to to_xy_m, faces relabelled by `faces`."""
    qpos, qvel = qpos0.copy(), qvel0.copy()
    qpos[:2] = to_xy_m
    qpos[3:] = quat_from_matrix(yaw @ quat_to_mat(qpos0[3:]) @ faces)
    qvel[:3] = yaw @ qvel0[:3]
    qvel[3:] = faces.T @ qvel0[3:]  # body-frame rate in the relabelled frame
    return qpos, qvel


def test_a_turned_relabelled_toss_is_found_to_be_the_same_motion() -> None:
    model = _cube_model()
    faces_all = _cube_rotations()
    assert len(faces_all) == 24 and len({tuple(np.rint(f).ravel()) for f in faces_all}) == 24
    quat0 = np.array([0.9, 0.3, -0.2, 0.25])
    qpos0 = np.r_[0.1, -0.05, 0.2, quat0 / np.linalg.norm(quat0)]
    qvel0 = np.array([0.8, 0.3, -0.5, 4.0, -6.0, 2.5])
    original = _toss(model, qpos0, qvel0, "original")
    assert original.qpos[-1, 2] < 0.06 and np.ptp(original.qpos[:, 0]) > 0.1  # it landed and moved along the board

    yaw, faces = _yaw_m(np.radians(137.0)), faces_all[17]
    qpos_b, qvel_b = _turned(qpos0, qvel0, yaw, faces, np.array([-0.3, 0.25]))
    copy = _toss(model, qpos_b, qvel_b, "copy")

    # the alignment recovers the inverse turn and relabelling from the starts alone
    rot_a, rot_b = quat_to_mat(original.qpos[:, 3:]), quat_to_mat(copy.qpos[:, 3:])
    left_rad, back_yaw, back_faces = _alignment(rot_a[0], rot_b[0], faces_all)
    assert left_rad < 1e-6
    np.testing.assert_allclose(back_yaw, yaw.T, atol=1e-6)
    # and carries the whole copy back onto the original: MuJoCo's motion does not depend on the turn or the labels
    moved = _aligned(copy.qpos[:, :3], rot_b, copy.qpos[0, :2], original.qpos[0, :2], back_yaw, back_faces)
    position, rotation_deg = _motion_distance(original.qpos[:, :3], rot_a, *moved)
    assert position < 1e-6 and rotation_deg < 0.01, (position, rotation_deg)  # 4e-14 and 1e-6 deg measured

    # a toss started 1 m/s faster along the board is not the same motion
    other = _toss(model, qpos0, qvel0 + np.array([1.0, 0, 0, 0, 0, 0]), "other")
    rot_o = quat_to_mat(other.qpos[:, 3:])
    left_o, yaw_o, faces_o = _alignment(rot_a[0], rot_o[0], faces_all)
    moved_o = _aligned(other.qpos[:, :3], rot_o, other.qpos[0, :2], original.qpos[0, :2], yaw_o, faces_o)
    assert left_o < 1e-6 and _motion_distance(original.qpos[:, :3], rot_a, *moved_o)[0] > 0.5


def test_repeated_motions_groups_a_turned_copy_and_nothing_else() -> None:
    """`grounder.core.repeats` finds the copy by what a turn, a shift and relabelled faces leave alone (heights,
    vertical velocity, horizontal speed), and keeps a toss 5 cm/s faster apart: it is another motion."""
    model = _cube_model()
    quat0 = np.array([0.9, 0.3, -0.2, 0.25])
    qpos0 = np.r_[0.1, -0.05, 0.2, quat0 / np.linalg.norm(quat0)]
    qvel0 = np.array([0.8, 0.3, -0.5, 4.0, -6.0, 2.5])
    original = _toss(model, qpos0, qvel0, "toss_2")
    copy = _toss(
        model, *_turned(qpos0, qvel0, _yaw_m(np.radians(137.0)), _cube_rotations()[17], np.r_[-0.3, 0.25]), "toss_10"
    )
    faster = _toss(model, qpos0, qvel0 + np.r_[0.05, 0, 0, 0, 0, 0], "toss_3")
    spun = _toss(model, qpos0, qvel0 + np.r_[0, 0, 0, 0, 0, 1.0], "toss_4")
    assert repeated_motions([copy, faster, original, spun], model) == [("toss_2", "toss_10")]
    assert repeated_motion_indices([copy, faster, original, spun], model) == [(0, 2)]
    # the same start a few cm higher is another motion too; a copy with 0.1 mm of tracking noise is still a copy
    higher = _toss(model, qpos0 + np.r_[0, 0, 0.03, 0, 0, 0, 0], qvel0, "toss_5")
    noisy_qpos = original.qpos.copy()
    noisy_qpos[:, :3] += np.random.default_rng(0).normal(scale=1e-4, size=(original.num_steps, 3))
    noisy = Trajectory(time_s=original.time_s + 5.0, qpos=noisy_qpos, qvel=original.qvel, name="toss_6")
    assert repeated_motions([original, higher, noisy], model) == [("toss_2", "toss_6")]


def test_the_real_tosses_hold_18_copies_kept_on_one_side_of_the_split() -> None:
    if not (SHARED_CUBE / "tosses").is_dir():
        pytest.skip(f"real cube tosses not available ({SHARED_CUBE} is absent)")
    trajs = load_dair_pll_cube(SHARED_CUBE)
    groups = repeated_motions(trajs, mujoco.MjModel.from_xml_path(str(NOMINAL_CUBE_XML)))
    # the 18 pairs `benchmarks/residual.py --twins` found by aligning every pair of tosses (docs/residual_cube.md)
    assert groups[:3] == [("41", "505"), ("43", "507"), ("44", "508")] and len(groups) == 18
    assert all(len(g) == 2 for g in groups)
    train, val = split_names([t.name for t in trajs], 0.3, 0, groups)
    assert len(val) == 120 and len(train) == 280
    assert all(set(g) <= set(train) or set(g) <= set(val) for g in groups)
