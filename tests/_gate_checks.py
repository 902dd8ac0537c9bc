"""What the residual tests (free-body and joint-space) compute the coverage gate's expected values with, directly
rather than through the residual's own code."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def nearest_centre_dist(residual: Any, feats: np.ndarray) -> np.ndarray:
    """(N, F) raw features -> (N,) standardised distance to the residual's nearest coverage centre."""
    from scipy.spatial.distance import cdist

    z = (feats - residual.feat_mean[0]) / residual.feat_std[0]
    return np.asarray(np.min(cdist(z, residual.centres[0]), axis=1))


def onnx_gate(
    onnx_path: Path, state: dict[str, np.ndarray], feats: np.ndarray, raw: np.ndarray, swapped: tuple[str, ...]
) -> np.ndarray:
    """The gate of the exported ONNX graph, run with onnx's reference evaluator, with the initialisers named in
    `swapped` replaced by `state`'s: the correction for `feats` divided by the ungated output `raw` (N, outputs)."""
    import onnx
    from onnx import numpy_helper
    from onnx.reference import ReferenceEvaluator

    graph = onnx.load(str(onnx_path))
    for init in graph.graph.initializer:
        if init.name in swapped:
            init.CopyFrom(numpy_helper.from_array(state[init.name], init.name))
    (corr,) = ReferenceEvaluator(graph).run(None, {"features": feats})
    return np.asarray(np.sum(corr[:, 0] * raw, axis=1) / np.sum(raw * raw, axis=1))
