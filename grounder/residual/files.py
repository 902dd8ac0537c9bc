"""The files of a residual scene folder: what makes a folder a residual scene, hashes, and loading with checks.

Files in a residual scene folder: ``scene.xml`` (+ assets), ``residual.pt`` (torch ``state_dict``: weights and the
normalisation, bounds and coverage statistics; read with ``weights_only=True``), ``residual.json`` (metadata:
period, bodies, feature and output names, gate thresholds, training summary) and ``residual.onnx`` (the same
features -> gated correction function, for use outside Python).

Both ``residual.json`` and ``residual.pt`` are untrusted input: :func:`load_residual` checks every field and tensor
against the metadata and the scene's model before the free-body residual (``grounder.residual.free_body``) or the
joint-space one (``grounder.residual.joint``) is built from them.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from grounder.core.json_files import read_json_file
from grounder.core.torch_files import load_weights_file, tensor_problem
from grounder.errors import GrounderError, shown
from grounder.residual.free_body import FreeBody, NumpyResidual, free_bodies
from grounder.residual.joint import JOINT_SPACE, NumpyJointResidual, check_joint_meta, history_of, joint_space
from grounder.residual.meta import META_FILE, RETRAIN, WEIGHTS_FILE, ResidualMeta


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def scene_files_sha256(xml: Path) -> dict[str, str]:
    """sha256 of each file ``xml`` includes or loads (`grounder.sim.scene_files`), keyed by its path relative
    to the MJCF's folder (POSIX separators); files the MJCF names but that do not exist are left out (MuJoCo then
    fails to load the scene anyway)."""
    from grounder.sim.scene_files import scene_files

    hashes = {}
    for rel in scene_files(xml):
        path = xml.parent / rel
        if path.is_file():
            hashes[rel.as_posix()] = file_sha256(path)
    return dict(sorted(hashes.items()))


def _changed_scene_file(xml: Path, trained: dict[str, str]) -> str | None:
    """The first file of the scene that differs from the one the residual was trained with (as a phrase), or None."""
    now = scene_files_sha256(xml)
    for name in sorted(set(now) | set(trained)):
        if name not in now:
            return f"{name} is gone"
        if name not in trained:
            return f"{name} is new"
        if now[name] != trained[name]:
            return f"{name} changed (sha256 {now[name][:12]}..., the residual was trained with {trained[name][:12]}...)"
    return None


def has_residual_files(scene_dir: Path) -> bool:
    scene_dir = Path(scene_dir)
    return scene_dir.is_dir() and (scene_dir / META_FILE).is_file() and (scene_dir / WEIGHTS_FILE).is_file()


def check_residual_pair(scene_dir: Path) -> None:
    """Refuses a scene folder that holds one of ``residual.json`` and ``residual.pt`` without the other.

    Such a folder would otherwise be simulated without its residual, silently.

    Raises:
        GrounderError: one line naming the file that is there and the one that is missing, and what to do.
    """
    scene_dir = Path(scene_dir)
    if not scene_dir.is_dir():
        return
    there = [name for name in (META_FILE, WEIGHTS_FILE) if (scene_dir / name).exists()]
    if len(there) == 1:
        missing = WEIGHTS_FILE if there[0] == META_FILE else META_FILE
        raise GrounderError(
            f"{scene_dir / there[0]} has no {missing} beside it: the residual is incomplete; copy the whole scene "
            "folder again, retrain it (image2sim residual train), or run without it (--no-residual)"
        )


def _checked_state(state: Any, meta: ResidualMeta, where: Path) -> dict[str, np.ndarray]:
    """``residual.pt``'s tensors as float64 arrays, each checked against the metadata first.

    Every tensor must be dense, of a real floating-point dtype (``speed_columns`` of a joint-space residual:
    integer), of the shape that ``residual.json`` implies (bodies, features, outputs, ``hidden``, ``layers``,
    ``gate.coverage_centres``) and finite; the ones the residual divides by positive (``feat_std``, ``out_bound``,
    ``coverage_dist``), ``out_gain`` >= 0 and ``range_lo`` <= ``range_hi``. No tensor may be missing or extra.

    Raises:
        GrounderError: one line naming the file, the tensor and the problem.
    """
    import torch

    if not isinstance(state, dict) or not all(isinstance(k, str) for k in state):
        raise GrounderError(
            f"{where}: expected a state_dict (names -> tensors), not a {type(state).__name__}; {RETRAIN}"
        )
    if len(state) < 2 * (meta.layers + 1):  # before listing the layers' tensors: a huge count must not build a list
        raise GrounderError(
            f"{where}: holds {len(state)} tensors, too few for the {meta.layers} hidden layers in {META_FILE}; "
            f"{RETRAIN}"
        )
    num_b = 1 if meta.space == "joint" else len(meta.bodies)
    num_f, num_o = len(meta.feature_names), len(meta.output_names)
    expected: dict[str, tuple[int, ...]] = {
        "feat_mean": (num_b, num_f),
        "feat_std": (num_b, num_f),
        "out_scale": (num_b, num_o),
        "out_bound": (num_b, num_o),
        "range_lo": (num_b, num_f),
        "range_hi": (num_b, num_f),
        "centres": (num_b, meta.gate.coverage_centres, num_f),
        "coverage_dist": (num_b,),
        "out_gain": (num_b,),
        "radius_m": (num_b,),
    }
    if meta.space == "joint":
        expected["speed_columns"] = (len(meta.bodies),)
    widths = (num_f, *([meta.hidden] * meta.layers), num_o)
    for b in range(num_b):
        for i in range(meta.layers + 1):
            expected[f"nets.{b}.{2 * i}.weight"] = (widths[i + 1], widths[i])
            expected[f"nets.{b}.{2 * i}.bias"] = (widths[i + 1],)
    if meta.spread_hidden:  # the learned spread (grounder.residual.spread): one hidden layer per body
        expected["spread.bound"] = (num_b, num_o)
        expected["spread.gain"] = (num_b,)
        for b in range(num_b):
            expected[f"spread.nets.{b}.0.weight"] = (meta.spread_hidden, num_f)
            expected[f"spread.nets.{b}.0.bias"] = (meta.spread_hidden,)
            expected[f"spread.nets.{b}.2.weight"] = (num_o, meta.spread_hidden)
            expected[f"spread.nets.{b}.2.bias"] = (num_o,)
    sizes = (
        f"{len(meta.bodies)} {'joints' if meta.space == 'joint' else 'bodies'}, {num_f} features, {num_o} outputs, "
        f"hidden={meta.hidden}, layers={meta.layers}, gate.coverage_centres={meta.gate.coverage_centres}"
    )
    missing = [name for name in expected if name not in state]
    if missing:
        raise GrounderError(f"{where}: missing tensor {shown(missing[0])} ({META_FILE}: {sizes}); {RETRAIN}")
    extra = [name for name in state if name not in expected]
    if extra:
        raise GrounderError(f"{where}: unexpected tensor {shown(extra[0])} ({META_FILE}: {sizes}); {RETRAIN}")
    arrays: dict[str, np.ndarray] = {}
    for name, shape in expected.items():
        tensor = state[name]
        problem = tensor_problem(tensor)
        if problem is None and tensor.dtype.is_floating_point == (name == "speed_columns"):
            wanted = "an integer" if name == "speed_columns" else "a floating-point"
            problem = f"has dtype {tensor.dtype}, expected {wanted} one"
        if problem is None and tuple(tensor.shape) != shape:
            problem = f"has shape {tuple(tensor.shape)}, expected {shape} ({META_FILE}: {sizes})"
        if problem is None:
            try:
                array = tensor.detach().resolve_conj().resolve_neg().to(torch.float64).numpy()
            except (RuntimeError, TypeError) as exc:
                raise GrounderError(
                    f"{where}: tensor {name!r} cannot be read as numbers ({type(exc).__name__}); {RETRAIN}"
                ) from exc
            if not np.isfinite(array).all():
                problem = "holds NaN or infinite values"
            elif name in ("feat_std", "out_bound", "coverage_dist", "spread.bound") and not (array > 0.0).all():
                problem = "holds values <= 0 (the residual divides by them)"
            elif name in ("out_gain", "spread.gain") and not (array >= 0.0).all():
                problem = "holds a negative output gain"
            elif name == "range_hi" and not (array >= arrays["range_lo"]).all():
                problem = "is below range_lo somewhere"
            arrays[name] = array
        if problem is not None:
            raise GrounderError(f"{where}: tensor {name!r} {problem}; {RETRAIN}")
    return arrays


def load_residual(
    scene_dir: Path, model: mujoco.MjModel, *, scene_xml: Path | None = None, check_scene_xml: bool = True
) -> NumpyResidual | NumpyJointResidual:
    """Reads ``residual.json`` and ``residual.pt`` from a scene folder, checked against the scene's model.

    Both files are untrusted input: the metadata's fields and every tensor are checked (types, ranges, shapes
    against the metadata, finite values) before anything uses them.

    Args:
        scene_dir: The residual scene folder.
        model: The scene's compiled model.
        scene_xml: The MJCF ``model`` was compiled from (default ``scene_dir/scene.xml``); its sha256 must be the
            one in ``residual.json``, so that a residual is never applied to a scene edited since training.
        check_scene_xml: Check that hash (off for a caller that only reads the period and never applies the
            residual, such as training a new residual on an edited residual scene).

    Returns:
        The free-body residual, or the joint-space one (``grounder.residual.joint``) for an articulated scene.

    Raises:
        GrounderError: missing or malformed files, a residual trained for other bodies or another timestep, or a
            scene.xml that changed since training.
    """
    scene_dir = Path(scene_dir)
    meta_path, weights_path = scene_dir / META_FILE, scene_dir / WEIGHTS_FILE
    raw = read_json_file(meta_path, RETRAIN)
    meta = ResidualMeta.from_json(raw, meta_path)
    if meta.space == JOINT_SPACE:
        try:
            space = joint_space(model, history_of(meta.feature_names))
        except GrounderError as exc:  # a scene of other joints: name the residual it does not fit
            raise GrounderError(f"{meta_path}: a joint-space residual, not for this scene ({exc}); retrain it") from exc
        check_joint_meta(meta, space, str(meta_path))
        if meta.output_names != space.output_names:
            raise GrounderError(
                f"{meta_path}: outputs {shown(list(meta.output_names))} are not the scene's joints' "
                f"{shown(list(space.output_names))}; retrain it on this scene"
            )
        bodies: list[FreeBody] = []
    else:
        try:
            bodies = free_bodies(model)
        except GrounderError as exc:  # a scene of hinges and slides: name the residual it does not fit
            raise GrounderError(
                f"{meta_path}: a residual of free bodies {list(meta.bodies)}, not for this scene ({exc}); retrain it "
                "on this scene, or run without it (--no-residual)"
            ) from exc
        if tuple(b.name for b in bodies) != meta.bodies:
            raise GrounderError(
                f"{meta_path}: the residual corrects bodies {list(meta.bodies)} but the scene's free bodies are "
                f"{[b.name for b in bodies]}; retrain it on this scene"
            )
    if not np.isclose(meta.timestep_s, model.opt.timestep, rtol=1e-9, atol=0.0):
        raise GrounderError(
            f"{meta_path}: trained with timestep {meta.timestep_s:.6g} s but the scene has {model.opt.timestep:.6g} s; "
            "retrain the residual on this scene"
        )
    if check_scene_xml:
        xml = Path(scene_xml) if scene_xml is not None else scene_dir / "scene.xml"
        try:
            digest = file_sha256(xml)
        except OSError as exc:
            raise GrounderError(f"{xml}: could not be read ({exc.strerror or type(exc).__name__})") from exc
        if digest != meta.scene_xml_sha256:
            raise GrounderError(
                f"{xml}: {xml.name} changed since the residual was trained (sha256 {digest[:12]}..., "
                f"{META_FILE} has {meta.scene_xml_sha256[:12]}...); retrain with `image2sim residual train` "
                "or restore the scene"
            )
        if meta.scene_files_sha256 is not None:
            try:
                changed = _changed_scene_file(xml, meta.scene_files_sha256)
            except OSError as exc:
                raise GrounderError(
                    f"{xml}: a file it uses could not be read ({exc.strerror or type(exc).__name__})"
                ) from exc
            if changed is not None:
                raise GrounderError(
                    f"{xml}: {changed} since the residual was trained; retrain with `image2sim residual train` "
                    "or restore the scene"
                )
    arrays = _checked_state(load_weights_file(weights_path, RETRAIN), meta, weights_path)
    if meta.space == JOINT_SPACE:
        return NumpyJointResidual(arrays, meta, space)
    return NumpyResidual(arrays, meta, bodies, model.opt.gravity)
