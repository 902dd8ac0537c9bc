"""The ``image2sim rollout`` command's library side: re-simulate a trajectory folder on a scene (with the scene's
learned residual when it has one) and write the predictions, with a ``rollout.json`` record, as a new folder.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
from pathlib import Path

from grounder.core.trajectory import load_trajectories, save_trajectories
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
    used = False
    scene_dir = scene if scene.is_dir() else scene.parent
    if use_residual and importlib.util.find_spec("grounder.residual.simulator") is not None:
        module = importlib.import_module("grounder.residual.simulator")
        module.check_residual_pair(scene_dir)  # half a residual is an error, not a silent plain-MuJoCo run
        if module.has_residual(scene_dir):
            preds = module.Simulator(scene).rollout(trajs, stable=True)
            used = True
    if not used:
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
