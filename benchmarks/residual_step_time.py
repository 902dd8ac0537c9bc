"""What the residual costs: single-simulation step time with and without it, and a batch of 1024 rolled out.

Trains a small residual on 40 real cube tosses, its output gain forced to 1 (a gain of 0 would skip the work),
then:

- single simulation: ``Simulator.step`` (one period = one 148 Hz frame = 8 model steps of the cube scene) with
  ``use_residual=False`` and ``True``, (1) one period from each recorded frame of 20 held-out tosses: identical
  states, so the difference is the residual's own cost (the acceptance figure); (2) free rollouts of those
  tosses, 100 periods each from their first frames: each simulation follows its own trajectory, so MuJoCo's
  cost differs too (contacts); (3) as (1) from the states (2)'s rollouts with the residual visit, which splits
  (2)'s overhead into the residual's work and the other trajectory. On a shared machine one timing is noise, so
  with and without are interleaved over ``--rounds`` rounds (order alternating) and the report gives medians over
  rounds of per-call CPU time (``time.process_time``) and wall time, the median of the per-round ratios, and the
  share of periods in which the residual's network ran (its gate not exactly 0); plus MuJoCo's own
  ``mujoco.rollout`` of the same period (no Python in the loop) for reference;
- batch: 1024 tosses rolled out together with ``Simulator.rollout`` (MuJoCo batched over threads with
  ``mujoco.rollout``, the residual vectorised with numpy), with and without the residual.

Run: ``.venv/bin/python benchmarks/residual_step_time.py [--rounds 15] [--no-batch]`` (target: the residual adds
<= 50% to the single simulation's step time; the batch of 1024 rolls out). ``--arm`` times the joint-space
residual instead, on the withheld-effect two-link arm (one period = 5 model steps of 2 ms, controls as features).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from grounder.core.trajectory import Trajectory  # noqa: E402
from grounder.residual.options import ResidualOptions  # noqa: E402
from grounder.residual.simulator import Simulator  # noqa: E402
from grounder.residual.train import train_residual  # noqa: E402
from grounder.sim.rollout import initial_state  # noqa: E402

DATA = REPO.parent / "shared" / "data" / "cube_toss"
NOMINAL_XML = REPO / "samples" / "cube_toss" / "cube.xml"


def _tosses() -> list[Trajectory]:
    if DATA.is_dir():
        from grounder.core.importers import load_dair_pll_cube

        return load_dair_pll_cube(DATA)
    raise SystemExit(f"{DATA} is absent; this benchmark needs the real cube tosses")


def _time_single(sim: Simulator, starts: list[tuple[np.ndarray, np.ndarray]], periods: int) -> tuple[float, float]:
    """(CPU, wall) seconds per period of Simulator.step over whole tosses."""
    cpu0, wall0 = time.process_time(), time.perf_counter()
    for qpos, qvel in starts:
        q, v = qpos, qvel
        for _ in range(periods):
            q, v = sim.step(q, v)
    calls = len(starts) * periods
    return (time.process_time() - cpu0) / calls, (time.perf_counter() - wall0) / calls


def _time_states(sim: Simulator, states: Sequence[tuple[np.ndarray, ...]]) -> tuple[float, float]:
    """(CPU, wall) seconds per call of Simulator.step, one call from each of the given (qpos, qvel[, ctrl])."""
    cpu0, wall0 = time.process_time(), time.perf_counter()
    for state in states:
        sim.step(*state)
    return (time.process_time() - cpu0) / len(states), (time.perf_counter() - wall0) / len(states)


def _visited(sim: Simulator, starts: list[tuple[np.ndarray, np.ndarray]], periods: int) -> list[tuple[np.ndarray, ...]]:
    states = []
    for qpos, qvel in starts:
        q, v = qpos, qvel
        for _ in range(periods):
            states.append((q, v))
            q, v = sim.step(q, v)
    return states


def _open_gate_share(sim: Simulator, states: list[tuple[np.ndarray, np.ndarray]]) -> float:
    """Share of states whose gate (times the output gain) is not exactly 0: where the network runs."""
    from grounder.residual.free_body import body_features

    assert sim.residual is not None
    feats, _ = body_features(np.stack([s[0] for s in states]), np.stack([s[1] for s in states]), sim.residual.bodies)
    return float(np.mean(sim.residual.gate(feats) * sim.residual.out_gain > 0.0))


def _interleaved(
    plain: Callable[[], tuple[float, float]], hybrid: Callable[[], tuple[float, float]], rounds: int
) -> np.ndarray:
    """(rounds, 4): CPU plain, CPU hybrid, wall plain, wall hybrid; the order alternates from round to round."""
    rows = []
    for r in range(rounds):
        if r % 2 == 0:
            (cpu_p, wall_p), (cpu_h, wall_h) = plain(), hybrid()
        else:
            (cpu_h, wall_h), (cpu_p, wall_p) = hybrid(), plain()
        rows.append((cpu_p, cpu_h, wall_p, wall_h))
    return np.array(rows)


def _report(title: str, times: np.ndarray, steps: int, share: float) -> float:
    """Prints medians and overheads of :func:`_interleaved` times; returns the CPU overhead (median ratio - 1)."""
    med = np.median(times, axis=0)
    ratio_cpu, ratio_wall = times[:, 1] / times[:, 0], times[:, 3] / times[:, 2]
    print(f"{title}; medians over {len(times)} interleaved rounds:")
    for name, cpu, wall in (
        ("MuJoCo only (Simulator.step, residual off)", med[0], med[2]),
        ("MuJoCo + residual", med[1], med[3]),
    ):
        print(
            f"  {name:44s} CPU {cpu * 1e6:7.1f} us/period ({cpu / steps * 1e6:5.2f} us/model step), "
            f"wall {wall * 1e6:7.1f} us/period"
        )
    overhead = float(np.median(ratio_cpu) - 1)
    print(
        f"  residual overhead, CPU time: {100 * overhead:+.0f}% (median of per-round ratios; "
        f"rounds {100 * (ratio_cpu.min() - 1):+.0f}% .. {100 * (ratio_cpu.max() - 1):+.0f}%; "
        f"ratio of medians {100 * (med[1] / med[0] - 1):+.0f}%)  target <= 50%"
    )
    print(
        f"  residual overhead, wall time: {100 * (np.median(ratio_wall) - 1):+.0f}% (median of per-round ratios; "
        f"ratio of medians {100 * (med[3] / med[2] - 1):+.0f}%)"
    )
    print(f"  periods in which the network ran (gate not exactly 0): {100 * share:.0f}%")
    return overhead


def _time_correction_alone(
    plain: Simulator, hybrid: Simulator, frames: Sequence[tuple[np.ndarray, ...]], mujoco_s: float
) -> None:
    """Prints the residual's own cost, timed alone: its single-state correction (what ``Simulator.step`` adds to
    MuJoCo's period) on each of ``frames`` and MuJoCo's prediction from it, best of 5 passes; ``mujoco_s``: MuJoCo's
    period, for the ratio. Less exposed to the machine's noise than the interleaved rounds: no MuJoCo in the loop."""
    residual = hybrid.residual
    assert residual is not None
    pairs = []
    for q0, v0, *ctrl in frames:
        q1, v1 = plain.step(q0, v0, *ctrl)
        pairs.append((q0, v0, q1, v1, *ctrl))
    best = np.inf
    for _ in range(5):
        work = [(q0, v0, q1.copy(), v1.copy(), *ctrl) for q0, v0, q1, v1, *ctrl in pairs]
        cpu0 = time.process_time()
        for args in work:
            residual.correct_one(*args)
        best = min(best, (time.process_time() - cpu0) / len(work))
    print(
        f"  the residual's correction alone (the single-state path Simulator.step runs after MuJoCo), best of 5 "
        f"passes over the same states: CPU {best * 1e6:.1f} us per period, {100 * best / mujoco_s:+.0f}% of "
        "MuJoCo's period above"
    )


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


def arm(rounds: int) -> None:
    """The joint-space residual on the withheld-effect arm (weak motors): one period from each recorded state."""
    from grounder.diagnosis.benchmark import select_cases
    from grounder.diagnosis.cases import make_case
    from grounder.residual.joint import NumpyJointResidual, joint_features

    case = make_case(select_cases(["arm/actuator_gain"])[0], 36, seed=0)
    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(tmp) / "nominal"
        scene.mkdir()
        (scene / "scene.xml").write_text(case.scene_xml)
        train_residual(scene, case.trajectories[:16], Path(tmp) / "residual", ResidualOptions(steps=300, gains=(1.0,)))
        plain = Simulator(Path(tmp) / "residual", use_residual=False)
        hybrid = Simulator(Path(tmp) / "residual")
        rows = [(q, v, u) for t in case.trajectories[16:] for q, v, u in zip(t.qpos, t.qvel, t.ctrl, strict=True)]
        for sim in (plain, hybrid):  # warm up
            _time_states(sim, rows)
        times = _interleaved(lambda: _time_states(plain, rows), lambda: _time_states(hybrid, rows), rounds)
        residual = hybrid.residual
        assert isinstance(residual, NumpyJointResidual)
        feats = joint_features(*(np.stack([r[i] for r in rows]) for i in range(3)), residual.space)
        share = float(np.mean(residual.gate(feats) * residual.out_gain > 0.0))
        _report(
            f"two-link arm (joint-space residual, controls as features): one period ({plain.period_steps} model "
            f"steps) from each of the {len(rows)} recorded states of 20 held-out trajectories",
            times,
            plain.period_steps,
            share,
        )
        _time_correction_alone(plain, hybrid, rows, float(np.median(times[:, 0])))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=15, help="interleaved timing rounds (medians over them)")
    parser.add_argument("--periods", type=int, default=100, help="periods per toss in each round")
    parser.add_argument("--no-batch", action="store_true", help="skip the batch of 1024")
    parser.add_argument("--arm", action="store_true", help="only the joint-space residual on a two-link arm")
    args = parser.parse_args()
    if args.arm:
        arm(args.rounds)
        return
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
        held_out = trajs[40:60]
        steps = plain.period_steps
        print(f"single simulation, one period = {steps} model steps ({plain.dt_s * 1e3:.3f} ms of simulated time)")
        # (1) the same states for both: every recorded frame of 20 held-out tosses, one period from each
        frames = [(q, v) for t in held_out for q, v in zip(t.qpos, t.qvel, strict=True)]
        for sim in (plain, hybrid):  # warm up
            _time_states(sim, frames[:200])
        times = _interleaved(lambda: _time_states(plain, frames), lambda: _time_states(hybrid, frames), args.rounds)
        _report(
            f"(1) one period from each of the {len(frames)} recorded frames of {len(held_out)} held-out tosses "
            "(identical states with and without the residual: its cost)",
            times,
            steps,
            _open_gate_share(hybrid, frames),
        )
        _time_correction_alone(plain, hybrid, frames, float(np.median(times[:, 0])))
        # (2) free rollouts: each simulation follows its own trajectory, so MuJoCo's own cost differs too
        starts = [(t.qpos[0], t.qvel[0]) for t in held_out]
        periods = args.periods
        times = _interleaved(
            lambda: _time_single(plain, starts, periods), lambda: _time_single(hybrid, starts, periods), args.rounds
        )
        _report(
            f"(2) free rollouts, {len(starts)} held-out tosses x {periods} periods from their first frames (the "
            "residual changes the trajectory, hence contacts and MuJoCo's cost as well)",
            times,
            steps,
            _open_gate_share(hybrid, _visited(hybrid, starts, periods)),
        )
        # (3) as (1), from the states that (2)'s rollouts with the residual visit: its cost along them
        visited = _visited(hybrid, starts, periods)
        times = _interleaved(lambda: _time_states(plain, visited), lambda: _time_states(hybrid, visited), args.rounds)
        _report(
            f"(3) one period from each of the {len(visited)} states visited by (2)'s rollouts with the residual "
            "(identical states with and without it)",
            times,
            steps,
            _open_gate_share(hybrid, visited),
        )
        # MuJoCo alone from the states of its own rollouts vs from those of the rollouts with the residual
        own = _visited(plain, starts, periods)
        times = _interleaved(lambda: _time_states(plain, own), lambda: _time_states(plain, visited), args.rounds)
        print(
            f"  MuJoCo alone, one period from each state of its own rollouts in (2) vs of those with the residual: "
            f"{np.median(times[:, 0]) * 1e6:.1f} vs {np.median(times[:, 1]) * 1e6:.1f} us CPU, "
            f"{100 * (np.median(times[:, 1] / times[:, 0]) - 1):+.0f}% (median of per-round ratios): the part of (2)'s "
            "overhead that is the other trajectory, not the residual's work"
        )
        t_c = _time_mujoco_rollout(plain, starts, periods)
        print(f"  reference, mujoco.rollout (C loop, no residual): {t_c * 1e6:7.1f} us/period")
        if args.no_batch:
            return

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
