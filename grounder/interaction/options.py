"""The settings and result of `ground --interaction` (`grounder.interaction.pipeline.ground_with_interaction`):
`InteractionOptions` (each stage's settings and the calibration method), `ImpactOptions` (the impacts calibration's,
`grounder.interaction.impacts`), `InteractionResult`, and the constants they start from: the screen's thresholds
(what tracking resolves), the calibration methods, the contact values calibrated per object (`default_params`) and
the windowed calibration's search settings (`CALIBRATE_SETTINGS`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from grounder.errors import GrounderError
from grounder.grounding.pipeline import GroundOptions
from grounder.interaction.shooting import ShootingOptions
from grounder.tracking.options import TrackOptions, TrackResult

# What tracking resolves (about its median error): a parameter whose +-20% step moves its object's rollouts by less,
# root mean square over the frames, is left at the prior (`screen_parameters`, `InteractionOptions.identify_*`).
SCREEN_MIN_POSITION_M = 0.001
SCREEN_MIN_ROTATION_DEG = 0.75
# `InteractionOptions.calibration`: windows from tracked starts, multiple shooting over each object's whole run, or
# the impacts between its free flights.
CALIBRATION_METHODS = ("windows", "shooting", "impacts")


CONTACT_FIELDS = ("friction.sliding", "solref.dampratio", "solref.timeconst")
# Calibration settings per object (three parameters), under `InteractionOptions.calibrate_settings`. Search: on the
# true motion of `samples/toss` from a prior of friction 0.45, damping ratio 0.4 and time constant 0.01 s,
# calibration's default 20 generations x 8 per parameter left the can's friction at +266% (a flat stretch of the
# loss); 30 x 10 finds every value within 3%. Robust loss: a window that starts at a badly tracked impact cannot be
# matched, and under the mean loss it alone moved scan F's bowl to friction x3.3; with `robust_scale` 0.5 eight
# scan-and-clip pairs of `benchmarks/track.py` came out 33 of 42 values within 20% (30 of 42 without; 32 at 1.0).
CALIBRATE_SETTINGS: dict[str, Any] = {"generations": 30, "popsize": 10, "robust_scale": 0.5}


@dataclass(frozen=True, kw_only=True)
class ImpactOptions:
    """Settings of `fit_impacts`.

    Attributes:
        clearance_m: a frame is clear (in flight) when the object's collision geometry is farther than this from every
            static geom.
        min_flight_frames: a flight has at least this many frames (2: the least that gives a position and a velocity
            with known curvature; the start covariance carries how uncertain that is). A run of clear frames is
            cut in two only into flights of 3 frames or more, which can show that they are not one flight.
        max_gap_s: two flights at most this far apart (last frame of one to first of the next) bracket one impact.
        position_sigma_m: the tracked centre of mass's error per axis where it cannot be estimated (and the scale
            outliers are measured in).
        rotation_sigma_deg: the tracked orientation's error per axis where it cannot be estimated.
        estimate_noise: estimate both from the object's own flights (the residuals of its flights of 3 frames or
            more, pooled), floored at `min_position_sigma_m` and `min_rotation_sigma_deg`. The residuals see only
            the frame-to-frame part of the tracking error; the part that drifts slowly over a few frames bends no
            parabola but does move a flight's end velocity. On `samples/toss` the bowl's flight residuals give
            0.2 mm while its tracked centre is 0.2-1.8 mm off the true one, in runs of frames; hence the floor of
            0.5 mm, about the per-axis tracking error against the truth (with 0.2 mm: 19 of 21 resolved values
            within 20% and 9 unresolved on scan D's five clips; with 0.5 mm 21 of 23 and 7).
        drift_sigma_m, drift_time_s: the part of the tracking error that drifts: an error along the camera's viewing
            ray (depth) that changes slowly, modelled as a Gaussian process with this standard deviation and
            correlation time (squared exponential) over the flight's frames and the frames compared after it. It
            moves the flight's fitted start and the compared frames together, and no flight's residuals show it.
            Model-based tracking reads depth from apparent size, so a grounded mesh or texture a little off places
            the object off along the ray. Sized (4 mm, 0.3 s; 2026-11-26) with the can's visual mesh snapped onto
            its cylinder (`GroundOptions.cylinder_snap`): tracked against that scan, `samples/toss`'s can is about
            1 mm nearer than true in flight (along-ray RMS of the moving objects 2.4 mm; the scan's rippled can was
            4.4-9.4 mm nearer, RMS 6.7 mm, and the drift was sized from it, 6 mm, and before from the bowl, 1 mm
            over 0.1 s). With 2 or 3 mm the can's values held in every sub-micrometre copy of `samples/toss` too,
            but 2 mm gave two wrong values on the held-out clips and 3 mm one; figures of each in
            docs/results/interaction.md and docs/interaction_history.md. Carried by the sampled propagation
            (`start_samples`) and the first, ballistic guess; needs a view point. 0 turns it off.
        drift_rotation_deg: the same for the tracked orientation (per axis, world frame; same correlation time).
        outlier_sigmas: a single frame this many sigmas off its flight's fit is dropped.
        friction_grid, restitution_grid, timeconst_grid: the grid searched (restitution at 1 m/s; time constants
            below `grounder.sim.restitution.MIN_TIMECONST_STEPS` steps are raised to it).
        delta_chi2: a value's range is that of the grid points within this chi-square increase of the best, times
            the misfit per degree of freedom where that exceeds 1 (4: two sigmas).
        resolution_fraction: a value is resolved where its range lies within this fraction of the best value (and
            away from the grid's ends).
        max_post_s: at most this much after the contact is compared (longer flights add little but cost steps).
        start_samples: how the start's uncertainty is carried to the compared frames: N, the sample covariance of N
            rollouts from starts drawn from it (seed `start_seed`); 0, a linear map (a secant Jacobian, 24 rollouts
            per impact). Over 0.3 s of bouncing and sliding the map is far from linear: on synthetic throws (three
            noise seeds, two throws) the secant left the chi-square at 2.5-7 per degree of freedom against 1.2-3
            sampled; on five tracked clips of scan D (noise floor 0.2 mm) it gave 21 of 27 resolved values within
            20% (6 wrong, mostly the held-out can) against 19 of 21 (2 wrong) sampled, which leaves more unresolved.
        start_seed: the draws' seed.
        compare: "flight": a contact counts where a second flight follows it, and that flight's frames are compared;
            "frames": every flight that ends in a contact counts, and every tracked frame after it (in flight, in
            contact, sliding) is compared, for at most `max_post_s`.
        compare_rotation: compare the simulated orientation with the tracked one at the compared frames as well as
            the centre of mass (rotation residuals, world frame, with the tracking's rotation noise): the friction
            that turns a landing's slide into spin shows in the orientation more than in the centre's path.
        stability_copies, stability_m: the fit is repeated on this many copies of the tracks with every tracked
            position moved by `stability_m` per axis (seeded; 0.1 um, the rounding of `track.json`), and a value
            stays resolved only where every copy resolves it within `resolution_fraction` of the first fit's best.
            A tumbling landing on convex hulls can be chaotic at that scale (which hull vertex touches first turns
            the spin): on `samples/toss`, with a drift of 1 mm (below the can's), the can's friction was -5% from
            the saved tracks and +29%, +57% or unresolved from such copies (`benchmarks/impacts_stability.py`), so
            a single fit would report a value the clip does not measure. Each copy also draws its own start states
            (`start_seed` + 1, + 2, ...): from the tracks of 2026-11-27's `ground --interaction` run on
            `samples/toss`, the can's friction fitted with start seeds 0-3 came out +29%, +29% (resolved), best
            +42% (unresolved) and +5% (resolved). 0 turns the check off.
        windows_for_unresolved: in `ground --interaction`, the values the impacts leave unresolved (friction where
            every landing sticks, everything of an object that only slides) are then screened and calibrated on
            windows, as the windowed calibration does, with the impacts' values written in
            (`grounder.interaction.per_object._windows_for_unresolved`).
    """

    clearance_m: float = 0.01
    min_flight_frames: int = 2
    max_gap_s: float = 0.12
    position_sigma_m: float = 1e-3
    rotation_sigma_deg: float = 1.0
    estimate_noise: bool = True
    min_position_sigma_m: float = 5e-4
    min_rotation_sigma_deg: float = 0.5
    drift_sigma_m: float = 4e-3
    drift_time_s: float = 0.3
    drift_rotation_deg: float = 1.0
    outlier_sigmas: float = 4.0
    friction_grid: tuple[float, ...] = tuple(float(v) for v in np.geomspace(0.1, 1.5, 28))
    restitution_grid: tuple[float, ...] = tuple(float(v) for v in np.linspace(0.1, 0.9, 33))
    timeconst_grid: tuple[float, ...] = tuple(float(v) for v in np.geomspace(0.012, 0.04, 6))
    delta_chi2: float = 4.0
    resolution_fraction: float = 0.2
    max_post_s: float = 0.3
    compare: str = "frames"
    start_samples: int = 64
    start_seed: int = 0
    compare_rotation: bool = True
    stability_copies: int = 2
    stability_m: float = 1e-7
    windows_for_unresolved: bool = True

    def __post_init__(self) -> None:
        if not self.clearance_m > 0:
            raise GrounderError(f"clearance_m={self.clearance_m} but expected a positive distance in metres")
        if self.min_flight_frames < 2:
            raise GrounderError(f"min_flight_frames={self.min_flight_frames} but expected 2 or more")
        if not self.max_gap_s > 0 or not self.max_post_s > 0:
            raise GrounderError("max_gap_s and max_post_s must be positive durations in seconds")
        if not self.drift_sigma_m >= 0 or not self.drift_rotation_deg >= 0 or not self.drift_time_s > 0:
            raise GrounderError("drift_sigma_m and drift_rotation_deg must be >= 0 and drift_time_s positive (s)")
        if not self.position_sigma_m > 0 or not self.outlier_sigmas > 0 or not self.delta_chi2 > 0:
            raise GrounderError("position_sigma_m, outlier_sigmas and delta_chi2 must be positive")
        for name in ("friction_grid", "restitution_grid", "timeconst_grid"):
            grid = np.asarray(getattr(self, name), np.float64)
            if len(grid) < 1 or np.any(grid <= 0) or np.any(np.diff(grid) <= 0):
                raise GrounderError(f"{name} must be positive values in increasing order")
        if self.stability_copies < 0 or not self.stability_m > 0:
            raise GrounderError("stability_copies must be >= 0 and stability_m a positive distance in metres")
        if self.compare not in ("flight", "frames"):
            raise GrounderError(f"compare={self.compare!r} but expected 'flight' or 'frames'")
        if np.any(np.asarray(self.restitution_grid) > 1.0):
            raise GrounderError("restitution_grid values must lie in (0, 1]")


@dataclass(frozen=True, kw_only=True)
class InteractionOptions:
    """Settings of `ground_with_interaction`.

    Attributes:
        ground: how the scan is grounded.
        track: how the clip is tracked; its `aruco_size_m` defaults to the scan's (`ground.reconstruct.aruco_size_m`).
        calibrate_params: parameters to fit (calibration's names); None: per object its sliding friction, its
            contact damping ratio (MuJoCo's restitution knob, `solref` dampratio) and its contact time constant
            (`solref` timeconst). A bounce's height depends on both solref values at MuJoCo's time step, so a time
            constant held at the prior biases the damping ratio: the property model gave `samples/tabletop`'s
            ceramic bowl 0.0086 s (rendered: 0.02 s), and with it held there the bowl's damping ratio came out +33%;
            calibrated too, it came out 0.0200 s and the damping ratio +0% (scan E, `benchmarks/track.py`). Each is
            screened like the others, except that a time constant is fitted wherever its body's damping ratio is
            (`_paired`).
        calibrate_settings: extra `CalibrateOptions` fields (e.g. {"generations": 10}), over `CALIBRATE_SETTINGS`.
        window_s: length of the calibration windows cut from the tracked segments, each rolled out from its first
            state (None: whole segments). Short windows keep a bounce's chaos from swamping the fit: rolled out
            over a whole toss, a 1% change of anything moves a tumbling object by centimetres.
        window_stride_s: start-to-start distance of the windows.
        per_object: when the objects never touch each other (`separable_bodies`), calibrate each one alone in a
            scene of its own, on windows that start where its state is well measured (`calibrate_per_body`).
        own_runs: with `per_object`, cut each object's windows from its own tracked runs, without the frames the
            backward pass recovered (`grounder.tracking.output.object_trajectories`), instead of from the segments
            in which every object is tracked. On scan H2 of `samples/tabletop` (`benchmarks/track.py --calibrate`): the
            toss went from 5 values within 20% and the can's friction unresolved to all 6 within 20% (the can's
            friction -4%); the occluded clip (box hidden in frames 20-40) from 3 of 4 to 4 of 4.
        rotation_weight: percent of the object's size per degree of rotation error in the loss; low, as tracked
            orientations and spins are noisier (about 1 degree) than positions.
        min_motion_m_s: windows where no object moves faster than this are dropped.
        identify: screen the parameters first (`screen_parameters`) and calibrate only those the clip constrains;
            the others keep the prior (the grounded scene's value) and are reported as unconstrained.
        identify_relative_change, identify_min_position_m, identify_min_rotation_deg: the screen's test: moving
            the parameter by this fraction must change its body's rollout by at least this much (root mean square
            over the frames; about the median tracking error measured on `samples/toss`, 0.83 mm and 0.47 deg). At
            2 mm / 1.5 deg (twice that) the screen dropped the box's damping ratio and the can's friction, which,
            fitted anyway, came out within 10% and 18% of the rendered values: the clip does resolve them.
        along_view_weight: weight of the position error along the camera's viewing ray in the calibration's loss
            and the start refits (`grounder.sim.rollout.along_view_weighted`). Tracked depth is 4-6 times noisier
            than the position across the image (`samples/toss`, four scans: 0.9-3.6 mm against 0.2-0.8 mm root mean
            square per axis), so it counts a quarter. The screen keeps all directions alike (its thresholds are
            the unweighted tracking error).
        start_rounds: after the first calibration, this many rounds of refitting each window's start state with
            the calibrated values (`grounder.interaction.starts`) and calibrating again (0: tracked starts only).
            Off by default: on tracked clips two rounds brought more values within 20% (21 of 27 against 19 of 26
            over four scans), but on the true motion of `samples/toss` one round moved the starts by at most 0.5 mm
            and 1 cm/s and the can's friction from -1% to +190%: where a parameter's loss is nearly flat the
            starts absorb what decides it.
        start_speed_error_m_s: the start-speed error (typical of tracking) under which each calibrated value is
            profiled again (`start_error_ranges`): the report gives each value's range under it and flags a value
            whose range goes past the screen's step as resting on the starts' accuracy (`start_sensitive`). The
            value itself is kept. 0: not computed.
        start_state_draws: how many random whole-state start errors `start_error_ranges` also profiles under: in
            each, every window's start moves by `start_position_error_m`, `start_rotation_error_deg`,
            `start_speed_error_m_s` and `start_spin_error_rad_s` (standard deviations per axis, seeded). A landing's
            outcome turns on the whole start, not only its speed: on a held-out toss (`samples/make_toss.py
            --heldout`) the can's tracked starts, 1-2 mm, about 1 deg and 30 mm/s off, put its friction at -35% and
            its damping ratio at +37%, each part of the start alone most of that, and the speed-only profile did not
            flag either. 0: the speed-only profile.
        start_position_error_m, start_rotation_error_deg, start_spin_error_rad_s: the whole-state draws' sizes, about
            tracking's error at a window start on `samples/toss` and the held-out toss.
        calibration: "impacts" (the default: `impacts`, below), "windows" (the above) or "shooting": with
            `per_object`, each object's contact values fitted
            with every state of its whole tracked run by multiple shooting (`grounder.interaction.shooting.
            fit_contact`, settings `shooting`), which does not rest on the tracked start states; the screen, the
            windows and the start-error profiles are not used. A value is calibrated where the points searched
            resolve it (`ContactFit.resolved`); the others keep the prior. Opt-in: docs/interaction_history.md,
            "Multiple shooting".
        shooting: settings of the "shooting" calibration.
        impacts: settings of the "impacts" calibration: with `per_object`, each object's contact values from the
            contacts after its tracked free flights (`grounder.interaction.impacts`): the state before each
            contact comes from a fit of the whole flight before it, not from a few frames. A value is calibrated
            where the impacts resolve it; the others go to the windows (`ImpactOptions.windows_for_unresolved`)
            or keep the prior. On five clips of scan D: 21 of 23 resolved friction and restitution values within
            20% (2 wrong, 7 unresolved) against the windows' 16 of 23 (7 wrong, 7 unresolved; docs/cli.md, "Contacts
            after free flights").
    """

    ground: GroundOptions = field(default_factory=GroundOptions)
    track: TrackOptions = field(default_factory=TrackOptions)
    calibrate_params: tuple[str, ...] | None = None
    calibrate_settings: dict[str, Any] = field(default_factory=dict)
    window_s: float | None = 0.3
    window_stride_s: float = 0.1
    min_motion_m_s: float = 0.05
    per_object: bool = True
    own_runs: bool = True
    rotation_weight: float = 0.25
    identify: bool = True
    identify_relative_change: float = 0.2
    identify_min_position_m: float = SCREEN_MIN_POSITION_M
    identify_min_rotation_deg: float = SCREEN_MIN_ROTATION_DEG
    along_view_weight: float = 0.25
    start_rounds: int = 0
    start_speed_error_m_s: float = 0.03
    start_state_draws: int = 6
    start_position_error_m: float = 0.0015
    start_rotation_error_deg: float = 1.0
    start_spin_error_rad_s: float = 0.1
    calibration: str = "impacts"
    shooting: ShootingOptions = field(default_factory=ShootingOptions)
    impacts: ImpactOptions = field(default_factory=ImpactOptions)

    def __post_init__(self) -> None:
        if self.calibration not in CALIBRATION_METHODS:
            raise GrounderError(f"calibration={self.calibration!r} but expected one of {CALIBRATION_METHODS}")
        if self.window_s is not None and not self.window_s > 0:
            raise GrounderError(f"window_s={self.window_s} but expected a positive length in seconds, or None")
        if not self.window_stride_s > 0:
            raise GrounderError(f"window_stride_s={self.window_stride_s} but expected > 0")
        if not 0.0 < self.along_view_weight <= 1.0:
            raise GrounderError(f"along_view_weight={self.along_view_weight} but expected a weight in (0, 1]")
        if not 0.0 <= self.start_speed_error_m_s <= 1.0:
            raise GrounderError(
                f"start_speed_error_m_s={self.start_speed_error_m_s} but expected a speed in [0, 1] m/s"
            )
        if self.start_rounds < 0:
            raise GrounderError(f"start_rounds={self.start_rounds} but expected 0 or more")
        if self.start_state_draws < 0:
            raise GrounderError(f"start_state_draws={self.start_state_draws} but expected 0 or more")
        for name in ("start_position_error_m", "start_rotation_error_deg", "start_spin_error_rad_s"):
            if not getattr(self, name) >= 0.0:
                raise GrounderError(f"{name}={getattr(self, name)} but expected a size >= 0")


@dataclass(frozen=True, kw_only=True)
class InteractionResult:
    """What `ground_with_interaction` wrote.

    Attributes:
        out_dir: the output folder; `scene_xml` is the calibrated scene (the grounded one if not calibrated).
        calibrated: whether a calibration ran.
        track: the tracking result (poses, valid mask, segments).
        report: the content of `interaction.json`.
    """

    out_dir: Path
    scene_xml: Path
    calibrated: bool
    track: TrackResult
    report: dict[str, Any]


def default_params(object_names: Sequence[str]) -> tuple[str, ...]:
    """Per object what `ground --interaction` calibrates: `CONTACT_FIELDS` (`InteractionOptions.calibrate_params`)."""
    return tuple(f"{name}.{field}" for name in object_names for field in CONTACT_FIELDS)
