"""The ``image2sim rollout`` command's library side: re-simulate a trajectory folder on a scene (with the scene's
learned residual when it has one) and write the predictions, with a ``rollout.json`` record, as a new folder.

With ``samples`` (``--samples K``), each trajectory is simulated K times instead (`run_sampled_rollout`): parameters
drawn from the scene folder's ``distribution.json`` (``image2sim calibrate --distribution``), each start the
recorded one perturbed by the measured start noise stored there, all in batched `mujoco.rollout` calls. Per
trajectory it writes ``NAME.npz`` (the per-time-step median of the samples, `grounder.sim.sampled.median_trajectory`,
in the usual trajectory format) and ``NAME.samples.npz`` (``time`` (T,), ``qpos`` (K, T, nq), ``qvel`` (K, T, nv)).
A scene with a learned residual is stepped with it (``use_residual``), each correction drawn from its learned spread
(``grounder.residual.spread``).
"""

from __future__ import annotations

import importlib
import importlib.util
import json
from pathlib import Path
from typing import Any

import numpy as np

from grounder.core.trajectory import SAMPLES_SUFFIX, Trajectory, load_trajectories, save_trajectories
from grounder.errors import GrounderError
from grounder.sim.rollout import simulate
from grounder.sim.scene_files import load_scene_spec


def run_rollout(
    scene: Path, traj_dir: Path, out: Path, *, use_residual: bool = True, overwrite: bool = False
) -> tuple[list, bool]:
    """The ``rollout`` command's library side: returns (predicted trajectories, whether the residual was used).

    Uses ``grounder.residual.simulator.Simulator`` when that module exists, the scene folder has a residual and
    ``use_residual``; plain :func:`grounder.sim.rollout.simulate` otherwise. Writes the predictions (same file names as
    the recordings) and ``rollout.json`` (what was rolled out, with or without the residual).
    """
    from reconstruction import check_output_dir, staged_output_dir

    check_output_dir(out, overwrite=overwrite, error=GrounderError, inputs=(scene, traj_dir))
    _, model = load_scene_spec(scene)
    trajs = load_trajectories(traj_dir, model)
    simulator = _residual_simulator(scene) if use_residual else None
    used = simulator is not None
    if simulator is not None:
        preds = simulator.rollout(trajs, stable=True)
    else:
        preds = simulate(model, trajs, stable=True)
    with staged_output_dir(out, overwrite=overwrite, error=GrounderError, inputs=(scene, traj_dir)) as stage:
        save_trajectories(preds, stage)  # the whole folder replaced at once, as every command does
        record = {
            "format": "image2sim.rollout/1",
            "scene": str(scene),
            "trajectories": str(traj_dir),
            "residual": used,
            "files": sorted(f"{t.name}.npz" for t in preds),
        }
        (stage / "rollout.json").write_text(json.dumps(record, indent=1) + "\n")  # marks it as an image2sim output
    return list(preds), used


MAX_SAMPLES = 4096


def _residual_simulator(scene: Path) -> Any:
    """``grounder.residual.simulator.Simulator`` of the scene when that module exists and the scene folder has a
    residual; None otherwise. Half a residual (one of its files without the other) is an error, not a silent
    plain-MuJoCo run."""
    if importlib.util.find_spec("grounder.residual.simulator") is None:
        return None
    module = importlib.import_module("grounder.residual.simulator")
    scene_dir = scene if scene.is_dir() else scene.parent
    module.check_residual_pair(scene_dir)
    return module.Simulator(scene) if module.has_residual(scene_dir) else None


def run_sampled_rollout(
    scene: Path,
    traj_dir: Path,
    out: Path,
    *,
    samples: int,
    seed: int = 0,
    overwrite: bool = False,
    use_residual: bool = True,
    nthread: int | None = None,
) -> tuple[list[Trajectory], dict[str, np.ndarray]]:
    """``rollout --samples``: returns (median trajectories, qpos samples (K, T, nq) by name); writes ``out``.

    Raises:
        GrounderError: the scene folder has no ``distribution.json`` (or it does not fit the scene), or ``samples``
            is out of range.
    """
    from grounder.calibration.distribution import DISTRIBUTION_FILE, read_scene_distribution
    from grounder.sim.sampled import median_trajectory, rollout_samples
    from grounder.sim.start_noise import perturbed_starts
    from reconstruction import check_output_dir, staged_output_dir

    if not 1 <= samples <= MAX_SAMPLES:
        raise GrounderError(f"--samples must be between 1 and {MAX_SAMPLES}, got {samples}")
    check_output_dir(out, overwrite=overwrite, error=GrounderError, inputs=(scene, traj_dir))
    _, model = load_scene_spec(scene)
    scene_dir = scene if scene.is_dir() else scene.parent
    dist = read_scene_distribution(scene_dir, model.nv, "and roll out the folder that writes")
    # MuJoCo + the residual, its corrections drawn from its spread, when the folder has one
    simulator = _residual_simulator(scene) if use_residual else None
    trajs = load_trajectories(traj_dir, model)
    rng = np.random.default_rng(seed)
    models = dist.draw_models(model, samples, rng)
    starts = [perturbed_starts(model, t.qpos[0], t.qvel[0], dist.start_noise, samples, rng) for t in trajs]
    if simulator is not None:
        sims = simulator.sample(trajs, starts, rng, models=models)
    else:
        sims = rollout_samples(models, trajs, starts, nthread=nthread)
    medians = []
    fans: dict[str, np.ndarray] = {}
    for traj, (qpos, qvel) in zip(trajs, sims, strict=True):
        if not (np.all(np.isfinite(qpos)) and np.all(np.isfinite(qvel))):
            raise GrounderError(
                f"trajectory {traj.name}: a sampled simulation diverged (non-finite state); the distribution reaches "
                "parameters the scene cannot simulate: re-run calibrate --distribution with narrower --params bounds"
            )
        med_q, med_v = median_trajectory(model, qpos, qvel)
        medians.append(Trajectory(time_s=traj.time_s, qpos=med_q, qvel=med_v, ctrl=traj.ctrl, name=traj.name))
        fans[traj.name] = qpos
    with staged_output_dir(out, overwrite=overwrite, error=GrounderError, inputs=(scene, traj_dir)) as stage:
        save_trajectories(medians, stage)
        for traj, (qpos, qvel) in zip(trajs, sims, strict=True):
            np.savez(stage / f"{traj.name}{SAMPLES_SUFFIX}", time=traj.time_s, qpos=qpos, qvel=qvel)
        record = {
            "format": "image2sim.rollout/1",
            "scene": str(scene),
            "trajectories": str(traj_dir),
            "residual": simulator is not None,
            "samples": samples,
            "seed": seed,
            "distribution": DISTRIBUTION_FILE,
            "files": sorted(f"{t.name}.npz" for t in medians),
            "sample_files": sorted(f"{t.name}{SAMPLES_SUFFIX}" for t in medians),
        }
        (stage / "rollout.json").write_text(json.dumps(record, indent=1) + "\n")
    return medians, fans
