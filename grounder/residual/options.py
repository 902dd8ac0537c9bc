"""What :func:`grounder.residual.train.train_residual` takes and returns: its options and its result.

:class:`ResidualOptions` (also the CLI's ``residual train`` options) with ``COUNT_LIMITS``, the ranges its integer
options are checked against, and :class:`ResidualTrainResult`, what a training wrote and how it went.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from grounder.errors import GrounderError, integer_in, shown
from grounder.residual.meta import GateOptions


@dataclass(frozen=True, kw_only=True)
class ResidualOptions:
    """How the residual is trained (also the CLI's ``residual train`` options).

    Attributes:
        hidden: Width of each hidden layer of the per-body MLP.
        layers: Hidden layers.
        steps: Optimiser steps per round.
        batch_size: Samples per optimiser step.
        learning_rate: Adam's learning rate (cosine-decayed to 5% within each round).
        weight_decay: AdamW weight decay.
        dagger_rounds: Rounds of data aggregation along rollouts after the one-step round (default 0: on the
            real cube tosses two rounds made held-out rollouts worse, 29.8% -> 40.9% of the cube width at gain 1).
        dagger_horizon: Periods each aggregation rollout runs.
        dagger_stride: A rollout starts at every this many-th recorded sample.
        dagger_max_pos_error_m: Rollout states farther than this from the recording are not used as targets.
        dagger_max_rot_error_deg: Same, for the orientation.
        dagger_pull: Fraction of a rollout state's drift from the recording that its target takes back in one
            period; the rest of the target matches the recorded increment (1 is plain data-as-demonstrator, whose
            one-period jumps back to the recording are not learnable from the state alone).
        ctrl_history_s: A joint-space residual (scenes of hinge and slide joints with actuators) also sees the
            controls of the periods within this many seconds before the present one, so that an actuator's delay
            or lag can be learnt.
        smooth_window: Train on free-body poses smoothed over this many samples and velocities re-estimated
            from them (``grounder.residual.free_body.smooth_free_bodies``); 0 (default) trains on the recording as it
            is. On the real cube tosses smoothing over 5 samples made rollouts worse (it blurs the impacts).
        selection_fraction: Share of the trajectories (seeded) held out of fitting to choose the output gain.
        gains: Candidate output gains; the one whose multi-step rollouts of the held-out trajectories (from
            their first state) are best is kept. 0 is MuJoCo alone, so a residual that does not help is switched
            off rather than shipped.
        bound_quantile: Each output component is capped at this quantile of the absolute training targets.
        gate: Where the correction is active (see ``GateOptions``).
        spread: Also learn a state-dependent spread of the correction (``grounder.residual.spread``; free bodies).
        spread_hidden: Width of the spread's hidden layer.
        spread_steps: Optimiser steps of its negative log-likelihood fit.
        spread_gains: Candidate spread gains (0: no spread), chosen by the energy score of sampled rollouts of the
            held-out trajectories.
        spread_samples: Sampled rollouts per held-out trajectory for that choice.
        seed: Seeds initialisation, shuffling and k-means.
        num_threads: torch threads (results are reproducible for a given value; 1 is fastest on a busy machine).
    """

    hidden: int = 64
    layers: int = 2
    steps: int = 2000
    batch_size: int = 256
    learning_rate: float = 3e-3
    weight_decay: float = 1e-4
    dagger_rounds: int = 0
    dagger_horizon: int = 30
    dagger_stride: int = 4
    dagger_max_pos_error_m: float = 0.03
    dagger_max_rot_error_deg: float = 30.0
    dagger_pull: float = 0.2
    smooth_window: int = 0
    ctrl_history_s: float = 0.05
    selection_fraction: float = 0.2
    gains: tuple[float, ...] = (0.0, 0.25, 0.5, 1.0)
    bound_quantile: float = 0.995
    gate: GateOptions = field(default_factory=GateOptions)
    spread: bool = True
    spread_hidden: int = 32
    spread_steps: int = 400
    spread_gains: tuple[float, ...] = (0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 1.0, 2.0)
    spread_samples: int = 8
    seed: int = 0
    num_threads: int = 1

    def __post_init__(self) -> None:
        for name, (low, high) in COUNT_LIMITS.items():  # high: a network or run that could never finish or fit
            value = getattr(self, name)
            if not integer_in(value, low, high):
                raise GrounderError(f"residual option {name} must be an integer in [{low}, {high}], got {shown(value)}")
        if not 0.0 <= self.ctrl_history_s <= 1.0:
            raise GrounderError(f"ctrl_history_s must be in [0, 1] s, got {self.ctrl_history_s}")
        if self.smooth_window < 0 or (self.smooth_window > 2 and self.smooth_window % 2 == 0):
            raise GrounderError(f"smooth_window must be 0 or odd, got {self.smooth_window}")
        if not all(isinstance(g, int | float) and 0.0 <= g <= 100.0 for g in self.spread_gains):
            raise GrounderError(f"spread_gains must be numbers in [0, 100], got {shown(self.spread_gains)}")
        if not 0.5 < self.bound_quantile <= 1.0:
            raise GrounderError(f"bound_quantile must be in (0.5, 1], got {self.bound_quantile}")


COUNT_LIMITS = {
    "hidden": (1, 4096),  # 4096 wide: 16 M weights per layer
    "layers": (1, 16),
    "steps": (1, 1_000_000),
    "batch_size": (1, 65_536),
    "dagger_rounds": (0, 100),
    "dagger_horizon": (1, 100_000),
    "dagger_stride": (1, 100_000),
    "spread_hidden": (1, 4096),
    "spread_steps": (0, 1_000_000),
    "spread_samples": (2, 1024),
    "seed": (0, 2**32 - 1),  # numpy's and torch's seeds
    "num_threads": (1, 256),
}


@dataclass(frozen=True, kw_only=True)
class ResidualTrainResult:
    """What ``train_residual`` wrote and how training went.

    Attributes:
        out: The residual scene folder.
        num_trajectories: Trajectories trained on.
        num_samples: Training samples in the last round (one-step and aggregated).
        one_step_rms_before: Per output group (pos m, rot rad, vel m/s, omega rad/s), RMS of the one-step error of
            MuJoCo alone on the recorded transitions.
        one_step_rms_after: The same with the residual at gain 1 (before the gain is chosen).
        seconds: Wall time.
        gain: The output gain chosen on held-out rollouts (0: the residual is switched off).
        gain_scores: Held-out rollout score per candidate gain (mean over trajectories of the time-averaged
            position error / body size + time-averaged rotation error / 100 deg; jointed scenes: joint error).
        space: ``free`` (free bodies) or ``joint`` (hinge and slide joints; the one-step RMS tuples are then
            (joint position, 0, joint velocity, 0) in rad or m, and rad/s or m/s).
    """

    out: Path
    gain: float
    gain_scores: dict[float, float]
    num_trajectories: int
    num_samples: int
    one_step_rms_before: tuple[float, float, float, float]
    one_step_rms_after: tuple[float, float, float, float]
    seconds: float
    space: str = "free"
