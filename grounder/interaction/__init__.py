"""Interaction: a calibrated scene from a scan and a clip of its objects moving (`ground SCAN --interaction CLIP`).

- `pipeline`: `ground_with_interaction`, the entry point (ground, track, calibrate, report: its module docstring);
- `options`: `InteractionOptions`, `ImpactOptions`, `InteractionResult` and the constants they start from;
- `tracks`: the saved tracks calibration reads (`saved_tracks`) and the camera centre (`view_point_of`);
- `per_object`: calibrating each object alone in a scene of its own, by the method the options name;
- `windows`: the windowed calibration: windows cut from tracked motion, screened and calibrated;
- `screen`: which parameters the clip constrains (`screen_parameters`), and a value's resolution range;
- `flights`: free flights in tracked runs, the tracking noise, and the impacts after them;
- `impacts`: contact values from those impacts (the default calibration: `impacts_body`, `fit_impacts`);
- `shooting`: contact values by multiple shooting over a whole tracked run (`fit_contact`);
- `starts`: window start states refitted to the window's own tracked motion (`refine_window_starts`);
- `record`: a parameter's entry in the report, and an object's calibration status;
- `report`: the clip match, each object's bounce and `interaction.md`.

The names below are loaded on first use (PEP 562), so that importing one module does not import them all.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from image2sim_common.lazy import lazy_attributes

# name -> module that defines it
_LAZY = {
    "ground_with_interaction": "grounder.interaction.pipeline",
    "CALIBRATION_METHODS": "grounder.interaction.options",
    "ImpactOptions": "grounder.interaction.options",
    "InteractionOptions": "grounder.interaction.options",
    "InteractionResult": "grounder.interaction.options",
    "default_params": "grounder.interaction.options",
    "saved_tracks": "grounder.interaction.tracks",
    "view_point_of": "grounder.interaction.tracks",
    "calibrate_per_body": "grounder.interaction.per_object",
    "calibrate_constrained": "grounder.interaction.windows",
    "screen_parameters": "grounder.interaction.screen",
    "impacts_body": "grounder.interaction.impacts",
    "ShootingOptions": "grounder.interaction.shooting",
    "fit_contact": "grounder.interaction.shooting",
    "refine_window_starts": "grounder.interaction.starts",
}


__getattr__ = lazy_attributes(__name__, _LAZY)


if TYPE_CHECKING:  # what the lazy names are, for type checkers and editors
    from grounder.interaction.impacts import impacts_body
    from grounder.interaction.options import (
        CALIBRATION_METHODS,
        ImpactOptions,
        InteractionOptions,
        InteractionResult,
        default_params,
    )
    from grounder.interaction.per_object import calibrate_per_body
    from grounder.interaction.pipeline import ground_with_interaction
    from grounder.interaction.screen import screen_parameters
    from grounder.interaction.shooting import ShootingOptions, fit_contact
    from grounder.interaction.starts import refine_window_starts
    from grounder.interaction.tracks import saved_tracks, view_point_of
    from grounder.interaction.windows import calibrate_constrained

__all__ = [  # spelled out (not built from _LAZY) so that linters and type checkers read it
    "CALIBRATION_METHODS",
    "ImpactOptions",
    "InteractionOptions",
    "InteractionResult",
    "ShootingOptions",
    "calibrate_constrained",
    "calibrate_per_body",
    "default_params",
    "fit_contact",
    "ground_with_interaction",
    "impacts_body",
    "refine_window_starts",
    "saved_tracks",
    "screen_parameters",
    "view_point_of",
]
