"""The learned residual: MuJoCo plus a bounded, gated correction trained on recorded motion, and its simulator.

- `meta`: ``residual.json``'s metadata and file names, the gate thresholds and the gate parts both kinds share.
- `free_body`: the residual of free bodies (body-frame features, corrections, targets, energy cap; numpy).
- `joint`: the residual of hinge and slide joints (joint-space features, corrections, targets; numpy).
- `files`: a residual scene folder's files: hashes, the pair check, and loading with every field checked.
- `kernel`: the compiled (numba) single-state path of both residuals.
- `torch_model`: the same function in torch, for training and the ONNX export (imported only when needed).
- `options`: what training takes and returns (`ResidualOptions`, `ResidualTrainResult`).
- `train`: `train_residual`: one-step targets, aggregation rounds, the output gain chosen on held-out rollouts.
- `spread`: the learned spread of the correction (negative log-likelihood, gain chosen by held-out energy score).
- `report`: rollout errors and the HTML report of a training.
- `simulator`: `Simulator`, MuJoCo plus the residual for one simulation or a batch.

The names load on first use: `train_residual` pulls in torch.
"""

from typing import TYPE_CHECKING

from image2sim_common.lazy import lazy_attributes

_LAZY = {
    "Simulator": "grounder.residual.simulator",
    "has_residual": "grounder.residual.simulator",
    "ResidualOptions": "grounder.residual.options",
    "ResidualTrainResult": "grounder.residual.options",
    "train_residual": "grounder.residual.train",
    "rollout_score": "grounder.residual.train",
    "GateOptions": "grounder.residual.meta",
    "ResidualMeta": "grounder.residual.meta",
    "RESIDUAL_FILES": "grounder.residual.meta",
    "check_residual_pair": "grounder.residual.files",
    "load_residual": "grounder.residual.files",
    "NumpyResidual": "grounder.residual.free_body",
    "NumpyJointResidual": "grounder.residual.joint",
}
__getattr__ = lazy_attributes(__name__, _LAZY)

if TYPE_CHECKING:
    from grounder.residual.files import check_residual_pair, load_residual
    from grounder.residual.free_body import NumpyResidual
    from grounder.residual.joint import NumpyJointResidual
    from grounder.residual.meta import RESIDUAL_FILES, GateOptions, ResidualMeta
    from grounder.residual.options import ResidualOptions, ResidualTrainResult
    from grounder.residual.simulator import Simulator, has_residual
    from grounder.residual.train import rollout_score, train_residual

__all__ = [
    "RESIDUAL_FILES",
    "GateOptions",
    "NumpyJointResidual",
    "NumpyResidual",
    "ResidualMeta",
    "ResidualOptions",
    "ResidualTrainResult",
    "Simulator",
    "check_residual_pair",
    "has_residual",
    "load_residual",
    "rollout_score",
    "train_residual",
]
