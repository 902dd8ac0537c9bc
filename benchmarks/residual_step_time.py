"""What the residual costs: single-simulation step time with and without it, and a batch of 1024 rolled out.

Trains a small residual on 40 real cube tosses, its output gain forced to 1 (a gain of 0 would skip the work),
then:

- single simulation: ``Simulator.step`` (one period = one 148 Hz frame = 8 model steps of the cube scene), the
  same code path with ``use_residual=False`` and ``True``; per period and per model step, plus MuJoCo's own
  ``mujoco.rollout`` of the same period (no Python in the loop) for reference;
- batch: 1024 tosses rolled out together with ``Simulator.rollout`` (MuJoCo batched over threads with
  ``mujoco.rollout``, the residual vectorised with numpy), with and without the residual.

Run: ``.venv/bin/python benchmarks/residual_step_time.py`` (target: the residual adds <= 50% to the single
simulation's step time; the batch of 1024 rolls out).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from grounder._residual_train import ResidualOptions, train_residual  # noqa: E402
from grounder._simulate import initial_state  # noqa: E402
from grounder._simulator import Simulator  # noqa: E402
from grounder._trajectory import Trajectory  # noqa: E402

DATA = REPO.parent / "shared" / "data" / "cube_toss"
NOMINAL_XML = REPO / "samples" / "cube_toss" / "cube.xml"


def _tosses() -> list[Trajectory]:
    if DATA.is_dir():
        from grounder._import import load_dair_pll_cube

        return load_dair_pll_cube(DATA)
    raise SystemExit(f"{DATA} is absent; this benchmark needs the real cube tosses")


def _time_single(sim: Simulator, starts: list[tuple[np.ndarray, np.ndarray]], periods: int, repeats: int) -> float:
    """Best-of-repeats seconds per period of Simulator.step over whole tosses."""
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        for qpos, qvel in starts:
            q, v = qpos, qvel
            for _ in range(periods):
                q, v = sim.step(q, v)
        best = min(best, (time.perf_counter() - t0) / (len(starts) * periods))
    return best


def _time_mujoco_rollout(sim: Simulator, starts: list[tuple[np.ndarray, np.ndarray]], periods: int) -> float:
    """Seconds per period of mujoco.rollout over a whole toss, one simulation, no Python in the loop."""
    data = mujoco.MjData(sim.model)
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        for qpos, qvel in starts:
            state = initial_state(sim.model, qpos, qvel, data)
            mj_rollout.rollout(sim.model, data, state[None], nstep=periods * sim.period_steps)
        best = min(best, (time.perf_counter() - t0) / (len(starts) * periods))
    return best


def main() -> None:
    trajs = _tosses()
    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(tmp) / "nominal"
        scene.mkdir()
        (scene / "scene.xml").write_text(NOMINAL_XML.read_text())
        train_residual(
            scene, trajs[:40], Path(tmp) / "residual", ResidualOptions(steps=300, dagger_rounds=0, gains=(1.0,))
        )
        plain = Simulator(Path(tmp) / "residual", use_residual=False)
        hybrid = Simulator(Path(tmp) / "residual")
        starts = [(t.qpos[0], t.qvel[0]) for t in trajs[40:60]]
        periods = 100
        for sim in (plain, hybrid):  # warm up
            _time_single(sim, starts[:2], 10, 1)
        t_plain = _time_single(plain, starts, periods, 3)
        t_hybrid = _time_single(hybrid, starts, periods, 3)
        t_c = _time_mujoco_rollout(plain, starts, periods)
        steps = plain.period_steps
        print(f"single simulation, one period = {steps} model steps ({plain.dt_s * 1e3:.3f} ms of simulated time):")
        for name, t in (("MuJoCo only (Simulator.step, residual off)", t_plain), ("MuJoCo + residual", t_hybrid)):
            print(f"  {name:44s} {t * 1e6:7.1f} us/period {t / steps * 1e6:6.2f} us/model step")
        print(f"  residual overhead: +{100 * (t_hybrid / t_plain - 1):.0f}% (target <= 50%)")
        print(f"  reference, mujoco.rollout (C loop, no residual): {t_c * 1e6:7.1f} us/period")

        batch = [trajs[i % len(trajs)] for i in range(1024)]
        for name, sim in (("residual off", plain), ("residual on", hybrid)):
            t0 = time.perf_counter()
            preds = sim.rollout(batch)
            seconds = time.perf_counter() - t0
            finite = all(np.isfinite(p.qpos).all() for p in preds)
            frames = sum(t.num_steps for t in batch)
            print(
                f"batch of {len(batch)} tosses ({frames} frames), {name}: {seconds:.2f} s, "
                f"{seconds / frames * 1e6:.1f} us/frame, all finite: {finite}"
            )


if __name__ == "__main__":
    main()
