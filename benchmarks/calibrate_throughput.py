"""Simulation throughput during calibration vs raw `mujoco.rollout` on the same model and initial states.

Calibration evaluates K candidate parameter vectors on B trajectories per call
(`grounder.calibration.evaluator.Evaluator`):
building the candidate models, one batched `mujoco.rollout` per length group, and the per-trajectory losses. The
raw figure is `mujoco.rollout.rollout` alone on the same candidate models, initial states and step counts (one call
per length group, as calibration makes), with nothing else; for reference also on the nominal model only (cheaper:
condim 3, pyramidal cone, where candidates range over condim 3/4/6 and both cones). Both count model steps per
second; the ratio is the median over repeats of back-to-back runs, by CPU time (robust on a shared machine) and
by wall clock.

    .venv/bin/python benchmarks/calibrate_throughput.py [--candidates 16] [--trajectories 24] [--repeats 5]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "cube_toss"
CUBE_XML = REPO / "samples" / "cube_toss" / "cube.xml"


def _trajectories(count: int) -> list:
    import grounder.sim.rollout as sim
    from grounder.core.importers import load_dair_pll_cube
    from grounder.core.trajectory import Trajectory

    if (DATA / "tosses").is_dir():
        return load_dair_pll_cube(DATA)[:count]
    # No shared data: synthetic tosses of the nominal cube.
    model = mujoco.MjModel.from_xml_path(str(CUBE_XML))
    rng = np.random.default_rng(0)
    seeds = []
    for i in range(count):
        qpos = np.array([0, 0, 0.14, 1, 0, 0, 0], dtype=float)
        qvel = np.concatenate([rng.uniform(-1, 1, 2), [-0.5], rng.uniform(-4, 4, 3)])
        seeds.append(
            Trajectory(
                time_s=np.arange(110) / 148.0, qpos=np.tile(qpos, (110, 1)), qvel=np.tile(qvel, (110, 1)), name=str(i)
            )
        )
    return sim.simulate(model, seeds)  # type: ignore[return-value]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--candidates", type=int, default=16)
    parser.add_argument("--trajectories", type=int, default=24)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--nthread", type=int, default=None)
    args = parser.parse_args()

    import grounder.sim.rollout as sim
    from grounder.calibration.evaluator import Evaluator
    from grounder.calibration.parameters import resolve_parameters

    model = mujoco.MjModel.from_xml_path(str(CUBE_XML))
    trajs = _trajectories(args.trajectories)
    nthread = args.nthread or sim.default_nthread()
    params = resolve_parameters(model, None)
    rng = np.random.default_rng(0)
    unit = rng.uniform(0.2, 0.8, size=(args.candidates, len(params)))
    values = np.stack([p.from_unit(unit[:, i]) for i, p in enumerate(params)], axis=1)

    ev = Evaluator(model, params, trajs, rotation_weight=0.0, nthread=nthread)
    # Raw: the same rows (every candidate x every trajectory), each simulated as long as in its length group.
    states0, nsteps = [], []
    for group, batch in zip(ev.groups, ev.batches, strict=True):
        for _ in range(args.candidates):
            states0.append(batch.states0)
            nsteps += [batch.nstep] * len(group)
    raw_rows = np.concatenate(states0)
    nstep_max = max(nsteps)
    total_steps = int(sum(nsteps))

    candidates = ev.models(values)
    # Wall-clock and CPU-time (this process, all threads) figures; on a shared machine the CPU-time ratio is the
    # stable one, as other processes' load changes the wall-clock figures from one run to the next.
    best = {"raw": 0.0, "nominal": 0.0, "cal": 0.0}
    ratios_wall, ratios_cpu = [], []
    for _ in range(args.repeats):
        datas = [mujoco.MjData(model) for _ in range(nthread)]
        measured: dict[str, tuple[float, float]] = {}
        # One call per length group, as calibration does, so both simulate exactly the same steps.
        for which in ("raw", "nominal"):
            wall, cpu = time.perf_counter(), time.process_time()
            start = 0
            for group, batch in zip(ev.groups, ev.batches, strict=True):
                rows = raw_rows[start : start + args.candidates * len(group)]
                start += len(rows)
                models = [m for m in candidates for _ in group] if which == "raw" else model
                mj_rollout.rollout(models, datas, rows, nstep=batch.nstep)
            measured[which] = (time.perf_counter() - wall, time.process_time() - cpu)
        steps0 = ev.steps
        wall, cpu = time.perf_counter(), time.process_time()
        ev.loss_of_values(values)
        measured["cal"] = (time.perf_counter() - wall, time.process_time() - cpu)
        assert ev.steps - steps0 == total_steps
        for key, (w, _) in measured.items():
            best[key] = max(best[key], total_steps / w)
        ratios_wall.append(measured["raw"][0] / measured["cal"][0])
        ratios_cpu.append(measured["raw"][1] / measured["cal"][1])
    print(
        f"model: {CUBE_XML.name}, {args.candidates} candidates x {len(trajs)} trajectories, "
        f"{total_steps:,} steps per evaluation (longest row {nstep_max}), {nthread} threads, {args.repeats} repeats"
    )
    print(f"raw mujoco.rollout, same candidate models: {best['raw']:12,.0f} steps/s (best wall clock)")
    print(f"raw mujoco.rollout, nominal model only:    {best['nominal']:12,.0f} steps/s")
    print(f"calibration evaluation:                    {best['cal']:12,.0f} steps/s (models + rollout + losses)")
    print(
        f"calibration / raw, median over repeats: {100 * float(np.median(ratios_cpu)):.1f}% by CPU time, "
        f"{100 * float(np.median(ratios_wall)):.1f}% by wall clock (target >= 90%)"
    )


if __name__ == "__main__":
    main()
