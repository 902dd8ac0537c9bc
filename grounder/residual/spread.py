"""The residual's learned spread: a state-dependent standard deviation of each correction output.

The mean residual (``grounder.residual.free_body``) corrects MuJoCo by what the recorded transitions say on average.
What they scatter by around it (a cube landing on an edge bounces one way or another) is the spread: per free body
and output (body-frame position, rotation, velocity, angular velocity), ``sd(x) = gain x gate(x) x bound x
sigmoid(MLP(x))``, with x the residual's standardised features. It is

- **bounded**: at most ``bound``, the 99th percentile of the leftover |target - mean| on the training transitions;
- **fading to zero outside the training data like the mean**: it is multiplied by the residual's own gate (zero at
  rest in contact, zero beyond the features' training range and far from the training states);
- **trained by negative log-likelihood** on the recorded transitions' leftovers, ``r / sqrt(sd^2 + floor^2)``, where
  the floor (a tenth of the leftover's RMS per output) stands for what the gate cannot express and is never sampled;
- **scaled by a gain chosen on held-out rollouts**, as the mean's: sampled rollouts of the held-out trajectories at
  each candidate gain (0 among them: zero spread stays a possible answer), scored by the energy score
  (`grounder.sim.sample_scores`); the lowest wins.

A sampled step adds ``sd x N(0, 1)`` to the mean correction before it is applied (`NumpyResidual.correct` with a
random generator). The ONNX export holds the mean only.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

SPREAD_PREFIX = "spread."
FLOOR_FRACTION = 0.1
BOUND_QUANTILE = 0.99


class NumpySpread:
    """`grounder.residual.torch_model.SpreadModel` in numpy, from ``residual.pt``'s ``spread.*`` arrays."""

    def __init__(self, state: dict[str, np.ndarray], num_bodies: int):
        self.bound = state[SPREAD_PREFIX + "bound"]  # (B, 12)
        self.gain = np.array(state[SPREAD_PREFIX + "gain"], dtype=np.float64)  # (B,), set in place to change it
        self.layers = []
        for b in range(num_bodies):
            pre = f"{SPREAD_PREFIX}nets.{b}."
            self.layers.append(
                (
                    np.ascontiguousarray(state[pre + "0.weight"].T),
                    state[pre + "0.bias"],
                    np.ascontiguousarray(state[pre + "2.weight"].T),
                    state[pre + "2.bias"],
                )
            )

    def std(self, z: np.ndarray, gate: np.ndarray) -> np.ndarray:
        """Standardised features (N, B, F) and gate (N, B) -> sd (N, B, 12)."""
        out = np.empty((*z.shape[:2], self.bound.shape[1]))
        for b, (w1, b1, w2, b2) in enumerate(self.layers):
            u = np.tanh(z[:, b] @ w1 + b1) @ w2 + b2
            out[:, b] = self.bound[b] / (1.0 + np.exp(-u))
        return out * (gate * self.gain)[..., None]


def fit_spread(
    residual_model: Any,
    feats: np.ndarray,
    targets: np.ndarray,
    mean_gain: float,
    *,
    hidden: int,
    steps: int,
    seed: int,
    batch_size: int = 1024,
    learning_rate: float = 3e-3,
) -> Any:
    """Trains the spread (module docstring) on transitions ``feats`` (N, B, F), ``targets`` (N, B, 12) around the
    trained mean ``residual_model`` at its chosen ``mean_gain``; returns the torch `SpreadModel` (gain 1)."""
    import torch

    from grounder.residual.torch_model import SpreadModel

    f = torch.as_tensor(feats)
    t = torch.as_tensor(targets)
    with torch.no_grad():
        gate = residual_model.gate(f)
        mean = residual_model.raw(f) * (gate * mean_gain).unsqueeze(-1)
        z = (f - residual_model.feat_mean) / residual_model.feat_std
    leftover = t - mean
    keep = gate.amax(dim=1) > 0
    z, gate, leftover = z[keep], gate[keep], leftover[keep]
    model = SpreadModel(num_bodies=feats.shape[1], hidden=hidden, num_outputs=targets.shape[2])
    if len(z) == 0:
        model.gain.zero_()
        return model
    active = gate > 0
    with torch.no_grad():
        used = leftover[active]  # (n, 12) over active (sample, body) pairs
        rms = torch.sqrt(torch.mean(used**2, dim=0)) + 1e-12
        bound = torch.quantile(used.abs(), BOUND_QUANTILE, dim=0) + 1e-12
        model.bound.copy_(bound.expand_as(model.bound))
    floor2 = (FLOOR_FRACTION * rms) ** 2
    generator = torch.Generator().manual_seed(seed)
    optim = torch.optim.Adam(model.nets.parameters(), lr=learning_rate)
    count = len(z)
    model.train()
    for _ in range(steps):
        batch = torch.randint(count, (min(batch_size, count),), generator=generator)
        sd = model(z[batch], gate[batch])
        var = sd**2 + floor2
        weight = active[batch].unsqueeze(-1).to(var.dtype)
        nll = 0.5 * (leftover[batch] ** 2 / var + torch.log(var)) * weight
        loss = nll.sum() / weight.sum().clamp(min=1.0)
        optim.zero_grad()
        loss.backward()
        optim.step()
    model.eval()
    return model


def spread_state(model: Any) -> dict[str, Any]:
    """The torch spread's tensors under their ``residual.pt`` names."""
    return {SPREAD_PREFIX + k: v.detach().clone() for k, v in model.state_dict().items()}


def select_spread_gain(
    sim: Any,
    residual: Any,
    trajs: Sequence[Any],
    gains: Sequence[float],
    *,
    samples: int,
    seed: int,
    noise: Any,
    models: Sequence[Any] | None = None,
) -> tuple[float, dict[float, float]]:
    """The spread gain whose sampled rollouts of the held-out ``trajs`` have the lowest energy score (ties to the
    smaller gain; 0 is a candidate): each trajectory ``samples`` times from its recorded start perturbed by
    ``noise`` (a `grounder.sim.start_noise.StartNoise`), with ``models`` (one per sample; parameters drawn from a
    fitted distribution) when given. Returns the gain and every gain's score; leaves ``residual`` at that gain."""
    from grounder.sim.start_noise import perturbed_starts

    if not trajs or residual.spread is None:
        return 0.0, {}
    scores: dict[float, float] = {}
    for gain in sorted(set(gains)):
        rng = np.random.default_rng(seed)  # the same starts and draws for every gain
        starts = [perturbed_starts(sim.model, t.qpos[0], t.qvel[0], noise, samples, rng) for t in trajs]
        residual.spread.gain[:] = gain
        sim._set_residual(residual)
        scores[gain] = energy_of_samples(sim.model, trajs, sim.sample(trajs, starts, rng, models=models))
    sim._set_residual(None)
    best = min(scores, key=lambda g: (scores[g], g))
    residual.spread.gain[:] = best
    return best, scores


def energy_of_samples(model: Any, trajs: Sequence[Any], samples: Sequence[tuple[np.ndarray, np.ndarray]]) -> float:
    """Mean energy score (`grounder.sim.sample_scores`) of sampled rollouts of ``trajs``."""
    from grounder.sim.sample_scores import score_samples

    return float(np.mean([score_samples(model, t, q, v).energy for t, (q, v) in zip(trajs, samples, strict=True)]))
