"""Fitted parameter distributions and sampled rollouts on the real cube tosses (issue 62), and a case with a known
answer.

Real tosses (``../shared/data/cube_toss``), the calibration's split (30% validation, seed 0, copies of one toss kept
on one side). The calibrated scene is ``benchmarks/cube_toss.py``'s (``--calibrated DIR`` reuses one written with
``cube_toss.py --out DIR``; otherwise it is calibrated here with those settings). The distribution is fitted on the
280 training tosses (`grounder.calibration.distribution`, Monte Carlo EM, the ``calibrate --distribution`` defaults);
its wall time is printed. Then each validation toss is simulated ``--samples`` (32) times by each method:

- (a) the calibrated scene, deterministic (every sample the same);
- (b) naive domain randomisation: each spread parameter uniform within +-30% of its calibrated value (clipped to its
  search bounds), starts as recorded;
- (c) start noise only: the calibrated parameters, starts perturbed by the start noise (measured, then scaled by the
  factor the fit chose on the training tosses);
- (d) the fitted distribution with the start noise (what ``rollout --samples`` draws);
- (e) (d) stepped with a residual trained on the 280 training tosses (`image2sim residual train` defaults, on the
  calibrated scene with its ``distribution.json``), each correction drawn from the residual's learned spread
  (`grounder.residual.spread`; its gain chosen on the residual's own held-out tosses, 0 allowed).

Per method (`grounder.sim.sample_scores`): energy score (position / cube width and rotation in radians), coverage of
the central 50% and 90% bands (position and rotation), their width, the best of 16 samples (Acosta's metric), and the
per-step median trajectory's errors. ``report.html`` (in ``--out``) shows sample fans against the recordings for a
few tosses, the reliability curve of every method and the fitted marginals.

Known answer (``--known-count`` tosses, seed ``--known-seed``, held out from the tests' seeds): friction and damping
ratio drawn per toss from N(0.5, 0.1^2) each; calibrated with a small budget, then the distribution fitted; the
recovered mean and spread against the values the tosses ran with, also as restitution
(`grounder.sim.restitution.simulated_restitution` of each drawn damping ratio). Repeated over ``--known-seeds``.

Run: ``.venv/bin/python benchmarks/distribution.py --out /tmp/dist [--calibrated DIR]`` (about 25 min on 2 cores
with a calibrated scene given; ``--json FILE`` writes the figures).
"""

from __future__ import annotations

import argparse
import base64
import io
import json
import sys
import time
from pathlib import Path

import mujoco
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from cube_toss import DEFAULT_PARAMS  # noqa: E402

from grounder.calibration.distribution import (  # noqa: E402
    EMSettings,
    FittedDistribution,
    calibrated_raw_distribution,
    fit_start_noise_scale,
)
from grounder.calibration.parameters import apply_to_model, resolve_parameters  # noqa: E402
from grounder.sim.sample_scores import score_samples, summarise  # noqa: E402
from grounder.sim.sampled import rollout_samples  # noqa: E402
from grounder.sim.start_noise import StartNoise, measure_start_noise, perturbed_starts  # noqa: E402

DATA = REPO.parent / "shared" / "data" / "cube_toss"
CUBE_XML = REPO / "samples" / "cube_toss" / "cube.xml"
METHODS = ("a", "b", "c", "d", "e")
LABELS = {
    "a": "(a) calibrated, deterministic",
    "b": "(b) naive DR +-30%",
    "c": "(c) start noise only",
    "d": "(d) fitted distribution",
    "e": "(e) (d) + residual spread",
}


def calibrated_scene(args: argparse.Namespace, trajs: list) -> tuple[Path, list[str], list[str]]:
    """The calibrated scene folder and its split (train, validation)."""
    if args.calibrated is not None:
        record = json.loads((args.calibrated / "calibration.json").read_text())
        return args.calibrated, record["split"]["train"], record["split"]["validation"]
    from grounder.calibration.fit import calibrate
    from grounder.calibration.options import CalibrateOptions

    out = args.out / "calibrated"
    options = CalibrateOptions(
        params=DEFAULT_PARAMS, max_train_trajectories=40, popsize=5, generations=12, local_iterations=4
    )
    result = calibrate(CUBE_XML, trajs, options=options, out=out)
    return out, list(result.train_names), list(result.validation_names)


def method_draws(
    method: str,
    model: mujoco.MjModel,
    dist: FittedDistribution,
    noise: StartNoise,
    val: list,
    count: int,
    seed: int,
) -> tuple[list[mujoco.MjModel], list[tuple[np.ndarray, np.ndarray]]]:
    """Models and starts of one method (module docstring)."""
    rng = np.random.default_rng(seed)
    params = dist.parameters(model)
    if method == "a":
        models = [model] * count
    elif method == "b":
        point = np.array([p.from_unit(u) for p, u in zip(params, dist.point, strict=True)])
        values = point * rng.uniform(0.7, 1.3, size=(count, len(params)))
        values = np.clip(values, [p.lower for p in params], [p.upper for p in params])
        models = [apply_to_model(model, params, row) for row in values]
    elif method == "c":
        models = [model] * count
    else:
        models = dist.draw_models(model, count, rng)
    start_noise = noise if method in ("c", "d") else StartNoise.zero(model.nv)
    starts = [perturbed_starts(model, t.qpos[0], t.qvel[0], start_noise, count, rng) for t in val]
    return models, starts


def residual_simulator(args, scene: Path, model, dist, dparams, train: list) -> tuple:
    """Method (e)'s simulator: a residual trained on the training tosses over the calibrated scene with its
    distribution.json (copied, so that the spread's gain is chosen on samples drawn as (d) draws them)."""
    import shutil

    from grounder.calibration.distribution import DISTRIBUTION_FILE, write_distribution
    from grounder.residual.options import ResidualOptions
    from grounder.residual.simulator import Simulator
    from grounder.residual.train import train_residual

    scene_copy = args.out / "distribution_scene"
    out = args.out / "residual_scene"
    for folder in (scene_copy, out):
        if folder.exists():
            shutil.rmtree(folder)
    shutil.copytree(scene, scene_copy)
    write_distribution(scene_copy / DISTRIBUTION_FILE, dist, dparams)
    tick = time.perf_counter()
    result = train_residual(scene_copy, train, out, ResidualOptions())
    seconds = time.perf_counter() - tick
    meta = json.loads((out / "residual.json").read_text())
    record = {"mean_gain": result.gain, "spread": meta["training"].get("spread"), "seconds": seconds}
    return Simulator(out), record


def known_answer(count: int, seed: int, settings: EMSettings) -> dict:
    """The known-answer case of the module docstring for one seed."""
    from grounder.calibration.fit import calibrate
    from grounder.calibration.known_case import VARYING, varying_tosses
    from grounder.calibration.options import CalibrateOptions
    from grounder.sim.restitution import simulated_restitution

    case = varying_tosses(count, seed)
    tmp = Path(__import__("tempfile").mkdtemp())
    (tmp / "cube.xml").write_text(case.xml)
    options = CalibrateOptions(
        params=VARYING,
        validation_fraction=0.0,
        generations=3,
        popsize=4,
        local_iterations=2,
        distribution=True,
        distribution_samples=settings.samples,
        distribution_iterations=settings.iterations,
        distribution_centre="point" if settings.fixed_mean else "fitted",
        seed=seed,
    )
    tick = time.perf_counter()
    result = calibrate(tmp / "cube.xml", case.trajectories, options=options)
    seconds = time.perf_counter() - tick
    dist = result.distribution
    params = dist.parameters(result.model)
    drawn = dist.draw_values(params, 2000, np.random.default_rng(0))
    option = result.model.opt

    def restitution(dampratios: np.ndarray) -> np.ndarray:
        return np.array(
            [simulated_restitution([0.02, float(d)], [0.9, 0.95, 0.001, 0.5, 2], option) for d in dampratios]
        )

    e_true = restitution(case.values[:, 1])
    e_fit = restitution(drawn[:200, 1])
    rows = {}
    for i, name in enumerate(VARYING):
        rows[name] = {
            "true_mean": float(case.values[:, i].mean()),
            "true_std": float(case.values[:, i].std()),
            "fit_mean": float(drawn[:, i].mean()),
            "fit_std": float(drawn[:, i].std()),
        }
    rows["restitution"] = {
        "true_mean": float(e_true.mean()),
        "true_std": float(e_true.std()),
        "fit_mean": float(e_fit.mean()),
        "fit_std": float(e_fit.std()),
    }
    for row in rows.values():
        row["mean_error"] = row["fit_mean"] / row["true_mean"] - 1.0
        row["std_error"] = row["fit_std"] / row["true_std"] - 1.0
    return {"seed": seed, "tosses": count, "seconds": seconds, "parameters": rows}


def figure_png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return base64.b64encode(buf.getvalue()).decode()


def write_report(path: Path, model, val, fans, results, dist, params) -> None:
    """report.html: fans, reliability curves, marginals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from image2sim_common.rotations import quat_angle_rad

    images = []
    shown = list(range(min(4, len(val))))
    fig, axes = plt.subplots(2, len(shown), figsize=(4 * len(shown), 6), squeeze=False)
    for col, b in enumerate(shown):
        traj = val[b]
        qpos = fans["d"][b][0]
        for k in range(len(qpos)):
            axes[0, col].plot(traj.time_s, qpos[k, :, 0], color="tab:blue", alpha=0.15, lw=0.8)
            ang = np.degrees(quat_angle_rad(qpos[k, :, 3:7], np.broadcast_to(traj.qpos[0, 3:7], qpos[k, :, 3:7].shape)))
            axes[1, col].plot(traj.time_s, ang, color="tab:blue", alpha=0.15, lw=0.8)
        axes[0, col].plot(traj.time_s, traj.qpos[:, 0], color="k", lw=1.5, label="recorded")
        rec = np.degrees(quat_angle_rad(traj.qpos[:, 3:7], np.broadcast_to(traj.qpos[0, 3:7], traj.qpos[:, 3:7].shape)))
        axes[1, col].plot(traj.time_s, rec, color="k", lw=1.5)
        axes[0, col].set_title(f"toss {traj.name}: x (m)")
        axes[1, col].set_title("turn from the first frame (deg)")
        axes[1, col].set_xlabel("time (s)")
    axes[0, 0].legend()
    images.append(("Sample fans of (d) (blue, 32 samples) against the recording (black)", figure_png(fig)))
    plt.close(fig)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for m in METHODS:
        s = results[m]
        axes[0].plot(s["reliability_levels"], s["reliability_position"], marker="o", label=LABELS[m])
        axes[1].plot(s["reliability_levels"], s["reliability_rotation"], marker="o", label=LABELS[m])
    for ax, what in zip(axes, ("position", "rotation"), strict=True):
        ax.plot([0, 1], [0, 1], "k--", lw=0.8)
        ax.set_xlabel("band level")
        ax.set_ylabel("share of recorded steps inside")
        ax.set_title(f"Reliability, {what}")
    axes[0].legend(fontsize=8)
    images.append(("Reliability: a calibrated fan lies on the diagonal", figure_png(fig)))
    plt.close(fig)
    drawn = dist.draw_values(params, 4000, np.random.default_rng(0))
    cols = min(4, len(params))
    rows_n = (len(params) + cols - 1) // cols
    fig, axes = plt.subplots(rows_n, cols, figsize=(3.5 * cols, 2.8 * rows_n), squeeze=False)
    for i, p in enumerate(params):
        ax = axes[i // cols, i % cols]
        ax.hist(drawn[:, i], bins=40, color="tab:green", alpha=0.8)
        ax.axvline(float(p.from_unit(dist.point[i])), color="k", lw=1.5)
        ax.set_title(f"{p.name} ({p.unit})", fontsize=9)
    for j in range(len(params), rows_n * cols):
        axes[j // cols, j % cols].axis("off")
    images.append(("Fitted marginals (black: the calibrated point)", figure_png(fig)))
    plt.close(fig)
    table = "".join(
        f"<tr><td>{LABELS[m]}</td><td>{results[m]['energy']:.4f}</td><td>{results[m]['coverage50_position']:.2f} / "
        f"{results[m]['coverage50_rotation']:.2f}</td><td>{results[m]['coverage90_position']:.2f} / "
        f"{results[m]['coverage90_rotation']:.2f}</td><td>{results[m]['best_position_pct']:.1f}% / "
        f"{results[m]['best_rotation_deg']:.1f} deg</td><td>{results[m]['median_position_pct']:.1f}% / "
        f"{results[m]['median_rotation_deg']:.1f} deg</td></tr>"
        for m in METHODS
    )
    body = "".join(f"<h2>{t}</h2><img src='data:image/png;base64,{png}'>" for t, png in images)
    path.write_text(
        "<html><head><meta charset='utf-8'><title>Fitted distribution: real cube tosses</title></head><body>"
        "<h1>Fitted distribution and sampled rollouts, real cube tosses (validation split)</h1>"
        "<table border='1' cellpadding='4'><tr><th>method</th><th>energy score</th><th>50% coverage pos / rot</th>"
        f"<th>90% coverage pos / rot</th><th>best of 16</th><th>median</th></tr>{table}</table>{body}</body></html>"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="folder for report.html (and a calibrated scene)")
    parser.add_argument("--calibrated", type=Path, default=None, help="a scene folder written by cube_toss.py --out")
    parser.add_argument("--samples", type=int, default=32, help="samples per validation toss and method")
    parser.add_argument(
        "--distribution", type=Path, default=None, help="reuse a distribution.json fitted before on the same split"
    )
    parser.add_argument("--fit-samples", type=int, default=64, help="draws per EM iteration")
    parser.add_argument("--iterations", type=int, default=6, help="EM iterations")
    parser.add_argument("--known-count", type=int, default=40)
    parser.add_argument("--known-seeds", type=int, nargs="*", default=[101, 102, 103])
    parser.add_argument("--skip-real", action="store_true")
    parser.add_argument("--point-centre", action="store_true", help="centre on the calibrated point; fit the spread")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    figures: dict = {"command": " ".join(sys.argv)}
    settings = EMSettings(samples=args.fit_samples, iterations=args.iterations, fixed_mean=args.point_centre)

    print("known answer: friction and damping ratio ~ N(0.5, 0.1^2) per toss")
    figures["known"] = []
    for seed in args.known_seeds:
        row = known_answer(args.known_count, seed, settings)
        figures["known"].append(row)
        for name, r in row["parameters"].items():
            print(
                f"  seed {seed} {name:24s} mean {r['fit_mean']:.3f} (true {r['true_mean']:.3f}, {r['mean_error']:+.0%})"
                f"  std {r['fit_std']:.3f} (true {r['true_std']:.3f}, {r['std_error']:+.0%})"
            )
        print(f"  seed {seed}: {row['seconds']:.0f} s (calibration + distribution, {row['tosses']} tosses)")
    if not args.skip_real:
        if not (DATA / "tosses").is_dir():
            sys.exit(f"real cube tosses not found at {DATA}")
        real(args, settings, figures)
    if args.json:
        args.json.write_text(json.dumps(figures, indent=1) + "\n")


def real(args: argparse.Namespace, settings: EMSettings, figures: dict) -> None:
    from grounder.core.importers import load_dair_pll_cube

    trajs = load_dair_pll_cube(DATA)
    by_name = {t.name: t for t in trajs}
    scene, train_names, val_names = calibrated_scene(args, trajs)
    train = [by_name[n] for n in train_names]
    val = [by_name[n] for n in val_names]
    model = mujoco.MjModel.from_xml_path(str(scene / "scene.xml"))
    nominal = mujoco.MjModel.from_xml_path(str(CUBE_XML))
    params = resolve_parameters(nominal, list(DEFAULT_PARAMS))
    tick = time.perf_counter()
    noise = measure_start_noise(model, train)
    if args.distribution is not None:  # fitted before (by this script: OUT/distribution_scene/distribution.json)
        from grounder.calibration.distribution import read_distribution

        dist = read_distribution(args.distribution, model.nv)
    else:
        dist = calibrated_raw_distribution(model, params, train, noise, settings)
        dist = fit_start_noise_scale(model, dist, train, settings)
    fit_s = time.perf_counter() - tick
    dparams = dist.parameters(model)
    print(f"real tosses: fit on {len(train)} training tosses in {fit_s:.0f} s; validation {len(val)} tosses")
    chosen = dist.fit["start_noise_scale"]
    print(f"  start noise scale {chosen['chosen']} (training energy by scale {chosen['energy_score_by_scale']})")
    print(
        f"  start noise: position {1e3 * noise.pose_std[:3].mean():.2f} mm, rotation "
        f"{np.degrees(noise.pose_std[3:].mean()):.2f} deg, velocity {noise.velocity_std[:3].mean():.3f} m/s, "
        f"angular {noise.velocity_std[3:].mean():.2f} rad/s"
    )
    summary = dist.summary(dparams)
    for row in summary:
        print(
            f"  {row['name']:26s} point {row['value']:.4g}  mean {row['mean']:.4g}  std {row['std']:.4g} {row['unit']}"
        )
    results = {}
    fans = {}
    rollout_s: dict[str, float] = {}
    simulator, spread_record = residual_simulator(args, scene, model, dist, dparams, train)
    for m in METHODS:
        models, starts = method_draws("d" if m == "e" else m, model, dist, dist.start_noise, val, args.samples, seed=7)
        tick = time.perf_counter()
        if m == "e":
            sims = simulator.sample(val, starts, np.random.default_rng(8), models=models)
        else:
            sims = rollout_samples(models, val, starts)
        rollout_s[m] = time.perf_counter() - tick
        fans[m] = sims
        results[m] = summarise([score_samples(model, t, q, v) for t, (q, v) in zip(val, sims, strict=True)])
    a, b = results["a"]["energy"], results["b"]["energy"]
    print(
        f"{'method':32s} {'energy':>7s} {'cov50 p/r':>11s} {'cov90 p/r':>11s} {'band90 p/r':>14s} "
        f"{'best of 16':>16s} {'median':>16s}"
    )
    for m in METHODS:
        s = results[m]
        print(
            f"{LABELS[m]:32s} {s['energy']:7.4f} {s['coverage50_position']:5.2f}/{s['coverage50_rotation']:4.2f} "
            f"{s['coverage90_position']:5.2f}/{s['coverage90_rotation']:4.2f} "
            f"{s['band90_position_pct']:5.1f}%/{s['band90_rotation_deg']:5.1f}d "
            f"{s['best_position_pct']:6.1f}%/{s['best_rotation_deg']:5.1f}d "
            f"{s['median_position_pct']:6.1f}%/{s['median_rotation_deg']:5.1f}d"
        )
    print(
        f"(e): residual gain {spread_record['mean_gain']}, spread gain {spread_record['spread']['gain']} "
        f"(held-out energy by spread gain {spread_record['spread']['energy_score_by_gain']}), "
        f"trained in {spread_record['seconds']:.0f} s"
    )
    print(
        f"sampled rollouts, {args.samples} per toss x {len(val)} tosses: (d) {rollout_s['d']:.1f} s (mujoco.rollout), "
        f"(e) {rollout_s['e']:.1f} s (MuJoCo + residual, period by period)"
    )
    d = results["d"]
    print(f"energy score of (d): {d['energy'] / a - 1:+.0%} against (a), {d['energy'] / b - 1:+.0%} against (b)")
    write_report(args.out / "report.html", model, val, fans, results, dist, dparams)
    print(f"report: {args.out / 'report.html'}")
    figures["real"] = {
        "fit_seconds": fit_s,
        "train": len(train),
        "validation": len(val),
        "start_noise_measured": noise.to_json(),
        "start_noise": dist.start_noise.to_json(),
        "distribution": summary,
        "fit": dist.fit,
        "methods": results,
        "residual": spread_record,
        "rollout_seconds": rollout_s,
    }


if __name__ == "__main__":
    main()
