"""Simulation: re-simulating recorded trajectories open loop with `mujoco.rollout`, a scene's files, and restitution.

- `rollout`: `simulate` and its parts (initial states, per-step controls, batched rollouts, the stability check) and
  the errors between two trajectories;
- `scene_files`: where a scene's MJCF is, the files it names (kept inside its folder), copying them, and loading the
  scene as a model (`load_scene_model`) or as a spec with its model (`load_scene_spec`);
- `rollout_files`: `run_rollout`, the ``image2sim rollout`` command's library side (a folder of predictions);
- `restitution`: the coefficient of restitution a body's contact parameters give, and the contact ``solref`` for one;
- `start_noise`: how wrong recorded first states are (measured from the recordings) and starts drawn to match;
- `sampled`: many (model, start) samples of each trajectory in batched `mujoco.rollout`, and the median of a fan;
- `sample_scores`: a fan against its recording: energy score, band coverage and width, best of N, median errors.

The names below are loaded on first use (PEP 562), so that importing one module does not import them all.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from image2sim_common.lazy import lazy_attributes

# name -> module that defines it
_LAZY = {
    "simulate": "grounder.sim.rollout",
    "free_body_errors": "grounder.sim.rollout",
    "free_joints": "grounder.sim.rollout",
    "step_indices": "grounder.sim.rollout",
    "SCENE_XML": "grounder.sim.scene_files",
    "copy_scene_files": "grounder.sim.scene_files",
    "load_scene_model": "grounder.sim.scene_files",
    "load_scene_spec": "grounder.sim.scene_files",
    "scene_xml_path": "grounder.sim.scene_files",
    "run_rollout": "grounder.sim.rollout_files",
    "run_sampled_rollout": "grounder.sim.rollout_files",
    "measure_start_noise": "grounder.sim.start_noise",
    "rollout_samples": "grounder.sim.sampled",
    "median_trajectory": "grounder.sim.sampled",
    "score_samples": "grounder.sim.sample_scores",
    "body_restitution": "grounder.sim.restitution",
    "contact_solref": "grounder.sim.restitution",
    "simulated_restitution": "grounder.sim.restitution",
}


__getattr__ = lazy_attributes(__name__, _LAZY)


if TYPE_CHECKING:  # what the lazy names are, for type checkers and editors
    from grounder.sim.restitution import body_restitution, contact_solref, simulated_restitution
    from grounder.sim.rollout import free_body_errors, free_joints, simulate, step_indices
    from grounder.sim.rollout_files import run_rollout, run_sampled_rollout
    from grounder.sim.sample_scores import score_samples
    from grounder.sim.sampled import median_trajectory, rollout_samples
    from grounder.sim.scene_files import SCENE_XML, copy_scene_files, load_scene_model, load_scene_spec, scene_xml_path
    from grounder.sim.start_noise import measure_start_noise

__all__ = [  # spelled out (not built from _LAZY) so that linters and type checkers read it
    "SCENE_XML",
    "body_restitution",
    "contact_solref",
    "copy_scene_files",
    "free_body_errors",
    "free_joints",
    "load_scene_model",
    "load_scene_spec",
    "measure_start_noise",
    "median_trajectory",
    "rollout_samples",
    "run_rollout",
    "run_sampled_rollout",
    "scene_xml_path",
    "score_samples",
    "simulate",
    "simulated_restitution",
    "step_indices",
]
