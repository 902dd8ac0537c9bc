"""Trajectories from tracked video: what ``track.json`` (written by `image2sim track`) tells the diagnosis."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from grounder.errors import GrounderError

MIN_SEGMENT_SAMPLES = 3
"""Tracked segments shorter than this (frames) are left out: a window needs a start and a sample to score, and the
noise estimate third differences."""


@dataclass(frozen=True, kw_only=True)
class TrackedInput:
    """What ``track.json`` says about a folder `image2sim track` wrote: its frame rate, the tracker's velocity
    smoothing window, the fraction of frames each object was tracked in, and the segments it cut."""

    fps: float
    smoothing_frames: int
    tracked_fraction: dict[str, float]
    segments: tuple[str, ...]


def read_track_folder(traj_dir: Path) -> TrackedInput | None:
    """``traj_dir``'s ``track.json`` (None when there is none: trajectories recorded some other way).

    Raises:
        GrounderError: a ``track.json`` that is not one `image2sim track` wrote.
    """
    import json

    from grounder.tracking.options import TRACK_JSON

    path = Path(traj_dir) / TRACK_JSON
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
        if doc.get("format") != "image2sim.track/1":
            raise ValueError(f"format {doc.get('format')!r}")
        smoothing = doc.get("options", {}).get("smoothing", {})
        return TrackedInput(
            fps=float(doc["fps"]),
            smoothing_frames=int(smoothing.get("window_frames", 7)),
            tracked_fraction={k: float(v["tracked_fraction"]) for k, v in doc.get("objects", {}).items()},
            segments=tuple(str(seg["name"]) for seg in doc.get("segments", [])),
        )
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise GrounderError(
            f"{path}: not a track.json that image2sim track wrote ({exc}); pass the folder track wrote, or remove "
            "the file to use the trajectories as recorded"
        ) from exc
