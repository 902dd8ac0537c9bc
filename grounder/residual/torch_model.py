"""The residual as a torch module (training, ONNX export). Imported lazily: torch is a heavy import.

Computes exactly what :class:`grounder.residual.free_body.NumpyResidual` computes; see
``grounder/residual/free_body.py``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from grounder.residual.meta import NUM_FEATURES, NUM_OUTPUTS, GateOptions, ResidualMeta

if TYPE_CHECKING:
    from grounder.residual.joint import JointSpace


def _smoothstep(x: torch.Tensor) -> torch.Tensor:
    x = torch.clamp(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


class ResidualModel(nn.Module):
    """Features (N, B, 11) -> gated, bounded correction (N, B, 12); one MLP per free body.

    Buffers hold everything the function needs besides weights (normalisation, bounds, coverage statistics), so
    the ``state_dict`` alone reproduces it.
    """

    feat_mean: torch.Tensor
    feat_std: torch.Tensor
    out_scale: torch.Tensor
    out_bound: torch.Tensor
    range_lo: torch.Tensor
    range_hi: torch.Tensor
    centres: torch.Tensor
    coverage_dist: torch.Tensor
    out_gain: torch.Tensor
    radius_m: torch.Tensor

    def __init__(
        self,
        *,
        num_bodies: int,
        hidden: int,
        layers: int,
        gate: GateOptions,
        radius_m: np.ndarray,
        num_features: int = NUM_FEATURES,
        num_outputs: int = NUM_OUTPUTS,
    ):
        super().__init__()
        self.gate_options = gate
        self.num_features = num_features
        nets = []
        for _ in range(num_bodies):
            mods: list[nn.Module] = []
            width = num_features
            for _ in range(layers):
                mods += [nn.Linear(width, hidden), nn.Tanh()]
                width = hidden
            mods.append(nn.Linear(width, num_outputs))
            nets.append(nn.Sequential(*mods))
        self.nets = nn.ModuleList(nets)
        b, k, f, o = num_bodies, gate.coverage_centres, num_features, num_outputs
        self.register_buffer("feat_mean", torch.zeros(b, f, dtype=torch.float64))
        self.register_buffer("feat_std", torch.ones(b, f, dtype=torch.float64))
        self.register_buffer("out_scale", torch.ones(b, o, dtype=torch.float64))
        self.register_buffer("out_bound", torch.ones(b, o, dtype=torch.float64))
        self.register_buffer("range_lo", torch.zeros(b, f, dtype=torch.float64))
        self.register_buffer("range_hi", torch.ones(b, f, dtype=torch.float64))
        self.register_buffer("centres", torch.zeros(b, k, f, dtype=torch.float64))
        self.register_buffer("coverage_dist", torch.ones(b, dtype=torch.float64))
        self.register_buffer("out_gain", torch.ones(b, dtype=torch.float64))
        self.register_buffer("radius_m", torch.as_tensor(np.asarray(radius_m, dtype=np.float64)))
        self.double()

    def active(self, feats: torch.Tensor) -> torch.Tensor:
        """(N, B) 0 for a body at rest in contact, 1 when moving or in flight."""
        g = self.gate_options
        speed = torch.linalg.vector_norm(feats[..., 5:8], dim=-1) + self.radius_m * torch.linalg.vector_norm(
            feats[..., 8:11], dim=-1
        )
        moving = _smoothstep((speed - g.rest_speed_m_s[0]) / (g.rest_speed_m_s[1] - g.rest_speed_m_s[0]))
        flying = _smoothstep((feats[..., 0] - g.air_clearance_m[0]) / (g.air_clearance_m[1] - g.air_clearance_m[0]))
        return 1.0 - (1.0 - moving) * (1.0 - flying)

    def gate(self, feats: torch.Tensor) -> torch.Tensor:
        g = self.gate_options
        active = self.active(feats)
        margin = g.range_margin * (self.range_hi - self.range_lo) + 1e-9
        outside = torch.clamp(torch.maximum(self.range_lo - feats, feats - self.range_hi), min=0.0) / margin
        in_range = torch.prod(1.0 - _smoothstep(outside), dim=-1)
        z = (feats - self.feat_mean) / self.feat_std
        d2 = (
            torch.sum(z * z, dim=-1, keepdim=True)
            - 2.0 * torch.einsum("nbf,bkf->nbk", z, self.centres)
            + torch.sum(self.centres**2, dim=-1)
        )
        dist = torch.sqrt(torch.clamp(torch.amin(d2, dim=-1), min=0.0))
        near = 1.0 - _smoothstep(dist / self.coverage_dist - 1.0)
        return active * in_range * near

    def raw(self, feats: torch.Tensor) -> torch.Tensor:
        z = (feats - self.feat_mean) / self.feat_std
        outs = []
        for b, net in enumerate(self.nets):
            u = net(z[:, b])
            outs.append(self.out_bound[b] * torch.tanh(u * self.out_scale[b] / self.out_bound[b]))
        return torch.stack(outs, dim=1)

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        return self.raw(feats) * (self.gate(feats) * self.out_gain).unsqueeze(-1)


class JointResidualModel(ResidualModel):
    """The joint-space residual (``grounder.residual.joint``): one MLP over all hinge and slide joints.

    Features (N, 1, F) -> gated, bounded correction (N, 1, 2 x joints); the gate's rest test is the fastest joint
    speed (columns ``speed_columns``) against ``gate.rest_speed_m_s`` read as rad/s (m/s for slide joints).
    """

    speed_columns: torch.Tensor

    def __init__(
        self, *, num_features: int, num_outputs: int, hidden: int, layers: int, gate: GateOptions, speed_columns: list
    ):
        super().__init__(
            num_bodies=1,
            hidden=hidden,
            layers=layers,
            gate=gate,
            radius_m=np.zeros(1),
            num_features=num_features,
            num_outputs=num_outputs,
        )
        self.register_buffer("speed_columns", torch.as_tensor(np.asarray(speed_columns, dtype=np.int64)))

    def active(self, feats: torch.Tensor) -> torch.Tensor:
        g = self.gate_options
        speed = torch.amax(torch.abs(feats[..., self.speed_columns]), dim=-1)
        return _smoothstep((speed - g.rest_speed_m_s[0]) / (g.rest_speed_m_s[1] - g.rest_speed_m_s[0]))


def residual_model(
    meta: ResidualMeta, *, radius_m: np.ndarray | None = None, space: JointSpace | None = None
) -> ResidualModel:
    """The untrained network that ``residual.pt``'s state_dict fills, sized by ``meta``: the joint-space model for
    ``space``, else the free-body model for bodies of these bounding radii (m)."""
    if space is not None:
        return JointResidualModel(
            num_features=len(space.feature_names),
            num_outputs=len(space.output_names),
            hidden=meta.hidden,
            layers=meta.layers,
            gate=meta.gate,
            speed_columns=space.speed_columns,
        )
    if radius_m is None:
        raise ValueError("a free-body residual needs its bodies' radii (radius_m)")
    return ResidualModel(
        num_bodies=len(radius_m), hidden=meta.hidden, layers=meta.layers, gate=meta.gate, radius_m=radius_m
    )


def export_onnx(model: ResidualModel, path: Path) -> None:
    """Writes the features -> gated correction function as ONNX (float64, dynamic batch) and checks the graph."""
    import onnx

    model.eval()
    example = torch.zeros(2, len(model.nets), model.num_features, dtype=torch.float64)
    example[..., min(4, model.num_features - 1)] = 1.0
    torch.onnx.export(
        model,
        (example,),
        str(path),
        input_names=["features"],
        output_names=["correction"],
        dynamic_axes={"features": {0: "batch"}, "correction": {0: "batch"}},
        opset_version=17,
        # The TorchScript exporter (deprecated since torch 2.9, still in 2.13). The dynamo one gives the same outputs
        # (checked 2026-11-26, max difference 0) but costs ~11 s on first use and prints torchvision warnings.
        dynamo=False,
    )
    onnx.checker.check_model(onnx.load(str(path)))


class SpreadModel(nn.Module):
    """The residual's learned spread (``grounder.residual.spread``): standardised features (N, B, F) and the
    residual's gate (N, B) -> the standard deviation of each correction output (N, B, 12), bounded by ``bound``
    (the sigmoid of one small MLP per body) and faded with the gate, times ``gain`` (chosen on held-out rollouts)."""

    bound: torch.Tensor
    gain: torch.Tensor

    def __init__(
        self, *, num_bodies: int, hidden: int, num_features: int = NUM_FEATURES, num_outputs: int = NUM_OUTPUTS
    ):
        super().__init__()
        self.nets = nn.ModuleList(
            nn.Sequential(nn.Linear(num_features, hidden), nn.Tanh(), nn.Linear(hidden, num_outputs))
            for _ in range(num_bodies)
        )
        self.register_buffer("bound", torch.ones(num_bodies, num_outputs, dtype=torch.float64))
        self.register_buffer("gain", torch.ones(num_bodies, dtype=torch.float64))
        self.double()

    def forward(self, z: torch.Tensor, gate: torch.Tensor) -> torch.Tensor:
        outs = [self.bound[b] * torch.sigmoid(net(z[:, b])) for b, net in enumerate(self.nets)]
        return torch.stack(outs, dim=1) * (gate * self.gain).unsqueeze(-1)
