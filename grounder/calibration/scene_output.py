"""Writing a calibrated scene folder: ``scene.xml`` from the calibrated spec, the source folder's other files and
assets (not those in `NOT_COPIED`), ``scene.json`` with a note of the calibration, ``calibration.json`` and
``report.html``; all staged and moved into place at once.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import mujoco

from grounder.calibration.result import CalibrationResult
from grounder.core.json_files import read_json_file
from grounder.core.trajectory import Trajectory
from grounder.errors import GrounderError
from grounder.residual.meta import RESIDUAL_FILES
from grounder.sim.scene_files import copy_scene_files
from image2sim_common.outdir import write_text_atomic

# Not copied from the scene folder: what calibrate writes anew, the large unchanged reconstruction, and a learned
# residual, which was trained against the uncalibrated model and no longer applies.
NOT_COPIED = (
    "scene.xml",
    "calibration.json",
    "distribution.json",
    "report.html",
    "reconstruction",
    *RESIDUAL_FILES,
)


def _check_manifest(scene: Path) -> None:
    """A scene folder's ``scene.json``, which the calibrated folder carries with a note (`_note_in_manifest`), must be
    readable JSON: found before the calibration runs, not after.

    Raises:
        GrounderError: scene.json cannot be read or parsed (including nesting deeper than the parser allows).
    """
    manifest = Path(scene) / "scene.json"
    if not Path(scene).is_dir() or not manifest.is_file():
        return
    read_json_file(manifest, "restore it (re-run `image2sim ground` for this scene) or remove it from the scene folder")


def _note_in_manifest(manifest: Path, result: CalibrationResult) -> None:
    """Records in a copied ``scene.json`` that scene.xml was calibrated, and with which values.

    The file is replaced (a temporary file renamed over it), never written through: a copied link would otherwise
    lead the write to the file it points at, outside the output folder.
    """
    if not manifest.is_file():
        return
    try:
        data = json.loads(manifest.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):  # checked by calibrate() first; changed since: copied as it is
        return
    if isinstance(data, dict):
        data["calibration"] = {
            "file": "calibration.json",
            "mode": result.mode,
            "parameters": result.values,
            "note": "scene.xml holds the calibrated values; per-object entries above are from before calibration",
        }
        write_text_atomic(manifest, json.dumps(data, indent=1) + "\n")


def write_calibrated_scene(
    scene: Path,
    result: CalibrationResult,
    report_trajs: Sequence[Trajectory],
    out: Path,
    base: mujoco.MjModel,
) -> Path:
    """Writes ``out``: calibrated ``scene.xml`` (+ assets), ``calibration.json``, ``report.html``; atomically."""
    from image2sim_common.outdir import staged_output_dir  # here: importing `reconstruction` loads pycolmap

    scene = Path(scene)
    out = Path(out)
    # The claim, the short staging names and the second look at `out` before the move are `staged_output_dir`'s: a
    # folder that appeared at `out` while calibrating is left as it is, and the result kept beside it.
    with staged_output_dir(out, error=GrounderError, inputs=(scene,)) as stage:
        copy_scene_files(scene, stage, skip=NOT_COPIED)
        (stage / "scene.xml").write_text(result.spec.to_xml())
        _note_in_manifest(stage / "scene.json", result)
        # The written MJCF must reproduce the calibrated model: a drifted writer would silently lose the fit.
        reloaded = mujoco.MjModel.from_xml_path(str(stage / "scene.xml"))
        if reloaded.nq != base.nq or reloaded.nv != base.nv:
            raise GrounderError("the written scene.xml does not match the scene's joints")
        (stage / "calibration.json").write_text(json.dumps(result.to_json(), indent=1) + "\n")
        if result.distribution is not None:
            from grounder.calibration.distribution import DISTRIBUTION_FILE, write_distribution

            write_distribution(stage / DISTRIBUTION_FILE, result.distribution, result.distribution.parameters(reloaded))
        from grounder.calibration.report import write_report

        write_report(stage / "report.html", result, base, report_trajs)
    return out
