"""Residual vs calibration vs diagnosis on the withheld-effect cases of the gap diagnosis (multi-step, held out).

Run: `.venv/bin/python benchmarks/residual_cases.py [--cases NAME ...] [--train 64] [--heldout 16] [--json F]`

Each case of `grounder.diagnosis.cases.BENCHMARK` (true system = nominal + hidden effect + sensor noise, 1 s at 100 Hz)
gives `--train` recorded trajectories (seed 0, default 64) and `--heldout` others (seed 1). From the training ones only:

- **calibrated**: `grounder.calibrate` of the nominal scene with the scene's default parameters (free bodies:
  friction and contact; joints: damping, friction loss, armature; actuators: gains), default budget, 2 threads,
  loss = position error in % of the body size + `--rotation-weight` (default 1) % per degree of rotation error
  (with calibrate's default of 0, position only, a ball's spin is invisible to the fit);
- **diagnosed**: `grounder.diagnose` of the nominal scene (default setting); the selected effects with their fitted
  values, measurement effects (length scale, velocity lag) applied to the start state and predictions;
- **calibrated + residual**: `grounder.train_residual` on the calibrated scene (default options, so its output
  gain is chosen on multi-step rollouts of a fifth of the training trajectories).

Every model is then rolled out open loop over each held-out trajectory from its first recorded state. Figures per
case: time-averaged position error (mm) and rotation error (deg) of the free body, or joint-angle error (mrad, a
full turn counts as none) for jointed scenes, mean over held-out trajectories. Jointed scenes (pendulum, arm) get
the joint-space residual (`grounder/residual/joint.py`).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import mujoco
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from grounder.calibration.fit import calibrate
from grounder.calibration.options import CalibrateOptions
from grounder.core.trajectory import Trajectory
from grounder.diagnosis.benchmark import select_cases
from grounder.diagnosis.cases import make_case
from grounder.diagnosis.effects import Transforms, apply_effects
from grounder.diagnosis.gap import make_windows, predict
from grounder.diagnosis.pipeline import DiagnoseOptions, diagnose
from grounder.residual.joint import joint_error, joint_space
from grounder.residual.options import ResidualOptions
from grounder.residual.simulator import Simulator
from grounder.residual.train import train_residual
from image2sim_common.rotations import quat_angle_rad

MODELS = ("nominal", "calibrated", "diagnosed", "calibrated + residual")


def errors(model: mujoco.MjModel, pred_qpos: list[np.ndarray], real: list[Trajectory]) -> dict[str, float]:
    """Mean over trajectories of the time-averaged error: free body position (mm) and rotation (deg), or joints."""
    free = [j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
    if free:
        a = int(model.jnt_qposadr[free[0]])
        pos = [
            np.linalg.norm(p[:, a : a + 3] - r.qpos[:, a : a + 3], axis=1).mean()
            for p, r in zip(pred_qpos, real, strict=True)
        ]
        rot = [
            quat_angle_rad(p[:, a + 3 : a + 7], r.qpos[:, a + 3 : a + 7]).mean()
            for p, r in zip(pred_qpos, real, strict=True)
        ]
        return {"pos_mm": 1e3 * float(np.mean(pos)), "rot_deg": float(np.degrees(np.mean(rot)))}
    space = joint_space(model)
    err = [np.abs(joint_error(p, r.qpos, space)).mean() for p, r in zip(pred_qpos, real, strict=True)]
    return {"joint_mrad": 1e3 * float(np.mean(err))}


def open_loop(model: mujoco.MjModel, transforms: Transforms, held: list[Trajectory]) -> list[np.ndarray]:
    """Open-loop predictions from each trajectory's first state (diagnosis transforms applied)."""
    from mujoco import rollout as mj_rollout

    windows = make_windows(model, held, None)
    with mj_rollout.Rollout(nthread=2) as runner:
        pred = predict([(model, transforms)], windows, runner, 2)[0]
    return [pred[w, : held[int(t)].num_steps] for w, t in enumerate(windows.traj_index)]


def run_case(name: str, n_train: int, n_held: int, rotation_weight: float, quiet: bool) -> dict:
    spec = select_cases([name])[0]
    train = make_case(spec, n_train, seed=0).trajectories
    case = make_case(spec, n_held, seed=1)
    held = case.trajectories
    nominal = mujoco.MjModel.from_xml_string(case.scene_xml)
    row: dict = {"case": name, "hidden": {h.name: h.values for h in spec.hidden}, "seconds": {}}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        (root / "nominal").mkdir()
        (root / "nominal" / "scene.xml").write_text(case.scene_xml)
        t0 = time.perf_counter()
        cal = calibrate(
            root / "nominal",
            train,
            options=CalibrateOptions(nthread=2, rotation_weight=rotation_weight),
            out=root / "calibrated",
        )
        row["seconds"]["calibrate"] = time.perf_counter() - t0
        row["calibrated_params"] = {p.name: p.value for p in cal.parameters}
        t0 = time.perf_counter()
        diag = diagnose(nominal, train, DiagnoseOptions(nthread=2))
        row["seconds"]["diagnose"] = time.perf_counter() - t0
        row["diagnosed"] = {a.effect.name: a.values for a in diag.applied}
        diagnosed, transforms = apply_effects(nominal, diag.applied)
        preds = {
            "nominal": open_loop(nominal, Transforms(), held),
            "calibrated": open_loop(cal.model, Transforms(), held),
            "diagnosed": open_loop(diagnosed, transforms, held),
        }
        t0 = time.perf_counter()
        res = train_residual(root / "calibrated", train, root / "residual", ResidualOptions())
        row["seconds"]["residual"] = time.perf_counter() - t0
        row["residual_gain"] = res.gain
        preds["calibrated + residual"] = [t.qpos for t in Simulator(root / "residual").rollout(held)]
    row["errors"] = {k: errors(nominal, v, held) for k, v in preds.items()}
    if not quiet:
        print(json.dumps(row, default=float), flush=True)
    return row


def _cell(err: dict[str, float] | None) -> str:
    if err is None:
        return "n/a"
    if "joint_mrad" in err:
        return f"{err['joint_mrad']:.1f} mrad"
    return f"{err['pos_mm']:.1f} mm / {err['rot_deg']:.1f} deg"


def table(rows: list[dict]) -> str:
    lines = [
        "| case | " + " | ".join(MODELS) + " | residual gain |",
        "|---|" + "---|" * (len(MODELS) + 1),
    ]
    for row in rows:
        cells = [_cell(row["errors"].get(m)) for m in MODELS]
        gain = f"{row['residual_gain']:g}" if "residual_gain" in row else "n/a"
        lines.append(f"| {row['case']} | " + " | ".join(cells) + f" | {gain} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", nargs="*", default=None, help="case names (default: all)")
    parser.add_argument("--train", type=int, default=64, help="training trajectories per case")
    parser.add_argument("--heldout", type=int, default=16, help="held-out trajectories per case")
    parser.add_argument(
        "--rotation-weight", type=float, default=1.0, help="calibration loss: percent of size per degree"
    )
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    parser.add_argument("--quiet", action="store_true", help="only the final table")
    args = parser.parse_args()
    rows = []
    started = time.perf_counter()
    for spec in select_cases(args.cases):
        rows.append(run_case(spec.name, args.train, args.heldout, args.rotation_weight, args.quiet))
    print(table(rows))
    print(f"{time.perf_counter() - started:.0f} s")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2, default=float) + "\n")


if __name__ == "__main__":
    main()
