"""Velocities of tracked free bodies from a smoothing fit (Savitzky-Golay); its rotation helpers are
`image2sim_common.rotations`'.

Conventions (MuJoCo's, as in the trajectory format): quaternions are w-first; a free joint's qvel is the world linear
velocity, then the body-frame angular velocity.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from grounder.errors import GrounderError
from image2sim_common.rotations import quat_conj, quat_mul, sign_continuous


@dataclass(frozen=True, kw_only=True)
class SmoothingOptions:
    """How velocities (and, if `smooth_poses`, the poses themselves) are fitted to a tracked body.

    A track is first cut where its velocity jumps (impacts: `impact_pieces`), then each piece is smoothed on its own:
    a Savitzky-Golay fit never mixes the frames before an impact with those after it. A piece that moves as a free
    body under gravity (`gravity_m_s2`, in the gravity-aligned world frame) is fitted with exactly that
    acceleration: the speed a throw leaves the hand with, which a rollout starts from, comes out right.

    Attributes:
        window_frames: odd window length in frames; shortened (to the largest odd length that fits) in short pieces.
        polyorder: polynomial order of the local fit (2 = constant acceleration, exact on free flight).
        smooth_poses: replace measured poses by the fitted ones (less jitter, rounder impacts).
        split_at_impacts: cut at velocity jumps before smoothing (off: one fit across the whole segment).
        min_position_noise_m, min_rotation_noise_deg: floors of the tracking noise, which is otherwise estimated from
            the track (third differences, a robust spread): the scale a velocity jump must stand out from.
        max_piece_frames: longest piece considered when cutting (longer smooth stretches become several pieces).
        gravity_m_s2: gravity in the world frame of the poses.
    """

    window_frames: int = 7
    polyorder: int = 2
    smooth_poses: bool = False
    split_at_impacts: bool = True
    min_position_noise_m: float = 0.0005
    min_rotation_noise_deg: float = 0.3
    max_piece_frames: int = 45
    gravity_m_s2: tuple[float, float, float] = (0.0, 0.0, -9.81)

    def __post_init__(self) -> None:
        if self.window_frames < 3 or self.window_frames % 2 == 0:
            raise GrounderError(f"{self.window_frames=} but expected an odd number >= 3")
        if not 1 <= self.polyorder < self.window_frames:
            raise GrounderError(f"{self.polyorder=} but expected 1 <= polyorder < window_frames")
        if not (self.min_position_noise_m > 0 and self.min_rotation_noise_deg > 0):
            raise GrounderError("min_position_noise_m and min_rotation_noise_deg must be positive")
        if self.max_piece_frames < 3:
            raise GrounderError(f"{self.max_piece_frames=} but expected >= 3")


def _window(num: int, options: SmoothingOptions) -> tuple[int, int]:
    window = min(options.window_frames, num if num % 2 else num - 1)
    return window, min(options.polyorder, window - 1)


def _robust_noise(values: np.ndarray, floor: float) -> float:
    """Per-sample noise of a (T, C) signal that is piecewise quadratic plus white noise: third differences cancel
    the quadratic (their variance is 20 sigma^2); the median absolute deviation ignores the few at impacts."""
    if len(values) < 8:
        return floor
    third = np.diff(values, n=3, axis=0).reshape(-1)
    mad = float(np.median(np.abs(third - np.median(third))))
    return max(1.4826 * mad / np.sqrt(20.0), floor)


class Piece(NamedTuple):
    """Frames `first` .. `last` (inclusive) of smooth motion; `ballistic`: a free flight under gravity."""

    first: int
    last: int
    ballistic: bool


def impact_pieces(pos_m: np.ndarray, options: SmoothingOptions | None = None, dt_s: float | None = None) -> list[Piece]:
    """Cuts one body's uniformly sampled track into pieces of smooth motion, where its velocity jumps (impacts).

    Within a piece the positions are either a free flight (a line plus the gravity term, given `dt_s`) or any
    constant-acceleration curve (a steady slide, rest). The cut minimises the total chi-square of the per-piece
    fits (in units of the position noise) plus a BIC penalty per fitted coefficient, by dynamic programming; a
    flight has fewer coefficients, so where it fits it is preferred. Pieces are at least 2 frames. Orientations are
    left out of the cut: a quaternion spinning at a steady rate is no low-order polynomial over a long flight, and
    an impact that changes the spin changes the velocity too.

    Args:
        pos_m: (T, 3) world positions, gravity-aligned frame.
        options: noise floor, the longest piece and gravity.
        dt_s: sample interval; None: no free-flight model.

    Returns:
        The pieces, covering frames 0 .. T-1 in order.
    """
    options = options or SmoothingOptions()
    pos = np.asarray(pos_m, np.float64)
    num = len(pos)
    if num < 4:
        return [Piece(0, num - 1, False)]
    sigma_p = _robust_noise(pos, options.min_position_noise_m)
    signal = pos / sigma_p  # (T, 3), unit noise
    log_n = np.log(num)
    longest = min(options.max_piece_frames, num)
    gravity = np.asarray(options.gravity_m_s2, np.float64) / sigma_p

    def chi2(windows: np.ndarray, n: int, order: int) -> np.ndarray:
        """(A, C', n) windows -> (A,) chi-square after removing a polynomial of `order` (fewer if n is short)."""
        local_t = np.arange(n, dtype=np.float64) - 0.5 * (n - 1)
        q, _ = np.linalg.qr(np.vander(local_t, min(order + 1, n), increasing=True))
        residual = np.eye(n) - q @ q.T
        return np.einsum("ij,acj->aci", residual, windows).__pow__(2).sum(axis=(1, 2))

    # cost[n][a], kind[n][a]: the cheaper model of frames a .. a + n - 1 and whether it is the flight
    cost: dict[int, np.ndarray] = {}
    kind: dict[int, np.ndarray] = {}
    for n in range(2, longest + 1):
        windows = np.lib.stride_tricks.sliding_window_view(signal, n, axis=0)  # (T - n + 1, 3, n)
        free = chi2(windows, n, 2) + 3 * 3 * log_n
        if dt_s is None:
            cost[n], kind[n] = free, np.zeros(len(free), bool)
            continue
        fall = 0.5 * (np.arange(n) * dt_s) ** 2  # the gravity term over the piece
        flight = chi2(windows - gravity[None, :, None] * fall[None, None, :], n, 1) + 2 * 3 * log_n
        kind[n] = flight <= free
        cost[n] = np.minimum(flight, free)
    best = np.full(num + 1, np.inf)  # best[b]: lowest total for frames 0 .. b - 1
    best[0] = 0.0
    start = np.zeros(num + 1, dtype=int)
    for end in range(2, num + 1):
        for n in range(2, min(longest, end) + 1):
            total = best[end - n] + cost[n][end - n]
            if total < best[end]:
                best[end], start[end] = total, end - n
    pieces = []
    end = num
    while end > 0:
        first = int(start[end])
        pieces.append(Piece(first, end - 1, bool(kind[end - first][first])))
        end = first
    return pieces[::-1]


def _piece_velocities(
    time_s: np.ndarray, pos: np.ndarray, quats: np.ndarray, options: SmoothingOptions, ballistic: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fitted positions, quaternions and their time derivatives over one smooth piece (see `free_body_velocities`).

    A flight's positions are the least-squares line plus the gravity term (its velocity is exact where the throw
    speed is read); other pieces use Savitzky-Golay within the piece (a line through a 2-frame piece).
    """
    from scipy.signal import savgol_filter

    num = len(time_s)
    dt_s = float(np.median(np.diff(time_s)))
    if num >= 3:
        window, order = _window(num, options)
        kwargs = {"window_length": window, "polyorder": order, "axis": 0, "mode": "interp"}
        pos_fit = savgol_filter(pos, deriv=0, **kwargs)
        linvel = savgol_filter(pos, deriv=1, delta=dt_s, **kwargs)
        quat_fit = savgol_filter(quats, deriv=0, **kwargs)
        quat_dot = savgol_filter(quats, deriv=1, delta=dt_s, **kwargs)
    else:
        pos_fit, quat_fit = pos.copy(), quats.copy()
        linvel = np.repeat((pos[1:] - pos[:1]) / dt_s, num, axis=0)
        quat_dot = np.repeat((quats[1:] - quats[:1]) / dt_s, num, axis=0)
    if ballistic:
        t = time_s - time_s[0]
        gravity = np.asarray(options.gravity_m_s2, np.float64)
        coef = np.linalg.lstsq(np.vander(t, 2, increasing=True), pos - 0.5 * t[:, None] ** 2 * gravity, rcond=None)[0]
        pos_fit = coef[0] + t[:, None] * coef[1] + 0.5 * t[:, None] ** 2 * gravity
        linvel = coef[1] + t[:, None] * gravity
    return pos_fit, quat_fit, linvel, quat_dot


def free_body_velocities(
    time_s: np.ndarray, pos_m: np.ndarray, quat_wxyz: np.ndarray, options: SmoothingOptions | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Velocities of one free body over one uniformly sampled segment, from a Savitzky-Golay fit.

    The quaternion is fitted component-wise after making its sign continuous; the body angular velocity is
    ``2 * vec(conj(q) * dq/dt)`` of the fitted, normalised quaternion.

    Args:
        time_s: (T,) sample times, uniform spacing, T >= 3.
        pos_m: (T, 3) world positions.
        quat_wxyz: (T, 4) orientations.
        options: smoothing window and order.

    Returns:
        (pos_m (T, 3), quat_wxyz (T, 4), linvel_world_m_s (T, 3), angvel_body_rad_s (T, 3)); the poses are the
        fitted ones if `options.smooth_poses`, else the inputs (quaternions sign-normalised).
    """
    options = options or SmoothingOptions()
    time_s = np.asarray(time_s, np.float64)
    pos_m = np.asarray(pos_m, np.float64)
    num = len(time_s)
    if num < 3:
        raise GrounderError(f"a segment needs at least 3 samples for velocities, got {num}")
    quats = sign_continuous(quat_wxyz)
    dt_s = float(np.median(np.diff(time_s)))
    pieces = impact_pieces(pos_m, options, dt_s) if options.split_at_impacts else [Piece(0, num - 1, False)]
    pos_fit, quat_fit = np.empty_like(pos_m), np.empty_like(quats)
    linvel, quat_dot = np.empty_like(pos_m), np.empty_like(quats)
    for first, last, ballistic in pieces:
        rows = slice(first, last + 1)
        fitted = _piece_velocities(time_s[rows], pos_m[rows], quats[rows], options, ballistic)
        pos_fit[rows], quat_fit[rows], linvel[rows], quat_dot[rows] = fitted
    norm = np.linalg.norm(quat_fit, axis=1, keepdims=True)
    unit = quat_fit / norm
    # d(q/|q|)/dt = (dq - q (q.dq)/|q|^2) / |q|: keep only the part tangent to the unit sphere.
    unit_dot = (quat_dot - unit * np.sum(unit * quat_dot, axis=1, keepdims=True)) / norm
    angvel_body = 2.0 * quat_mul(quat_conj(unit), unit_dot)[:, 1:]
    if options.smooth_poses:
        return pos_fit, unit, linvel, angvel_body
    return (
        np.asarray(pos_m, np.float64).copy(),
        quats / np.linalg.norm(quats, axis=1, keepdims=True),
        linvel,
        angvel_body,
    )
