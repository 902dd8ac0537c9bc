"""Residual dynamics on the real cube tosses: calibrated-only vs calibrated + residual, on held-out tosses.

Metric (Acosta, Yang & Posa, RA-L 2022): per toss, the time-average of the position error divided by the cube
width (0.1048 m) and of the geodesic rotation error (deg), rolled out from the first recorded state; mean and std
over the validation tosses. Split: the calibration's (`grounder.calibration.fit.split_names`: 30% validation, seed 0,
the tosses the data holds twice kept on one side).

The calibrated scene comes from ``grounder.calibration.fit.calibrate`` with ``benchmarks/cube_toss.py``'s settings
(``--calibrated DIR`` reuses one); without that module (or with ``--grid``) this script calibrates friction and
contact softness itself by a grid search on the training tosses.

Run: ``.venv/bin/python benchmarks/residual.py [--quick] [--grid]`` (needs ../shared/data/cube_toss). Also runs a
withheld-effect case (a synthetic cube with hidden air drag) unless ``--no-synthetic``.

``--oracle`` (with ``--calibrated DIR``) measures how far physics alone could go with hindsight: every validation
toss is rolled out with each of 75 variants of the calibrated contact (sliding friction, torsional friction and
damping ratio, each scaled over a grid around the calibrated value) and the best variant *for that toss* is kept.
No model learned from other tosses sees the toss it is scored on, so this per-toss choice is an optimistic bound
for what a state-independent change of contact parameters can reach on this protocol. It also scores the mean of
the 75 rollouts (positions averaged, quaternions by their chordal mean): where the tosses scatter unpredictably
after the impacts, a model trained to minimise the expected error would drift toward such an average.

``--predictability`` (with ``--calibrated DIR``) measures how much of the calibrated scene's horizontal position
error the toss's first recorded state predicts at all: a ridge regression, fitted on the training tosses, from
that state (position, linear and angular velocity, gravity's direction in the cube frame) to each toss's error
(time-averaged and final, x and y), scored on the validation tosses. A residual sees no more than the state, so
what this linear read of it cannot predict is mostly scatter; the same with the recorded final position added is
a hindsight reference.

``--noise-floor`` (with ``--calibrated DIR``) measures how much of the error the recorded first state's own error
sets. Each toss's first free-flight frames (every corner of the cube at least 10 mm above the board, at least 8
frames) are fitted by free flight: a parabola under the scene's gravity for the position, a constant body rate for
the orientation (exact for the cube's isotropic inertia). The fit's residuals give the tracking noise, and the
fitted state at the first frame, against the recorded one, gives the error of the recorded first state (its
velocities are differences of the poses). The calibrated scene is then rolled out from the fitted start (a
hindsight reference: it reads later frames), and from the fitted start plus another toss's first-state error
drawn at random, scored against the roll-out from the fitted start. That last figure is the error a model as
sensitive to its start as the calibrated scene would show against *itself* when started from a state as wrong as
the recorded ones: a floor for any model rolled out from the recorded first state, unless reality is much less
sensitive to its start than the simulation.

``--board-position`` (with ``--calibrated DIR``) asks whether the board varies from place to place in a way the
residual's features (all in the cube's own frame) cannot see: all tosses are rolled out with the 75 contact
variants of ``--oracle``, and each validation toss gets the variant that scores best on its k nearest training
tosses by where it lands (or starts, or, with hindsight, ends) on the board.

``--published-protocol`` (with ``--calibrated DIR``) scores the validation tosses the way the published fits were
scored: each rollout starts 3 frames before the first contact (a cube corner within 3 mm of the board), from a
velocity refitted by free flight over the frames before it (the same fit as ``--noise-floor``), and is compared
over the rest of the toss; beside it, from the recorded state at that frame, and this project's metric from the
first recorded state, on the same tosses. Context only: the issues' targets are on this project's metric.

``--twins`` (with ``--calibrated DIR``) asks whether tosses that the calibrated scene calls alike end alike. The
board is level and uniform and the cube has 24 rotational symmetries, so the motion of a toss carried by a turn of
the board about the vertical, a shift along it and a relabelling of the cube's faces is a motion just as possible.
Every pair of tosses with a free-flight start (the ``--noise-floor`` fit) is so aligned (the relabelling and turn
that bring the second start's orientation nearest the first's) and compared over their common frames with the
metric, both as recorded and as the calibrated scene rolls them out from those starts. Pairs whose records
coincide (copies of one toss in the data, see docs/residual_cube.md) are counted apart. For any model, the two
tosses' errors add up to at least the records' distance less the model's distance between its two roll-outs (the
triangle inequality), so where the calibrated roll-outs are close and the records far apart, a model within the
target on both would have to tell the two starts apart far more than the calibrated scene does.

``--ablation`` also rolls the validation tosses out with only the pose outputs (position, rotation) or only the
velocity outputs of the trained residual, at forced gains 0.25, 0.5 and 1, to show which part helps or hurts.
"""

from __future__ import annotations

import argparse
import copy
import itertools
import re
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import mujoco
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from cube_toss import DEFAULT_PARAMS as CUBE_TOSS_PARAMS  # noqa: E402  (benchmarks/cube_toss.py's fit)

from grounder.core.importers import DAIR_PLL_CUBE_RATE_HZ, load_dair_pll_cube  # noqa: E402
from grounder.core.repeats import repeated_motions  # noqa: E402
from grounder.core.trajectory import Trajectory  # noqa: E402
from grounder.interaction.flights import fit_flight  # noqa: E402
from grounder.residual.options import ResidualOptions  # noqa: E402
from grounder.residual.simulator import Simulator  # noqa: E402
from grounder.residual.train import train_residual  # noqa: E402
from grounder.sim.rollout import simulate  # noqa: E402
from image2sim_common.rotations import (  # noqa: E402
    quat_angle_rad,
    quat_conj,
    quat_mul,
    quat_to_mat,
    quat_to_rotvec,
    rotvec_to_quat,
)

DATA = REPO.parent / "shared" / "data" / "cube_toss"
NOMINAL_XML = REPO / "samples" / "cube_toss" / "cube.xml"
CUBE_WIDTH_M = 0.1048
SPLIT_SEED = 0
TRAIN_FRACTION = 0.7


def split(trajs: list[Trajectory]) -> tuple[list[Trajectory], list[Trajectory]]:
    """The calibration's split (``grounder.calibration.fit.split_names``, 30% validation, seed 0, copies of one toss
    kept on one side as `image2sim calibrate` keeps them), so that validation here is validation there."""
    from grounder.calibration.fit import split_names

    by_name = {t.name: t for t in trajs}
    repeats = repeated_motions(trajs, mujoco.MjModel.from_xml_path(str(NOMINAL_XML)))
    train_names, val_names = split_names(list(by_name), 1.0 - TRAIN_FRACTION, SPLIT_SEED, repeats)
    print(
        f"split: grounder.calibration.fit.split_names(validation 0.3, seed 0), as benchmarks/cube_toss.py; "
        f"{len(repeats)} tosses stored twice kept on one side"
    )
    return [by_name[n] for n in train_names], [by_name[n] for n in val_names]


def metric(preds: list[Trajectory], real: list[Trajectory]) -> tuple[np.ndarray, np.ndarray]:
    """Per toss: time-averaged position error / cube width, time-averaged rotation error in degrees."""
    pos = np.array(
        [np.mean(np.linalg.norm(p.qpos[:, :3] - r.qpos[:, :3], axis=1)) for p, r in zip(preds, real, strict=True)]
    )
    rot = np.array(
        [np.degrees(np.mean(quat_angle_rad(p.qpos[:, 3:], r.qpos[:, 3:]))) for p, r in zip(preds, real, strict=True)]
    )
    return pos / CUBE_WIDTH_M, rot


def fmt(pos: np.ndarray, rot: np.ndarray) -> str:
    return f"{100 * pos.mean():5.1f}% +- {100 * pos.std():4.1f}   {rot.mean():5.1f} +- {rot.std():4.1f} deg"


def _with_contact(xml: str, friction: float, dampratio: float, timeconst: float) -> str:
    xml = re.sub(r'friction="[^"]*"', f'friction="{friction} 0.005 0.0001"', xml, count=1)
    return re.sub(r'solref="[^"]*"', f'solref="{timeconst} {dampratio}"', xml, count=1)


def grid_calibrate(train: list[Trajectory], out_dir: Path) -> tuple[Path, str]:
    """Friction x contact damping ratio x time constant grid on the training tosses; writes out_dir/scene.xml."""
    nominal = NOMINAL_XML.read_text()
    best: tuple[float, str, str] | None = None
    for friction in (0.15, 0.18, 0.2, 0.22, 0.25, 0.28):
        for dampratio in (0.5, 1.0, 2.0):
            for timeconst in (0.01, 0.02):
                xml = _with_contact(nominal, friction, dampratio, timeconst)
                pos, rot = metric(_rollouts(mujoco.MjModel.from_xml_string(xml), train), train)
                score = float(pos.mean() + rot.mean() / 90.0)  # position (widths) + rotation (quarter turns)
                if best is None or score < best[0]:
                    best = (score, xml, f"friction {friction}, solref ({timeconst}, {dampratio})")
    assert best is not None
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "scene.xml").write_text(best[1])
    return out_dir, f"grid search in this benchmark: {best[2]}"


def calibrated_scene(
    trajs: list[Trajectory], train: list[Trajectory], work: Path, force_grid: bool
) -> tuple[Path, str]:
    """The calibration engineer's calibration (benchmarks/cube_toss.py's settings), else this script's grid."""
    if not force_grid:
        try:
            from grounder.calibration.fit import calibrate
            from grounder.calibration.options import CalibrateOptions
        except ImportError:
            calibrate = None  # type: ignore[assignment]
        if calibrate is not None:
            nominal = work / "nominal"
            nominal.mkdir()
            (nominal / "scene.xml").write_text(NOMINAL_XML.read_text())
            out = work / "calibrated"
            options = CalibrateOptions(
                params=CUBE_TOSS_PARAMS,
                validation_fraction=1.0 - TRAIN_FRACTION,
                split_seed=SPLIT_SEED,
                max_train_trajectories=40,
                popsize=5,
                generations=12,
                local_iterations=4,
            )
            calibrate(nominal, trajs, options=options, out=out)
            return (
                out,
                "grounder.calibration.fit.calibrate, benchmarks/cube_toss.py settings (fit on 40 training tosses)",
            )
    return grid_calibrate(train, work / "grid")


def cube_tosses(
    options: ResidualOptions, force_grid: bool, quick: bool, calibrated: Path | None, ablation: bool = False
) -> None:
    trajs = load_dair_pll_cube(DATA)
    train, val = split(trajs)
    if quick:
        train, val = train[:60], val[:30]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        t0 = time.perf_counter()
        if calibrated is not None:
            scene, how = calibrated, f"given: {calibrated}"
        else:
            scene, how = calibrated_scene(trajs, train, work, force_grid)
        print(f"calibrated scene: {how} ({time.perf_counter() - t0:.0f} s)")
        base = Simulator(scene, use_residual=False)
        t0 = time.perf_counter()
        result = train_residual(scene, train, work / "residual", options)
        print(
            f"residual trained in {time.perf_counter() - t0:.0f} s on {len(train)} tosses, {result.num_samples} samples"
        )
        hybrid = Simulator(work / "residual")
        forced = Simulator(work / "residual")
        assert hybrid.residual is not None and forced.residual is not None
        forced.residual.out_gain[:] = 1.0
        scores = ", ".join(f"{g:g}: {v:.3f}" for g, v in result.gain_scores.items())
        print(f"output gain chosen on held-out training tosses: {result.gain:g} (scores {scores})")
        print(f"\n{'':36s}{'position / width':>20s}   {'rotation':>16s}")
        sims = (
            ("calibrated only", base),
            (f"calibrated + residual (gain {result.gain:g})", hybrid),
            ("calibrated + residual at gain 1", forced),
        )
        for label, tosses in (("train", train), ("validation", val)):
            for name, sim in sims:
                pos, rot = metric(sim.rollout(tosses), tosses)
                print(f"{label:11s} {name:34s} {fmt(pos, rot)}")
        if ablation:
            output_ablation(work / "residual", val)
        print("\ntarget (validation, residual): <= 10% of cube width and <= 10 deg")


def output_ablation(residual_dir: Path, val: list[Trajectory]) -> None:
    """Validation rollouts with only the pose outputs, or only the velocity outputs, of the trained residual."""
    import shutil

    import torch

    from grounder.residual.meta import WEIGHTS_FILE

    state = torch.load(residual_dir / WEIGHTS_FILE, weights_only=True)
    last = max(int(k.split(".")[2]) for k in state if k.startswith("nets.0."))
    print("\nvalidation, one group of outputs switched off (rows of the output layer zeroed), forced gain:")
    for label, off in (("pose outputs only", slice(6, 12)), ("velocity outputs only", slice(0, 6))):
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp) / "ablated"
            shutil.copytree(residual_dir, folder)
            ablated = {k: v.clone() for k, v in state.items()}
            for key in list(ablated):
                if key.startswith("nets.") and key.split(".")[2] == str(last):
                    ablated[key][off] = 0.0
            torch.save(ablated, folder / WEIGHTS_FILE)
            for gain in (0.25, 0.5, 1.0):
                sim = Simulator(folder)
                assert sim.residual is not None
                sim.residual.out_gain[:] = gain
                print(f"  {label:22s} gain {gain:4g}  {fmt(*metric(sim.rollout(val), val))}")


ORACLE_SCALES = {  # factors applied to the calibrated value; 1 is the calibrated scene itself
    "sliding friction": (0.53, 0.74, 1.0, 1.32, 1.84),
    "torsional friction": (0.19, 1.0, 2.26),
    "damping ratio": (0.36, 0.62, 1.0, 1.54, 2.57),
}


def _contact_variants(scene: Path) -> tuple[list[mujoco.MjModel], list[tuple[float, float, float]]]:
    """The calibrated scene with the cube's sliding friction, torsional friction and damping ratio scaled over
    ``ORACLE_SCALES`` (75 models), and each one's (sliding, torsional, damping) scales."""
    base = Simulator(scene, use_residual=False).model
    contact = [g for g in range(base.ngeom) if base.body_dofnum[base.geom_bodyid[g]] == 6]  # the cube's geoms
    models, labels = [], []
    for fs in ORACLE_SCALES["sliding friction"]:
        for ft in ORACLE_SCALES["torsional friction"]:
            for fd in ORACLE_SCALES["damping ratio"]:
                model = copy.copy(base)
                model.geom_friction[contact, 0] = base.geom_friction[contact, 0] * fs
                model.geom_friction[contact, 1] = base.geom_friction[contact, 1] * ft
                model.geom_solref[contact, 1] = base.geom_solref[contact, 1] * fd
                models.append(model)
                labels.append((fs, ft, fd))
    return models, labels


def _landing_xy(toss: Trajectory) -> np.ndarray:
    """Recorded x, y where the cube's centre first comes within 1.6 half-widths of the board (its last frame if
    never): roughly where it first lands."""
    low = toss.qpos[:, 2] < 0.8 * CUBE_WIDTH_M
    return toss.qpos[int(np.argmax(low)) if low.any() else -1, :2]


def board_position(scene: Path) -> None:
    """Whether where on the board a toss lands says which contact variant it wants (see the module docstring)."""
    train, val = split(load_dair_pll_cube(DATA))
    models, labels = _contact_variants(scene)
    t0 = time.perf_counter()
    scores = {}
    for name, tosses in (("train", train), ("val", val)):
        pos = np.empty((len(models), len(tosses)))
        rot = np.empty_like(pos)
        for i, model in enumerate(models):
            pos[i], rot[i] = metric(_rollouts(model, tosses), tosses)
        scores[name] = (pos, rot)
    (pos_tr, rot_tr), (pos_va, rot_va) = scores["train"], scores["val"]
    cols = np.arange(len(val))
    seconds = time.perf_counter() - t0
    print(f"\n{len(models)} contact variants x {len(train) + len(val)} tosses rolled out in {seconds:.0f} s")
    single = int(np.argmin((pos_tr + rot_tr / 100.0).mean(axis=1)))
    print(f"  one variant best over the training tosses {labels[single]}: {fmt(pos_va[single], rot_va[single])}")
    places = {
        "landing x, y": _landing_xy,
        "start x, y": lambda t: t.qpos[0, :2],
        "final x, y (hindsight)": lambda t: t.qpos[-1, :2],
    }
    for place, of in places.items():
        x_train = np.array([of(t) for t in train])
        x_val = np.array([of(t) for t in val])
        nearest = np.argsort(np.linalg.norm(x_val[:, None] - x_train[None], axis=2), axis=1)
        for label, train_score in (("position", pos_tr), ("position + rotation / 100", pos_tr + rot_tr / 100.0)):
            for k in (5, 10, 20, 40, 80):
                choice = np.array([np.argmin(train_score[:, nearest[v, :k]].mean(axis=1)) for v in cols])
                print(
                    f"  variant best on the {k:2d} nearest training tosses by {place:22s} ({label:25s}): "
                    f"{fmt(pos_va[choice, cols], rot_va[choice, cols])}"
                )
    best = np.argmin(pos_tr + rot_tr / 100.0, axis=0)
    log_sliding = np.log([labels[b][0] for b in best])
    landing = np.array([_landing_xy(t) for t in train])
    for axis, name in enumerate("xy"):
        below = landing[:, axis] < np.median(landing[:, axis])
        halves = [log_sliding[m] for m in (below, ~below)]
        print(
            f"  per-toss best sliding friction, log multiplier, landing {name} below / above its median: "
            + " / ".join(f"{h.mean():+.3f} +- {h.std() / np.sqrt(len(h)):.3f}" for h in halves)
        )


def hindsight_oracle(scene: Path) -> None:
    """Per validation toss, the best of 75 contact variants of the calibrated scene (see the module docstring)."""
    _, val = split(load_dair_pll_cube(DATA))
    models, labels = _contact_variants(scene)
    t0 = time.perf_counter()
    pos = np.empty((len(models), len(val)))
    rot = np.empty_like(pos)
    mean_pos = [np.zeros((len(t.time_s), 3)) for t in val]  # ensemble sums, per toss
    mean_quat = [np.zeros((len(t.time_s), 4)) for t in val]
    for i, model in enumerate(models):
        preds = _rollouts(model, val)
        pos[i], rot[i] = metric(preds, val)
        for b, pred in enumerate(preds):
            quat = pred.qpos[:, 3:]
            mean_pos[b] += pred.qpos[:, :3] / len(models)
            # chordal mean: each quaternion's sign matched to the recorded one, then summed and normalised
            mean_quat[b] += quat * np.sign(np.sum(quat * val[b].qpos[:, 3:], axis=1, keepdims=True) + 1e-12)
    calibrated = labels.index((1.0, 1.0, 1.0))
    cols = np.arange(len(val))
    joint = np.argmin(pos + rot / 100.0, axis=0)  # the residual's gain score: widths + degrees / 100
    print(
        f"\nhindsight oracle over {len(models)} contact variants, {len(val)} validation tosses "
        f"({time.perf_counter() - t0:.0f} s)"
    )
    print(f"  calibrated scene                          {fmt(pos[calibrated], rot[calibrated])}")
    print(f"  best variant per toss, position only      {fmt(pos.min(axis=0), rot[pos.argmin(axis=0), cols])}")
    print(f"  best variant per toss, rotation only      {fmt(pos[rot.argmin(axis=0), cols], rot.min(axis=0))}")
    print(f"  best per toss, position + rotation / 100  {fmt(pos[joint, cols], rot[joint, cols])}")
    share = np.mean(joint != calibrated)
    print(f"  tosses whose best variant is not the calibrated one: {100 * share:.0f}%")
    ensemble = [
        replace(t, qpos=np.concatenate([p, q / np.linalg.norm(q, axis=1, keepdims=True)], axis=1))
        for t, p, q in zip(val, mean_pos, mean_quat, strict=True)
    ]
    label = f"mean of the {len(models)} variants' rollouts"
    print(f"  {label:41s}  {fmt(*metric(ensemble, val))}")


def _first_state_features(toss: Trajectory, with_landing: bool) -> list[float]:
    """Position, linear and angular velocity, and gravity's direction in the cube frame at the first recorded
    state; with ``with_landing`` also the recorded final x, y (hindsight)."""
    world_from_cube = np.empty(9)
    mujoco.mju_quat2Mat(world_from_cube, toss.qpos[0, 3:7])
    up_in_cube = world_from_cube.reshape(3, 3).T @ np.array([0.0, 0.0, 1.0])
    features = [*toss.qpos[0, :3], *toss.qvel[0, :6], *up_in_cube]
    return features + list(toss.qpos[-1, :2]) if with_landing else features


def error_predictability(scene: Path) -> None:
    """How much of the calibrated scene's horizontal position error a linear read of the first state predicts
    (ridge regression fitted on the training tosses, R^2 on the validation tosses; see the module docstring)."""
    train, val = split(load_dair_pll_cube(DATA))
    model = Simulator(scene, use_residual=False).model
    errors = {}
    for label, tosses in (("train", train), ("val", val)):
        preds = _rollouts(model, tosses)
        horizontal = [p.qpos[:, :2] - t.qpos[:, :2] for p, t in zip(preds, tosses, strict=True)]
        errors[label] = {
            "time-averaged": np.array([e.mean(axis=0) for e in horizontal]),
            "final": np.array([e[-1] for e in horizontal]),
        }
    print(
        f"\nhorizontal position error of the calibrated scene, predicted from the first state "
        f"(R^2 on {len(val)} validation tosses)"
    )
    final = errors["val"]["final"]
    mean_mm, std_mm = (np.array2string(1000 * v, precision=1) for v in (final.mean(axis=0), final.std(axis=0)))
    print(f"  final error x, y over the validation tosses: mean {mean_mm} mm, std {std_mm} mm")
    for with_landing in (False, True):
        x_train = np.array([_first_state_features(t, with_landing) for t in train])
        x_val = np.array([_first_state_features(t, with_landing) for t in val])
        mean, std = x_train.mean(axis=0), x_train.std(axis=0) + 1e-12
        x_train = np.c_[np.ones(len(train)), (x_train - mean) / std]
        x_val = np.c_[np.ones(len(val)), (x_val - mean) / std]
        for ridge in (1.0, 10.0, 100.0):
            normal = x_train.T @ x_train + ridge * np.diag([0.0] + [1.0] * (x_train.shape[1] - 1))
            for kind in ("time-averaged", "final"):
                y_train, y_val = errors["train"][kind], errors["val"][kind]
                coef = np.linalg.solve(normal, x_train.T @ y_train)
                left = y_val - x_val @ coef
                r2 = 1.0 - np.sum(left**2) / np.sum((y_val - y_val.mean(axis=0)) ** 2)
                size, after = (1000 * np.linalg.norm(y, axis=1).mean() for y in (y_val, left))
                inputs = "first state + recorded final x, y (hindsight)" if with_landing else "first state"
                print(
                    f"  {inputs:46s} ridge {ridge:4g}  {kind:13s} R^2 {r2:6.3f}  "
                    f"mean |error| {size:5.1f} -> {after:5.1f} mm"
                )


FLIGHT_CLEARANCE_M = 0.01  # every cube corner at least this far above the board: free flight
MIN_FLIGHT_FRAMES = 8


def _leading_flight_frames(toss: Trajectory, corners_body_m: np.ndarray) -> int:
    """How many frames from the first one the cube is in free flight (every corner above the clearance)."""
    lowest_m = _lowest_corner_m(toss, corners_body_m)
    touching = np.flatnonzero(lowest_m < FLIGHT_CLEARANCE_M)
    return int(touching[0]) if len(touching) else len(lowest_m)


@dataclass(frozen=True)
class _FlightStart:
    """A toss's first state from a free-flight fit of its first frames, and the recorded first state's error."""

    frames: int
    qpos0: np.ndarray
    qvel0: np.ndarray
    pos_rms_m: float  # fit residuals: the tracking noise
    rot_rms_rad: float
    dpos_world_m: np.ndarray  # recorded - fitted, first frame
    drot_body_rad: np.ndarray
    dvel: np.ndarray  # (6,) world linear m/s, body angular rad/s


def _free_flight_start(toss: Trajectory, frames: int, gravity_m_s2: float, at: int = 0) -> _FlightStart:
    """Fits the first ``frames`` frames by free flight: the position a parabola under gravity, the orientation
    q(t) = q_mid exp(omega_body (t - t_mid)); the state at frame ``at`` (the first by default), against the
    recorded one."""
    tau_s = toss.time_s[:frames] - toss.time_s[0]
    # the calibration's flight fit (known gravity), given the frames with ``at`` last so that it is expressed there
    # (the rest last to first); the cube's origin is its centre of mass
    order = np.r_[np.delete(np.arange(frames), at)[::-1], at]
    flight = fit_flight(0, order, toss.time_s[order], toss.qpos[order, :3], np.array([0.0, 0.0, -gravity_m_s2]))
    mid = frames // 2
    quat_mid = toss.qpos[mid, 3:]
    rotvec_rad = quat_to_rotvec(quat_mul(quat_conj(quat_mid)[None], toss.qpos[:frames, 3:]))  # body frame at mid
    line_mid = np.c_[np.ones(frames), tau_s - tau_s[mid]]
    rot_coef, *_ = np.linalg.lstsq(line_mid, rotvec_rad, rcond=None)
    dof = max(frames - 2, 1)
    quat0 = quat_mul(quat_mid, rotvec_to_quat(rot_coef[0] + rot_coef[1] * (tau_s[at] - tau_s[mid])))
    qpos0, qvel0 = np.r_[flight.com_ref_m, quat0], np.r_[flight.vel_ref_m_s, rot_coef[1]]
    return _FlightStart(
        frames=frames,
        qpos0=qpos0,
        qvel0=qvel0,
        pos_rms_m=float(np.sqrt(np.sum(flight.residual_m**2) / dof)),
        rot_rms_rad=float(np.sqrt(np.sum((rotvec_rad - line_mid @ rot_coef) ** 2) / dof)),
        dpos_world_m=toss.qpos[at, :3] - qpos0[:3],
        drot_body_rad=quat_to_rotvec(quat_mul(quat_conj(quat0), toss.qpos[at, 3:])),
        dvel=toss.qvel[at] - qvel0,
    )


def _started_at(toss: Trajectory, qpos0: np.ndarray, qvel0: np.ndarray) -> Trajectory:
    qpos, qvel = toss.qpos.copy(), toss.qvel.copy()
    qpos[0], qvel[0] = qpos0, qvel0
    return replace(toss, qpos=qpos, qvel=qvel)


def _rollouts(model: mujoco.MjModel, tosses: list[Trajectory]) -> list[Trajectory]:
    return [p for p in simulate(model, tosses) if isinstance(p, Trajectory)]


def _cube_half_size_m(model: mujoco.MjModel) -> np.ndarray:
    """(3,) half sizes of the scene's cube (its first box geom)."""
    boxes = [g for g in range(model.ngeom) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX]
    return model.geom_size[boxes[0]].copy()


def _cube_corners_body_m(model: mujoco.MjModel) -> np.ndarray:
    """(8, 3) the scene's cube's corners in its body frame."""
    return np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * _cube_half_size_m(model)


def _p50_p90(values: list[float], scale: float = 1.0) -> str:
    p50, p90 = np.percentile(np.array(values) * scale, [50, 90])
    return f"{p50:.3g} / {p90:.3g}"


def _check_free_flight_fit(
    model: mujoco.MjModel, pos_noise_m: float, rot_noise_rad: float, flights: int = 20
) -> tuple[float, float]:
    """The free-flight fit on simulated flights of the scene's cube (no board; 16 frames at the data rate, random
    starts) with tracking noise added: the worst linear (m/s) and angular (rad/s) velocity error of its start."""
    spec = mujoco.MjSpec()
    body = spec.worldbody.add_body()
    body.add_freejoint()
    body.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=_cube_half_size_m(model), mass=0.37)
    spec.option.timestep = model.opt.timestep
    spec.option.gravity = model.opt.gravity
    flight_model = spec.compile()
    data = mujoco.MjData(flight_model)
    frame_steps = round((1.0 / DAIR_PLL_CUBE_RATE_HZ) / model.opt.timestep)
    rng = np.random.default_rng(1)
    worst = np.zeros(2)
    for _ in range(flights):
        mujoco.mj_resetData(flight_model, data)
        quat = rng.normal(size=4)
        data.qpos[:] = np.r_[0.0, 0.0, 0.4, quat / np.linalg.norm(quat)]
        data.qvel[:] = np.r_[rng.normal(0.0, 1.0, 3), rng.normal(0.0, 8.0, 3)]
        qvel_true = data.qvel.copy()
        time_s, qpos = [], []
        for _ in range(16):
            time_s.append(data.time)
            noisy = data.qpos.copy()
            noisy[:3] += rng.normal(0.0, pos_noise_m, 3)
            noisy[3:] = quat_mul(noisy[3:], rotvec_to_quat(rng.normal(0.0, rot_noise_rad, 3)))
            qpos.append(noisy)
            mujoco.mj_step(flight_model, data, nstep=frame_steps)
        toss = Trajectory(time_s=np.array(time_s), qpos=np.array(qpos), qvel=np.zeros((16, 6)))
        fit = _free_flight_start(toss, 16, float(-model.opt.gravity[2]))
        error = np.abs(fit.qvel0 - qvel_true)
        worst = np.maximum(worst, [np.linalg.norm(error[:3]), np.linalg.norm(error[3:])])
    return float(worst[0]), float(worst[1])


def start_noise_floor(scene: Path) -> None:
    """What the recorded first state's own error costs a rollout (see the module docstring)."""
    train, val = split(load_dair_pll_cube(DATA))
    model = Simulator(scene, use_residual=False).model
    corners_body_m = _cube_corners_body_m(model)
    gravity_m_s2 = float(-model.opt.gravity[2])
    starts: dict[str, _FlightStart] = {}
    for toss in train + val:
        frames = _leading_flight_frames(toss, corners_body_m)
        if frames >= MIN_FLIGHT_FRAMES:
            starts[toss.name] = _free_flight_start(toss, frames, gravity_m_s2)
    fits = list(starts.values())
    print(
        f"\nfirst state of the recorded tosses, against a free-flight fit of their first frames "
        f"({len(starts)} of {len(train) + len(val)} tosses with >= {MIN_FLIGHT_FRAMES} frames clear of the board by "
        f"{1000 * FLIGHT_CLEARANCE_M:g} mm; median {np.median([f.frames for f in fits]):.0f} frames); median / p90"
    )
    degrees = 180.0 / np.pi
    print(
        f"  fit residual rms (tracking noise)   position {_p50_p90([f.pos_rms_m for f in fits], 1000)} mm, "
        f"rotation {_p50_p90([f.rot_rms_rad for f in fits], degrees)} deg"
    )
    # per-axis noise with the median rms above (that rms is of the 3-vector)
    noise_m = float(np.median([f.pos_rms_m for f in fits])) / np.sqrt(3.0)
    noise_rad = float(np.median([f.rot_rms_rad for f in fits])) / np.sqrt(3.0)
    worst_linear, worst_angular = _check_free_flight_fit(model, noise_m, noise_rad)
    print(
        f"  the fit itself, on 20 simulated flights with that noise: start within {worst_linear:.3g} m/s and "
        f"{worst_angular:.3g} rad/s (worst)"
    )
    print(
        "  recorded - fitted, first frame      position "
        f"{_p50_p90([float(np.linalg.norm(f.dpos_world_m)) for f in fits], 1000)} mm, rotation "
        f"{_p50_p90([float(np.linalg.norm(f.drot_body_rad)) for f in fits], degrees)} deg"
    )
    mean_dvel = np.mean([f.dvel for f in fits], axis=0)
    print(
        "  recorded - fitted, first frame      linear velocity "
        f"{_p50_p90([float(np.linalg.norm(f.dvel[:3])) for f in fits])} m/s (mean "
        f"{np.array2string(mean_dvel[:3], precision=3)}), angular velocity "
        f"{_p50_p90([float(np.linalg.norm(f.dvel[3:])) for f in fits])} rad/s"
    )
    scored = [t for t in val if t.name in starts]
    from_recorded = _rollouts(model, scored)
    from_fitted = _rollouts(model, [_started_at(t, starts[t.name].qpos0, starts[t.name].qvel0) for t in scored])
    print(f"\ncalibrated scene on the {len(scored)} of {len(val)} validation tosses with a fitted start")
    print(f"  {'from the recorded first state, against the recording':70s} {fmt(*metric(from_recorded, scored))}")
    print(f"  {'from the fitted start (hindsight), against the recording':70s} {fmt(*metric(from_fitted, scored))}")
    label = "from the recorded first state, against the fitted start's roll-out"
    print(f"  {label:70s} {fmt(*metric(from_recorded, from_fitted))}")
    rng = np.random.default_rng(0)
    draws = (
        ("another toss's first-state error (draw 1)", True, True, False),
        ("another toss's first-state error (draw 2)", True, True, False),
        ("another toss's first-state error (draw 3)", True, True, False),
        ("  the same, the errors' mean taken out", True, True, True),
        ("  its pose part only", True, False, False),
        ("  its velocity part only", False, True, False),
    )
    print("noise floor: the fitted start's roll-out against a roll-out from the fitted start plus")
    for label, pose, velocity, unbiased in draws:
        perturbed = []
        for toss in scored:
            start, error = starts[toss.name], fits[rng.integers(len(fits))]
            qpos0, qvel0 = start.qpos0.copy(), start.qvel0.copy()
            if pose:
                qpos0[:3] += error.dpos_world_m
                qpos0[3:] = quat_mul(qpos0[3:], rotvec_to_quat(error.drot_body_rad))
            if velocity:
                qvel0 += error.dvel - (mean_dvel if unbiased else 0.0)
            perturbed.append(_started_at(toss, qpos0, qvel0))
        print(f"  {label:68s} {fmt(*metric(_rollouts(model, perturbed), from_fitted))}")


CONTACT_CLEARANCE_M = 0.003  # a corner this close to the board (with the scene's cube size): first contact
PROTOCOL_FRAMES_BEFORE_CONTACT = 3


def published_protocol(scene: Path) -> None:
    """The validation tosses under the published protocol (see the module docstring), beside this project's."""
    _, val = split(load_dair_pll_cube(DATA))
    scenes = {"nominal MuJoCo (samples/cube_toss/cube.xml)": REPO / "samples" / "cube_toss" / "cube.xml"}
    scenes["calibrated scene"] = scene
    model = Simulator(scene, use_residual=False).model
    corners_body_m = _cube_corners_body_m(model)
    recorded, refitted, whole = [], [], []
    for toss in val:
        touching = np.flatnonzero(_lowest_corner_m(toss, corners_body_m) < CONTACT_CLEARANCE_M)
        start = (int(touching[0]) if len(touching) else len(toss.time_s)) - PROTOCOL_FRAMES_BEFORE_CONTACT
        if start + 1 < MIN_FLIGHT_FRAMES:
            continue  # too few frames before contact to refit the velocity
        tail = replace(toss, time_s=toss.time_s[start:], qpos=toss.qpos[start:], qvel=toss.qvel[start:])
        fit = _free_flight_start(toss, start + 1, float(-model.opt.gravity[2]), at=start)
        whole.append(toss)
        recorded.append(tail)
        refitted.append(_started_at(tail, fit.qpos0, fit.qvel0))
    print(
        f"\npublished protocol: {len(recorded)} of {len(val)} validation tosses with >= {MIN_FLIGHT_FRAMES} frames "
        f"before the start, {PROTOCOL_FRAMES_BEFORE_CONTACT} frames before the first contact (a corner within "
        f"{1000 * CONTACT_CLEARANCE_M:g} mm of the board)"
    )
    for label, path in scenes.items():
        m = Simulator(path, use_residual=False).model
        print(f"  {label}")
        print(f"    {'from the first recorded state (this project)':62s} {fmt(*metric(_rollouts(m, whole), whole))}")
        from_recorded = _rollouts(m, recorded)
        print(f"    {'3 frames before contact, recorded state':62s} {fmt(*metric(from_recorded, recorded))}")
        label = "3 frames before contact, velocity refitted (published)"
        print(f"    {label:62s} {fmt(*metric(_rollouts(m, refitted), recorded))}")


def _lowest_corner_m(toss: Trajectory, corners_body_m: np.ndarray) -> np.ndarray:
    """(T,) height of the cube's lowest corner above the board."""
    corners_world_m = toss.qpos[:, None, :3] + np.einsum("tij,cj->tci", quat_to_mat(toss.qpos[:, 3:]), corners_body_m)
    return corners_world_m[..., 2].min(axis=1)


def synthetic_drag(options: ResidualOptions) -> None:
    """Withheld effect: the recorded cube feels air drag the nominal model lacks
    (tests/grounder/residual/test_train.py's case)."""
    from tests.grounder.residual.test_train import DRAG_DENSITY, _cube_xml, _tosses

    train, val = _tosses(80, seed=1, fluid_density=DRAG_DENSITY), _tosses(40, seed=2, fluid_density=DRAG_DENSITY)
    with tempfile.TemporaryDirectory() as tmp:
        nominal = Path(tmp) / "nominal"
        nominal.mkdir()
        (nominal / "scene.xml").write_text(_cube_xml())
        # noise-free synthetic recordings: no pose smoothing (it only blurs the impacts)
        train_residual(nominal, train, Path(tmp) / "residual", replace(options, smooth_window=0))
        width = 0.1
        print(
            f"\nwithheld effect: hidden air drag (fluid density {DRAG_DENSITY} kg/m^3), 80 train / 40 held-out tosses"
        )
        for name, scene in (("nominal (no drag)", nominal), ("nominal + residual", Path(tmp) / "residual")):
            pos, rot = metric(Simulator(scene).rollout(val), val)
            print(f"held-out {name:22s} {fmt(pos * CUBE_WIDTH_M / width, rot)}  (position / 0.1 m cube width)")


def _cube_rotations() -> np.ndarray:
    """(24, 3, 3) the proper rotations that map a cube onto itself (signed permutations, det +1)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((-1.0, 1.0), repeat=3):
            m = np.zeros((3, 3))
            m[range(3), perm] = signs
            if np.linalg.det(m) > 0:
                out.append(m)
    return np.array(out)


def _yaw_m(psi_rad: float) -> np.ndarray:
    c, s = np.cos(psi_rad), np.sin(psi_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _angle_rad(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., 3, 3) x2 -> (...) angle between rotation matrices."""
    cosine = (np.trace(np.swapaxes(a, -1, -2) @ b, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(cosine, -1.0, 1.0))


def _alignment(rot_a: np.ndarray, rot_b: np.ndarray, faces_all: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The turn of the board (yaw, (3, 3)) and relabelling of the faces (one of `faces_all`) that bring orientation
    rot_b nearest rot_a (yaw @ rot_b @ faces ~ rot_a), and the angle left between them (rad)."""
    # for each relabelling S, the yaw nearest Q = R_a (R_b S)^T, and the angle of yaw^T Q
    q = rot_a[None] @ np.swapaxes(rot_b[None] @ faces_all, -1, -2)
    psi = np.arctan2(q[:, 1, 0] - q[:, 0, 1], q[:, 0, 0] + q[:, 1, 1])
    trace = np.cos(psi) * (q[:, 0, 0] + q[:, 1, 1]) + np.sin(psi) * (q[:, 1, 0] - q[:, 0, 1]) + q[:, 2, 2]
    left = np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0))
    k = int(np.argmin(left))
    return float(left[k]), _yaw_m(float(psi[k])), faces_all[k]


def _aligned(
    pos_m: np.ndarray, rot: np.ndarray, from_xy_m: np.ndarray, to_xy_m: np.ndarray, yaw: np.ndarray, faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A motion turned by `yaw` about the vertical through its start (from_xy_m), moved to to_xy_m, faces
    relabelled by `faces` (body frame)."""
    moved = pos_m.copy()
    moved[:, :2] -= from_xy_m
    moved = moved @ yaw.T
    moved[:, :2] += to_xy_m
    return moved, yaw @ rot @ faces


def _motion_distance(pos_a: np.ndarray, rot_a: np.ndarray, pos_b: np.ndarray, rot_b: np.ndarray) -> tuple[float, float]:
    """The metric between two motions over their common frames: position / cube width, rotation (deg)."""
    n = min(len(pos_a), len(pos_b))
    position = float(np.mean(np.linalg.norm(pos_a[:n] - pos_b[:n], axis=1))) / CUBE_WIDTH_M
    return position, float(np.degrees(np.mean(_angle_rad(rot_a[:n], rot_b[:n]))))


def twin_tosses(scene: Path) -> None:
    """Pairs of tosses the calibrated scene rolls out alike, against how far apart they were recorded."""
    train, val = split(load_dair_pll_cube(DATA))
    model = Simulator(scene, use_residual=False).model
    corners_body_m = _cube_corners_body_m(model)
    gravity_m_s2 = float(-model.opt.gravity[2])
    tosses = []
    for toss in train + val:
        frames = _leading_flight_frames(toss, corners_body_m)
        if frames >= MIN_FLIGHT_FRAMES:
            fit = _free_flight_start(toss, frames, gravity_m_s2)
            tosses.append(_started_at(toss, fit.qpos0, fit.qvel0))
    rolled = _rollouts(model, tosses)
    rot_real = [quat_to_mat(t.qpos[:, 3:]) for t in tosses]
    rot_sim = [quat_to_mat(t.qpos[:, 3:]) for t in rolled]
    start_rot = np.array([r[0] for r in rot_real])
    faces_all = _cube_rotations()
    print(f"\n{len(tosses)} tosses with a free-flight start; every ordered pair aligned (turn of the board, faces)")
    rows = []  # a, b, start angle (deg), |dv| (m/s), |dw| (rad/s), |dz| (m), sim pos, sim rot, real pos, real rot
    for a in range(len(tosses)):
        for b in range(len(tosses)):
            if a == b:
                continue
            left_rad, yaw, faces = _alignment(start_rot[a], start_rot[b], faces_all)
            if left_rad > np.radians(20.0):
                continue
            qa, qb = tosses[a], tosses[b]
            xy_a, xy_b = qa.qpos[0, :2], qb.qpos[0, :2]
            sim_b = _aligned(rolled[b].qpos[:, :3], rot_sim[b], xy_b, xy_a, yaw, faces)
            real_b = _aligned(qb.qpos[:, :3], rot_real[b], xy_b, xy_a, yaw, faces)
            rows.append(
                (
                    a,
                    b,
                    np.degrees(left_rad),
                    np.linalg.norm(qa.qvel[0, :3] - yaw @ qb.qvel[0, :3]),
                    np.linalg.norm(qa.qvel[0, 3:] - faces.T @ qb.qvel[0, 3:]),
                    abs(qa.qpos[0, 2] - qb.qpos[0, 2]),
                    *_motion_distance(rolled[a].qpos[:, :3], rot_sim[a], *sim_b),
                    *_motion_distance(qa.qpos[:, :3], rot_real[a], *real_b),
                )
            )
    pairs = np.array(rows)
    pairs = pairs[pairs[:, 0] < pairs[:, 1]]
    is_copy = (pairs[:, 2] < 0.05) & (pairs[:, 8] < 0.005) & (pairs[:, 9] < 0.2)
    val_names = {t.name for t in val}
    names = [(tosses[int(a)].name, tosses[int(b)].name) for a, b in pairs[is_copy, :2]]
    across = [n for n in names if (n[0] in val_names) != (n[1] in val_names)]
    found = {frozenset(g) for g in repeated_motions(tosses, model)}
    print(
        f"copies (records within 0.5% / 0.2 deg once aligned): {int(is_copy.sum())} pairs, {len(across)} of them "
        f"across the split{': ' if across else ''}{', '.join(f'{x}~{y}' for x, y in across)}; the same pairs as "
        f"grounder.core.repeats finds (heights and speeds alone): {found == {frozenset(n) for n in names}}"
    )
    others = pairs[~is_copy]
    for within, within_deg in ((0.05, 5.0), (0.10, 10.0), (0.15, 15.0)):
        sel = others[(others[:, 6] < within) & (others[:, 7] < within_deg)]
        if not len(sel):
            print(f"other pairs rolled out within {100 * within:.0f}% / {within_deg:g} deg of each other: none")
            continue
        far = int(np.sum((sel[:, 8] > 0.2) | (sel[:, 9] > 20.0)))
        # a model within 10% / 10 deg on both must roll the pair out >= records' distance - 20% / 20 deg apart
        wider = int(np.sum((sel[:, 8] - 0.2 > sel[:, 6]) | (sel[:, 9] - 20.0 > sel[:, 7])))
        print(
            f"other pairs rolled out within {100 * within:.0f}% / {within_deg:g} deg of each other: {len(sel)}; "
            f"roll-outs {100 * sel[:, 6].mean():.1f}% / {sel[:, 7].mean():.1f} deg apart, records "
            f"{100 * sel[:, 8].mean():.1f}% / {sel[:, 9].mean():.1f} deg (median {100 * np.median(sel[:, 8]):.1f}% / "
            f"{np.median(sel[:, 9]):.1f}); records over 20% or 20 deg apart: {far}, "
            f"over the roll-outs' distance + 20% or 20 deg: {wider}; "
            f"starts apart (median) {np.median(sel[:, 2]):.1f} deg, {np.median(sel[:, 3]):.2f} m/s, "
            f"{np.median(sel[:, 4]):.2f} rad/s, {1000 * np.median(sel[:, 5]):.0f} mm"
        )
    copied = {a if a in val_names else b for a, b in across}  # the validation member of each pair across
    base = Simulator(scene, use_residual=False)
    rest = [t for t in val if t.name not in copied]
    groups = [("validation", val)]
    if copied:
        groups.append((f"validation less the {len(copied)} copies of training tosses", rest))
    for label, group in groups:
        pos, rot = metric(base.rollout(group), group)
        print(f"calibrated scene, {label} ({len(group)}): {fmt(pos, rot)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="60 training / 30 validation tosses")
    parser.add_argument("--grid", action="store_true", help="calibrate by this script's grid search")
    parser.add_argument("--calibrated", type=Path, default=None, help="use this calibrated scene folder")
    parser.add_argument("--no-synthetic", action="store_true", help="skip the withheld-effect case")
    parser.add_argument(
        "--oracle", action="store_true", help="with --calibrated: only the per-toss hindsight bound of contact changes"
    )
    parser.add_argument(
        "--predictability",
        action="store_true",
        help="with --calibrated: how much of the error the first state predicts",
    )
    parser.add_argument(
        "--noise-floor",
        action="store_true",
        help="with --calibrated: the error the recorded first state's own error sets",
    )
    parser.add_argument(
        "--published-protocol",
        action="store_true",
        help="with --calibrated: also score 3 frames before the first contact with a refitted velocity",
    )
    parser.add_argument(
        "--board-position",
        action="store_true",
        help="with --calibrated: whether where a toss lands says which contact variant it wants",
    )
    parser.add_argument(
        "--twins", action="store_true", help="with --calibrated: whether tosses the scene calls alike end alike"
    )
    parser.add_argument(
        "--ablation", action="store_true", help="also roll out with only the pose or only the velocity outputs"
    )
    parser.add_argument("--steps", type=int, default=ResidualOptions().steps)
    parser.add_argument("--smooth", type=int, default=ResidualOptions().smooth_window)
    parser.add_argument("--rounds", type=int, default=ResidualOptions().dagger_rounds)
    args = parser.parse_args()
    options = ResidualOptions(steps=args.steps, dagger_rounds=args.rounds, smooth_window=args.smooth)
    analyses = {  # each a measurement on a calibrated scene alone, no residual trained
        "oracle": hindsight_oracle,
        "predictability": error_predictability,
        "noise_floor": start_noise_floor,
        "published_protocol": published_protocol,
        "board_position": board_position,
        "twins": twin_tosses,
    }
    for flag, analyse in analyses.items():
        if getattr(args, flag):
            if args.calibrated is None or not DATA.is_dir():
                parser.error(f"--{flag.replace('_', '-')} needs --calibrated DIR and ../shared/data/cube_toss")
            analyse(args.calibrated)
            return
    if not DATA.is_dir():
        print(f"{DATA} is absent: skipping the cube tosses")
    else:
        cube_tosses(options, args.grid, args.quick, args.calibrated, args.ablation)
    if not args.no_synthetic:
        synthetic_drag(options)


if __name__ == "__main__":
    main()
