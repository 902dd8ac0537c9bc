"""What a residual is, independent of the kind of bodies it corrects: ``residual.json``'s metadata and the gate.

Holds the file names and format of a residual scene folder, the free-body residual's feature and output names,
:class:`ResidualMeta` (the metadata in ``residual.json``, read back with every field checked) with its
:class:`GateOptions`, and the parts of the gate and network that the free-body residual
(``grounder.residual.free_body``) and the joint-space one (``grounder.residual.joint``) share: ``smoothstep``,
the coverage check (:func:`coverage_gate`) and the packing of ranges and networks for the compiled single-state
path (:func:`fade_ranges`, :func:`network_layers`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from grounder.errors import GrounderError, shown

RESIDUAL_FORMAT = "image2sim-residual"
RESIDUAL_VERSION = 1
WEIGHTS_FILE = "residual.pt"
META_FILE = "residual.json"
ONNX_FILE = "residual.onnx"
RESIDUAL_FILES = (WEIGHTS_FILE, META_FILE, ONNX_FILE)  # what makes a scene folder a residual scene

FEATURE_NAMES = (
    "clearance_m",
    "height_m",
    "up_body_x",
    "up_body_y",
    "up_body_z",
    "vel_body_x_m_s",
    "vel_body_y_m_s",
    "vel_body_z_m_s",
    "omega_body_x_rad_s",
    "omega_body_y_rad_s",
    "omega_body_z_rad_s",
)
OUTPUT_NAMES = (
    "dpos_body_x_m",
    "dpos_body_y_m",
    "dpos_body_z_m",
    "drot_body_x_rad",
    "drot_body_y_rad",
    "drot_body_z_rad",
    "dvel_body_x_m_s",
    "dvel_body_y_m_s",
    "dvel_body_z_m_s",
    "domega_body_x_rad_s",
    "domega_body_y_rad_s",
    "domega_body_z_rad_s",
)
NUM_FEATURES = len(FEATURE_NAMES)
NUM_OUTPUTS = len(OUTPUT_NAMES)


# --- gate and metadata ---------------------------------------------------------------------------------------


def smoothstep(x: np.ndarray) -> np.ndarray:
    """0 for x <= 0, 1 for x >= 1, C1 in between (3x^2 - 2x^3)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


@dataclass(frozen=True, kw_only=True)
class GateOptions:
    """Where the correction is switched on; see ``grounder.residual.free_body``'s module docstring.

    Attributes:
        rest_speed_m_s: (off, on) speed of the fastest point, ``|v| + radius |omega|``: below ``off`` a body in
            contact gets exactly zero correction.
        air_clearance_m: (off, on) clearance of the lowest point above z = 0: above ``on`` a body is in flight and
            is corrected whatever its speed (at the top of a toss).
        range_margin: Fraction of each feature's training range over which the correction fades out beyond it.
        coverage_centres: k-means centres summarising the training states for the distance check.
        coverage_quantile: Quantile of the training states' distances to their nearest centre where fading starts;
            the correction reaches 0 at twice that distance.
        energy_restore_fraction: The corrected state's energy may exceed MuJoCo's by at most this fraction of
            what MuJoCo dissipated over the period, and never the energy at its start (see ``cap_energy``).
    """

    rest_speed_m_s: tuple[float, float] = (0.01, 0.05)
    air_clearance_m: tuple[float, float] = (0.005, 0.02)
    range_margin: float = 0.1
    coverage_centres: int = 256
    coverage_quantile: float = 0.99
    energy_restore_fraction: float = 0.5


@dataclass(frozen=True, kw_only=True)
class ResidualMeta:
    """The metadata in ``residual.json``.

    Attributes:
        period_steps: Model steps between corrections (one data sample interval).
        timestep_s: The model timestep the residual was trained with.
        bodies: Names of the corrected free bodies, in joint order.
        hidden: Width of the MLP's hidden layers.
        layers: Number of hidden layers.
        gate: The gate thresholds.
        scene_xml_sha256: Hash of the scene.xml the residual was trained on.
        scene_files_sha256: Hash of each file that scene.xml includes or loads (meshes, textures, ...), by its path
            relative to the scene's folder (:func:`scene_files_sha256`); None for a residual written before this
            field, whose included files are then not checked.
        training: Free-form training summary (data, seeds, errors), for provenance.
        space: ``free`` (body-frame corrections of free bodies, ``grounder.residual.free_body``) or ``joint``
            (hinge and slide joints, ``grounder.residual.joint``; ``bodies`` then names the joints).
        feature_names, output_names: The network's inputs and outputs (fixed for ``free``, per scene for ``joint``).
        spread_hidden: Width of the learned spread's hidden layer (``grounder.residual.spread``); 0: no spread (a
            deterministic residual, and every residual written before the spread existed).
    """

    period_steps: int
    timestep_s: float
    bodies: tuple[str, ...]
    hidden: int
    layers: int
    gate: GateOptions
    scene_xml_sha256: str
    training: dict[str, Any]
    space: str = "free"
    scene_files_sha256: dict[str, str] | None = None
    feature_names: tuple[str, ...] = FEATURE_NAMES
    output_names: tuple[str, ...] = OUTPUT_NAMES
    spread_hidden: int = 0

    @property
    def period_s(self) -> float:
        return self.period_steps * self.timestep_s

    def to_json(self) -> dict[str, Any]:
        return {
            "format": RESIDUAL_FORMAT,
            "version": RESIDUAL_VERSION,
            "kind": (
                "body-frame state correction at the data rate, bounded and gated"
                if self.space == "free"
                else "joint-space state correction at the data rate, bounded and gated"
            ),
            "space": self.space,
            "period_steps": self.period_steps,
            "timestep_s": self.timestep_s,
            "period_s": self.period_s,
            "bodies": list(self.bodies),
            "features": list(self.feature_names),
            "outputs": list(self.output_names),
            "hidden": self.hidden,
            "layers": self.layers,
            "gate": {
                "rest_speed_m_s": list(self.gate.rest_speed_m_s),
                "air_clearance_m": list(self.gate.air_clearance_m),
                "range_margin": self.gate.range_margin,
                "coverage_centres": self.gate.coverage_centres,
                "coverage_quantile": self.gate.coverage_quantile,
                "energy_restore_fraction": self.gate.energy_restore_fraction,
            },
            "scene_xml_sha256": self.scene_xml_sha256,
            **({} if self.scene_files_sha256 is None else {"scene_files_sha256": dict(self.scene_files_sha256)}),
            "files": {"weights": WEIGHTS_FILE, "onnx": ONNX_FILE},
            **({"spread": {"hidden": self.spread_hidden}} if self.spread_hidden else {}),
            "training": self.training,
        }

    @staticmethod
    def from_json(raw: Any, where: Path) -> ResidualMeta:
        """The metadata from ``residual.json``'s parsed content, an untrusted file: every field's type and range is
        checked here, so that the residual and :class:`grounder.Simulator` can use them as they are.

        Raises:
            GrounderError: one line naming the field, its value and what it must be.
        """
        if not isinstance(raw, dict):
            raise GrounderError(f"{where}: expected a JSON object, got a JSON {_json_type(raw)}; {RETRAIN}")
        if raw.get("format") != RESIDUAL_FORMAT or raw.get("version") != RESIDUAL_VERSION:
            raise GrounderError(
                f"{where}: not an {RESIDUAL_FORMAT} v{RESIDUAL_VERSION} file (format={shown(raw.get('format'))}, "
                f"version={shown(raw.get('version'))}); {RETRAIN}"
            )
        space = raw.get("space", "free")
        if space not in ("free", "joint"):
            raise GrounderError(f"{where}: unknown residual space {shown(space)}; {RETRAIN}")
        field = _MetaFields(raw, where)
        features, outputs = field.names("features"), field.names("outputs")
        if space == "free" and (features != FEATURE_NAMES or outputs != OUTPUT_NAMES):
            raise GrounderError(f"{where}: features or outputs differ from this version's; {RETRAIN}")
        gate = _MetaFields(field.value("gate", dict, "an object"), where, "gate.")
        training = raw.get("training", {})
        if not isinstance(training, dict):
            raise GrounderError(f"{where}: training is a JSON {_json_type(training)}, expected an object; {RETRAIN}")
        sha256 = field.value("scene_xml_sha256", str, "the scene.xml's sha256 (64 hex digits)")
        if re.fullmatch(r"[0-9a-f]{64}", sha256) is None:
            raise field.bad("scene_xml_sha256", sha256, "the scene.xml's sha256 (64 lowercase hex digits)")
        files_sha256 = None
        if "scene_files_sha256" in raw:  # absent in residuals written before it
            expected = "an object of file path -> sha256 (64 lowercase hex digits)"
            files_sha256 = field.value("scene_files_sha256", dict, expected)
            if len(files_sha256) > MAX_SCENE_FILES or not all(
                isinstance(v, str) and re.fullmatch(r"[0-9a-f]{64}", v) is not None for v in files_sha256.values()
            ):
                raise field.bad("scene_files_sha256", files_sha256, expected)
        return ResidualMeta(
            period_steps=field.integer("period_steps", 1, MAX_PERIOD_STEPS),
            timestep_s=field.number("timestep_s", lambda x: x > 0.0, "a number > 0"),
            bodies=field.names("bodies", nonempty=True),
            hidden=field.integer("hidden", 1),
            layers=field.integer("layers", 1),
            gate=GateOptions(
                rest_speed_m_s=gate.pair("rest_speed_m_s", lowest=0.0),
                air_clearance_m=gate.pair("air_clearance_m"),
                range_margin=gate.number("range_margin", lambda x: x >= 0.0, "a number >= 0"),
                coverage_centres=gate.integer("coverage_centres", 1),
                coverage_quantile=gate.number("coverage_quantile", lambda x: 0.0 < x <= 1.0, "a number in (0, 1]"),
                energy_restore_fraction=gate.number(
                    "energy_restore_fraction", lambda x: 0.0 <= x <= 1.0, "a number in [0, 1]"
                ),
            ),
            scene_xml_sha256=sha256,
            training=dict(training),
            space=space,
            feature_names=features,
            output_names=outputs,
            scene_files_sha256=None if files_sha256 is None else dict(files_sha256),
            spread_hidden=_spread_hidden(raw, where, space),
        )


def _spread_hidden(raw: dict[str, Any], where: Path, space: str) -> int:
    """``spread.hidden`` of ``residual.json``: absent (0) or an integer in [1, 4096], free-body residuals only."""
    if "spread" not in raw:
        return 0
    spread = _MetaFields(_MetaFields(raw, where).value("spread", dict, "an object"), where, "spread.")
    hidden = spread.integer("hidden", 1, 4096)
    if space != "free":
        raise GrounderError(f"{where}: a learned spread is for free-body residuals only; {RETRAIN}")
    return hidden


RETRAIN = "retrain with `image2sim residual train`"
"""What every complaint about a broken residual file ends with."""

MAX_SCENE_FILES = 100_000
"""Most entries ``scene_files_sha256`` may hold (a scene's meshes, textures and includes)."""

MAX_PERIOD_STEPS = 100_000
"""Most model steps one period may span: far beyond any data rate (1 Hz at a 10 us timestep), while a rollout's
buffers, which grow with the period whatever the data, stay small."""


def _json_type(value: Any) -> str:
    names = {dict: "object", list: "array", str: "string", bool: "boolean", int: "number", float: "number"}
    return "null" if value is None else names.get(type(value), type(value).__name__)


class _MetaFields:
    """Typed reads of one JSON object of ``residual.json``; each failure is one GrounderError line naming the field."""

    def __init__(self, raw: dict[str, Any], where: Path, prefix: str = ""):
        self.raw, self.where, self.prefix = raw, where, prefix

    def bad(self, key: str, value: Any, expected: str) -> GrounderError:
        return GrounderError(f"{self.where}: {self.prefix}{key} is {shown(value)}, expected {expected}; {RETRAIN}")

    def value(self, key: str, kind: type | tuple[type, ...], expected: str) -> Any:
        if key not in self.raw:
            raise GrounderError(f"{self.where}: {self.prefix}{key} is missing, expected {expected}; {RETRAIN}")
        value = self.raw[key]
        if not isinstance(value, kind) or isinstance(value, bool) is not (kind is bool):
            raise self.bad(key, value, expected)
        return value

    def integer(self, key: str, lowest: int, highest: int | None = None) -> int:
        expected = f"an integer >= {lowest}" if highest is None else f"an integer in [{lowest}, {highest}]"
        value = self.value(key, int, expected)  # not a float: 8.7 steps must not become 8
        if value < lowest or (highest is not None and value > highest):
            raise self.bad(key, value, expected)
        return int(value)

    def number(self, key: str, ok: Callable[[float], bool], expected: str) -> float:
        return self._finite(key, self.value(key, (int, float), expected), ok, expected)

    def _finite(self, key: str, value: int | float, ok: Callable[[float], bool], expected: str) -> float:
        try:
            number = float(value)
        except OverflowError:  # an integer beyond float range
            number = math.inf
        if not math.isfinite(number) or not ok(number):
            raise self.bad(key, value, expected)
        return number

    def pair(self, key: str, lowest: float = -math.inf) -> tuple[float, float]:
        """(off, on) thresholds: finite, off >= lowest, on > off (the gate divides by on - off)."""
        expected = "[off, on], finite numbers with on > off"
        expected += "" if lowest == -math.inf else f" and off >= {lowest:g}"
        value = self.value(key, list, expected)
        if len(value) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            raise self.bad(key, value, expected)
        try:
            off = self._finite(key, value[0], lambda x: x >= lowest, expected)
            on = self._finite(key, value[1], lambda x: x > off, expected)
        except GrounderError:
            raise self.bad(key, value, expected) from None  # the pair, not one number of it
        return off, on

    def names(self, key: str, *, nonempty: bool = False) -> tuple[str, ...]:
        expected = "a non-empty list of names" if nonempty else "a list of names"
        value = self.value(key, list, expected)
        if not all(isinstance(v, str) for v in value) or (nonempty and not value):
            raise self.bad(key, value, expected)
        return tuple(value)


class CoverageStats(Protocol):
    """What :func:`coverage_gate` reads: the training statistics a numpy residual holds (see ``NumpyResidual``)."""

    range_lo: np.ndarray  # (B, F)
    range_hi: np.ndarray
    feat_mean: np.ndarray
    feat_std: np.ndarray
    centres: np.ndarray  # (B, K, F), standardised
    coverage_dist: np.ndarray  # (B,)
    meta: ResidualMeta


def coverage_gate(stats: CoverageStats, feats: np.ndarray) -> np.ndarray:
    """(N, B, F) -> (N, B): inside the training ranges (fading over ``range_margin`` of each range) times near the
    training states (distance to the nearest k-means centre, fading from ``coverage_dist`` to twice that)."""
    margin = stats.meta.gate.range_margin * (stats.range_hi - stats.range_lo) + 1e-9
    outside = np.maximum(np.maximum(stats.range_lo - feats, feats - stats.range_hi), 0.0) / margin
    in_range = np.prod(1.0 - smoothstep(outside), axis=-1)
    z = (feats - stats.feat_mean) / stats.feat_std
    # squared distances to every centre: |z|^2 - 2 z.c + |c|^2
    centre_sq = np.sum(stats.centres**2, axis=-1)
    d2 = np.sum(z * z, axis=-1)[..., None] - 2.0 * np.einsum("nbf,bkf->nbk", z, stats.centres) + centre_sq
    dist = np.sqrt(np.maximum(np.min(d2, axis=-1), 0.0))
    return in_range * (1.0 - smoothstep(dist / stats.coverage_dist - 1.0))


def fade_ranges(range_lo: np.ndarray, range_hi: np.ndarray, range_margin: float) -> np.ndarray:
    """(..., 3, F): each feature's training range, low and high, and 1 / the margin the gate fades over beyond it
    (:func:`coverage_gate`'s), as the compiled single-state path takes them."""
    inv_margin = 1.0 / (range_margin * (range_hi - range_lo) + 1e-9)
    return np.ascontiguousarray(np.stack([range_lo, range_hi, inv_margin], axis=-2), dtype=np.float64)


def network_layers(
    layers: list[tuple[np.ndarray, np.ndarray]],
    feat_mean: np.ndarray,
    feat_std: np.ndarray,
    out_scale: np.ndarray,
    out_bound: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One network as the compiled single-state path takes it (``grounder.residual.kernel._gated_network``):
    ``(first (F + 1, H + F), mids (L, H + 1, H), last (H + 2, O))`` from its layers ``(weight (in, out), bias
    (out,))``, the feature standardisation (F,) and the output's scale and bound (O,).

    Every layer takes ``[x, 1]`` (its bias is its last row; the output layer's is times scale / bound, and the
    bound follows as one more row). The first one works on the raw features: it gives the first layer's
    pre-activations and the standardised features z (both linear in the raw features, as z = (f - mean) / std),
    from which the coverage check measures distances.
    """
    inv_std = 1.0 / feat_std
    standardise = np.vstack([np.diag(inv_std), -feat_mean * inv_std])  # (F + 1, F)
    w1, b1 = layers[0]
    first_layer = standardise @ w1
    first_layer[-1] += b1
    first = np.hstack([first_layer, standardise])
    hidden = w1.shape[1]
    mids = np.array([np.vstack([w, bias]) for w, bias in layers[1:-1]], dtype=np.float64).reshape(
        -1, hidden + 1, hidden
    )
    w_out, b_out = layers[-1]
    last = np.vstack([np.vstack([w_out, b_out]) * (out_scale / out_bound), out_bound])
    return np.ascontiguousarray(first), np.ascontiguousarray(mids), np.ascontiguousarray(last, dtype=np.float64)
