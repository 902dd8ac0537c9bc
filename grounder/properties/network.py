"""The property network, its training recipe and its evaluation (torch; imported only when needed).

Encoder: three object crops -> a small CNN per view, pooled (mean and max) over views; shape features -> an MLP;
both -> the embedding's posterior N(z_mu, diag(z_std^2)) (16 dims). Decoder (smooth: SiLU MLP, no normalisation
layers): z -> per target a Gaussian mean and log-std in standardised units, plus material logits. Training loss:
Gaussian negative log-likelihood of the targets + 0.5 x cross-entropy of the material + beta x KL(q(z) || N(0, I)),
with z drawn from the posterior (reparameterised), so the decoder's spread also covers the embedding's uncertainty.
The spreads are then calibrated on a validation set of other seeds: each target's std is scaled so that 90% of the
validation truths fall in mean +- 1.645 std (split-conformal scaling).
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from grounder.core.json_files import read_json_file
from grounder.errors import GrounderError, finite_number, integer_in
from grounder.properties.materials import MATERIAL_NAMES, TARGET_NAMES
from grounder.properties.training_data import (
    MAX_EPOCHS,
    MAX_NUM_TRAIN,
    MAX_SAMPLES,
    MIN_EVAL_SAMPLES,
    MIN_NUM_TRAIN,
    NUM_SHAPE_FEATURES,
    NUM_VIEWS,
    PropertyDataset,
    generate_dataset,
)
from image2sim_common.progress import ProgressFn, no_progress

log = logging.getLogger(__name__)

Z90 = 1.6448536269514722  # standard normal 95th percentile: mean +- Z90 std is a 90% interval
MODEL_VERSION = "image2sim.properties/1"
WEIGHTS_FILE = "property_net.pt"
META_FILE = "property_net.json"


@dataclass(frozen=True, kw_only=True)
class TrainOptions:
    """The training recipe; `image2sim properties train` runs it and writes the weights and metadata.

    Attributes:
        num_train, num_val: rendered objects for training and for calibrating the spread.
        train_seed, val_seed: data seeds (other shape pools and texture banks; the test seed differs again).
        embed_dim: size of the embedding z.
        epochs, batch_size, learning_rate, weight_decay: optimiser settings (AdamW, cosine schedule).
        kl_weight: beta of the KL term.
        torch_seed: weight initialisation and batch order.
        num_threads: torch CPU threads.
    """

    num_train: int = 14000
    num_val: int = 1000
    train_seed: int = 1
    val_seed: int = 2
    embed_dim: int = 16
    epochs: int = 30
    batch_size: int = 128
    learning_rate: float = 3e-3
    weight_decay: float = 1e-3
    kl_weight: float = 1e-3
    torch_seed: int = 0
    num_threads: int = 2

    def __post_init__(self) -> None:  # checked when built: a huge count would otherwise allocate or run for days
        def count(name: str, least: int, most: int) -> None:
            value = getattr(self, name)
            if not integer_in(value, least, most):
                raise GrounderError(f"TrainOptions.{name}={value!r} but expected an integer between {least} and {most}")

        count("num_train", MIN_NUM_TRAIN, MAX_NUM_TRAIN)
        count("num_val", MIN_EVAL_SAMPLES, MAX_SAMPLES)
        count("epochs", 1, MAX_EPOCHS)
        count("embed_dim", 1, 1024)
        count("batch_size", 1, MAX_NUM_TRAIN)
        count("num_threads", 1, 1024)
        for name in ("train_seed", "val_seed", "torch_seed"):
            count(name, 0, 2**63 - 1)  # torch.manual_seed takes at most 64 bits; numpy any integer >= 0
        for name in ("learning_rate", "weight_decay", "kl_weight"):
            value = getattr(self, name)
            positive = name == "learning_rate"
            if not (finite_number(value) and (value > 0 if positive else value >= 0)):
                rule = "> 0" if positive else ">= 0"
                raise GrounderError(f"TrainOptions.{name}={value!r} but expected a finite number {rule}")


TEST_SEED = 3
NUM_TEST = 1000


_NUM_STATS = 13


def appearance_stats(images: torch.Tensor) -> torch.Tensor:
    """(N, 3, H, W) in [0, 1] -> (N, 13) colour, gloss and texture statistics of the crop's centre.

    Mean and std of RGB, mean saturation, mean and std of value, fraction of highlights, fine detail (mean
    |gray - 3x3 box blur|), coarse variation (std of 8x8 cell means), gradient anisotropy |ln(|gx| / |gy|)|.
    Cheap hand-made cues that the small CNN would otherwise need many epochs to learn.
    """
    h, w = images.shape[2:]
    c = images[:, :, h // 4 : 3 * h // 4, w // 4 : 3 * w // 4]
    value = c.amax(dim=1)
    saturation = (value - c.amin(dim=1)) / (value + 1e-3)
    gray = c.mean(dim=1, keepdim=True)
    fine = (gray - F.avg_pool2d(gray, 3, stride=1, padding=1, count_include_pad=False)).abs().mean(dim=(1, 2, 3))
    coarse = F.avg_pool2d(gray, 8).std(dim=(1, 2, 3))
    gx = (gray[..., 1:] - gray[..., :-1]).abs().mean(dim=(1, 2, 3))
    gy = (gray[..., 1:, :] - gray[..., :-1, :]).abs().mean(dim=(1, 2, 3))
    return torch.cat(
        [
            c.mean(dim=(2, 3)),
            c.std(dim=(2, 3)),
            torch.stack(
                [
                    saturation.mean(dim=(1, 2)),
                    value.mean(dim=(1, 2)),
                    value.std(dim=(1, 2)),
                    (value > 0.92).float().mean(dim=(1, 2)),
                    fine,
                    coarse,
                    (torch.log(gx + 1e-4) - torch.log(gy + 1e-4)).abs(),
                ],
                dim=1,
            ),
        ],
        dim=1,
    )


class PropertyNet(nn.Module):
    """Crops (B, V, 3, 64, 64) in [0, 1] and standardised shape features (B, 8) -> embedding and decoded outputs."""

    def __init__(self, embed_dim: int = 16, num_targets: int = len(TARGET_NAMES)) -> None:
        super().__init__()

        def block(c_in: int, c_out: int, stride: int) -> list[nn.Module]:
            return [nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU()]

        self.cnn = nn.Sequential(
            nn.Conv2d(3, 12, 5, stride=2, padding=2, bias=False),  # 64 -> 32: fine grain seen at full resolution
            nn.BatchNorm2d(12),
            nn.ReLU(),
            nn.MaxPool2d(2),  # 16
            *block(12, 24, 1),
            nn.MaxPool2d(2),  # 8
            *block(24, 48, 1),
            nn.MaxPool2d(2),  # 4
            *block(48, 48, 1),
        )
        self.stats_norm = nn.BatchNorm1d(2 * _NUM_STATS)
        self.shape_mlp = nn.Sequential(
            nn.Linear(NUM_SHAPE_FEATURES + 2 * _NUM_STATS, 64), nn.SiLU(), nn.Linear(64, 64), nn.SiLU()
        )
        self.trunk = nn.Sequential(nn.Linear(2 * 2 * 48 + 64, 128), nn.SiLU(), nn.Dropout(0.2))
        self.z_head = nn.Linear(128, 2 * embed_dim)
        self.decoder = nn.Sequential(nn.Linear(embed_dim, 96), nn.SiLU(), nn.Linear(96, 96), nn.SiLU())
        self.mean_head = nn.Linear(96, num_targets)
        self.log_std_head = nn.Linear(96, num_targets)
        self.material_head = nn.Linear(96, len(MATERIAL_NAMES))
        self.embed_dim = embed_dim

    def encode(self, crops: torch.Tensor, shape: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Posterior mean and log-std of the embedding, each (B, embed_dim)."""
        b, v = crops.shape[:2]
        flat = crops.reshape(b * v, *crops.shape[2:])
        maps = self.cnn(flat)
        per_view = torch.cat([maps.mean(dim=(2, 3)), maps.amax(dim=(2, 3))], dim=1).reshape(b, v, -1)
        pooled = torch.cat([per_view.mean(dim=1), per_view.amax(dim=1)], dim=1)
        stats = appearance_stats(flat).reshape(b, v, -1)
        stats = self.stats_norm(torch.cat([stats.mean(dim=1), stats.std(dim=1, correction=0)], dim=1))
        h = self.trunk(torch.cat([pooled, self.shape_mlp(torch.cat([shape, stats], dim=1))], dim=1))
        z_mu, z_log_std = self.z_head(h).chunk(2, dim=1)
        return z_mu, z_log_std.clamp(-6.0, 2.0)

    def decode(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Standardised target means (B, T), log-stds (B, T) and material logits (B, M); smooth in z."""
        h = self.decoder(z)
        return self.mean_head(h), self.log_std_head(h).clamp(-5.0, 3.0), self.material_head(h)


def crops_to_tensor(crops: np.ndarray) -> torch.Tensor:
    """(B, V, H, W, 3) uint8 -> (B, V, 3, H, W) float32 in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(crops)).permute(0, 1, 4, 2, 3).float().div_(255.0)


def _augment(crops: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Exposure, white balance and contrast jitter per object; horizontal flips per view."""
    b = crops.shape[0]
    gain = 1 + 0.25 * (torch.rand(b, 1, 1, 1, 1, generator=generator) - 0.5)
    balance = 1 + 0.08 * (torch.rand(b, 1, 3, 1, 1, generator=generator) - 0.5)
    contrast = 1 + 0.3 * (torch.rand(b, 1, 1, 1, 1, generator=generator) - 0.5)
    mean = crops.mean(dim=(2, 3, 4), keepdim=True)
    out = ((crops - mean) * contrast + mean) * gain * balance
    flip = torch.rand(b, crops.shape[1], generator=generator) < 0.5
    out[flip] = out[flip].flip(-1)
    return out.clamp(0, 1)


@dataclass(frozen=True, kw_only=True)
class Normalisation:
    """Standardisation of shape features and targets, and the calibrated spread scale per target."""

    shape_mean: np.ndarray
    shape_std: np.ndarray
    target_mean: np.ndarray
    target_std: np.ndarray
    spread_scale: np.ndarray

    def to_json(self) -> dict[str, list[float]]:
        return {k: [float(x) for x in getattr(self, k)] for k in self.__dataclass_fields__}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Normalisation:
        return cls(**{k: np.asarray(data[k], dtype=np.float64) for k in cls.__dataclass_fields__})


@dataclass(frozen=True, kw_only=True)
class Predictions:
    """Model outputs in natural target units (`TARGET_NAMES` order).

    Attributes:
        z_mu, z_std: (N, D) embedding posterior.
        mean, std: (N, T) calibrated Gaussian per target.
        material_probs: (N, M) material class probabilities.
    """

    z_mu: np.ndarray
    z_std: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    material_probs: np.ndarray


def decode_arrays(net: PropertyNet, norm: Normalisation, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, D) embeddings -> target means (N, T), calibrated stds (N, T) and material probabilities (N, M)."""
    dtype = next(net.parameters()).dtype
    with torch.no_grad():
        mean_s, log_std_s, logits = net.decode(torch.as_tensor(np.asarray(z), dtype=dtype))
    mean = mean_s.double().numpy() * norm.target_std + norm.target_mean
    std = np.exp(log_std_s.double().numpy()) * norm.target_std * norm.spread_scale
    return mean, std, torch.softmax(logits.double(), dim=1).numpy()


def predict(
    net: PropertyNet, norm: Normalisation, crops: np.ndarray, shape_features: np.ndarray, batch: int = 256
) -> Predictions:
    """Model outputs for (N, V, 64, 64, 3) uint8 crops and (N, 8) shape features."""
    net.eval()
    dtype = next(net.parameters()).dtype
    z_mu_all, z_std_all = [], []
    with torch.no_grad():
        for start in range(0, len(crops), batch):
            shape = (shape_features[start : start + batch] - norm.shape_mean) / norm.shape_std
            z_mu, z_log_std = net.encode(
                crops_to_tensor(crops[start : start + batch]).to(dtype), torch.as_tensor(shape, dtype=dtype)
            )
            z_mu_all.append(z_mu.double().numpy())
            z_std_all.append(np.exp(z_log_std.double().numpy()))
    z_mu_np = np.concatenate(z_mu_all)
    mean, std, probs = decode_arrays(net, norm, z_mu_np)
    return Predictions(z_mu=z_mu_np, z_std=np.concatenate(z_std_all), mean=mean, std=std, material_probs=probs)


# ---------------------------------------------------------------- training


def train(out_dir: Path, options: TrainOptions | None = None, *, progress: ProgressFn | None = None) -> dict[str, Any]:
    """Generates the data, trains, calibrates the spread and writes `property_net.pt` + `property_net.json`.

    Returns:
        The metadata written (normalisation, recipe, validation figures, timings).
    """
    options = options or TrainOptions()
    report = progress or no_progress
    torch.set_num_threads(options.num_threads)
    torch.manual_seed(options.torch_seed)
    seconds: dict[str, float] = {}
    tick = time.perf_counter()
    train_set = generate_dataset(options.num_train, options.train_seed, progress=report)
    val_set = generate_dataset(options.num_val, options.val_seed, progress=report)
    seconds["render"] = time.perf_counter() - tick

    shape_mean = train_set.shape_features.mean(axis=0).astype(np.float64)
    shape_std = train_set.shape_features.std(axis=0).astype(np.float64) + 1e-6
    target_mean = train_set.targets.mean(axis=0).astype(np.float64)
    target_std = train_set.targets.std(axis=0).astype(np.float64) + 1e-6
    norm = Normalisation(
        shape_mean=shape_mean,
        shape_std=shape_std,
        target_mean=target_mean,
        target_std=target_std,
        spread_scale=np.ones(len(TARGET_NAMES)),
    )

    net = PropertyNet(options.embed_dim)
    crops = crops_to_tensor(train_set.crops)
    shape = torch.as_tensor((train_set.shape_features - shape_mean) / shape_std, dtype=torch.float32)
    targets = torch.as_tensor((train_set.targets - target_mean) / target_std, dtype=torch.float32)
    material = torch.as_tensor(train_set.material)
    optimiser = torch.optim.AdamW(net.parameters(), lr=options.learning_rate, weight_decay=options.weight_decay)
    steps_per_epoch = math.ceil(len(crops) / options.batch_size)
    scheduler = torch.optim.lr_scheduler.OneCycleLR(
        optimiser, max_lr=options.learning_rate, total_steps=options.epochs * steps_per_epoch, pct_start=0.15
    )
    generator = torch.Generator().manual_seed(options.torch_seed)
    tick = time.perf_counter()
    history = []
    for epoch in range(options.epochs):
        net.train()
        order = torch.randperm(len(crops), generator=generator)
        total = 0.0
        for step in range(steps_per_epoch):
            idx = order[step * options.batch_size : (step + 1) * options.batch_size]
            z_mu, z_log_std = net.encode(_augment(crops[idx], generator), shape[idx])
            z = z_mu + torch.exp(z_log_std) * torch.randn(z_mu.shape, generator=generator)
            mean, log_std, logits = net.decode(z)
            nll = (0.5 * ((targets[idx] - mean) / torch.exp(log_std)) ** 2 + log_std).sum(dim=1).mean()
            ce = F.cross_entropy(logits, material[idx])
            kl = 0.5 * (z_mu**2 + torch.exp(2 * z_log_std) - 2 * z_log_std - 1).sum(dim=1).mean()
            loss = nll + 0.5 * ce + options.kl_weight * kl
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            scheduler.step()
            total += float(loss.detach()) * len(idx)
        history.append(total / len(crops))
        report("training", epoch + 1, options.epochs)
        log.info("epoch %d: loss %.4f", epoch + 1, history[-1])
    seconds["train"] = time.perf_counter() - tick

    # Split-conformal calibration of the spread on the validation seed.
    raw = predict(net, norm, val_set.crops, val_set.shape_features)
    ratio = np.abs(val_set.targets - raw.mean) / raw.std
    spread_scale = np.quantile(ratio, 0.9, axis=0) / Z90
    norm = Normalisation(
        shape_mean=shape_mean,
        shape_std=shape_std,
        target_mean=target_mean,
        target_std=target_std,
        spread_scale=spread_scale,
    )
    baseline = {
        "train_mean_log_density": float(train_set.targets[:, 0].mean()),
        "train_mean_sliding_friction": float(np.exp(train_set.targets[:, 1]).mean()),
    }
    val_metrics = metrics(predict(net, norm, val_set.crops, val_set.shape_features), val_set, baseline)
    meta = {
        "model_version": MODEL_VERSION,
        "embed_dim": options.embed_dim,
        "num_views": NUM_VIEWS,
        "target_names": list(TARGET_NAMES),
        "material_names": list(MATERIAL_NAMES),
        "normalisation": norm.to_json(),
        "baseline": baseline,
        "recipe": {
            "command": "image2sim properties train",
            "options": {k: getattr(options, k) for k in options.__dataclass_fields__},
            "test_seed": TEST_SEED,
            "torch": torch.__version__,
        },
        "loss_history": [round(x, 4) for x in history],
        "validation": val_metrics,
        "seconds": {k: round(v, 1) for k, v in seconds.items()},
    }
    save(net, meta, out_dir)
    return meta


def save(net: PropertyNet, meta: dict[str, Any], out_dir: Path) -> None:
    """Writes the weights (float32 state dict) and the metadata JSON: both written in full to temporary files
    first, then each moved into place, so a failure while writing (a full disk, Ctrl-C) leaves the old pair
    untouched and no temporary file behind."""
    out_dir.mkdir(parents=True, exist_ok=True)
    weights_tmp = out_dir / f".{WEIGHTS_FILE}.tmp"
    meta_tmp = out_dir / f".{META_FILE}.tmp"
    try:
        torch.save({k: v.detach().clone() for k, v in net.state_dict().items()}, weights_tmp)
        meta_tmp.write_text(json.dumps(meta, indent=1) + "\n")
        weights_tmp.replace(out_dir / WEIGHTS_FILE)
        meta_tmp.replace(out_dir / META_FILE)
    finally:
        weights_tmp.unlink(missing_ok=True)
        meta_tmp.unlink(missing_ok=True)


def _regenerate(weights_dir: Path) -> str:
    """What to do about a broken weights folder: the `train` command that rewrites it."""
    from grounder.properties.model_files import WEIGHTS_DIR

    command = "image2sim properties train"
    command += "" if Path(weights_dir).resolve() == WEIGHTS_DIR else f" -o {weights_dir} --overwrite"
    return f"regenerate with `{command}`"


def _checked_meta(meta: Any, meta_path: Path, remedy: str) -> dict[str, Any]:
    """`property_net.json` checked for every field that loading and prediction read (before any of it sizes
    memory): version, embedding size, target and material names, normalisation (finite; stds and spread scales
    positive) and baseline (finite)."""
    from grounder.errors import finite_number
    from grounder.properties.model_files import PropertyModelError, finite_numbers

    def bad(field: str, expected: str, value: Any) -> PropertyModelError:
        got = "a JSON object" if isinstance(value, dict) else json.dumps(value)
        got = got if len(got) <= 60 else got[:57] + "..."
        return PropertyModelError(f"{meta_path}: {field} must be {expected}, got {got}; {remedy}")

    if not isinstance(meta, dict):
        raise bad("the top level", "a JSON object", "a list" if isinstance(meta, list) else meta)
    if not isinstance(meta.get("model_version"), str):
        raise bad("model_version", "a string", meta.get("model_version"))
    embed_dim = meta.get("embed_dim")
    if isinstance(embed_dim, bool) or not isinstance(embed_dim, int) or embed_dim < 1:
        raise bad("embed_dim", "a positive integer", embed_dim)
    for key, names in (("target_names", TARGET_NAMES), ("material_names", MATERIAL_NAMES)):
        if meta.get(key) != list(names):
            raise bad(key, f"this version's {list(names)}", meta.get(key))
    norm = meta.get("normalisation")
    if not isinstance(norm, dict):
        raise bad("normalisation", "a JSON object", norm)
    for key in Normalisation.__dataclass_fields__:
        length = NUM_SHAPE_FEATURES if key.startswith("shape_") else len(TARGET_NAMES)
        if not finite_numbers(norm.get(key), length):
            raise bad(f"normalisation.{key}", f"a list of {length} finite numbers", norm.get(key))
        if key.endswith("_std") or key == "spread_scale":
            if not all(v > 0 for v in norm[key]):
                raise bad(f"normalisation.{key}", "positive", norm[key])
    baseline = meta.get("baseline")
    if not isinstance(baseline, dict):
        raise bad("baseline", "a JSON object", baseline)
    for key in ("train_mean_log_density", "train_mean_sliding_friction"):
        if not finite_number(baseline.get(key)):
            raise bad(f"baseline.{key}", "a finite number", baseline.get(key))
    return meta


def load(weights_dir: Path) -> tuple[PropertyNet, Normalisation, dict[str, Any]]:
    """The network (eval mode), its normalisation and metadata from a weights folder.

    Both files are untrusted: the metadata is checked field by field, the weights are read with
    `weights_only=True`, and the metadata's embedding size is checked against the tensors' shapes before the
    network is built from it (a wrong size in the JSON alone would otherwise allocate whatever it says).

    Raises:
        GrounderError: one line naming the file and the field or tensor, and the `train` command that rewrites them.
    """
    from grounder.core.torch_files import load_weights_file, tensor_problem
    from grounder.properties.model_files import PropertyModelError

    weights_dir = Path(weights_dir)
    meta_path, weights_path = weights_dir / META_FILE, weights_dir / WEIGHTS_FILE
    remedy = _regenerate(weights_dir)
    meta = read_json_file(meta_path, remedy, PropertyModelError)
    meta = _checked_meta(meta, meta_path, remedy)
    state = load_weights_file(weights_path, remedy)
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise PropertyModelError(f"{weights_path}: not a state dict of tensors; {remedy}")
    for key, tensor in state.items():  # before any tensor is read: a sparse or meta one fails wherever it is used
        problem = tensor_problem(tensor)
        if problem is not None:
            raise PropertyModelError(f"{weights_path}: tensor {key} {problem}; {remedy}")
    embed_dim = meta["embed_dim"]
    z_head = state.get("z_head.weight")
    if z_head is None or z_head.ndim != 2:
        raise PropertyModelError(f"{weights_path}: no 2-D tensor z_head.weight; {remedy}")
    if z_head.shape[0] != 2 * embed_dim:
        raise PropertyModelError(
            f"{meta_path}: embed_dim {embed_dim} does not match {WEIGHTS_FILE} (z_head.weight has "
            f"{z_head.shape[0]} rows, i.e. embed_dim {z_head.shape[0] // 2}); {remedy}"
        )
    net = PropertyNet(embed_dim)  # sized as the tensors in the file are: no more memory than the file itself
    own = net.state_dict()
    expected = {k: tuple(v.shape) for k, v in own.items()}
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    if missing or unexpected:
        raise PropertyModelError(
            f"{weights_path}: tensors {', '.join(missing[:3]) or '-'} missing, {', '.join(unexpected[:3]) or '-'} "
            f"unexpected for a property network; {remedy}"
        )
    for key, shape in expected.items():
        tensor = state[key]
        if tuple(tensor.shape) != shape:
            raise PropertyModelError(
                f"{weights_path}: tensor {key} has shape {tuple(tensor.shape)}, expected {shape}; {remedy}"
            )
        if tensor.is_floating_point() != own[key].is_floating_point():  # integer weights, or a float step count
            raise PropertyModelError(
                f"{weights_path}: tensor {key} has dtype {tensor.dtype}, expected {own[key].dtype}; {remedy}"
            )
        if not bool(torch.isfinite(tensor).all()):
            raise PropertyModelError(f"{weights_path}: tensor {key} has non-finite values; {remedy}")
    net.load_state_dict(state)
    # Inference in float64: `decode_embedding` is differentiated numerically by calibration code.
    net.double().eval()
    return net, Normalisation.from_json(meta["normalisation"]), meta


# ---------------------------------------------------------------- evaluation


def metrics(pred: Predictions, data: PropertyDataset, baseline: dict[str, float]) -> dict[str, Any]:
    """Model vs train-mean baseline on a dataset; 90% interval coverage per target and overall.

    Args:
        pred: model outputs for `data`.
        data: samples with true targets.
        baseline: training means, `train_mean_log_density` and `train_mean_sliding_friction`.
    """
    y = data.targets.astype(np.float64)
    inside = np.abs(y - pred.mean) <= Z90 * pred.std
    friction_true = np.exp(y[:, 1])
    baseline_friction = baseline["train_mean_sliding_friction"]
    return {
        "num_samples": len(y),
        "seed": data.seed,
        "density_mae_log": float(np.abs(pred.mean[:, 0] - y[:, 0]).mean()),
        "baseline_density_mae_log": float(np.abs(baseline["train_mean_log_density"] - y[:, 0]).mean()),
        "friction_mae": float(np.abs(np.exp(pred.mean[:, 1]) - friction_true).mean()),
        "baseline_friction_mae": float(np.abs(baseline_friction - friction_true).mean()),
        "coverage90": float(inside[:, :2].mean()),
        "coverage90_per_target": {n: float(c) for n, c in zip(TARGET_NAMES, inside.mean(axis=0), strict=True)},
        "material_accuracy": float((pred.material_probs.argmax(axis=1) == data.material).mean()),
    }


def evaluate(
    weights_dir: Path, *, num_samples: int = NUM_TEST, seed: int = TEST_SEED, progress: ProgressFn | None = None
) -> dict[str, Any]:
    """Figures on held-out objects (another seed: other shapes, textures, lights and cameras).

    Raises:
        GrounderError: `num_samples` outside `MIN_EVAL_SAMPLES`..`MAX_SAMPLES`, or a broken weights folder.
    """
    if not integer_in(num_samples, MIN_EVAL_SAMPLES, MAX_SAMPLES):
        raise GrounderError(
            f"num_samples={num_samples!r} but expected an integer between {MIN_EVAL_SAMPLES} and {MAX_SAMPLES}"
        )
    net, norm, meta = load(weights_dir)
    data = generate_dataset(num_samples, seed, progress=progress)
    return metrics(predict(net, norm, data.crops, data.shape_features), data, meta["baseline"])
