"""`ground SCAN --interaction CLIP`: a calibrated scene from video alone.

1. **Ground** the scan (`grounder.ground`: reconstruct, segment, mesh, texture, hulls; the property prior when
   `GroundOptions` asks for it).
2. **Track** every grounded object through the interaction clip (`grounder.tracking.pipeline.track`); frames where an
   object is lost or hidden are flagged and cut out: only segments in which every object is tracked become
   trajectories.
3. **Calibrate** (`grounder.calibration.fit.calibrate`, when present) the objects' contact parameters on tracked frames
   only. By default (`calibration` "impacts", `grounder.interaction.impacts`) each object's contact values come
   from the contacts that follow its free flights: each is rolled out from the state a fit of the whole flight
   gives, not from a few tracked frames, and what no flight's landing resolves is calibrated on windows as follows
   (a windowed value that rests on the start states' accuracy keeps the prior there). The windowed calibration
   (`calibration` "windows"): objects that never touch each other (`separable_bodies`) are calibrated one at a
   time, each in a scene of its own with the table (`calibrate_per_body`), on short windows (0.3 s) of its own
   tracked runs (`own_runs`;
   without the frames the backward pass extrapolated), rolled out open loop from states that tracking measures well
   (`reliable_starts`: in a free flight, or away from impacts); windows keep a bounce's chaos out of the loss.
   First a screen (`screen_parameters`) asks, per parameter, whether moving it by 20% changes its object's
   rollouts by more than tracking resolves (1 mm / 0.75 deg, root mean square over the frames, about the median
   tracking error): an object that never slides says nothing about its friction, one that lands without bouncing
   little about its damping ratio. Only constrained parameters are calibrated; the others
   keep the prior and are reported as unconstrained (interval = bounds), not as a number the clip never measured.
   The same ±20% rule is applied again where the fit lands (the screen looked at its grid best): a value that fails
   there keeps the prior too (reported with its `unresolved_fit`), and the rest is fitted again.
   Each calibrated value also gets its resolution range (`indistinguishable_range`). Contact parameters are
   calibrated as the contact's values (the object's geoms get top priority). The loss counts position errors
   along the camera's viewing rays a quarter (`along_view_weight`: tracked depth is 4-6 times noisier than the
   position across the image). Optionally (`start_rounds`, off by default), each window's start state is then
   refitted to the window's own tracked motion with the calibrated values (`grounder.interaction.starts`: a fresh
   detection's pose and a velocity from a few frames are what the tracking measures worst) and the screen and
   calibration run again.
4. **Report** what was calibrated and how well the scene now matches the clip: `interaction.json` and
   `interaction.md` in the output folder.

Output folder (written in a temporary sibling and moved into place at the end):

- `scene.xml`, `assets/`, `scene.json`, `calibration.json`, `report.html`: the calibrated scene (the grounded one,
  unchanged, if nothing could be calibrated);
- `grounded/`: the scene as grounded from the scan, before calibration (with `reconstruction/`);
- `interaction/tracks/`: the tracked trajectories and `track.json` (per-frame valid mask, scores);
- `interaction/windows/`: the windows the calibration was fitted and validated on, with their tracked starts (how
  far the refits moved each start is in the report's `start_refinement`);
- `interaction/impacts.png`: with the impacts calibration, each object's chi-square over friction x restitution and its
  tracked height after each flight against the rollout at the best values;
- `interaction.json`, `interaction.md`: the report.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import shutil
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from grounder.core.trajectory import Trajectory, load_trajectories, save_trajectories
from grounder.errors import GrounderError
from grounder.grounding.pipeline import GroundOptions, ground
from grounder.interaction.impacts import ImpactOptions, impacts_body, impacts_figure
from grounder.interaction.shooting import ShootingOptions, fit_contact, moving_runs
from grounder.sim.restitution import REFERENCE_IMPACT_SPEED_M_S, body_restitution
from grounder.tracking.pipeline import TrackOptions, TrackResult, read_clip, track, track_payload_trajectories
from grounder.tracking.smooth import SmoothingOptions
from image2sim_common.progress import ProgressFn
from image2sim_common.rotations import quat_from_matrix
from reconstruction.errors import InputError

log = logging.getLogger(__name__)


# What tracking resolves (about its median error): a parameter whose +-20% step moves its object's rollouts by less,
# root mean square over the frames, is left at the prior (`screen_parameters`, `InteractionOptions.identify_*`).
SCREEN_MIN_POSITION_M = 0.001
SCREEN_MIN_ROTATION_DEG = 0.75
# `InteractionOptions.calibration`: windows from tracked starts, multiple shooting over each object's whole run, or
# the impacts between its free flights.
CALIBRATION_METHODS = ("windows", "shooting", "impacts")


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
            backward pass recovered (`grounder.tracking.pipeline.object_trajectories`), instead of from the segments
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


def calibration_available() -> bool:
    return importlib.util.find_spec("grounder.calibration.fit") is not None


def _copies_text(copies: Sequence[Mapping[str, Any]], moved_um: float) -> str:
    """The report's words for the impacts' stability copies (`ImpactOptions.stability_copies`): each copy's best
    friction and restitution, "?" where it did not resolve them."""
    if not copies:
        return ""

    def value(copy: Mapping[str, Any], name: str) -> str:
        return f"{copy[name]:.3g}" if copy[f"{name}_resolved"] else "?"

    shown = "; ".join(f"{value(c, 'friction')}, {value(c, 'restitution')}" for c in copies)
    return f"; on copies of the tracks moved by {moved_um:g} um (friction, restitution; ? not resolved): {shown}"


def view_point_of(world_from_cam: np.ndarray) -> tuple[float, float, float] | None:
    """The camera centre (world, metres) of a clip's (F, 4, 4) or (4, 4) camera poses, for weighing tracked depth:
    the mean over the frames where the camera is known (a moving camera's rays are then approximate); None if it is
    never known."""
    poses = np.asarray(world_from_cam, np.float64).reshape(-1, 4, 4)
    centres = poses[:, :3, 3]
    known = np.all(np.isfinite(centres), axis=1)
    if not known.any():
        return None
    x, y, z = (float(v) for v in centres[known].mean(axis=0))
    return (x, y, z)


@dataclass(frozen=True)
class SavedTracks:
    """What calibration reads of an `image2sim track` output folder.

    Attributes:
        segments: the trajectories of the tracked segments (every object tracked), in name order.
        object_tracks: per object its own tracked runs (`object_trajectories` of `track.json`).
        view_point_m: the camera centre (world, metres) from `track.json`'s camera poses; None if never known.
    """

    segments: list[Trajectory]
    object_tracks: dict[str, list[Trajectory]]
    view_point_m: tuple[float, float, float] | None


def saved_tracks(tracks_dir: Path, track_options: TrackOptions | None = None) -> SavedTracks:
    """The tracks of a `track` output folder as written: the segments' trajectory files, and each object's runs
    and the camera from `track.json` (poses rounded to 0.1 um there).

    `ground --interaction` calibrates from these rather than from the tracks it holds in memory, so that calibrating
    its saved tracks again (`benchmarks/track.py --calibrate --tracks`, which reads them here too) gives the same
    scene: a tumbling object's landings on its convex hulls are chaotic at the scale of that rounding, and on
    `samples/toss` the can's fit differed between the two (docs/results/interaction.md).
    """
    options = track_options or TrackOptions()
    track_json = Path(tracks_dir) / "track.json"
    try:
        payload = json.loads(track_json.read_text())
    except (OSError, ValueError) as exc:
        raise GrounderError(f"cannot read {track_json} ({exc}); pass a folder written by `image2sim track`") from exc
    segments = load_trajectories(tracks_dir) if any(Path(tracks_dir).glob("*.npz")) else []
    return SavedTracks(
        segments=segments,
        object_tracks=track_payload_trajectories(payload, options.smoothing, options.min_segment_frames),
        view_point_m=view_point_of(camera_poses_of(payload["world_from_cam"])),
    )


def camera_poses_of(rows: Sequence[Any]) -> np.ndarray:
    """(F, 4, 4) camera poses from `track.json`'s `world_from_cam` rows, NaN where a row is null (a moving camera
    in a frame without the marker)."""
    poses = np.full((len(rows), 4, 4), np.nan)
    for f, row in enumerate(rows):
        if row is not None:
            poses[f] = np.asarray(row, dtype=np.float64).reshape(4, 4)
    return poses


def reliable_starts(traj: Trajectory, smoothing: SmoothingOptions | None = None) -> np.ndarray:
    """(T,) mask of the samples of a tracked trajectory whose state a rollout can start from.

    A tracked state is only as good as its velocity, which comes from a fit over a piece of smooth motion between
    impacts (`grounder.tracking.smooth.impact_pieces`). A sample is a good start for one free body when it lies in
    a piece of at least 3 samples (a free flight's velocity from the ballistic fit, another's from the smoothing
    fit), and is not next to an impact: impacts are only resolved to a frame, so the last sample before a detected
    impact may already be past it and the first sample after one may still be mid-bounce (nor is the first sample
    of a segment that begins in contact a start: what came before it is unknown). On `samples/toss` those samples
    carried 6-38 cm/s of velocity error against under 3 cm/s elsewhere, and the calibration absorbed it into
    friction and damping. A start must be good for every free body of the trajectory (all are simulated from it).
    """
    from grounder.tracking.smooth import impact_pieces

    num = len(traj.time_s)
    good = np.ones(num, bool)
    dt_s = float(np.median(np.diff(traj.time_s))) if num > 1 else None
    for body in range(traj.qvel.shape[1] // 6):
        body_good = np.zeros(num, bool)
        pieces = impact_pieces(traj.qpos[:, 7 * body : 7 * body + 3], smoothing, dt_s)
        for k, (first, last, flight) in enumerate(pieces):
            # Two samples fix a velocity by their difference alone: no redundancy against the poses' noise. On
            # two scans of `samples/tabletop` (SfM on 120 / 100 frames) the box's first flight was such a piece,
            # and the windows started there missed by 10-13 mm at any value (its damping ratio came out +43%).
            if last - first + 1 >= 3:
                start = first + (1 if k > 0 or not flight else 0)
                stop = last if k == len(pieces) - 1 else last - 1
                body_good[start : stop + 1] = True
        good &= body_good
    return good


def windows(
    trajs: Sequence[Trajectory],
    window_s: float | None,
    stride_s: float,
    min_motion_m_s: float,
    *,
    starts: Sequence[np.ndarray] | None = None,
) -> list[Trajectory]:
    """Cuts trajectories into overlapping windows (each at least 3 samples); drops windows where nothing moves.

    With `starts` ((T,) masks, one per trajectory, e.g. from `reliable_starts`), a window begins at the first
    allowed sample at or after its nominal start and keeps its length; a window with no allowed start is dropped.
    """
    out: list[Trajectory] = []
    for index, traj in enumerate(trajs):
        spans: list[tuple[int, int]] = []
        allowed = None if starts is None else np.asarray(starts[index], bool)
        if window_s is None:
            spans = [(0, len(traj.time_s))]
        else:
            t0 = float(traj.time_s[0])
            start = 0.0
            while True:
                first = int(np.searchsorted(traj.time_s, t0 + start - 1e-9))
                if allowed is not None:
                    later = np.nonzero(allowed[first:])[0]
                    first = first + int(later[0]) if len(later) else len(traj.time_s)
                if first < len(traj.time_s):
                    t_first = float(traj.time_s[first])
                    rows = np.nonzero((traj.time_s >= t_first - 1e-9) & (traj.time_s <= t_first + window_s + 1e-9))[0]
                    if len(rows) >= 3 and (int(rows[0]), int(rows[-1]) + 1) not in spans:
                        spans.append((int(rows[0]), int(rows[-1]) + 1))
                if t0 + start + window_s >= traj.time_s[-1] - 1e-9:
                    break
                start += stride_s
        for k, (a, b) in enumerate(spans):
            qvel = traj.qvel[a:b]
            speeds = [np.linalg.norm(qvel[:, d : d + 3], axis=1).max() for d in range(0, qvel.shape[1] - 5, 6)]
            if max(speeds, default=0.0) < min_motion_m_s:
                continue
            out.append(
                Trajectory(
                    time_s=traj.time_s[a:b],
                    qpos=traj.qpos[a:b],
                    qvel=traj.qvel[a:b],
                    ctrl=None if traj.ctrl is None else traj.ctrl[a:b],
                    name=f"{traj.name}_w{k:02d}" if len(spans) > 1 else traj.name,
                )
            )
    return out


CONTACT_FIELDS = ("friction.sliding", "solref.dampratio", "solref.timeconst")
# Calibration settings per object (three parameters), under `InteractionOptions.calibrate_settings`. Search: on the
# true motion of `samples/toss` from a prior of friction 0.45, damping ratio 0.4 and time constant 0.01 s,
# calibration's default 20 generations x 8 per parameter left the can's friction at +266% (a flat stretch of the
# loss); 30 x 10 finds every value within 3%. Robust loss: a window that starts at a badly tracked impact cannot be
# matched, and under the mean loss it alone moved scan F's bowl to friction x3.3; with `robust_scale` 0.5 eight
# scan-and-clip pairs of `benchmarks/track.py` came out 33 of 42 values within 20% (30 of 42 without; 32 at 1.0).
CALIBRATE_SETTINGS: dict[str, Any] = {"generations": 30, "popsize": 10, "robust_scale": 0.5}


# Below this frame rate a bounce or a slide lasts a few frames, and contact values rest on a handful of window starts:
# the same toss calibrated 22 of 24 resolved values within 20% at 30 fps (12 unresolved) and 23 of 24 at 60 fps
# (6 unresolved), over the same scans (docs/interaction_history.md, "Frame rate").
MIN_ADVISED_FPS = 50.0


def frame_rate_advice(fps: float | None) -> str | None:
    """The warning for an interaction clip filmed slower than `MIN_ADVISED_FPS`, or None."""
    if fps is None or fps >= MIN_ADVISED_FPS:
        return None
    return (
        f"the interaction clip has {fps:g} frames per second: a bounce or a slide then spans only a few frames, and "
        "friction and restitution are often unresolved or rest on one or two window starts; film at 60 fps or more "
        "if the camera can"
    )


def default_params(object_names: Sequence[str]) -> tuple[str, ...]:
    """Per object what `ground --interaction` calibrates: `CONTACT_FIELDS` (`InteractionOptions.calibrate_params`)."""
    return tuple(f"{name}.{field}" for name in object_names for field in CONTACT_FIELDS)


def _open_loop_errors(model: Any, trajs: Sequence[Trajectory]) -> list[dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Per trajectory, each free body's per-frame position (m) and rotation (rad) error of the open-loop rollout from
    its first state (`grounder.sim.rollout.free_body_errors`)."""
    from grounder.sim.rollout import free_body_errors, simulate

    if not trajs:
        return []
    predicted = simulate(model, list(trajs))
    out = []
    for pred, real in zip(predicted, trajs, strict=True):
        assert isinstance(pred, Trajectory)
        out.append(free_body_errors(model, pred, real))
    return out


def _clip_match(scene_xml: Path, trajs: Sequence[Trajectory]) -> dict[str, dict[str, float]]:
    """Per object, open-loop rollout of each tracked segment from its first state: mean / max position error (mm)
    and mean rotation error (deg) against the tracked poses, over all segments."""
    import mujoco

    model = mujoco.MjModel.from_xml_path(str(scene_xml))
    per_body: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for errors in _open_loop_errors(model, trajs):
        for body, (pos, rot) in errors.items():
            per_body.setdefault(body, []).append((pos, rot))
    return {
        body: {
            "mean_position_error_mm": round(1e3 * float(np.mean(np.concatenate([p for p, _ in errs]))), 2),
            "max_position_error_mm": round(1e3 * float(np.max(np.concatenate([p for p, _ in errs]))), 2),
            "mean_rotation_error_deg": round(float(np.rad2deg(np.mean(np.concatenate([r for _, r in errs])))), 2),
        }
        for body, errs in per_body.items()
    }


def _window_match(
    scene_xml: Path, fit: Sequence[Trajectory], params: Sequence[str], records: Mapping[str, Mapping[str, Any]]
) -> dict[str, Any]:
    """How well one object's calibration windows match before (prior) and after calibration (`records`' values):
    per window the mean position (mm) and rotation (deg) error of the open-loop rollout from its tracked start; the
    median and mean over the windows. What the calibration fits, so what it can be held to."""
    import mujoco

    from grounder.calibration.parameters import apply_to_model, resolve_parameters

    base = mujoco.MjModel.from_xml_path(str(scene_xml))
    resolved = resolve_parameters(base, list(params))
    out: dict[str, Any] = {"windows": len(fit)}
    for label, values in (
        ("before", [p.nominal for p in resolved]),
        ("after", [float(records.get(p.name, {}).get("value", p.nominal)) for p in resolved]),
    ):
        position_mm, rotation_deg = [], []
        for errors in _open_loop_errors(apply_to_model(base, resolved, values), fit):
            for pos, rot in errors.values():
                position_mm.append(1e3 * float(np.mean(pos)))
                rotation_deg.append(float(np.rad2deg(np.mean(rot))))
        out[label] = {
            "median_position_error_mm": round(float(np.median(position_mm)), 2),
            "mean_position_error_mm": round(float(np.mean(position_mm)), 2),
            "median_rotation_error_deg": round(float(np.median(rotation_deg)), 2),
            "mean_rotation_error_deg": round(float(np.mean(rotation_deg)), 2),
        }
    return out


def _prior_record(p: Any) -> dict[str, Any]:
    """A parameter's report entry when the prior stands: value = nominal, interval = bounds, unconstrained."""
    bounds = [p.lower, p.upper]
    return {
        "nominal": p.nominal,
        "value": p.nominal,
        "interval": bounds,
        "bounds": list(bounds),
        "unit": p.unit,
        "constrained": False,
    }


def fitted_record(parameter: Any, value: float, span: Sequence[float], resolved: bool) -> dict[str, Any]:
    """A parameter's report entry after a fit that gives a best value and the range the clip cannot tell apart
    (`indistinguishable`): calibrated to the value where `resolved`, else the prior with the fit as `unresolved_fit`.
    Shared by the multiple-shooting and the impacts calibrations."""
    record = _prior_record(parameter)
    record["indistinguishable"] = [float(v) for v in span]
    if resolved:
        record.update(value=float(value), interval=[float(v) for v in span], constrained=True)
    else:
        record["unresolved_fit"] = float(value)
    return record


def fit_status(searched: str, records: Mapping[str, Mapping[str, Any]]) -> str:
    """One object's calibration status after such a fit: what was searched (`searched`, a phrase) and which values
    it left at the prior."""
    kept = [n for n, r in records.items() if not r["constrained"]]
    if len(kept) == len(records):
        return f"not calibrated: {searched} resolved none of its values; prior kept"
    return f"calibrated by {searched}" + (f"; not resolved by the clip, prior kept: {kept}" if kept else "")


def calibrate_constrained(
    scene_xml: Path,
    trajs: Sequence[Trajectory],
    params: Sequence[str],
    options: InteractionOptions,
    *,
    view_point_m: Sequence[float] | None = None,
    out: Path | None = None,
    progress: ProgressFn | None = None,
) -> dict[str, Any]:
    """Screens `params` on `trajs` (unless `options.identify` is off) and calibrates only the constrained ones; then
    `options.start_rounds` times refits the windows' start states with the calibrated values
    (`grounder.interaction.starts`) and screens and calibrates again on the refitted windows.

    Args:
        view_point_m: the camera centre (world, metres) the trajectories were tracked from: position errors along
            its rays count `options.along_view_weight` as much (None: all directions alike).

    Returns the report's `calibration` entry: `status`; per parameter (all of `params`) `nominal`, `value`,
    `interval`, `bounds`, `unit`, `constrained` and the screen's figures; unconstrained parameters keep the prior
    (`value` = `nominal`, `interval` = `bounds`); `start_refinement`: per round, what each window's start moved.
    Writes the calibrated scene to `out` only if something was calibrated (in the last round).
    """
    import mujoco

    from grounder.calibration.parameters import apply_to_model, resolve_parameters
    from grounder.interaction.starts import refine_window_starts

    windows_now = list(trajs)
    rounds: list[dict[str, Any]] = []
    entry: dict[str, Any] = {}
    for round_index in range(options.start_rounds + 1):
        last = round_index == options.start_rounds
        if round_index:
            base = mujoco.MjModel.from_xml_path(str(scene_xml))
            resolved = resolve_parameters(base, list(entry["parameters"]))
            model = apply_to_model(base, resolved, [entry["parameters"][p.name]["value"] for p in resolved])
            windows_now, fits = refine_window_starts(
                model,
                windows_now,
                rotation_weight=options.rotation_weight,
                view_point_m=view_point_m,
                along_view_weight=options.along_view_weight,
            )
            rounds.append({"round": round_index, "windows": [f.as_dict() for f in fits]})
        entry = _screen_and_calibrate(
            scene_xml,
            windows_now,
            params,
            options,
            view_point_m=view_point_m,
            out=out if last else None,
            progress=progress,
        )
        if not any(r.get("constrained") for r in entry["parameters"].values()):
            break
    entry["start_refinement"] = rounds
    return entry


def _screen_and_calibrate(
    scene_xml: Path,
    trajs: Sequence[Trajectory],
    params: Sequence[str],
    options: InteractionOptions,
    *,
    view_point_m: Sequence[float] | None,
    out: Path | None,
    progress: ProgressFn | None,
) -> dict[str, Any]:
    """One round of `calibrate_constrained`: screen, then calibrate the constrained parameters on `trajs`; a value
    that is not resolved where the fit lands (`_unresolved_at`) keeps the prior and the rest is fitted again."""
    import mujoco

    from grounder.calibration.fit import CalibrateOptions, calibrate, write_calibrated_scene
    from grounder.calibration.parameters import resolve_parameters

    base = mujoco.MjModel.from_xml_path(str(scene_xml))
    resolved = {p.name: p for p in resolve_parameters(base, list(params))}
    screens: dict[str, ParameterScreen] = {}
    if options.identify:
        for screen in screen_parameters(
            scene_xml,
            trajs,
            params,
            relative_change=options.identify_relative_change,
            min_position_m=options.identify_min_position_m,
            min_rotation_deg=options.identify_min_rotation_deg,
        ):
            screens[screen.name] = screen
    fit = [n for n in resolved if not options.identify or screens[n].constrained or _paired(n, resolved, screens)]
    entry: dict[str, Any] = {"parameters": {}}
    for name, p in resolved.items():
        entry["parameters"][name] = {
            **_prior_record(p),
            "constrained": name in fit,
            **({"screen": screens[name].as_dict()} if name in screens else {}),
        }
    settings = {
        # Windows cut from one clip overlap and share its errors: holding some out would not test anything new.
        "validation_fraction": 0.0,
        "rotation_weight": options.rotation_weight,
        **_view_settings(options, view_point_m),
        **CALIBRATE_SETTINGS,
        **options.calibrate_settings,
    }
    scene = scene_xml.parent if scene_xml.name == "scene.xml" else scene_xml
    while fit:
        result = calibrate(scene, trajs, options=CalibrateOptions(params=tuple(fit), **settings), progress=progress)
        values = np.array([f.value for f in result.parameters])
        # The screen looked at its grid best; the answer must be resolved where it landed, by the same rule (a
        # -/+ step visible both ways). Where it is not, the fit's number says nothing the clip measured: the prior
        # stands and the rest is fitted again without it. A time constant stays with its fitted damping ratio
        # (`_paired`): held at a wrong prior it biases the damping ratio, resolved or not.
        unresolved = [
            name
            for name in (_unresolved_at(base, trajs, fit, values, options) if options.identify else [])
            if _damping_partner(name) not in fit
        ]
        if not unresolved:
            break
        for name in unresolved:
            entry["parameters"][name].update(constrained=False, unresolved_fit=float(values[fit.index(name)]))
        fit = [n for n in fit if n not in unresolved]
    if not fit:
        entry["status"] = "skipped: the clip constrains none of the parameters (prior kept)"
        return entry
    start_ranges = start_error_ranges(base, trajs, [f.name for f in result.parameters], values, options, view_point_m)
    for i, fitted in enumerate(result.parameters):
        if fitted.name in start_ranges:
            lo, hi = start_ranges[fitted.name]
            entry["parameters"][fitted.name].update(
                start_error_range=[lo, hi],
                start_sensitive=bool(
                    lo < fitted.value * (1.0 - options.identify_relative_change)
                    or hi > fitted.value * (1.0 + options.identify_relative_change)
                ),
            )
        entry["parameters"][fitted.name].update(
            value=fitted.value,
            interval=[fitted.interval_low, fitted.interval_high],
            indistinguishable=indistinguishable_range(
                scene_xml,
                trajs,
                [f.name for f in result.parameters],
                values,
                i,
                min_position_m=options.identify_min_position_m,
                min_rotation_deg=options.identify_min_rotation_deg,
            ),
        )
    if out is not None:
        write_calibrated_scene(scene, result, list(trajs), out, base)
    unconstrained = [n for n in resolved if n not in fit]
    entry["status"] = "calibrated" + (
        f"; unconstrained by the clip, prior kept: {unconstrained}" if unconstrained else ""
    )
    entry.update(
        train=list(result.train_names),
        validation=list(result.validation_names),
        before={k: v.as_dict() for k, v in result.before.items()},
        after={k: v.as_dict() for k, v in result.after.items()},
    )
    return entry


def _unresolved_at(
    base: Any, trajs: Sequence[Trajectory], fit: Sequence[str], values: np.ndarray, options: InteractionOptions
) -> list[str]:
    """The fitted parameters whose -/+ `identify_relative_change` step, taken at the fitted `values` in the scene
    model `base`, does not show in their body's rollouts both ways (`_step_visible`, the screen's rule)."""
    from grounder.calibration.parameters import resolve_parameters

    resolved = resolve_parameters(base, list(fit))
    return [
        p.name
        for i, p in enumerate(resolved)
        if not _step_visible(
            base,
            resolved,
            values,
            i,
            trajs,
            options.identify_relative_change,
            options.identify_min_position_m,
            options.identify_min_rotation_deg,
        )[2]
    ]


def start_error_ranges(
    base: Any,
    trajs: Sequence[Trajectory],
    fit: Sequence[str],
    values: np.ndarray,
    options: InteractionOptions,
    view_point_m: Sequence[float] | None = None,
) -> dict[str, list[float]]:
    """Per fitted parameter, the range of its best value when every window's start is off by a tracking-sized
    error (the fitted value included): how far such a start error moves the answer. Empty when
    `start_speed_error_m_s` is 0.

    Each window is rolled out from its tracked start. A slide's length trades friction against the start speed: on
    `samples/toss` (scan D) the bowl's tracked start speeds were off by 0.002-0.07 m/s (median about 0.03), its
    friction came out -45%, and rollouts from the true starts of the same windows fit best at the rendered value.
    So each parameter is profiled again with the starts moved along their velocity by `start_speed_error_m_s`,
    both ways, and then under `start_state_draws` random errors of the whole start (position, orientation, linear
    and angular velocity; see `InteractionOptions`), which a landing turns on (the other parameters held at the
    fit; the calibration's loss over the windows, through the same pseudo-Huber function, its scale taken from the
    windows' errors at the fit rather than at the prior). A range wider than the screen's step
    (`identify_relative_change`) says the value rests on the starts' accuracy.
    """
    import mujoco

    from grounder.calibration.fit import Evaluator, pseudo_huber_residuals
    from grounder.calibration.parameters import resolve_parameters

    if options.start_speed_error_m_s <= 0.0 or not fit:
        return {}
    resolved = resolve_parameters(base, list(fit))
    free = [j for j in range(base.njnt) if base.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
    settings = {"rotation_weight": options.rotation_weight, **_view_settings(options, view_point_m), "nthread": 1}
    at_fit = Evaluator(base, resolved, list(trajs), **settings).loss_of_values(values[None])[0]
    robust = {**CALIBRATE_SETTINGS, **options.calibrate_settings}.get("robust_scale")
    c = None if robust is None else max(robust * float(np.median(np.sqrt(np.maximum(at_fit, 0.0)))), 1e-9)

    def objective(loss: np.ndarray) -> np.ndarray:
        r = np.sqrt(np.maximum(loss, 0.0))
        return np.sum((r if c is None else pseudo_huber_residuals(r, c)) ** 2, axis=1)

    scan = np.geomspace(0.5, 2.0, 29)
    ranges = {p.name: [float(values[i]), float(values[i])] for i, p in enumerate(resolved)}

    def profile(shifted: list[Trajectory]) -> None:
        ev = Evaluator(base, resolved, shifted, **settings)
        for i, p in enumerate(resolved):
            rows = np.repeat(values[None], len(scan), axis=0)
            rows[:, i] = np.clip(values[i] * scan, p.lower, p.upper)
            best = float(rows[int(np.argmin(objective(ev.loss_of_values(rows)))), i])
            ranges[p.name] = [min(ranges[p.name][0], best), max(ranges[p.name][1], best)]

    for sign in (-1.0, 1.0):
        shifted = []
        for traj in trajs:
            qvel = np.array(traj.qvel, dtype=np.float64, copy=True)
            for j in free:
                d = int(base.jnt_dofadr[j])
                speed = float(np.linalg.norm(qvel[0, d : d + 3]))
                if speed > 1e-9:
                    qvel[0, d : d + 3] *= max(0.0, 1.0 + sign * options.start_speed_error_m_s / speed)
            shifted.append(replace(traj, qvel=qvel))
        profile(shifted)
    rng = np.random.default_rng(0)
    for _ in range(options.start_state_draws):
        shifted = []
        for traj in trajs:
            qpos = np.array(traj.qpos, dtype=np.float64, copy=True)
            qvel = np.array(traj.qvel, dtype=np.float64, copy=True)
            for j in free:
                a, d = int(base.jnt_qposadr[j]), int(base.jnt_dofadr[j])
                qpos[0, a : a + 3] += rng.normal(0.0, options.start_position_error_m, 3)
                # a small rotation in the body frame, its vector drawn per axis
                tilt_rad = rng.normal(0.0, np.deg2rad(options.start_rotation_error_deg), 3)
                mujoco.mju_quatIntegrate(qpos[0, a + 3 : a + 7], tilt_rad, 1.0)
                qvel[0, d : d + 3] += rng.normal(0.0, options.start_speed_error_m_s, 3)
                qvel[0, d + 3 : d + 6] += rng.normal(0.0, options.start_spin_error_rad_s, 3)
            shifted.append(replace(traj, qpos=qpos, qvel=qvel))
        profile(shifted)
    return ranges


def _paired(name: str, resolved: Mapping[str, Any], screens: Mapping[str, ParameterScreen]) -> bool:
    """A contact time constant is fitted wherever its body's damping ratio is, whatever its own screen says: a bounce
    fixes a combination of the two, and a time constant held at a wrong prior moves the damping ratio instead
    (`InteractionOptions.calibrate_params`)."""
    partner = _damping_partner(name)
    return partner is not None and partner in resolved and screens[partner].constrained


def _damping_partner(name: str) -> str | None:
    """The damping ratio a contact time constant (`….solref.timeconst`) is fitted with, or None for other names."""
    return name.removesuffix("timeconst") + "dampratio" if name.endswith(".solref.timeconst") else None


def _view_settings(options: InteractionOptions, view_point_m: Sequence[float] | None) -> dict[str, Any]:
    """`CalibrateOptions` fields that weigh tracked depth less (none without a camera centre)."""
    if view_point_m is None:
        return {}
    return {
        "view_point_m": tuple(float(v) for v in view_point_m),
        "along_view_weight": options.along_view_weight,
    }


def separable_bodies(scene_xml: Path, trajs: Sequence[Trajectory], clearance_m: float = 0.005) -> bool:
    """Whether the scene's free bodies stay at least `clearance_m` apart in every sample of `trajs` (collision
    geometry), so that each moves as if alone with the table and can be calibrated on its own."""
    import mujoco

    from grounder.sim.rollout import free_joints

    model = mujoco.MjModel.from_xml_path(str(scene_xml))
    bodies = [model.body(fj.body).id for fj in free_joints(model)]
    geoms = {
        b: [
            g
            for g in range(model.ngeom)
            if model.geom_bodyid[g] == b and (model.geom_contype[g] or model.geom_conaffinity[g])
        ]
        for b in bodies
    }
    pairs = [(g1, g2) for i, b1 in enumerate(bodies) for b2 in bodies[i + 1 :] for g1 in geoms[b1] for g2 in geoms[b2]]
    if not pairs:
        return True
    data = mujoco.MjData(model)
    for traj in trajs:
        for qpos in traj.qpos:
            data.qpos[:] = qpos
            mujoco.mj_kinematics(model, data)
            for g1, g2 in pairs:
                if mujoco.mj_geomDistance(model, data, g1, g2, clearance_m, None) < clearance_m:
                    return False
    return True


def tracked_states(model: Any, tracked: TrackResult) -> list[Trajectory]:
    """Every frame in which at least two objects are tracked, as one whole-scene trajectory (zero velocities), with
    the untracked objects parked far from the table and from each other: what `separable_bodies` checks when no
    segment has every object tracked at once."""
    from grounder.sim.rollout import free_joints

    joints = free_joints(model)
    rows = np.nonzero(tracked.valid.sum(axis=1) >= 2)[0]
    if not len(rows):
        return []
    qpos = np.tile(model.qpos0, (len(rows), 1))
    for i, fj in enumerate(joints):
        qpos[:, fj.pos] = [1000.0 + 10.0 * i, 1000.0, 1000.0]
        qpos[:, fj.quat] = [1.0, 0.0, 0.0, 0.0]
        for k, f in enumerate(rows):
            if tracked.valid[f, i]:
                qpos[k, fj.pos] = tracked.world_from_objects[f, i, :3, 3]
                qpos[k, fj.quat] = quat_from_matrix(tracked.world_from_objects[f, i, :3, :3])
    return [Trajectory(time_s=tracked.time_s[rows], qpos=qpos, qvel=np.zeros((len(rows), model.nv)), name="tracked")]


def write_values(scene_xml: Path, values: Mapping[str, float], out: Path) -> Path:
    """Writes `out/scene.xml` (with the scene folder's files): the scene with the given parameter values, and their
    record in its `scene.json`. For when the values were fitted per object and no whole-scene trajectory exists to
    evaluate them on (`calibrate` writes the scene otherwise)."""
    import mujoco

    from grounder.calibration.fit import NOT_COPIED
    from grounder.calibration.parameters import apply_to_spec, resolve_parameters
    from grounder.sim.rollout import copy_scene_files

    base = mujoco.MjModel.from_xml_path(str(scene_xml))
    spec = mujoco.MjSpec.from_file(str(scene_xml))
    resolved = resolve_parameters(base, list(values))
    apply_to_spec(spec, base, resolved, [values[p.name] for p in resolved])
    out.mkdir(parents=True)
    copy_scene_files(scene_xml.parent, out, skip=NOT_COPIED)
    (out / "scene.xml").write_text(spec.to_xml())
    reloaded = mujoco.MjModel.from_xml_path(str(out / "scene.xml"))
    if reloaded.nq != base.nq or reloaded.nv != base.nv:
        raise GrounderError("the written scene.xml does not match the scene's joints")
    manifest = out / "scene.json"
    if manifest.is_file():
        data = json.loads(manifest.read_text())
        data["calibration"] = {
            "mode": "per object, no whole-scene evaluation",
            "parameters": dict(values),
            "note": "scene.xml holds the calibrated values; per-object entries above are from before calibration",
        }
        manifest.write_text(json.dumps(data, indent=1) + "\n")
    return out / "scene.xml"


def _single_body_trajectory(model: Any, traj: Trajectory, body: str) -> Trajectory:
    """The columns of one free body of a trajectory of a scene with free bodies only."""
    from grounder.sim.rollout import free_joints

    joint = next(fj for fj in free_joints(model) if fj.body == body)
    dof = int(model.jnt_dofadr[model.body(body).jntadr[0]])
    return Trajectory(
        time_s=traj.time_s,
        qpos=traj.qpos[:, joint.pos.start : joint.pos.start + 7],
        qvel=traj.qvel[:, dof : dof + 6],
        name=traj.name,
    )


@contextmanager
def single_body_scene(scene_xml: Path, body: str) -> Iterator[Path]:
    """The scene with only `body` of its free bodies (and the table), as an MJCF file in a private temporary folder
    that is removed afterwards.

    A private folder with a copy of the scene's mesh and texture files: written beside scene.xml under a fixed name,
    two calibrations of one scene at once (batch jobs, two terminals) deleted each other's file mid-run, and a
    read-only scene folder could not be calibrated at all. A copy rather than absolute asset paths, because a scene
    may not name files outside its folder (`grounder.sim.rollout.scene_files`).
    """
    import mujoco

    from grounder.sim.rollout import copy_scene_files

    single = mujoco.MjSpec.from_file(str(scene_xml))
    for other in list(single.worldbody.bodies):  # a free joint can only sit on a child of the world
        if other.name != body and any(j.type == mujoco.mjtJoint.mjJNT_FREE for j in other.joints):
            single.delete(other)
    tmp = Path(tempfile.mkdtemp(prefix="image2sim_calibrate_"))
    try:
        copy_scene_files(scene_xml, tmp)
        sub_xml = tmp / f"{body}.xml"
        sub_xml.write_text(single.to_xml())
        yield sub_xml
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def object_windows(body_trajs: Sequence[Trajectory], options: InteractionOptions) -> list[Trajectory]:
    """One object's calibration windows: cut from its single-body trajectories, starting only where its state is
    well measured (`reliable_starts`)."""
    return windows(
        body_trajs,
        options.window_s,
        options.window_stride_s,
        options.min_motion_m_s,
        starts=[reliable_starts(t, options.track.smoothing) for t in body_trajs],
    )


def calibrate_per_body(
    scene_xml: Path,
    segments: Sequence[Trajectory],
    params: Sequence[str],
    options: InteractionOptions,
    *,
    view_point_m: Sequence[float] | None = None,
    object_tracks: Mapping[str, Sequence[Trajectory]] | None = None,
    out: Path | None = None,
    progress: ProgressFn | None = None,
) -> tuple[dict[str, Any], list[str]]:
    """Screens and calibrates each object's parameters in a scene of its own (the object and the table).

    For objects that never touch each other (`separable_bodies`): each object's tracked motion is cut into windows
    that start only where its state is well measured (`reliable_starts`), and its parameters are screened and fitted
    on those, alone (a few dimensions, with no other object's tracking errors in the loss). The values found are
    then written into the whole scene (`out`), evaluated on the whole tracked segments. `view_point_m`: as in
    `calibrate_constrained`. `object_tracks`: per object, single-body trajectories of its own tracked frames
    (`grounder.tracking.pipeline.object_trajectories`) to cut its windows from, instead of its columns of `segments`
    (the frames in which every object is tracked).

    Returns:
        The report's `calibration` entry (as `calibrate_constrained`'s, with `windows` per object) and the names of
        all windows used.
    """
    import mujoco

    from grounder.calibration.fit import CalibrateOptions, calibrate
    from grounder.calibration.parameters import resolve_parameters
    from grounder.sim.rollout import free_joints

    model = mujoco.MjModel.from_xml_path(str(scene_xml))

    bodies = [fj.body for fj in free_joints(model)]
    by_body: dict[str, list[str]] = {}
    for name in params:
        body = name.split(".", 1)[0]
        if body not in bodies:
            raise GrounderError(f"{name}: per-object calibration needs parameters of the scene's objects {bodies}")
        by_body.setdefault(body, []).append(name)
    entry: dict[str, Any] = {"parameters": {}, "per_object": {}}
    used: list[str] = []
    values: dict[str, float] = {}
    for body, body_params in by_body.items():
        with single_body_scene(scene_xml, body) as sub_xml:
            body_trajs = (
                list(object_tracks[body])
                if object_tracks is not None
                else [_single_body_trajectory(model, t, body) for t in segments]
            )
            match: dict[str, Any] = {}
            if options.calibration == "shooting":
                sub, fit = shoot_body(
                    sub_xml, body_trajs, body_params, options.shooting, view_point_m=view_point_m, progress=progress
                )
                fit_names = [t.name for t in fit]
            elif options.calibration == "impacts":
                sub, fit_names = impacts_body(
                    sub_xml, body_trajs, body_params, options.impacts, view_point_m=view_point_m, progress=progress
                )
                if options.impacts.windows_for_unresolved:
                    fit = _windows_for_unresolved(
                        sub_xml, body_trajs, body_params, sub, options, view_point_m=view_point_m, progress=progress
                    )
                    fit_names += [t.name for t in fit]
                    if fit:
                        match = _window_match(sub_xml, fit, body_params, sub["parameters"])
            else:
                fit = object_windows(body_trajs, options)
                fit_names = [t.name for t in fit]
                sub = {"status": "skipped: no well-measured window shows motion", "parameters": {}}
                if fit:
                    sub = calibrate_constrained(
                        sub_xml, fit, body_params, options, view_point_m=view_point_m, progress=progress
                    )
                    match = _window_match(sub_xml, fit, body_params, sub["parameters"])
            used += [f"{body}:{name}" for name in fit_names]
        entry["per_object"][body] = {
            "status": sub["status"],
            "windows": fit_names,
            "start_refinement": sub.get("start_refinement", []),
            "window_match": match,
        }
        if "shooting" in sub:
            entry["per_object"][body]["shooting"] = sub["shooting"]
        if "impacts" in sub:
            entry["per_object"][body]["impacts"] = sub["impacts"]
        if "restitution" in sub:
            entry["per_object"][body]["restitution"] = sub["restitution"]
        for name in body_params:
            record = sub["parameters"].get(name, {})
            entry["parameters"][name] = record
            if record.get("constrained"):
                values[name] = record["value"]
    resolved = {p.name: p for p in resolve_parameters(model, list(params))}
    for name, record in entry["parameters"].items():
        if "value" not in record:  # skipped body: the prior, unconstrained
            record.update(_prior_record(resolved[name]))
    unconstrained = [n for n, r in entry["parameters"].items() if not r.get("constrained")]
    if not values:
        entry["status"] = "skipped: the clip constrains none of the parameters (prior kept)"
        return entry, used
    if not segments:
        if out is not None:
            write_values(scene_xml, values, out)
        entry["status"] = (
            "calibrated per object; no segment has every object tracked at once, so the values were not evaluated "
            "on the whole scene"
            + (f"; unconstrained by the clip, prior kept: {unconstrained}" if unconstrained else "")
        )
        return entry, used
    result = calibrate(
        scene_xml.parent if scene_xml.name == "scene.xml" else scene_xml,
        list(segments),
        options=CalibrateOptions(
            params=tuple(values),
            initial=values,
            generations=0,
            local_iterations=0,
            validation_fraction=0.0,
            rotation_weight=options.rotation_weight,
            **_view_settings(options, view_point_m),
        ),
        out=out,
        progress=progress,
    )
    entry["status"] = "calibrated per object" + (
        f"; unconstrained by the clip, prior kept: {unconstrained}" if unconstrained else ""
    )
    entry.update(
        train=list(result.train_names),
        validation=[],
        before={k: v.as_dict() for k, v in result.before.items()},
        after={k: v.as_dict() for k, v in result.after.items()},
    )
    return entry, used


def _windows_for_unresolved(
    sub_xml: Path,
    body_trajs: Sequence[Trajectory],
    params: Sequence[str],
    sub: dict[str, Any],
    options: InteractionOptions,
    *,
    view_point_m: Sequence[float] | None = None,
    progress: ProgressFn | None = None,
) -> list[Trajectory]:
    """With `calibration` "impacts": the values the impacts left unresolved are screened and calibrated on the
    object's windows (as `calibration` "windows" does), in its scene with the impacts' resolved values written in;
    their records in `sub` are replaced (marked `"method": "windows"`) and `sub["status"]` says so. A windowed value
    flagged as resting on the start states' accuracy (`start_sensitive`, `start_error_ranges`) keeps the prior
    (its fit is `unresolved_fit`): on five clips of scan D the windows' values for the can were all wrong by 20-34%
    and all flagged. A bounce the impacts resolved keeps its time constant and damping ratio together. Returns the
    windows (none where nothing was left or no window shows motion)."""
    import mujoco

    from grounder.calibration.parameters import apply_to_spec, resolve_parameters

    records = sub["parameters"]
    fixed = {name: r["value"] for name, r in records.items() if r.get("constrained")}
    rest = [name for name in params if not records.get(name, {}).get("constrained")]
    if not rest:
        return []
    fit = object_windows(body_trajs, options)
    if not fit:
        return []
    base = mujoco.MjModel.from_xml_path(str(sub_xml))
    scene = sub_xml
    if fixed:
        spec = mujoco.MjSpec.from_file(str(sub_xml))
        resolved = resolve_parameters(base, list(fixed))
        apply_to_spec(spec, base, resolved, [fixed[p.name] for p in resolved])
        scene = sub_xml.with_name(f"{sub_xml.stem}_impacts.xml")  # in `single_body_scene`'s private folder
        scene.write_text(spec.to_xml())
    windowed = calibrate_constrained(scene, fit, rest, options, view_point_m=view_point_m, progress=progress)
    parameters = {p.name: p for p in resolve_parameters(base, rest)}
    for name in rest:
        record = dict(windowed["parameters"][name])
        if record.get("constrained") and record.get("start_sensitive"):
            # A windowed value that moves past the screen's step under tracking-sized start errors is not taken
            # here: the impacts, which do not rest on the starts, could not resolve it either.
            record = {**_prior_record(parameters[name]), "unresolved_fit": record["value"], "start_sensitive": True}
        if "unresolved_fit" in records.get(name, {}):
            record["impacts_unresolved_fit"] = records[name]["unresolved_fit"]
        record["method"] = "windows"
        records[name] = record
    calibrated = [n for n in rest if records[n].get("constrained")]
    sub["status"] += f"; on {len(fit)} window(s), the values the impacts left: {windowed['status']}" + (
        f" (calibrated there: {calibrated})" if calibrated else ""
    )
    return fit


def shoot_body(
    scene_xml: Path,
    body_trajs: Sequence[Trajectory],
    params: Sequence[str],
    options: ShootingOptions,
    *,
    view_point_m: Sequence[float] | None = None,
    progress: ProgressFn | None = None,
) -> tuple[dict[str, Any], list[Trajectory]]:
    """Calibrates one object's contact values in its own scene by multiple shooting over its tracked runs
    (`InteractionOptions.calibration` "shooting").

    Returns the object's calibration entry (as `calibrate_constrained`'s: `status`, per parameter `nominal`,
    `value`, `interval`, `bounds`, `unit`, `constrained`, and `indistinguishable`: the values within
    `options.resolution_cost` of the best cost; an unresolved value keeps the prior and its best point is
    `unresolved_fit`; `shooting`: nodes, runs, cost and the points searched) and the runs used.
    """
    import mujoco

    from grounder.calibration.parameters import resolve_parameters

    runs = []
    if body_trajs:
        fps = 1.0 / float(np.median(np.concatenate([np.diff(t.time_s) for t in body_trajs])))
        runs = moving_runs(body_trajs, fps, options)
    if not runs:
        return {"status": "skipped: no tracked run shows motion", "parameters": {}}, []
    model = mujoco.MjModel.from_xml_path(str(scene_xml))
    contact = resolve_parameters(model, list(params))
    result = fit_contact(model, contact, runs, options, view_point_m=view_point_m, progress=progress)
    records = {
        parameter.name: fitted_record(parameter, value, span, ok)
        for parameter, value, span, ok in zip(contact, result.values, result.ranges, result.resolved, strict=True)
    }
    bounce = result.restitution
    restitution: dict[str, Any] = {}
    if bounce is not None:
        restitution = {
            "value": bounce.value,
            "range": list(bounce.range),
            "resolved": bounce.resolved,
            "impact_speed_m_s": REFERENCE_IMPACT_SPEED_M_S,
        }
        if bounce.resolved:
            # The bounce pins the pair (time constant, damping ratio), not each value: where one of them is not
            # resolved by itself, keeping its prior beside the other's fit would bounce differently from the fit.
            for parameter, value in zip(contact, result.values, strict=True):
                record = records[parameter.name]
                if ".solref." in parameter.name and not record["constrained"]:
                    record.pop("unresolved_fit", None)
                    record.update(value=value, interval=record["indistinguishable"], constrained=True)
                    record["set_with_restitution"] = True
    status = fit_status(
        f"multiple shooting ({result.nodes} nodes over {len(runs)} run(s), cost {result.cost:.1f}, "
        f"{len(result.evaluations)} points searched)",
        records,
    )
    shooting = {
        "nodes": result.nodes,
        "runs": [t.name for t in runs],
        "cost": round(result.cost, 3),
        "evaluations": [{"values": list(v), "cost": round(c, 3)} for v, c in result.evaluations],
    }
    entry = {"status": status, "parameters": records, "shooting": shooting}
    if restitution:
        entry["restitution"] = restitution
    return entry, runs


def ground_with_interaction(
    scan: Path,
    clip: Path,
    out: Path,
    options: InteractionOptions | None = None,
    *,
    grounded_scene: Path | None = None,
    overwrite: bool = False,
    progress: ProgressFn | None = None,
) -> InteractionResult:
    """A calibrated scene from a scan video and an interaction clip (module docstring).

    Args:
        scan: video (or image folder) of the still tabletop.
        clip: video in which the scan's objects move (pushed, tossed, dropped), filmed with the same camera.
        out: output folder (new or empty unless `overwrite`).
        options: settings of each stage.
        grounded_scene: an existing `ground` output of `scan` to reuse instead of grounding again (copied).
        overwrite: replace a non-empty `out` once the result is complete.
        progress: called as progress(stage, done, total).

    Returns:
        Where the scene is, whether it was calibrated, the tracking result and the report.

    Raises:
        GrounderError, ReconstructionError, SceneExportError: bad input, nothing grounded or nothing tracked.
    """
    from reconstruction import check_source, staged_output_dir

    options = options or InteractionOptions()
    report = progress or (lambda stage, done, total: None)
    track_options = options.track
    if track_options.aruco_size_m is None:
        track_options = replace(track_options, aruco_size_m=options.ground.reconstruct.aruco_size_m)
    seconds: dict[str, float] = {}
    if grounded_scene is None:  # the videos that will be read fail now, not after the grounding
        check_source(Path(scan))
    check_source(Path(clip))
    if track_options.aruco_size_m is None:  # found now, not after the grounding
        raise GrounderError(
            "tracking the interaction clip finds the camera from the ArUco marker on the table, so it needs the "
            "marker's size: pass --aruco-size M (--known-extent cannot stand in for it)"
        )
    needed = track_options.min_segment_frames  # a few frames decoded now: a clip too short to track fails here
    first, _ = read_clip(Path(clip), needed, track_options.start_frame)
    if len(first) < needed:
        raise GrounderError(
            f"{clip}: {len(first)} frames; tracking needs at least {needed} to make a trajectory: film a longer "
            "interaction clip"
        )
    del first
    with staged_output_dir(
        Path(out), overwrite=overwrite, inputs=(scan, clip, grounded_scene), error=InputError
    ) as stage:
        tick = time.perf_counter()
        grounded = stage / "grounded"
        if grounded_scene is not None:
            if not (Path(grounded_scene) / "scene.xml").is_file():
                raise GrounderError(f"{grounded_scene} has no scene.xml; pass a folder written by `image2sim ground`")
            shutil.copytree(grounded_scene, grounded)
        else:
            ground(Path(scan), grounded, options.ground, progress=report)
        seconds["ground"] = time.perf_counter() - tick

        tick = time.perf_counter()
        tracks_dir = stage / "interaction" / "tracks"
        # track.json names the grounded scene where it will be, not in the staging folder.
        tracked = track(
            Path(clip),
            grounded,
            tracks_dir,
            track_options,
            progress=report,
            scene_recorded_as=Path(out) / "grounded" / "scene.xml",
        )
        seconds["track"] = time.perf_counter() - tick
        # Calibrate from the tracks as written, not as held in memory: they reproduce this scene (`saved_tracks`).
        saved = saved_tracks(tracks_dir, track_options)
        segments = saved.segments
        if segments:
            per_body = options.per_object and separable_bodies(grounded / "scene.xml", segments)
        else:
            # No frame has every object: each object's own runs, if the objects never touch where tracked together.
            import mujoco

            model = mujoco.MjModel.from_xml_path(str(grounded / "scene.xml"))
            per_body = (
                options.per_object
                and options.own_runs
                and separable_bodies(grounded / "scene.xml", tracked_states(model, tracked))
            )
        fit_trajs = (
            [] if per_body else windows(segments, options.window_s, options.window_stride_s, options.min_motion_m_s)
        )

        names = tracked.object_names
        payload: dict[str, Any] = {
            "format": "image2sim.interaction/1",
            "scan": str(scan),
            "clip": str(clip),
            "tracking": {
                "frames": len(tracked.time_s),
                "fps": round(1.0 / float(np.median(np.diff(tracked.time_s))), 3) if len(tracked.time_s) > 1 else None,
                "objects": {
                    n: {
                        "tracked_fraction": round(float(tracked.valid[:, i].mean()), 4),
                        "lost_frames": [int(tracked.frame_index[f]) for f in np.nonzero(~tracked.valid[:, i])[0]],
                    }
                    for i, n in enumerate(names)
                },
                "segments": [
                    {
                        "name": t.name,
                        "first_frame": int(tracked.frame_index[a]),
                        "last_frame": int(tracked.frame_index[b]),
                    }
                    for t, (a, b) in zip(tracked.trajectories, tracked.segments, strict=True)
                ],
                "note": (
                    "calibration uses only tracked frames: the segments (every object tracked), or with "
                    "InteractionOptions.own_runs, per object its own tracked runs"
                ),
            },
            "windows": [t.name for t in fit_trajs],  # per-object calibration replaces this with its own
            "start_speed_error_m_s": options.start_speed_error_m_s,
            "start_state_errors": {
                "draws": options.start_state_draws,
                "position_m": options.start_position_error_m,
                "rotation_deg": options.start_rotation_error_deg,
                "speed_m_s": options.start_speed_error_m_s,
                "spin_rad_s": options.start_spin_error_rad_s,
            },
        }
        advice = frame_rate_advice(payload["tracking"]["fps"])
        if advice:
            log.warning("%s", advice)
        payload["calibration_method"] = options.calibration
        payload["match_before"] = _clip_match(grounded / "scene.xml", segments)
        calibrated = False
        view_point_m = saved.view_point_m
        if not calibration_available():
            payload["calibration"] = {"status": "skipped: grounder.calibration.fit is not installed"}
        elif per_body:
            params = options.calibrate_params or default_params(names)
            tick = time.perf_counter()
            payload["calibration"], payload["windows"] = calibrate_per_body(
                grounded / "scene.xml",
                segments,
                params,
                options,
                view_point_m=view_point_m,
                object_tracks=saved.object_tracks if options.own_runs else None,
                out=stage / "calibrated",
                progress=report,
            )
            seconds["calibrate"] = time.perf_counter() - tick
        elif options.calibration == "shooting":
            payload["calibration"] = {
                "status": "skipped: multiple shooting calibrates one object at a time, and these objects touch where "
                "tracked together (or per-object calibration is off); use calibration 'windows'"
            }
        elif not segments:
            payload["calibration"] = {
                "status": "skipped: no frame has every object tracked, and the objects cannot be calibrated one at a "
                "time (they touch where tracked together, or per-object calibration is off)"
            }
        elif not fit_trajs:
            payload["calibration"] = {"status": "skipped: no tracked window shows motion"}
        else:
            save_trajectories(fit_trajs, stage / "interaction" / "windows")
            params = options.calibrate_params or default_params(names)
            tick = time.perf_counter()
            payload["calibration"] = calibrate_constrained(
                grounded / "scene.xml",
                fit_trajs,
                params,
                options,
                view_point_m=view_point_m,
                out=stage / "calibrated",
                progress=report,
            )
            seconds["calibrate"] = time.perf_counter() - tick
        calibrated = (stage / "calibrated" / "scene.xml").is_file()
        if calibrated:
            for child in (stage / "calibrated").iterdir():
                shutil.move(str(child), stage / child.name)
            (stage / "calibrated").rmdir()
            payload["match_after"] = _clip_match(stage / "scene.xml", segments)
        payload["restitution"] = scene_restitution(
            grounded / "scene.xml", stage / "scene.xml" if calibrated else None, names
        )
        if not calibrated:
            for child in grounded.iterdir():
                if child.name != "reconstruction":
                    target = stage / child.name
                    if child.is_dir():
                        shutil.copytree(child, target)
                    else:
                        shutil.copy2(child, target)
        payload["stage_seconds"] = {k: round(v, 1) for k, v in seconds.items()}
        if impacts_figure(payload["calibration"].get("per_object", {}), stage / "interaction" / "impacts.png"):
            payload["impacts_figure"] = "interaction/impacts.png"
        (stage / "interaction.json").write_text(json.dumps(payload, indent=1) + "\n")
        (stage / "interaction.md").write_text(_markdown(payload))
    return InteractionResult(
        out_dir=Path(out),
        scene_xml=Path(out) / "scene.xml",
        calibrated=calibrated,
        track=tracked,
        report=payload,
    )


def scene_restitution(before_xml: Path, after_xml: Path | None, objects: Sequence[str]) -> dict[str, Any]:
    """Per object, the coefficient of restitution of its contacts (`grounder.sim.restitution.body_restitution`, a
    normal impact at `REFERENCE_IMPACT_SPEED_M_S`) in the grounded scene (`before`: the property model's prior)
    and in the calibrated one (`after`; the prior's where not calibrated)."""
    import mujoco

    models = {"before": mujoco.MjModel.from_xml_path(str(before_xml))}
    if after_xml is not None:
        models["after"] = mujoco.MjModel.from_xml_path(str(after_xml))
    out: dict[str, Any] = {"impact_speed_m_s": REFERENCE_IMPACT_SPEED_M_S, "objects": {}}
    for name in objects:
        values = {key: round(body_restitution(model, name), 4) for key, model in models.items()}
        out["objects"][name] = {"before": values["before"], "after": values.get("after", values["before"])}
    return out


def _markdown(payload: dict[str, Any]) -> str:
    lines = ["# Interaction report", "", f"Scan `{payload['scan']}`, clip `{payload['clip']}`.", "", "## Tracking", ""]
    for name, info in payload["tracking"]["objects"].items():
        lost = info["lost_frames"]
        lost_text = f"lost in frames {lost}" if lost else "never lost"
        lines.append(f"- {name}: tracked in {100 * info['tracked_fraction']:.0f}% of the frames, {lost_text}")
    spans = ", ".join(f"{s['first_frame']}-{s['last_frame']}" for s in payload["tracking"]["segments"])
    lines += ["", f"Segments with every object tracked: {spans}. Calibration sees only tracked frames.", ""]
    lines += ["![tracked outlines and per-frame status](interaction/tracks/overview.png)", ""]
    lines += ["## Calibration", "", f"Status: {payload['calibration']['status']}.", ""]
    params = payload["calibration"].get("parameters", {})
    if params:
        speed = payload.get("start_speed_error_m_s")
        draws = payload.get("start_state_errors", {}).get("draws", 0)
        probe = "start speeds " + ("off" if speed is None else f"+-{speed:g} m/s")
        if draws:
            probe = f"starts off (speeds +-{speed:g} m/s; {draws} random whole-state errors)"
        lines += [
            f"| parameter | before | after | interval | constrained by the clip | best value with {probe} |",
            "|---|---|---|---|---|---|",
        ]
        for name, p in params.items():
            seen = "yes" if p.get("constrained", True) else "no: prior kept"
            if p.get("set_with_restitution"):
                seen = "with the bounce: the restitution is resolved, this value alone is not"
            if "unresolved_fit" in p:
                seen += f" (the fit, {p['unresolved_fit']:.4g}, is not resolved where it landed)"
            starts = "-"
            if "start_error_range" in p:
                starts = "{:.4g} .. {:.4g}".format(*p["start_error_range"])
                if p.get("start_sensitive"):
                    starts += ": **rests on the start states' accuracy**"
            lines.append(
                f"| {name} | {p['nominal']:.4g} | {p['value']:.4g} | {p['interval'][0]:.4g} .. "
                f"{p['interval'][1]:.4g} | {seen} | {starts} |"
            )
        lines.append("")
        if any(p.get("start_sensitive") for p in params.values()):
            fps = payload["tracking"].get("fps")
            rate = "" if fps is None else f" This clip has {fps:g} frames per second."
            lines += [
                "A value that rests on the start states' accuracy moves past the screen's step when the windows'",
                "starts are off by a typical tracking error: treat it as a rough estimate. A clip filmed at",
                f"60 fps or more, or markers on the object, measure the starts better.{rate}",
                "",
            ]
    if payload.get("impacts_figure"):
        lines += [
            f"![each object's fit to the contacts after its free flights]({payload['impacts_figure']})",
            "",
        ]
    for body, info in payload["calibration"].get("per_object", {}).items():
        if "impacts" in info:
            hits = info["impacts"]
            lines.append(
                f"- {body}: {len(hits['names'])} contact(s) after a tracked free flight ({', '.join(hits['names'])}), "
                f"chi-square {hits['chi2']:.1f} for {hits['dof']} residuals, tracking noise across / along the "
                f"viewing ray {hits['noise_mm'][0]:.2f} / {hits['noise_mm'][1]:.2f} mm; best friction "
                f"{hits['best']['friction']:.3g}, restitution {hits['best']['restitution']:.3g}"
                + _copies_text(hits.get("stability_copies", []), hits.get("stability_um", 0.0))
            )
        if "shooting" in info:
            shot = info["shooting"]
            lines.append(
                f"- {body}: multiple shooting over {shot['nodes']} nodes ({len(shot['runs'])} run(s)), best cost "
                f"{shot['cost']:.1f} of {len(shot['evaluations'])} points searched"
            )
        for refit in info.get("start_refinement", []):
            fits = refit["windows"]
            if fits:
                velocity = [f["velocity_change_m_s"] for f in fits]
                position = [f["position_change_mm"] for f in fits]
                lines.append(
                    f"- {body}, start refit {refit['round']}: {len(fits)} windows, start velocity moved by median "
                    f"{np.median(velocity):.3f} m/s (max {max(velocity):.3f}), position by median "
                    f"{np.median(position):.1f} mm (max {max(position):.1f})"
                )
    if payload["calibration"].get("per_object"):
        lines.append("")
    bounce = payload.get("restitution", {})
    if bounce.get("objects"):
        speed = bounce["impact_speed_m_s"]
        lines += [
            f"## Bounce: coefficient of restitution of each object's contacts ({speed:g} m/s normal impact)",
            "",
            "MuJoCo's contact has no restitution parameter; this is the bounce its time constant and damping ratio",
            "produce in this scene (a drop test, `grounder.sim.restitution`).",
            "",
            "| object | before | after | range the clip allows (shooting: within the resolution cost; impacts: "
            "within the chi-square threshold) |",
            "|---|---|---|---|",
        ]
        for name, e in bounce["objects"].items():
            shot = payload["calibration"].get("per_object", {}).get(name, {}).get("restitution")
            span = "-"
            if shot:
                span = "{:.3f} .. {:.3f}".format(*shot["range"]) + ("" if shot["resolved"] else " (not resolved)")
            lines.append(f"| {name} | {e['before']:.3f} | {e['after']:.3f} | {span} |")
        lines.append("")
    lines += ["## Match with the clip", ""]
    per_object = {b: i["window_match"] for b, i in payload["calibration"].get("per_object", {}).items()}
    if any(per_object.values()):
        lines += [
            "Calibration windows (what calibration fits): each rolled out open loop from its tracked start; per",
            "window the mean error over its frames, then the median (and mean) over the object's windows:",
            "",
            "| object | windows | position error before (mm) | after (mm) | rotation error before (deg) | after |",
            "|---|---|---|---|---|---|",
        ]
        for name, m in per_object.items():
            if not m:
                lines.append(f"| {name} | 0 | - | - | - | - |")
                continue
            b, a = m["before"], m["after"]
            lines.append(
                f"| {name} | {m['windows']} | {b['median_position_error_mm']} ({b['mean_position_error_mm']}) | "
                f"{a['median_position_error_mm']} ({a['mean_position_error_mm']}) | "
                f"{b['median_rotation_error_deg']} ({b['mean_rotation_error_deg']}) | "
                f"{a['median_rotation_error_deg']} ({a['mean_rotation_error_deg']}) |"
            )
        lines += [""]
    lines += [
        "Whole tracked segments, open loop from the first tracked state. After the first bounce a tossed object's",
        "motion hinges on that state (often in the air, where tracking is least certain), so this figure can grow",
        "even as the windows above improve:",
        "",
    ]
    lines += ["| object | mean position error before (mm) | after (mm) | mean rotation error before (deg) | after |"]
    lines += ["|---|---|---|---|---|"]
    after = payload.get("match_after", {})
    for name, before in payload["match_before"].items():
        a = after.get(name, {})
        lines.append(
            f"| {name} | {before['mean_position_error_mm']} | {a.get('mean_position_error_mm', '-')} | "
            f"{before['mean_rotation_error_deg']} | {a.get('mean_rotation_error_deg', '-')} |"
        )
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------------------------------------------
# Identifiability: which parameters the clip constrains


@dataclass(frozen=True, kw_only=True)
class ParameterScreen:
    """How much one parameter's value shows in the clip.

    Attributes:
        name: the calibration parameter name (`BODY.friction.sliding`, ...).
        body: the free body whose motion is compared (the name's first part).
        nominal: the scene's (prior) value.
        lower, upper: the search bounds.
        best: the grid value whose rollout matches the tracked motion best (others at their grid best).
        change_down, change_up: (mean position change m, mean rotation change deg) of the body's rollout when the
            parameter moves from `best` to `best * (1 - relative_change)` / `best * (1 + relative_change)`.
        constrained: both changes exceed the thresholds: the clip tells the parameter to within `relative_change`.
        curve: (value, mean position error m, mean rotation error deg) against the tracked motion along the grid.
    """

    name: str
    body: str
    nominal: float
    lower: float
    upper: float
    best: float
    change_down: tuple[float, float]
    change_up: tuple[float, float]
    constrained: bool
    curve: tuple[tuple[float, float, float], ...]

    def as_dict(self) -> dict[str, Any]:
        return {
            "constrained": self.constrained,
            "grid_best": round(self.best, 5),
            "change_down_mm_deg": [round(1e3 * self.change_down[0], 3), round(self.change_down[1], 3)],
            "change_up_mm_deg": [round(1e3 * self.change_up[0], 3), round(self.change_up[1], 3)],
            "curve": [[round(v, 5), round(1e3 * p, 3), round(r, 3)] for v, p, r in self.curve],
        }


def _body_errors(
    model: Any, preds: Sequence[Trajectory], reals: Sequence[Trajectory], body: str | None, *, rms: bool = False
) -> tuple[float, float]:
    """Position error (m) and rotation error (deg) of one free body (None: the worst body) over trajectories: the
    mean over all samples, or with `rms` the root mean square (a change confined to a bounce counts fully)."""
    from grounder.sim.rollout import free_body_errors

    per: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for pred, real in zip(preds, reals, strict=True):
        for name, (pos, rot) in free_body_errors(model, pred, real).items():
            per.setdefault(name, []).append((pos, rot))

    def reduce(values: np.ndarray) -> float:
        return float(np.sqrt(np.mean(values**2))) if rms else float(np.mean(values))

    stats = {
        name: (
            reduce(np.concatenate([p for p, _ in errs])),
            float(np.rad2deg(reduce(np.concatenate([r for _, r in errs])))),
        )
        for name, errs in per.items()
    }
    if body is not None and body in stats:
        return stats[body]
    return max(stats.values(), key=lambda s: s[0])


def screen_parameters(
    scene_xml: Path,
    trajs: Sequence[Trajectory],
    params: Sequence[str],
    *,
    relative_change: float = 0.2,
    min_position_m: float = SCREEN_MIN_POSITION_M,
    min_rotation_deg: float = SCREEN_MIN_ROTATION_DEG,
    grid_points: int = 13,
    passes: int = 2,
    nthread: int | None = 1,
) -> list[ParameterScreen]:
    """Which parameters the tracked motion constrains to within `relative_change`.

    Each trajectory is rolled out open loop from its first state (as calibration does). Coordinate-wise grid search
    (`passes` sweeps over `grid_points` values across each parameter's bounds, in its search coordinate, every other
    parameter at its current grid best) finds where the rollouts match the tracks best; there each parameter is
    moved by -/+ `relative_change`, and it counts as constrained only if the moved body's rollout changes by at
    least `min_position_m` (root mean square over the frames) or `min_rotation_deg` in both directions: a smaller
    change is below what tracking resolves (a parameter of an object that never slides, or never bounces, leaves no
    trace).

    Contact parameters are applied as calibration applies them (the body's geoms get top priority), so on a scene
    whose contacts mix parameters (MuJoCo: the larger friction, the solmix-weighted solref) the values found are the
    contact's effective ones.
    """
    import mujoco

    from grounder.calibration.parameters import apply_to_model, resolve_parameters
    from grounder.sim.rollout import simulate

    base = mujoco.MjModel.from_xml_path(str(scene_xml))
    resolved = resolve_parameters(base, list(params))
    data = mujoco.MjData(base)
    trajs = list(trajs)
    current = np.array([p.nominal for p in resolved], float)

    def run(rows: np.ndarray) -> list[tuple[Any, list[Trajectory]]]:
        models = [apply_to_model(base, resolved, row, data=data) for row in rows]
        preds = simulate(models, trajs, nthread=nthread)
        return list(zip(models, preds, strict=True))  # type: ignore[arg-type]

    curves: list[list[tuple[float, float, float]]] = [[] for _ in resolved]
    for _ in range(passes):
        for i, p in enumerate(resolved):
            values = [float(v) for v in p.from_unit(np.linspace(0.0, 1.0, grid_points))]
            rows = np.repeat(current[None], len(values), axis=0)
            rows[:, i] = values
            body = _body_of(p.name)
            curve = []
            for v, (model, preds) in zip(values, run(rows), strict=True):
                pos_m, rot_deg = _body_errors(model, preds, trajs, body)
                curve.append((v, pos_m, rot_deg))
            score = [pos / min_position_m + rot / min_rotation_deg for _, pos, rot in curve]
            current[i] = curve[int(np.argmin(score))][0]
            curves[i] = curve
    out = []
    for i, p in enumerate(resolved):
        change_down, change_up, constrained = _step_visible(
            base, resolved, current, i, trajs, relative_change, min_position_m, min_rotation_deg, nthread=nthread
        )
        out.append(
            ParameterScreen(
                name=p.name,
                body=_body_of(p.name) or "",
                nominal=p.nominal,
                lower=p.lower,
                upper=p.upper,
                best=float(current[i]),
                change_down=change_down,
                change_up=change_up,
                constrained=constrained,
                curve=tuple(curves[i]),
            )
        )
    return out


def _body_of(name: str) -> str | None:
    """The free body whose motion shows a parameter (`BODY.field`), or None for a pair parameter (`A:B.field`)."""
    head = name.split(".", 1)[0]
    return None if ":" in head else head


def _step_visible(
    base: Any,
    resolved: Sequence[Any],
    values: np.ndarray,
    index: int,
    trajs: Sequence[Trajectory],
    relative_change: float,
    min_position_m: float,
    min_rotation_deg: float,
    *,
    nthread: int | None = 1,
) -> tuple[tuple[float, float], tuple[float, float], bool]:
    """Moves parameter `index` from `values[index]` by -/+ `relative_change` (the others at `values`) and returns the
    changes of its body's rollouts, (position m, rotation deg) root mean square each way, and whether both are at
    least `min_position_m` or `min_rotation_deg`. A bound hit counts as no change in that direction: the clip may not
    rule out the bound's far side."""
    import mujoco

    from grounder.calibration.parameters import apply_to_model
    from grounder.sim.rollout import simulate

    p = resolved[index]
    centre = float(values[index])
    rows = np.repeat(np.asarray(values, float)[None], 3, axis=0)
    rows[1, index] = float(np.clip(centre * (1.0 - relative_change), p.lower, p.upper))
    rows[2, index] = float(np.clip(centre * (1.0 + relative_change), p.lower, p.upper))
    data = mujoco.MjData(base)
    models = [apply_to_model(base, resolved, row, data=data) for row in rows]
    ref, down, up = simulate(models, list(trajs), nthread=nthread)
    body = _body_of(p.name)
    change_down = _body_errors(models[1], down, ref, body, rms=True)  # type: ignore[arg-type]
    change_up = _body_errors(models[2], up, ref, body, rms=True)  # type: ignore[arg-type]

    def visible(change: tuple[float, float]) -> bool:
        return change[0] >= min_position_m or change[1] >= min_rotation_deg

    down_ok = visible(change_down) and rows[1, index] < centre
    up_ok = visible(change_up) and rows[2, index] > centre
    return change_down, change_up, bool(down_ok and up_ok)


def indistinguishable_range(
    scene_xml: Path,
    trajs: Sequence[Trajectory],
    params: Sequence[str],
    values: np.ndarray,
    index: int,
    *,
    min_position_m: float,
    min_rotation_deg: float,
    max_factor: float = 2.0,
    points: int = 41,
    nthread: int | None = 1,
) -> list[float]:
    """The range of `params[index]` outside which the tracks tell a rollout from the one at `values[index]`.

    The parameter is scanned over `values[index]` times [1 / max_factor, max_factor] (log spaced, within its bounds),
    the others held at `values`; a value is distinguishable when the body's rollout moves by at least
    `min_position_m` or `min_rotation_deg` (means over the frames) from the calibrated one. The range runs from the
    nearest distinguishable value below to the nearest above (an outer bound of the indistinguishable values); a
    side with none is open: the parameter's bound.

    A resolution interval, not a statistical one: the Laplace interval of the calibration needs many independent
    trajectories and a smooth loss; a single toss gives one of each object and a kinked loss.
    """
    import mujoco

    from grounder.calibration.parameters import apply_to_model, resolve_parameters
    from grounder.sim.rollout import simulate

    base = mujoco.MjModel.from_xml_path(str(scene_xml))
    resolved = resolve_parameters(base, list(params))
    p = resolved[index]
    centre = float(values[index])
    scan = np.unique(np.clip(centre * np.geomspace(1.0 / max_factor, max_factor, points), p.lower, p.upper))
    rows = np.repeat(np.asarray(values, float)[None], len(scan) + 1, axis=0)
    rows[1:, index] = scan
    data = mujoco.MjData(base)
    models = [apply_to_model(base, resolved, row, data=data) for row in rows]
    preds = simulate(models, list(trajs), nthread=nthread)
    body = _body_of(p.name)
    ref = preds[0]
    same = []
    for model, pred in zip(models[1:], preds[1:], strict=True):
        pos_m, rot_deg = _body_errors(model, pred, ref, body, rms=True)  # type: ignore[arg-type]
        same.append(pos_m < min_position_m and rot_deg < min_rotation_deg)
    below = [v for v, ok in zip(scan, same, strict=True) if v < centre and not ok]
    above = [v for v, ok in zip(scan, same, strict=True) if v > centre and not ok]
    return [float(max(below)) if below else p.lower, float(min(above)) if above else p.upper]
