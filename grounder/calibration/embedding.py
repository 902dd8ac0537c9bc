"""Embedding-mode calibration: fit each object's property embedding instead of raw parameters.

A grounded scene's ``scene.json`` stores per object ``properties.embedding`` and ``properties.embedding_std``: the
property model's prior ``z ~ N(embedding, diag(embedding_std^2))``, and
``grounder.properties.prior.decode_embedding(z)`` maps z to density, friction (sliding, torsional, rolling) and solref
(timeconst, dampratio). Calibration searches the standardised offset ``w = (z - embedding) / embedding_std`` in ``[-3,
3]^D`` per object and minimises the negative log posterior

    J(w) = sum_b loss_b(w) / s^2 + |w|^2,

with ``loss_b`` the per-trajectory loss of raw mode and ``s^2`` a noise scale: the mean training loss left at the
data-only optimum (what no embedding explains). So: (1) differential evolution, then least squares, on the data
alone, from the prior mean; (2) `mujoco.minimize.least_squares` on the residuals ``[sqrt(loss_b) / s, w]`` from
there, for the posterior's mode; its covariance from the Gauss-Newton Hessian. The decoded properties are applied
as raw parameters (``BODY.mass`` scaled with the density, ``BODY.friction.*``, ``BODY.solref.*``), and their
intervals are percentiles of the decoded posterior samples.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from grounder.calibration.parameters import Parameter, resolve_parameter
from grounder.core.json_files import read_json_file
from grounder.errors import GrounderError, shown

Decoder = Callable[[np.ndarray], Mapping[str, Any]]
W_BOUND = 3.0
# What a scene.json may hold for an object's prior. The shipped property model's encoder gives |embedding| ~ 1 and
# std < 1. Its decoder, along each axis of z (measured): at |z| = 60 sliding friction 0.19-0.88, density 6-24000
# kg/m^3; at 1000 friction up to 5e4 and density 1e28; overflow by 1e4. The search reaches embedding +- W_BOUND std,
# so with both bounded it stays within |z| <= 60.
MAX_ABS_EMBEDDING = 30.0
MAX_EMBEDDING_STD = 10.0
DENSITY_RANGE_KG_M3 = (0.1, 1e5)  # a scene.json density outside it is a corrupt file, not a material
_FIELDS = ("mass", "friction.sliding", "friction.torsional", "friction.rolling", "solref.timeconst", "solref.dampratio")


def embedding_decoder() -> Decoder:
    """``z -> {"density_kg_m3", "friction", "solref", ...}`` from the property model (``grounder.properties.prior``).

    Raises:
        GrounderError: the property model is not available.
    """
    import importlib
    import importlib.util

    if importlib.util.find_spec("grounder.properties.prior") is None:
        raise GrounderError(
            "embedding mode needs the property model (grounder.properties.prior), which is not installed"
        )
    module = importlib.import_module("grounder.properties.prior")
    decoder: Decoder = module.decode_embedding
    return decoder


def scene_manifest(scene: Path) -> dict[str, Any]:
    """The scene's ``scene.json`` (next to ``scene.xml``)."""
    manifest = manifest_path(scene)
    if not manifest.is_file():
        raise GrounderError(f"{scene}: scene has no property embedding (no scene.json next to it); use --mode raw")
    redo = "re-run `image2sim ground` for this scene, or use --mode raw"
    data = read_json_file(manifest, redo)
    if not isinstance(data, dict):
        raise GrounderError(f"{manifest}: expected a JSON object; {redo}")
    return data


def manifest_path(scene: Path) -> Path:
    """Where the scene's ``scene.json`` is: in a scene folder, or next to a lone MJCF."""
    scene = Path(scene)
    return scene / "scene.json" if scene.is_dir() else scene.parent / "scene.json"


@dataclass(frozen=True, kw_only=True)
class ObjectPrior:
    """One object's embedding prior and what its raw parameters are now."""

    body: str
    embedding: np.ndarray  # (D,)
    embedding_std: np.ndarray  # (D,)
    density0_kg_m3: float  # the density the scene's mass was computed with
    mass0_kg: float


@dataclass(frozen=True, kw_only=True, eq=False)
class EmbeddingSpace:
    """The search space of embedding mode and its map to raw parameters."""

    objects: tuple[ObjectPrior, ...]
    params: tuple[Parameter, ...]  # per object, the _FIELDS in order
    decoder: Decoder

    @property
    def dim(self) -> int:
        return sum(len(o.embedding) for o in self.objects)

    def split(self, w: np.ndarray) -> list[np.ndarray]:
        out, start = [], 0
        for o in self.objects:
            out.append(w[start : start + len(o.embedding)])
            start += len(o.embedding)
        return out

    def z_of(self, w: np.ndarray) -> list[np.ndarray]:
        return [o.embedding + o.embedding_std * wi for o, wi in zip(self.objects, self.split(w), strict=True)]

    def decoded(self, w: np.ndarray) -> list[Mapping[str, Any]]:
        return [self.decoder(z) for z in self.z_of(w)]

    def values(self, w_rows: np.ndarray) -> np.ndarray:
        """(K, dim) standardised offsets -> (K, P) raw parameter values."""
        rows = []
        for w in np.atleast_2d(w_rows):
            row: list[float] = []
            for o, d in zip(self.objects, self.decoded(w), strict=True):
                friction = [float(x) for x in d["friction"]]
                solref = [float(x) for x in d["solref"]]
                mass = o.mass0_kg * float(d["density_kg_m3"]) / o.density0_kg_m3
                row += [mass, *friction, *solref]
            rows.append(row)
        return np.asarray(rows, dtype=np.float64)


def embedding_space(scene: Path, model: mujoco.MjModel, decoder: Decoder | None = None) -> EmbeddingSpace:
    """Reads the priors from ``scene.json`` and resolves the raw parameters they decode to.

    Raises:
        GrounderError: no scene.json, no object with ``properties.embedding``, malformed embeddings, or a body
            named in scene.json that the MJCF lacks.
    """
    manifest = scene_manifest(scene)
    redo = "re-run `image2sim ground` for this scene, or use --mode raw"
    objects = manifest.get("objects", {})
    if isinstance(objects, dict):
        items = list(objects.items())
    elif isinstance(objects, list) and all(isinstance(o, dict) for o in objects):
        items = [(o.get("name", ""), o) for o in objects]
    else:
        raise GrounderError(f"scene.json: 'objects' is not a mapping of body names to entries; {redo}")
    priors: list[ObjectPrior] = []
    for body, entry in items:
        props = entry.get("properties") if isinstance(entry, dict) else None
        if not isinstance(props, dict) or "embedding" not in props:
            continue
        if not isinstance(body, str):
            raise GrounderError(f"scene.json: object name {body!r} is not text; {redo}")
        try:
            emb = np.asarray(props["embedding"], dtype=np.float64)
            std = np.asarray(props.get("embedding_std", np.ones_like(emb)), dtype=np.float64)
            density0 = entry.get("density_kg_m3")
            density0_kg_m3 = float(density0) if density0 else math.nan
        except (TypeError, ValueError, OverflowError) as exc:
            raise GrounderError(
                f"scene.json: object {body!r} has a non-numeric embedding or density ({exc}); {redo}"
            ) from exc
        where = f"{manifest_path(scene)}: object {shown(body)}"
        if emb.ndim != 1 or emb.shape != std.shape:
            raise GrounderError(
                f"{where} has a malformed embedding / embedding_std (shapes {emb.shape} and {std.shape}, expected "
                f"two lists of the same length); {redo}"
            )
        if not (np.isfinite(emb).all() and (np.abs(emb) <= MAX_ABS_EMBEDDING).all()):
            raise GrounderError(
                f"{where}: properties.embedding must be finite numbers within +-{MAX_ABS_EMBEDDING:g}, "
                f"got {shown(props['embedding'])}; {redo}"
            )
        if not (np.isfinite(std).all() and (std > 0).all() and (std <= MAX_EMBEDDING_STD).all()):
            raise GrounderError(
                f"{where}: properties.embedding_std must be finite numbers in (0, {MAX_EMBEDDING_STD:g}], "
                f"got {shown(props.get('embedding_std'))}; {redo}"
            )
        lo, hi = DENSITY_RANGE_KG_M3
        if math.isfinite(density0_kg_m3) and density0_kg_m3 > 0 and not lo <= density0_kg_m3 <= hi:
            # the scene's mass is rescaled by the decoded density over this one: 1e-300 gave a mass of 5e302 kg
            raise GrounderError(
                f"{where}: density_kg_m3 {density0_kg_m3:g} is outside {lo:g}-{hi:g} kg/m^3 (aerogel to osmium); {redo}"
            )
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
        if bid <= 0:
            raise GrounderError(f"scene.json names object {body!r} but the MJCF has no such body")
        priors.append(
            ObjectPrior(
                body=body,
                embedding=emb,
                embedding_std=std,
                density0_kg_m3=density0_kg_m3,
                mass0_kg=float(model.body_mass[bid]),
            )
        )
    if not priors:
        raise GrounderError(f"{scene}: scene has no property embedding (no object has properties.embedding)")
    decoder = decoder or embedding_decoder()
    # Without the density the mass was computed with, the prior mean's density stands for the scene's mass.
    fixed = []
    for p in priors:
        try:
            decoded_density = float(decoder(p.embedding)["density_kg_m3"])
        except (GrounderError, ValueError, RuntimeError) as exc:  # e.g. an embedding of another model's size
            raise GrounderError(
                f"scene.json: object {p.body!r}: its embedding does not fit this property model "
                f"({' '.join(str(exc).split())}); {redo}"
            ) from exc
        if not math.isfinite(p.density0_kg_m3) or p.density0_kg_m3 <= 0:
            p = ObjectPrior(**{**p.__dict__, "density0_kg_m3": decoded_density})
        fixed.append(p)
    params = tuple(resolve_parameter(model, f"{p.body}.{f}") for p in fixed for f in _FIELDS)
    return EmbeddingSpace(objects=tuple(fixed), params=params, decoder=decoder)


def to_unit(w: np.ndarray) -> np.ndarray:
    return (np.asarray(w) + W_BOUND) / (2 * W_BOUND)


def from_unit(u: np.ndarray) -> np.ndarray:
    return np.clip(np.asarray(u), 0.0, 1.0) * 2 * W_BOUND - W_BOUND


def posterior_samples(space: EmbeddingSpace, w: np.ndarray, cov: np.ndarray, count: int, seed: int) -> np.ndarray:
    """Raw parameter values (count, P) decoded from samples of the posterior N(w, cov)."""
    rng = np.random.default_rng(seed)
    cov = 0.5 * (cov + cov.T)
    lam, vec = np.linalg.eigh(cov)
    draws = w + (rng.standard_normal((count, len(w))) * np.sqrt(np.maximum(lam, 0.0))) @ vec.T
    return space.values(np.clip(draws, -W_BOUND, W_BOUND))


def summaries(space: EmbeddingSpace, w: np.ndarray, w_std: np.ndarray) -> dict[str, Any]:
    """Per object: prior and posterior embedding (with std) and the decoded posterior mean, for calibration.json."""
    out: dict[str, Any] = {}
    for o, wi, si, d in zip(space.objects, space.split(w), space.split(w_std), space.decoded(w), strict=True):
        out[o.body] = {
            "prior_embedding": o.embedding.tolist(),
            "prior_embedding_std": o.embedding_std.tolist(),
            "posterior_embedding": (o.embedding + o.embedding_std * wi).tolist(),
            "posterior_embedding_std": (o.embedding_std * si).tolist(),
            "decoded": {k: d[k] for k in ("density_kg_m3", "friction", "solref") if k in d},
        }
    return out
