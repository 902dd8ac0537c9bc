"""Tests for the trajectory file format (grounder/core/trajectory.py)."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest

from grounder import (
    Trajectory,
    TrajectoryError,
    load_trajectories,
    load_trajectory,
    save_trajectories,
    save_trajectory,
    validate_against_model,
)

# One free-joint body (nq 7, nv 6) and one hinge with a motor (nq 1, nv 1, nu 1).
SCENE_XML = """
<mujoco>
  <worldbody>
    <body name="box" pos="0 0 1">
      <freejoint name="box_free"/>
      <geom type="box" size="0.05 0.05 0.05" mass="0.2"/>
    </body>
    <body name="arm" pos="1 0 0.5">
      <joint name="arm_hinge" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02" mass="0.1"/>
    </body>
  </worldbody>
  <actuator>
    <motor name="arm_motor" joint="arm_hinge"/>
  </actuator>
</mujoco>
"""

BALL_XML = """
<mujoco>
  <worldbody>
    <body name="pendulum">
      <joint name="pivot" type="ball"/>
      <geom type="sphere" pos="0 0 -0.3" size="0.05"/>
    </body>
  </worldbody>
</mujoco>
"""

NQ, NV, NU = 8, 7, 1


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    m = mujoco.MjModel.from_xml_string(SCENE_XML)
    assert (m.nq, m.nv, m.nu) == (NQ, NV, NU)
    return m


def make_traj(
    name: str = "toss", num_steps: int = 6, with_ctrl: bool = True, seed: int = 0, nq: int = NQ
) -> Trajectory:
    """A valid trajectory for the scene above, with random unit quaternions and arbitrary values."""
    rng = np.random.default_rng(seed)
    qpos = rng.normal(size=(num_steps, nq))
    quat = rng.normal(size=(num_steps, 4))
    qpos[:, 3:7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    return Trajectory(
        time_s=0.5 + 0.01 * np.arange(num_steps) + rng.uniform(0, 1e-3, num_steps),
        qpos=qpos,
        qvel=rng.normal(size=(num_steps, NV)),
        ctrl=rng.normal(size=(num_steps, NU)) if with_ctrl else None,
        name=name,
    )


def raw_arrays(num_steps: int = 4) -> dict[str, Any]:
    """Valid file contents, to be spoiled one key at a time."""
    qpos = np.zeros((num_steps, NQ))
    qpos[:, 3] = 1.0
    return {
        "time": 0.1 * np.arange(num_steps),
        "qpos": qpos,
        "qvel": np.zeros((num_steps, NV)),
        "ctrl": np.zeros((num_steps, NU)),
    }


def assert_same(a: Trajectory, b: Trajectory) -> None:
    assert a.name == b.name
    for field in ("time_s", "qpos", "qvel", "ctrl"):
        x, y = getattr(a, field), getattr(b, field)
        if x is None or y is None:
            assert x is None and y is None, field
            continue
        assert x.dtype == y.dtype == np.float64
        assert x.tobytes() == y.tobytes(), field  # bit-exact


# --- the dataclass ---------------------------------------------------------------------------------------


def test_properties() -> None:
    t = Trajectory(
        time_s=np.array([1.0, 1.5, 3.0]),
        qpos=np.zeros((3, 2), dtype=np.int32),
        qvel=np.zeros((3, 1)),
        name="x",
    )
    assert (t.num_steps, t.nq, t.nv, t.nu) == (3, 2, 1, 0)
    assert t.duration_s == pytest.approx(2.0, abs=0.0)
    assert t.qpos.dtype == np.float64
    assert "num_steps=3" in repr(t)


def test_arrays_are_read_only_copies() -> None:
    qpos = np.zeros((2, 1))
    t = Trajectory(time_s=np.array([0.0, 1.0]), qpos=qpos, qvel=np.zeros((2, 1)))
    qpos[0, 0] = 5.0
    assert t.qpos[0, 0] == 0.0
    with pytest.raises(ValueError, match="read-only"):
        t.qpos[0, 0] = 1.0


# --- round trips -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("with_ctrl", [True, False])
def test_round_trip_single(tmp_path: Path, with_ctrl: bool) -> None:
    traj = make_traj("toss_03", with_ctrl=with_ctrl)
    written = save_trajectory(traj, tmp_path / "toss_03.npz")
    assert written == tmp_path / "toss_03.npz"
    with np.load(written, allow_pickle=False) as archive:
        expected = {"time", "qpos", "qvel"} | ({"ctrl"} if with_ctrl else set())
        assert set(archive.files) == expected
    assert_same(load_trajectory(written), traj)


def test_save_adds_suffix_and_creates_parent(tmp_path: Path) -> None:
    written = save_trajectory(make_traj("a"), tmp_path / "new" / "a")
    assert written == tmp_path / "new" / "a.npz"
    assert written.is_file()


def test_atomic_save_leaves_no_temp_files(tmp_path: Path) -> None:
    save_trajectory(make_traj("a", seed=1), tmp_path / "a.npz")
    save_trajectory(make_traj("a", seed=2), tmp_path / "a.npz")  # overwrite
    save_trajectories([make_traj("b"), make_traj("c")], tmp_path / "dir")
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")) == [
        "a.npz",
        "dir",
        "dir/b.npz",
        "dir/c.npz",
    ]
    assert_same(load_trajectory(tmp_path / "a.npz"), make_traj("a", seed=2))


def test_atomic_save_failure_keeps_old_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = save_trajectory(make_traj("a", seed=1), tmp_path / "a.npz")

    def broken_savez(*args: object, **kwargs: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", broken_savez)
    with pytest.raises(OSError, match="disk full"):
        save_trajectory(make_traj("a", seed=2), path)
    monkeypatch.undo()
    assert [p.name for p in tmp_path.iterdir()] == ["a.npz"]
    assert_same(load_trajectory(path), make_traj("a", seed=1))


@pytest.mark.parametrize("with_ctrl", [True, False])
def test_round_trip_directory_natural_order(tmp_path: Path, model: mujoco.MjModel, with_ctrl: bool) -> None:
    names = ["toss_10", "toss_2", "toss_1", "Toss_3"]
    trajs = [make_traj(n, seed=i, with_ctrl=with_ctrl) for i, n in enumerate(names)]
    out = save_trajectories(trajs, tmp_path / "traj")
    assert out == tmp_path / "traj"
    (out / "notes.txt").write_text("ignored")
    (out / "sub.npz").mkdir()  # a folder named like a trajectory is not one

    loaded = load_trajectories(out, model=model)
    assert [t.name for t in loaded] == ["toss_1", "toss_2", "Toss_3", "toss_10"]
    by_name = {t.name: t for t in trajs}
    for t in loaded:
        assert_same(t, by_name[t.name])


def test_extra_keys_are_ignored(tmp_path: Path) -> None:
    arrays = raw_arrays()
    np.savez(tmp_path / "x.npz", **arrays, comment=np.array(["hello"]), fps=np.array(30))
    traj = load_trajectory(tmp_path / "x.npz")
    assert traj.name == "x"
    np.testing.assert_array_equal(traj.qpos, arrays["qpos"])


def test_simulated_trajectory_fits_model(tmp_path: Path, model: mujoco.MjModel) -> None:
    """A trajectory recorded from MuJoCo itself, coarser than the timestep, passes every check."""
    data = mujoco.MjData(model)
    data.qvel[:3] = [0.5, 0.0, 2.0]
    data.qvel[3:6] = [3.0, -1.0, 7.0]
    rows = []
    for step in range(50):
        data.ctrl[0] = np.sin(step * 0.1)
        if step % 5 == 0:
            rows.append((data.time, data.qpos.copy(), data.qvel.copy(), data.ctrl.copy()))
        mujoco.mj_step(model, data)
    time_s, qpos, qvel, ctrl = (np.array(col) for col in zip(*rows, strict=True))
    traj = Trajectory(time_s=time_s, qpos=qpos, qvel=qvel, ctrl=ctrl, name="sim")
    validate_against_model(traj, model)
    save_trajectories([traj], tmp_path)
    (loaded,) = load_trajectories(tmp_path, model=model)
    assert loaded.duration_s == pytest.approx(45 * model.opt.timestep)


# --- validation errors -----------------------------------------------------------------------------------


def _set(key: str, value: object) -> Callable[[dict[str, np.ndarray]], None]:
    def spoil(arrays: dict[str, np.ndarray]) -> None:
        arrays[key] = np.asarray(value)

    return spoil


def _nan_qpos(arrays: dict[str, np.ndarray]) -> None:
    arrays["qpos"][2, 5] = np.nan


def _inf_qvel(arrays: dict[str, np.ndarray]) -> None:
    arrays["qvel"][1, 0] = np.inf


def _drop(key: str) -> Callable[[dict[str, np.ndarray]], None]:
    def spoil(arrays: dict[str, np.ndarray]) -> None:
        del arrays[key]

    return spoil


FILE_ERRORS = {
    "non_increasing_time": (_set("time", [0.0, 0.2, 0.1, 0.3]), "time[2]=0.1 <= time[1]=0.2"),
    "equal_timestamps": (_set("time", [0.0, 0.1, 0.1, 0.3]), "strictly increasing"),
    "nan_in_qpos": (_nan_qpos, "qpos[2, 5]=nan"),
    "inf_in_qvel": (_inf_qvel, "qvel[1, 0]=inf"),
    "wrong_ndim_time": (_set("time", np.zeros((4, 1))), "'time' must have shape (T,)"),
    "wrong_ndim_qpos": (_set("qpos", np.zeros(4)), "'qpos' must have shape (T, nq)"),
    "mismatched_T": (_set("qvel", np.zeros((3, NV))), "'qvel' has 3 rows but 'time' has 4"),
    "mismatched_T_ctrl": (_set("ctrl", np.zeros((5, NU))), "'ctrl' has 5 rows"),
    "too_short": (
        lambda a: a.update(time=a["time"][:1], qpos=a["qpos"][:1], qvel=a["qvel"][:1], ctrl=a["ctrl"][:1]),
        "at least 2 time samples",
    ),
    "missing_time": (_drop("time"), "missing required key(s) ['time']"),
    "missing_qvel": (_drop("qvel"), "missing required key(s) ['qvel']"),
    "string_dtype": (_set("qpos", np.full((4, NQ), "1.0")), "'qpos' must hold real numbers"),
    "bool_dtype": (_set("ctrl", np.ones((4, NU), dtype=bool)), "'ctrl' must hold real numbers"),
    "complex_dtype": (_set("qvel", np.ones((4, NV), dtype=complex)), "'qvel' must hold real numbers"),
    # was a traceback from an integer cast of the step count, deep in the simulation
    "time_beyond_1e10": (_set("time", [0.0, 0.1, 0.2, 1e300]), "'time[3]' is 1e+300, beyond the 1e+10"),
}


@pytest.mark.parametrize("spoil, expected", FILE_ERRORS.values(), ids=FILE_ERRORS.keys())
def test_load_rejects_bad_file(tmp_path: Path, spoil: Callable[[dict[str, np.ndarray]], None], expected: str) -> None:
    arrays = raw_arrays()
    spoil(arrays)
    path = tmp_path / "toss_03.npz"
    np.savez(path, **arrays)
    with pytest.raises(TrajectoryError, match=r"toss_03\.npz") as info:
        load_trajectory(path)
    assert expected in str(info.value)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    "spoil, expected",
    [v for k, v in FILE_ERRORS.items() if not k.startswith("missing")],
    ids=[k for k in FILE_ERRORS if not k.startswith("missing")],
)
def test_constructor_rejects_bad_arrays(spoil: Callable[[dict[str, np.ndarray]], None], expected: str) -> None:
    arrays = raw_arrays()
    spoil(arrays)
    with pytest.raises(TrajectoryError, match="trajectory 'bad'") as info:
        Trajectory(time_s=arrays["time"], qpos=arrays["qpos"], qvel=arrays["qvel"], ctrl=arrays["ctrl"], name="bad")
    assert expected in str(info.value)


_CANARY_FIRED: list[str] = []


def _canary(message: str) -> None:
    _CANARY_FIRED.append(message)


class _Canary:
    """Unpickling this would call _canary: proof that loading executed pickled code."""

    def __reduce__(self) -> tuple[Callable[[str], None], tuple[str]]:
        return _canary, ("unpickled!",)


def test_pickled_object_array_is_refused_without_executing(tmp_path: Path) -> None:
    arrays = raw_arrays()
    qpos = np.empty(arrays["qpos"].shape, dtype=object)
    qpos[...] = 0.0
    qpos[0, 0] = _Canary()
    arrays["qpos"] = qpos
    path = tmp_path / "evil.npz"
    np.savez(path, allow_pickle=True, **arrays)
    with pytest.raises(TrajectoryError, match=r"evil\.npz: 'qpos'.*holds pickled objects, which are refused"):
        load_trajectory(path)
    assert _CANARY_FIRED == []
    with pytest.raises(TrajectoryError, match=r"evil\.npz"):
        load_trajectories(tmp_path)
    assert _CANARY_FIRED == []


def _npz_with_member(path: Path, name: str, payload: bytes, arrays: dict[str, np.ndarray]) -> Path:
    """An .npz whose member `name` holds `payload` as written (the others saved normally)."""
    import io
    import zipfile

    with zipfile.ZipFile(path, "w") as archive:
        for key, value in arrays.items():
            if f"{key}.npy" != name:
                buffer = io.BytesIO()
                np.save(buffer, value)
                archive.writestr(f"{key}.npy", buffer.getvalue())
        archive.writestr(name, payload)
    return path


def test_corrupt_or_lying_members_are_one_error_without_allocating(tmp_path: Path) -> None:
    """Untrusted archives: a corrupt compressed stream (was zlib.error), a header claiming 800 GB over 8 bytes (was
    numpy trying to allocate it), a malformed header (was reported as pickled objects) and a member too large to be a
    trajectory each give one TrajectoryError naming the file and the array."""
    import io
    import struct
    import zipfile

    arrays = raw_arrays()
    # The member numpy reads for 'time': `time.npy`, or `time` itself (which the size check once did not look at).
    for name, member, shape in (("lying", "time.npy", "100000000000"), ("nosuffix", "time", "1000000000000")):
        header = io.BytesIO()
        np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": (int(shape),)})
        lying = _npz_with_member(tmp_path / f"{name}.npz", member, header.getvalue() + b"\0" * 8, arrays)
        with pytest.raises(TrajectoryError, match=rf"{name}\.npz: 'time' claims shape \({shape},\).*corrupt"):
            load_trajectory(lying)
    malformed = _npz_with_member(tmp_path / "malformed.npz", "qpos.npy", b"\x93NUMPY\x01\x00\x06\x00{}    ", arrays)
    with pytest.raises(TrajectoryError, match=r"malformed\.npz: 'qpos' is not a readable array") as info:
        load_trajectory(malformed)
    assert "pickled" not in str(info.value)

    # A deflate stream broken at its start (its first block header), with its CRC and sizes left as they were.
    np.savez_compressed(tmp_path / "deflated.npz", **arrays)
    with zipfile.ZipFile(tmp_path / "deflated.npz") as archive:
        offset = archive.getinfo("time.npy").header_offset
    raw = bytearray((tmp_path / "deflated.npz").read_bytes())
    name_len, extra_len = struct.unpack("<HH", raw[offset + 26 : offset + 30])
    data = offset + 30 + name_len + extra_len
    raw[data : data + 4] = b"\xff\xff\xff\xff"
    (tmp_path / "broken.npz").write_bytes(bytes(raw))
    with pytest.raises(TrajectoryError, match=r"broken\.npz: 'time' is corrupt \((error|BadZipFile)"):
        load_trajectory(tmp_path / "broken.npz")

    import grounder.core.trajectory as trajectory

    np.savez(tmp_path / "big.npz", **arrays)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(trajectory, "_MAX_ARRAY_BYTES", 64)
        with pytest.raises(TrajectoryError, match=r"big\.npz: 'time' is .* GB uncompressed.*split the recording"):
            load_trajectory(tmp_path / "big.npz")


def test_members_zipfile_cannot_read_are_one_error(tmp_path: Path) -> None:
    """An encrypted member, or one compressed by a method zipfile does not know, was a traceback (RuntimeError,
    NotImplementedError)."""
    import struct

    arrays = raw_arrays()
    np.savez(tmp_path / "plain.npz", **arrays)
    load_trajectory(tmp_path / "plain.npz")  # the control: the archive before its flags are changed
    for name, (local_at, central_at, patch) in {
        "encrypted": (6, 8, lambda flags: flags | 1),  # the general-purpose flags' bit 0
        "method": (8, 10, lambda _: 99),  # the compression method
    }.items():
        raw = bytearray((tmp_path / "plain.npz").read_bytes())
        for signature, at in ((b"PK\x03\x04", local_at), (b"PK\x01\x02", central_at)):
            start = raw.find(signature)
            while start >= 0:
                (value,) = struct.unpack_from("<H", raw, start + at)
                struct.pack_into("<H", raw, start + at, patch(value))
                start = raw.find(signature, start + 4)
        (tmp_path / f"{name}.npz").write_bytes(bytes(raw))
        with pytest.raises(TrajectoryError, match=rf"{name}\.npz: 'time' cannot be read \(.*\); write it unencrypted"):
            load_trajectory(tmp_path / f"{name}.npz")


@pytest.mark.parametrize(
    "content, expected",
    [
        (b"", "not an .npz archive"),
        (b"time,qpos\n0,1\n", "not an .npz archive"),
        (b"PK\x03\x04truncated", "not a valid .npz archive"),
    ],
    ids=["empty", "text", "truncated_zip"],
)
def test_load_rejects_non_npz(tmp_path: Path, content: bytes, expected: str) -> None:
    path = tmp_path / "junk.npz"
    path.write_bytes(content)
    with pytest.raises(TrajectoryError, match=expected) as caught:
        load_trajectory(path)
    assert "allow_pickle" not in str(caught.value)  # numpy's own message would suggest loading it unsafely


def test_raw_pickle_named_npz_is_refused_without_executing(tmp_path: Path) -> None:
    import pickle

    path = tmp_path / "evil.npz"
    path.write_bytes(pickle.dumps(_Canary()))
    with pytest.raises(TrajectoryError, match=r"evil\.npz: not an \.npz archive"):
        load_trajectory(path)
    assert _CANARY_FIRED == []


def test_load_rejects_npy_file(tmp_path: Path) -> None:
    path = tmp_path / "single.npz"
    with path.open("wb") as f:
        np.save(f, np.zeros(3))
    with pytest.raises(TrajectoryError, match=r"single \.npy array"):
        load_trajectory(path)


def test_load_missing_file(tmp_path: Path) -> None:
    with pytest.raises(TrajectoryError, match=r"nope\.npz: trajectory file does not exist"):
        load_trajectory(tmp_path / "nope.npz")


def test_load_directory_as_file(tmp_path: Path) -> None:
    with pytest.raises(TrajectoryError, match=r"expected a trajectory \.npz file"):
        load_trajectory(tmp_path)


def test_load_trajectories_empty_dir(tmp_path: Path) -> None:
    (tmp_path / "readme.txt").write_text("no trajectories here")
    with pytest.raises(TrajectoryError, match=r"contains no \.npz trajectory files"):
        load_trajectories(tmp_path)


def test_load_trajectories_missing_dir(tmp_path: Path) -> None:
    with pytest.raises(TrajectoryError, match="trajectory directory does not exist"):
        load_trajectories(tmp_path / "missing")


def test_load_trajectories_file_not_dir(tmp_path: Path) -> None:
    path = save_trajectory(make_traj("a"), tmp_path / "a.npz")
    with pytest.raises(TrajectoryError, match="expected a directory"):
        load_trajectories(path)


@pytest.mark.parametrize(
    "other, expected",
    [
        (lambda: make_traj("b", nq=NQ + 1), "b.npz: has nq=9, nv=7, nu=1 but a.npz has nq=8, nv=7, nu=1"),
        (lambda: make_traj("b", with_ctrl=False), "nu=none (no ctrl) but a.npz has nq=8, nv=7, nu=1"),
    ],
    ids=["mixed_nq", "mixed_ctrl"],
)
def test_load_trajectories_mixed_dims(tmp_path: Path, other: Callable[[], Trajectory], expected: str) -> None:
    save_trajectories([make_traj("a"), other()], tmp_path)
    with pytest.raises(TrajectoryError) as info:
        load_trajectories(tmp_path)
    assert expected in str(info.value)


# --- against a model -------------------------------------------------------------------------------------


def _with(traj: Trajectory, **changes: object) -> Trajectory:
    fields: dict[str, Any] = {
        "time_s": traj.time_s,
        "qpos": traj.qpos,
        "qvel": traj.qvel,
        "ctrl": traj.ctrl,
        "name": traj.name,
    }
    fields.update(changes)
    return Trajectory(**fields)


@pytest.mark.parametrize(
    "change, expected",
    [
        ({"qpos": np.zeros((6, NQ - 1))}, "nq=7, nv=7, nu=1"),
        ({"qvel": np.zeros((6, NV + 2))}, "nq=8, nv=9, nu=1"),
        ({"ctrl": np.zeros((6, 2))}, "nq=8, nv=7, nu=2"),
    ],
    ids=["nq", "nv", "nu"],
)
def test_dimension_mismatch_with_model(model: mujoco.MjModel, change: dict[str, object], expected: str) -> None:
    traj = _with(make_traj("toss_03"), **change)
    with pytest.raises(TrajectoryError, match="trajectory 'toss_03': does not fit the model") as info:
        validate_against_model(traj, model)
    message = str(info.value)
    assert "model, which has nq=8, nv=7, nu=1" in message
    assert f"trajectory has {expected}" in message


def test_missing_ctrl_is_fine_for_actuated_model(model: mujoco.MjModel) -> None:
    validate_against_model(make_traj(with_ctrl=False), model)


@pytest.mark.parametrize("norm, ok", [(1.0 + 9e-4, True), (1.0 - 9e-4, True), (1.0 + 2e-3, False), (0.0, False)])
def test_free_joint_quaternion_norm(model: mujoco.MjModel, norm: float, ok: bool) -> None:
    traj = make_traj("toss_03")
    qpos = traj.qpos.copy()
    qpos[4, 3:7] *= norm
    bad = _with(traj, qpos=qpos)
    if ok:
        validate_against_model(bad, model)
        return
    with pytest.raises(TrajectoryError) as info:
        validate_against_model(bad, model)
    message = str(info.value)
    assert "free joint 'box_free'" in message
    assert "at row 4" in message
    assert "qpos[:, 3:7]" in message


def test_hinge_is_not_checked_as_quaternion(model: mujoco.MjModel) -> None:
    traj = make_traj()
    qpos = traj.qpos.copy()
    qpos[:, 7] = 123.0  # the hinge angle, any value is fine
    validate_against_model(_with(traj, qpos=qpos), model)


def test_ball_joint_quaternion_norm(tmp_path: Path) -> None:
    ball = mujoco.MjModel.from_xml_string(BALL_XML)
    qpos = np.tile([1.0, 0.0, 0.0, 0.0], (3, 1))
    good = Trajectory(time_s=np.arange(3.0), qpos=qpos, qvel=np.zeros((3, 3)), name="swing")
    validate_against_model(good, ball)
    qpos[1] = [0.5, 0.5, 0.0, 0.0]
    save_trajectory(_with(good, qpos=qpos), tmp_path / "swing.npz")
    with pytest.raises(TrajectoryError, match=r"swing\.npz: .*ball joint 'pivot'.*at row 1 its norm is 0\.707"):
        load_trajectories(tmp_path, model=ball)


# --- saving a directory ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "names, expected",
    [
        (["a", ""], "has name '', which is not a safe file name"),
        (["../escape"], "'../escape', which is not a safe file name"),
        (["sub/dir"], "not a safe file name"),
        (["back\\slash"], "not a safe file name"),
        ([".."], "not a safe file name"),
        (["a", "b", "a"], "'a' and 'a' collide"),
        (["Toss", "toss"], "'toss' and 'Toss' collide"),
    ],
    ids=["empty", "parent", "slash", "backslash", "dotdot", "duplicate", "case_duplicate"],
)
def test_save_trajectories_rejects_bad_names(tmp_path: Path, names: list[str], expected: str) -> None:
    out = tmp_path / "out"
    with pytest.raises(TrajectoryError) as info:
        save_trajectories([make_traj(n, seed=i) for i, n in enumerate(names)], out)
    assert expected in str(info.value)
    assert list(tmp_path.iterdir()) == []  # checked before anything is written


def test_save_trajectories_nothing_to_save(tmp_path: Path) -> None:
    with pytest.raises(TrajectoryError, match="no trajectories to save"):
        save_trajectories([], tmp_path / "out")


def test_save_trajectories_into_existing_dir_keeps_other_files(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("keep me")
    save_trajectories([make_traj("a")], tmp_path)
    assert sorted(os.listdir(tmp_path)) == ["a.npz", "notes.txt"]
