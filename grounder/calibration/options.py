"""The settings of one calibration, `CalibrateOptions` (also the ``image2sim calibrate`` options and a batch job's
``settings``), each field checked for type and range when the options are made.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from grounder.errors import GrounderError, finite_number, integer_in, shown

MAX_SEED = 2**32 - 1  # numpy's and scipy's seeds


@dataclass(frozen=True, kw_only=True)
class CalibrateOptions:
    """Settings of one calibration (also the ``image2sim calibrate`` options and a batch job's ``settings``).

    Attributes:
        params: Parameter specifications ``NAME`` or ``NAME=LOW:HIGH``; empty: the scene kind's defaults.
        mode: ``raw`` (parameters within bounds) or ``embedding`` (the object's property embedding).
        validation_fraction: Share of trajectories held out for validation.
        split_seed: Seed of the train/validation shuffle.
        max_train_trajectories: Fit on at most this many training trajectories (a seeded subset); None: all.
        rotation_weight: Percent-of-size per degree of rotation error in the loss (0: position only).
        view_point_m: World position (metres) of the camera that measured the trajectories (tracked from video);
            with ``along_view_weight`` the loss weighs the position error along the camera's viewing ray by that
            factor (`grounder.sim.rollout.along_view_weighted`): tracked depth is far noisier than the position
            across the image. None: every direction counts alike (motion capture, simulation).
        along_view_weight: Weight of the along-ray position error, in (0, 1]; used only with ``view_point_m``.
        global_search_trajectories: The global search (differential evolution) scores its candidates on a seeded
            subset of at most this many of the fitting trajectories; the local refinement, the intervals and the
            distribution use them all. None: all. The global search only has to land in the right basin, which a few
            dozen trajectories locate as well as a few hundred: on the 280 real training tosses, 48 here and all 280 in
            the refinement took 242 s at 13.1% held out, all 280 throughout 12 min at 13.3% (another day's machine;
            docs/results/speed.md).
        popsize: Differential-evolution population per parameter (SciPy's ``popsize``).
        generations: Differential-evolution generations (0 skips the global search).
        local_iterations: `mujoco.minimize.least_squares` iterations (0 skips the local refinement).
        fd_step: Finite-difference step in search coordinates (unit box); large, as contact losses are rough.
        interval_level: Two-sided level of the parameter intervals.
        seed: Seed of the global search.
        nthread: Rollout threads; None: the CPU cores this process may use.
        max_batch_mb: Memory cap of one rollout call's recorded states; larger batches are split.
        initial: Start values by parameter name instead of the scene's (the scene's stay the "nominal" ones that
            before/after compare with); with no search budget the result is these values, evaluated.
        robust_scale: Raw mode. None: the objective is the mean of the trajectories' losses. A number k: each
            trajectory's error r = sqrt(loss) enters through the pseudo-Huber function with scale c = k x the median
            r at the start values (quadratic below c, linear above), so one trajectory that cannot be matched (a
            badly tracked impact) weighs like a few, not like all the others together.
        separate_bodies: The bodies never touch each other (objects tossed apart): search each body's parameters on
            its own, one body after another, the others held at their current values. Exact when the loss is a
            sum over bodies that each depend only on their own parameters; each search is then a few dimensions
            instead of all of them, which a small budget covers. Raw mode, per-body parameters (``BODY.*``) only.
        distribution: Also fit a distribution over the parameters (`grounder.calibration.distribution`), written as
            ``distribution.json`` beside ``scene.xml``; on every training trajectory (``max_train_trajectories``
            bounds the point search only).
        distribution_params: The parameters given a spread (names among the calibrated ones; empty: every
            continuous one). Raw mode only: embedding mode spreads the embedding.
        distribution_samples: Parameter draws per iteration of the distribution fit.
        distribution_iterations: Iterations of the distribution fit.
        distribution_centre: ``fitted``: the fit finds the mean and the covariance; ``point``: the distribution is
            centred on the calibrated values and the fit finds its spread only (raw mode; embedding mode always fits
            both).
    """

    params: tuple[str, ...] = ()
    mode: Literal["raw", "embedding"] = "raw"
    validation_fraction: float = 0.3
    split_seed: int = 0
    max_train_trajectories: int | None = None
    global_search_trajectories: int | None = 48
    rotation_weight: float = 0.0
    view_point_m: tuple[float, float, float] | None = None
    along_view_weight: float = 1.0
    popsize: int = 8
    generations: int = 20
    local_iterations: int = 10
    fd_step: float = 0.02
    interval_level: float = 0.95
    seed: int = 0
    nthread: int | None = None
    max_batch_mb: float = 256.0
    initial: dict[str, float] = field(default_factory=dict)
    separate_bodies: bool = False
    robust_scale: float | None = None
    distribution: bool = False
    distribution_params: tuple[str, ...] = ()
    distribution_samples: int = 64
    distribution_iterations: int = 6
    distribution_centre: Literal["point", "fitted"] = "fitted"

    def __post_init__(self) -> None:
        # Options come from the CLI, a batch file's settings and Python callers: each field is checked for type and
        # range here, as a NaN weight or a float generation count would otherwise run a calibration that means nothing.
        def bad(name: str, expected: str) -> GrounderError:
            return GrounderError(f"calibrate option {name} must be {expected}, got {shown(getattr(self, name))}")

        def count(name: str, least: int, most: int | None = None, *, optional: bool = False) -> None:
            value = getattr(self, name)
            if optional and value is None:
                return
            if not integer_in(value, least, most):
                rule = f"an integer >= {least}" if most is None else f"an integer in [{least}, {most}]"
                raise bad(name, rule + (" or null" if optional else ""))

        def number(name: str, expected: str, ok: Callable[[float], bool], *, optional: bool = False) -> None:
            value = getattr(self, name)
            if optional and value is None:
                return
            if not (finite_number(value) and ok(float(value))):
                raise bad(name, expected + (" or null" if optional else ""))

        if self.mode not in ("raw", "embedding"):
            raise bad("mode", "'raw' or 'embedding'")
        if isinstance(self.params, str) or not isinstance(self.params, Sequence):
            raise bad("params", "a list of parameter names (NAME or NAME=LOW:HIGH)")
        if not all(isinstance(p, str) for p in self.params):
            raise bad("params", "a list of parameter names (text: NAME or NAME=LOW:HIGH)")
        object.__setattr__(self, "params", tuple(self.params))
        number("validation_fraction", "a number in [0, 1)", lambda v: 0.0 <= v < 1.0)
        count("split_seed", 0, MAX_SEED)
        count("max_train_trajectories", 1, optional=True)
        count("global_search_trajectories", 1, optional=True)
        number("rotation_weight", "a number in [0, 100] (percent of size per degree)", lambda v: 0.0 <= v <= 100.0)
        if self.view_point_m is not None:
            point = self.view_point_m
            if isinstance(point, str) or not isinstance(point, Sequence | np.ndarray) or len(point) != 3:
                raise bad("view_point_m", "3 finite numbers (x, y, z in metres) or null")
            if not all(finite_number(v) for v in point):
                raise bad("view_point_m", "3 finite numbers (x, y, z in metres) or null")
            object.__setattr__(self, "view_point_m", tuple(float(v) for v in point))
        number("along_view_weight", "a number in (0, 1]", lambda v: 0.0 < v <= 1.0)
        count("popsize", 1, 1000)  # per parameter: 1000 x 10 parameters is 10000 rollouts per generation
        count("generations", 0)
        count("local_iterations", 0)
        number("fd_step", "a number in (0, 1) (a step in the unit search box)", lambda v: 0.0 < v < 1.0)
        number("interval_level", "a number in (0, 1)", lambda v: 0.0 < v < 1.0)
        count("seed", 0, MAX_SEED)
        count("nthread", 1, 256, optional=True)  # 1e5 threads hung the run
        number("max_batch_mb", "a finite number > 0 (MiB)", lambda v: v > 0.0)
        if not isinstance(self.initial, Mapping) or not all(
            isinstance(k, str) and finite_number(v) for k, v in self.initial.items()
        ):
            raise bad("initial", "a mapping of parameter names to finite numbers")
        object.__setattr__(self, "initial", {k: float(v) for k, v in self.initial.items()})
        if not isinstance(self.separate_bodies, bool | np.bool_):
            raise bad("separate_bodies", "true or false")
        object.__setattr__(self, "separate_bodies", bool(self.separate_bodies))
        number("robust_scale", "a finite number > 0", lambda v: v > 0.0, optional=True)
        if not isinstance(self.distribution, bool | np.bool_):
            raise bad("distribution", "true or false")
        object.__setattr__(self, "distribution", bool(self.distribution))
        if isinstance(self.distribution_params, str) or not isinstance(self.distribution_params, Sequence):
            raise bad("distribution_params", "a list of parameter names")
        if not all(isinstance(p, str) for p in self.distribution_params):
            raise bad("distribution_params", "a list of parameter names (text)")
        object.__setattr__(self, "distribution_params", tuple(self.distribution_params))
        count("distribution_samples", 4, 4096)
        count("distribution_iterations", 1, 1000)
        if self.distribution_centre not in ("point", "fitted"):
            raise bad("distribution_centre", "'point' or 'fitted'")
        if self.distribution_params and self.mode != "raw":
            raise GrounderError("distribution_params applies to raw mode only (embedding mode spreads the embedding)")
        if self.separate_bodies and self.mode != "raw":
            raise GrounderError("separate_bodies applies to raw mode only")
        if self.robust_scale is not None and self.mode != "raw":
            raise GrounderError("robust_scale applies to raw mode only (embedding mode weighs its prior by the misfit)")
