"""Learned physical-property embeddings: a prior over mass, friction and contact for every grounded object.

What an object looks like (three crops from the video) and its shape (extents, volume, fill, convexity, thickness)
go through an encoder to an embedding z (16 dims) with a Gaussian posterior N(embedding, diag(embedding_std^2)).
A smooth decoder maps any z to a Gaussian over each property on an unbounded scale (ln density, ln sliding,
ln torsional and ln rolling friction, logit restitution, ln solref time constant) plus material probabilities.
The spreads are calibrated on held-out renders (90% intervals cover ~90% of held-out truths).

For calibration in embedding space: the prior over z is N(embedding, diag(embedding_std^2)) as stored in
`scene.json`; `decode_embedding(z)` is a smooth (SiLU MLP, exp/sigmoid link) function of z, so it can be optimised
with gradients or finite differences, and its mean/spread stay physical (positive densities and frictions,
restitution in (0, 1)).

Units and mappings: density kg/m^3 (effective: mass / volume of the watertight outer mesh); friction =
(sliding, torsional m, rolling m) as MuJoCo's geom friction; solref = (timeconst s, dampratio) with
dampratio = -ln(e) / sqrt(pi^2 + ln(e)^2) for restitution e (see `_properties_materials`).

The weights and their metadata ship in `grounder/properties/weights/`; `image2sim properties train` regenerates
them from scratch (data rendered with MuJoCo, see `_properties_data`).
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from grounder.core.json_files import read_json_file
from grounder.errors import GrounderError, finite_number, shown
from grounder.properties.model_files import WEIGHTS_DIR, PropertyModelError, finite_numbers
from grounder.properties.training_data import (
    CROP_PX,
    NUM_VIEWS,
    bbox_corners,
    crop_box_px,
    crop_square,
    project_points,
    shape_features,
)
from grounder.sim.restitution import contact_solref
from reconstruction.errors import InputError

if TYPE_CHECKING:
    import mujoco

    from grounder.properties.network import Normalisation, PropertyNet

Z90 = 1.6448536269514722


@dataclass(frozen=True, kw_only=True)
class PropertyModel:
    """Loaded weights: the network, its normalisation and metadata."""

    net: PropertyNet
    norm: Normalisation
    meta: dict[str, Any]
    weights_dir: Path

    @property
    def version(self) -> str:
        return str(self.meta["model_version"])


@functools.lru_cache(maxsize=4)
def load_property_model(weights_dir: Path | None = None) -> PropertyModel:
    """The property model from `weights_dir` (default: the weights shipped with the package), cached."""
    from grounder.core.torch_files import quiet_pickle_protocol_warning
    from grounder.properties.network import META_FILE, WEIGHTS_FILE, load

    weights_dir = Path(weights_dir or WEIGHTS_DIR)
    if not (weights_dir / WEIGHTS_FILE).is_file() or not (weights_dir / META_FILE).is_file():
        make = (
            "reinstall the package (make install) or regenerate them with `image2sim properties train` (~11 min)"
            if weights_dir == WEIGHTS_DIR
            else f"make one there with `image2sim properties train -o {weights_dir}`"
        )
        raise PropertyModelError(
            f"no property model in {weights_dir} (expected {WEIGHTS_FILE} and {META_FILE}); {make}"
        )
    try:
        with quiet_pickle_protocol_warning():
            net, norm, meta = load(weights_dir)
    except PropertyModelError:
        raise
    except GrounderError as exc:  # already one line naming the file and the field: only the type is the model's
        raise PropertyModelError(str(exc)) from exc
    except Exception as exc:
        # Not the exception's own text: torch's runs over several lines and suggests weights_only=False, unsafe for
        # a file of unknown origin.
        command = "image2sim properties train"
        command += "" if weights_dir == WEIGHTS_DIR else f" -o {weights_dir} --overwrite"
        raise PropertyModelError(
            f"{weights_dir / WEIGHTS_FILE}: not a valid property-model weights file, or {META_FILE} beside it does not "
            f"match it ({type(exc).__name__}); regenerate both with `{command}`"
        ) from exc
    return PropertyModel(net=net, norm=norm, meta=meta, weights_dir=weights_dir)


# ---------------------------------------------------------------- decoding


def _natural(mean_t: np.ndarray, std_t: np.ndarray) -> dict[str, Any]:
    """Mean and 90% interval in natural units from the Gaussian over the transformed targets (T,)."""

    def sigmoid(x: np.ndarray) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-x))

    lo_t, hi_t = mean_t - Z90 * std_t, mean_t + Z90 * std_t
    # The mean of each property is the transformed mean mapped back (the median of the lognormal / logit-normal).
    values = []
    for t in (mean_t, lo_t, hi_t):
        density = float(np.exp(t[0]))
        sliding, torsional, rolling = (float(np.exp(t[i])) for i in (1, 2, 3))
        restitution = float(sigmoid(t[4]))
        values.append((density, [sliding, torsional, rolling], restitution, float(np.exp(t[5]))))
    (d, f, e, tc), (d_lo, f_lo, e_lo, tc_lo), (d_hi, f_hi, e_hi, tc_hi) = values
    # solref is what the exported scene writes: the time constant raised to what its step resolves, the damping ratio
    # that bounces at the restitution there (`contact_solref`); dampratio falls as restitution rises, so the ends swap.
    solref = contact_solref(e, tc)
    return {
        "mean": {"density_kg_m3": d, "friction": f, "solref": list(solref), "restitution": e},
        "spread": {
            "density_kg_m3": [d_lo, d_hi],
            "friction": [[lo, hi] for lo, hi in zip(f_lo, f_hi, strict=True)],
            "solref": [
                [contact_solref(e, tc_lo)[0], contact_solref(e, tc_hi)[0]],
                [contact_solref(e_hi, solref[0])[1], contact_solref(e_lo, solref[0])[1]],
            ],
            "restitution": [e_lo, e_hi],
        },
    }


def decode_embedding(z: np.ndarray, model: PropertyModel | None = None) -> dict[str, Any]:
    """The property distribution that embedding `z` stands for; a smooth function of z.

    Args:
        z: (D,) embedding (D = 16 for the shipped model). The prior for an object is N(embedding,
            diag(embedding_std^2)) from its `scene.json` entry.
        model: a loaded model; default the shipped one.

    Returns:
        {"density_kg_m3": float, "friction": [sliding, torsional_m, rolling_m], "solref": [timeconst_s,
        dampratio], "restitution": float, "spread": {same keys: 90% intervals [low, high] (lists of them for
        vectors)}, "spread_kind": "90% interval", "material_probs": {name: p}, "transformed": {"names": [...],
        "mean": [...], "std": [...]}} where "transformed" is the Gaussian over the model's unbounded targets.
    """
    from grounder.properties.network import decode_arrays

    model = model or load_property_model()
    z = np.asarray(z, dtype=np.float64)
    if z.shape != (model.net.embed_dim,) or not np.isfinite(z).all():
        raise PropertyModelError(f"{z.shape=} but expected ({model.net.embed_dim},) finite numbers")
    mean_t, std_t, probs = decode_arrays(model.net, model.norm, z[None])
    out = _natural(mean_t[0], std_t[0])
    return {
        **out["mean"],
        "spread": out["spread"],
        "spread_kind": "90% interval",
        "material_probs": dict(zip(model.meta["material_names"], (float(p) for p in probs[0]), strict=True)),
        "transformed": {
            "names": list(model.meta["target_names"]),
            "mean": mean_t[0].tolist(),
            "std": std_t[0].tolist(),
        },
    }


@dataclass(frozen=True, kw_only=True)
class ObjectProperties:
    """What the model says about one object (the `properties` entry of `scene.json`)."""

    embedding: np.ndarray  # (D,)
    embedding_std: np.ndarray  # (D,)
    decoded: dict[str, Any]  # decode_embedding(embedding)
    model_version: str
    views: int  # distinct video views the crops came from

    @property
    def density_kg_m3(self) -> float:
        return float(self.decoded["density_kg_m3"])

    @property
    def friction(self) -> tuple[float, float, float]:
        f = self.decoded["friction"]
        return (float(f[0]), float(f[1]), float(f[2]))

    @property
    def solref(self) -> tuple[float, float]:
        s = self.decoded["solref"]
        return (float(s[0]), float(s[1]))

    def to_json(self) -> dict[str, Any]:
        d = self.decoded
        return {
            "embedding": [float(x) for x in self.embedding],
            "embedding_std": [float(x) for x in self.embedding_std],
            "embedding_prior": "z ~ N(embedding, diag(embedding_std^2)); grounder.properties.prior.decode_embedding(z)",
            "mean": {k: d[k] for k in ("density_kg_m3", "friction", "solref", "restitution")},
            "spread": d["spread"],
            "spread_kind": d["spread_kind"],
            "material_probs": d["material_probs"],
            "transformed": d["transformed"],
            "model_version": self.model_version,
            "views": self.views,
        }


def predict_properties(
    crops: np.ndarray, features: np.ndarray, model: PropertyModel | None = None, *, views: Sequence[int] = ()
) -> list[ObjectProperties]:
    """Properties of N objects from their crops (N, V, 64, 64, 3) uint8 RGB and shape features (N, 8)."""
    from grounder.properties.network import predict

    model = model or load_property_model()
    crops = np.asarray(crops)
    if crops.ndim != 5 or crops.shape[2:] != (CROP_PX, CROP_PX, 3) or crops.dtype != np.uint8:
        raise PropertyModelError(
            f"crops: shape {crops.shape}, dtype {crops.dtype} but expected (N, V, 64, 64, 3) uint8"
        )
    pred = predict(model.net, model.norm, crops, np.asarray(features, dtype=np.float32))
    return [
        ObjectProperties(
            embedding=pred.z_mu[i],
            embedding_std=pred.z_std[i],
            decoded=decode_embedding(pred.z_mu[i], model),
            model_version=model.version,
            views=int(views[i]) if len(views) > i else crops.shape[1],
        )
        for i in range(len(crops))
    ]


# ---------------------------------------------------------------- crops from a video


@dataclass(frozen=True, kw_only=True)
class CropView:
    """One registered video frame: image and camera (OpenCV axes, pixels)."""

    image_bgr: np.ndarray  # (H, W, 3) uint8
    world_from_cam: np.ndarray  # (4, 4)
    camera_matrix: np.ndarray  # (3, 3) K


def _rect_overlap(a: np.ndarray, b: np.ndarray) -> float:
    """Fraction of rectangle a = (u0, v0, u1, v1) covered by b."""
    w = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    h = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    return w * h / max((a[2] - a[0]) * (a[3] - a[1]), 1e-9)


def object_crops(
    vertices_world_m: np.ndarray,
    views: Sequence[CropView],
    others_world_m: Sequence[np.ndarray] = (),
    num_views: int = NUM_VIEWS,
) -> tuple[np.ndarray, int]:
    """Crops of one object from up to `num_views` frames, spread around it and not hidden by other objects.

    The crop is the square around the projection of the object's world-axis-aligned bounding box, 15% margin,
    resized to 64 px: the rule the training renders use (`crop_box_px`).

    Returns:
        (num_views, 64, 64, 3) uint8 RGB (views repeated when fewer are usable) and the number of distinct views.
    """
    corners = bbox_corners(vertices_world_m)
    centre = corners.mean(axis=0)
    other_corners = [bbox_corners(v) for v in others_world_m]
    candidates = []
    for k, view in enumerate(views):
        h, w = view.image_bgr.shape[:2]
        uvz = project_points(corners, view.world_from_cam, view.camera_matrix)
        if (uvz[:, 2] <= 0).any():
            continue
        rect = np.concatenate([uvz[:, :2].min(axis=0), uvz[:, :2].max(axis=0)])
        inside = _rect_overlap(rect, np.array([0.0, 0.0, w, h]))
        if inside < 0.9:
            continue
        depth = float(np.linalg.norm(centre - view.world_from_cam[:3, 3]))
        occluded = 0.0
        for oc in other_corners:
            o_uvz = project_points(oc, view.world_from_cam, view.camera_matrix)
            nearest = float(np.linalg.norm(oc.mean(axis=0) - view.world_from_cam[:3, 3]))
            if (o_uvz[:, 2] > 0).all() and nearest < depth:
                o_rect = np.concatenate([o_uvz[:, :2].min(axis=0), o_uvz[:, :2].max(axis=0)])
                occluded = max(occluded, _rect_overlap(rect, o_rect))
        offset = view.world_from_cam[:3, 3] - centre
        azimuth = math.atan2(offset[1], offset[0])
        candidates.append((occluded + (1 - inside), azimuth, k, uvz))
    if not candidates:
        raise PropertyModelError("the object is not fully in view in any frame; cannot crop it for the property model")
    best = min(c[0] for c in candidates)
    usable = [c for c in candidates if c[0] <= max(0.15, best + 0.05)]
    # Greedy farthest-point selection in azimuth, starting from the least occluded view.
    chosen = [min(usable, key=lambda c: c[0])]
    while len(chosen) < min(num_views, len(usable)):

        def gap(c: tuple[float, float, int, np.ndarray]) -> float:
            return min(abs(math.remainder(c[1] - s[1], 2 * math.pi)) for s in chosen)

        chosen.append(max((c for c in usable if c not in chosen), key=gap))
    crops = []
    for _, _, k, uvz in chosen:
        image_rgb = np.ascontiguousarray(views[k].image_bgr[..., ::-1])
        crops.append(crop_square(image_rgb, crop_box_px(uvz)))
    distinct = len(crops)
    while len(crops) < num_views:
        crops.append(crops[len(crops) % distinct])
    return np.stack(crops), distinct


def assign_properties(
    objects: Sequence[tuple[str, np.ndarray, np.ndarray]],
    views: Sequence[CropView],
    model: PropertyModel | None = None,
) -> dict[str, ObjectProperties]:
    """Properties of every object of a scene from the video frames.

    Args:
        objects: (name, vertices_world_m (V, 3), faces (F, 3)) of each watertight object mesh, world frame (z up).
        views: the registered frames with their cameras.
        model: default the shipped model.

    Returns:
        name -> ObjectProperties.
    """
    if not objects:
        return {}
    model = model or load_property_model()
    crops, counts, features = [], [], []
    for i, (_, vertices, faces) in enumerate(objects):
        others = [v for j, (_, v, _) in enumerate(objects) if j != i]
        c, n = object_crops(np.asarray(vertices, dtype=np.float64), views, others)
        crops.append(c)
        counts.append(n)
        features.append(shape_features(vertices, faces))
    results = predict_properties(np.stack(crops), np.stack(features), model, views=counts)
    return {name: r for (name, _, _), r in zip(objects, results, strict=True)}


# ---------------------------------------------------------------- informed domain randomisation


# Bounds on the transformed targets (ln density, ln frictions, logit restitution, ln time constant) of a stored
# Gaussian: a mean beyond +-30 (exp(30) ~ 1e13) is no physical density, friction or time constant, so it is refused;
# each draw is clipped to the mean +-10 (a factor 2e4 either way), so that exp() of it stays finite and the drawn
# masses stay well above MuJoCo's minimum whatever the stored spread. At the model's spreads (std <= ~1.5) that is
# beyond 6 std: the clip does not change the distribution `scene.json` states.
_MAX_ABS_TRANSFORMED_MEAN = 30.0
_MAX_TRANSFORMED_DEVIATION = 10.0
_NUM_TRANSFORMED = 6


def _checked_objects(manifest: Any, manifest_path: Path) -> dict[str, dict[str, Any]]:
    """`scene.json`'s objects, each one that carries `properties` checked for what sampling reads.

    Checks the structure (an object at the top, `objects` an object of objects), and per object with `properties`:
    `properties.transformed.mean` and `.std` (lists of 6 finite numbers, std > 0, |mean| <= 30) and `density_kg_m3`
    (finite, > 0). Objects without `properties` are returned unchecked; sampling keeps their values.

    Raises:
        GrounderError: one line naming the file, the object and the field, and what to do.
    """
    redo = "re-run `image2sim ground` to rewrite it"

    def bad(field: str, expected: str, value: Any, *, got: str | None = None) -> GrounderError:
        got = got or shown(value)
        return GrounderError(f"{manifest_path}: {field} must be {expected}, got {got}; {redo}")

    if not isinstance(manifest, dict):
        raise bad("the top level", "a JSON object", manifest, got="a list" if isinstance(manifest, list) else None)
    objects = manifest.get("objects", {})
    if not isinstance(objects, dict):
        raise bad(
            "objects",
            "a JSON object (body name -> object)",
            objects,
            got="a list" if isinstance(objects, list) else None,
        )
    for name, entry in objects.items():
        where = f"objects.{name}"
        if not isinstance(entry, dict):
            raise bad(where, "a JSON object", entry)
        if "properties" not in entry:
            continue
        props = entry["properties"]
        if not isinstance(props, dict):
            raise bad(f"{where}.properties", "a JSON object", props)
        transformed = props.get("transformed")
        if not isinstance(transformed, dict):
            raise bad(f"{where}.properties.transformed", "a JSON object with mean and std", transformed)
        for key in ("mean", "std"):
            values = transformed.get(key)
            if not finite_numbers(values, _NUM_TRANSFORMED):
                raise bad(
                    f"{where}.properties.transformed.{key}", f"a list of {_NUM_TRANSFORMED} finite numbers", values
                )
        if not all(v > 0 for v in transformed["std"]):
            raise bad(f"{where}.properties.transformed.std", "positive", transformed["std"])
        if not all(abs(v) <= _MAX_ABS_TRANSFORMED_MEAN for v in transformed["mean"]):
            raise bad(
                f"{where}.properties.transformed.mean",
                f"within +-{_MAX_ABS_TRANSFORMED_MEAN:g} (logs of physical values)",
                transformed["mean"],
            )
        density: Any = entry.get("density_kg_m3")
        if not (finite_number(density) and density > 0):
            raise bad(f"{where}.density_kg_m3", "a finite number > 0 (kg/m^3)", density)
    return objects


def _sample_physical(entry: dict[str, Any], rng: np.random.Generator) -> dict[str, Any]:
    """Draws one set of properties from an object's stored Gaussian over the transformed targets (checked by
    `_checked_objects`)."""
    transformed = entry["transformed"]
    mean_t = np.asarray(transformed["mean"], dtype=np.float64)
    std_t = np.asarray(transformed["std"], dtype=np.float64)
    draw = mean_t + std_t * rng.standard_normal(len(mean_t))
    draw = np.clip(draw, mean_t - _MAX_TRANSFORMED_DEVIATION, mean_t + _MAX_TRANSFORMED_DEVIATION)
    e = float(1.0 / (1.0 + math.exp(-draw[4])))
    return {
        "density_kg_m3": float(math.exp(draw[0])),
        "friction": [float(math.exp(draw[i])) for i in (1, 2, 3)],
        "restitution": e,
        "solref": list(contact_solref(e, math.exp(draw[5]))),
    }


def sample_scene_variants(scene_dir: str | Path, n: int, seed: int = 0) -> list[mujoco.MjModel]:
    """N variants of a grounded scene with object properties drawn from their predicted distributions.

    Each object's density (mass and inertia scale with it; geometry is fixed), friction and solref (on its
    collision hulls) are drawn independently from the Gaussian over the model's transformed targets stored in
    `scene.json` (`properties.transformed`), i.e. the distribution whose mean and 90% interval `scene.json` shows.
    Objects without a `properties` entry keep their values.

    Args:
        scene_dir: a `ground` output folder (scene.xml + scene.json).
        n: number of variants (>= 1).
        seed: random seed; the same seed gives the same variants.

    Returns:
        n compiled `mujoco.MjModel`s.
    """
    return [spec.compile() for spec, _ in sample_variant_specs(scene_dir, n, seed)]


def sample_variant_specs(scene_dir: str | Path, n: int, seed: int = 0) -> list[tuple[mujoco.MjSpec, dict[str, Any]]]:
    """As `sample_scene_variants`, but uncompiled specs, each with the values drawn per object (body name)."""
    import mujoco

    from grounder.sim.scene_files import scene_files

    scene_dir = Path(scene_dir)
    manifest_path, xml_path = scene_dir / "scene.json", scene_dir / "scene.xml"
    if not scene_dir.exists():
        raise GrounderError(f"{scene_dir} does not exist; pass a scene folder written by `image2sim ground`")
    if not scene_dir.is_dir():
        raise GrounderError(
            f"{scene_dir} is a file; pass the scene folder that holds it (written by `image2sim ground`)"
        )
    missing = [p.name for p in (manifest_path, xml_path) if not p.is_file()]
    if missing:
        raise GrounderError(
            f"{scene_dir} has no {' and no '.join(missing)}; pass a folder written by `image2sim ground`"
        )
    if n < 1:
        raise GrounderError(f"{n=} but expected at least 1 variant")
    scene_files(xml_path)  # nothing outside the scene folder
    manifest = read_json_file(manifest_path, "re-run `image2sim ground` to rewrite it")
    objects = _checked_objects(manifest, manifest_path)
    if not any("properties" in entry for entry in objects.values()):
        raise GrounderError(
            f"{manifest_path}: no object has predicted properties to draw from, so every variant would be the same "
            "scene; ground the scene with the property model on (`image2sim ground` without --density)"
        )
    try:  # compiled, so that a mesh or texture missing from the folder is found here, not while copying it
        mujoco.MjSpec.from_file(str(xml_path)).compile()
    except ValueError as exc:  # MuJoCo's message spans lines
        raise GrounderError(
            f"{xml_path}: MuJoCo cannot load it ({' '.join(str(exc).split())}); re-run `image2sim ground` to rewrite it"
        ) from exc
    rng = np.random.default_rng(seed)
    out: list[tuple[mujoco.MjSpec, dict[str, Any]]] = []
    for _ in range(n):
        spec = mujoco.MjSpec.from_file(str(xml_path))
        sampled: dict[str, Any] = {}
        for body_name, entry in objects.items():
            if "properties" not in entry:
                continue
            props = _sample_physical(entry["properties"], rng)
            sampled[body_name] = props
            body = spec.body(body_name)
            if body is None:
                raise GrounderError(
                    f"{manifest_path}: objects.{body_name} has no body of that name in {xml_path.name}; "
                    "re-run `image2sim ground` to write the two together"
                )
            ratio = props["density_kg_m3"] / float(entry["density_kg_m3"])
            body.mass = body.mass * ratio
            full = np.asarray(body.fullinertia, dtype=np.float64)
            if np.isfinite(full).all() and full.any():
                body.fullinertia = (full * ratio).tolist()
            else:
                body.inertia = (np.asarray(body.inertia, dtype=np.float64) * ratio).tolist()
            for geom in body.geoms:
                if geom.contype or geom.conaffinity:
                    geom.friction = props["friction"]
                    geom.solref = props["solref"]
        out.append((spec, sampled))
    return out


def write_scene_variants(
    scene_dir: str | Path, out_dir: str | Path, n: int, seed: int = 0, *, overwrite: bool = False
) -> list[Path]:
    """Writes `sample_scene_variants` as `out_dir/variant_NNN.xml`, `out_dir/variants.json` (the values drawn per
    variant and object) and one copy of the files the scene's MJCF loads (its meshes and textures), so that the
    folder is self-contained like every scene folder (`grounder.sim.scene_files.scene_files`).

    Returns:
        The written MJCF paths; each loads with `mujoco.MjModel.from_xml_path`.
    """
    from grounder.sim.scene_files import copy_scene_files
    from reconstruction import staged_output_dir

    scene_dir, out_dir = Path(scene_dir).resolve(), Path(out_dir).resolve()
    variants = sample_variant_specs(scene_dir, n, seed)
    paths = []
    record = []
    with staged_output_dir(out_dir, overwrite=overwrite, inputs=(scene_dir,), error=InputError) as stage:
        copy_scene_files(scene_dir / "scene.xml", stage)  # one copy of the meshes and textures, shared by all variants
        for i, (spec, sampled) in enumerate(variants):
            try:
                spec.compile()  # with the scene's own asset folder
            except ValueError as exc:  # MuJoCo's compiler error, over several lines
                raise GrounderError(
                    f"{scene_dir / 'scene.json'}: variant {i} drawn from its objects' properties does not compile "
                    f"({' '.join(str(exc).split())}); re-run `image2sim ground` to rewrite the scene"
                ) from exc
            name = f"variant_{i:03d}.xml"
            (stage / name).write_text(spec.to_xml())
            paths.append(out_dir / name)
            record.append({"xml": name, "objects": sampled})
        (stage / "variants.json").write_text(
            json.dumps({"scene": str(scene_dir), "seed": seed, "variants": record}, indent=1) + "\n"
        )
    return paths
