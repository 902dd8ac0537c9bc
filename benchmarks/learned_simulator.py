"""A learned simulator on the real cube tosses, in place of MuJoCo's contact model (after Allen et al., CoRL 2022).

The direction ``docs/residual_cube.md`` names as the one left for issue 7: instead of correcting MuJoCo, learn the
cube's motion outright, the way a graph network simulator does. Measured on the same split and metric as
``benchmarks/residual.py`` (per toss, time-averaged centre error / cube width and rotation error, rolled out from the
first recorded state; 120 validation tosses).

Model (a small graph network over one rigid body): the nodes are the cube's 8 corners. Each corner's input is its
last ``--history`` frame-to-frame displacements (m per frame), its height above the board (clipped at 0.15 m, and
exp(-height / 5 mm) for contact), and its offset from the centre (the orientation). An encoder, two rounds of
node updates from [node, mean over nodes] (a fully connected graph of 8 nodes, blind to corner order), and a decoder
give each corner's acceleration (m per frame^2). The next corners are ``2 x_t - x_(t-1) + a``, projected onto a
rigid cube by a Kabsch fit, from which the pose is read. Training is one step ahead with the graph network
simulators' recipe: random-walk noise on the input history (``--noise-m`` at the last frame) and the target the
acceleration that reaches the recorded next frame from the noisy present, so the model learns to undo its own
drift; each batch is turned by a random yaw (the board is level and, measured by ``residual.py
--board-position``, the same everywhere). At the first recorded state the history is made by flying the recorded
pose and velocity backwards under gravity.

``--rollout-steps N`` then fine-tunes the network on its own rollouts (backpropagation through the learned
simulator, which unlike MuJoCo is differentiable everywhere): windows of ``--rollout-horizon`` frames, half of them
from a toss's first recorded state the way evaluation starts, half from a random recorded frame; the loss is the
mean corner distance along the window (as a share of the cube width), so the network is trained on the multi-step
error the metric measures rather than only one frame ahead. The rigid projection inside the rollout is the polar
factor by Newton's iteration (differentiable; Kabsch's SVD has degenerate singular values for a cube's corners).

``--scene DIR`` trains a hybrid instead: MuJoCo (that scene, restarted every frame from the pose and
backward-difference velocity of the last two frames) predicts the next corners, and the network, which also sees
that prediction, corrects it.

Run: ``.venv/bin/python benchmarks/learned_simulator.py`` (needs ../shared/data/cube_toss; about 6 min on an idle 2-core
machine, the hybrid about 11 min; ``--rollout-steps 1500`` adds about 8 min). Seeded; torch's thread count can change
the last digit.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import mujoco
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from residual import DATA, fmt, metric, split  # noqa: E402  (benchmarks/residual.py: same split and metric)

from grounder.core.importers import DAIR_PLL_CUBE_RATE_HZ, load_dair_pll_cube  # noqa: E402
from grounder.core.trajectory import Trajectory  # noqa: E402
from grounder.sim.rollout import _offsets  # noqa: E402
from grounder.sim.scene_files import load_scene_model  # noqa: E402
from image2sim_common.rotations import (  # noqa: E402
    quat_from_matrix,
    quat_to_mat,
    quat_to_rotvec,
)

CUBE_HALF_WIDTH_M = 0.0524
CORNERS_BODY_M = CUBE_HALF_WIDTH_M * np.array(
    [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64
)
FRAME_S = 1.0 / DAIR_PLL_CUBE_RATE_HZ
GRAVITY_M_S2 = np.array([0.0, 0.0, -9.81])
BATCH = 256


def corners_world_m(qpos: np.ndarray) -> np.ndarray:
    """Poses (T, 7: position, quaternion wxyz) -> corner positions (T, 8, 3) in the world frame."""
    rot = np.stack([quat_to_mat(q) for q in qpos[:, 3:]])
    return qpos[:, None, :3] + np.einsum("tij,kj->tki", rot, CORNERS_BODY_M)


def kabsch(corners: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Best rigid fit of the cube's corners to ``corners`` (B, 8, 3): centre (B, 3) and rotation (B, 3, 3)."""
    ref = torch.as_tensor(CORNERS_BODY_M, dtype=corners.dtype)
    centre = corners.mean(1)
    cov = torch.einsum("kj,bki->bji", ref, corners - centre[:, None])
    u, _, vt = torch.linalg.svd(cov)
    det = torch.sign(torch.linalg.det(vt.transpose(1, 2) @ u.transpose(1, 2)))
    fix = torch.diag_embed(torch.stack([torch.ones_like(det), torch.ones_like(det), det], -1))
    return centre, vt.transpose(1, 2) @ fix @ u.transpose(1, 2)


def rigid(corners: torch.Tensor) -> torch.Tensor:
    """``corners`` projected onto the nearest rigid placement of the cube."""
    centre, rot = kabsch(corners)
    return centre[:, None] + torch.einsum("bij,kj->bki", rot, torch.as_tensor(CORNERS_BODY_M, dtype=corners.dtype))


def polar_rigid(corners: torch.Tensor) -> torch.Tensor:
    """``corners`` (..., 8, 3) projected onto a rigid cube, differentiably: the rotation is the polar factor of
    sum_k c_k ref_k^T / (8 h^2) (the Kabsch rotation; equal to it when the corners are already rigid), by Newton's
    iteration X <- (X + X^-T) / 2, which converges in a few steps from a near-rotation."""
    ref = torch.as_tensor(CORNERS_BODY_M, dtype=corners.dtype)
    centre = corners.mean(-2)
    rot = torch.einsum("...ki,kj->...ij", corners - centre[..., None, :], ref) / (8 * CUBE_HALF_WIDTH_M**2)
    for _ in range(8):
        rot = 0.5 * (rot + torch.linalg.inv(rot).transpose(-1, -2))
    return centre[..., None, :] + torch.einsum("...ij,kj->...ki", rot, ref)


def features(history_m: torch.Tensor) -> torch.Tensor:
    """Corner histories (B, C + 1, 8, 3), oldest first -> node inputs (B, 8, 3 C + 5)."""
    steps = history_m[:, 1:] - history_m[:, :-1]
    count, frames = steps.shape[:2]
    now = history_m[:, -1]
    height = now[..., 2:3]
    return torch.cat(
        [
            steps.permute(0, 2, 1, 3).reshape(count, 8, 3 * frames),
            torch.clamp(height, max=0.15),
            now - now.mean(1, keepdim=True),
            torch.exp(-torch.clamp(height, min=0.0) / 0.005),
        ],
        -1,
    )


class CornerNet(torch.nn.Module):
    """Per-corner encoder, two rounds of [node, mean of nodes] updates, per-corner decoder; normalised in and out."""

    def __init__(self, num_inputs: int, hidden: int):
        super().__init__()

        def mlp(n_in: int, n_out: int) -> torch.nn.Sequential:
            return torch.nn.Sequential(torch.nn.Linear(n_in, hidden), torch.nn.SiLU(), torch.nn.Linear(hidden, n_out))

        self.encode = mlp(num_inputs, hidden)
        self.rounds = torch.nn.ModuleList(mlp(2 * hidden, hidden) for _ in range(2))
        self.decode = mlp(hidden, 3)
        self.register_buffer("in_mean", torch.zeros(num_inputs))
        self.register_buffer("in_std", torch.ones(num_inputs))
        self.register_buffer("out_mean", torch.zeros(3))
        self.register_buffer("out_std", torch.ones(3))

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        h = self.encode((inputs - self.in_mean) / self.in_std)
        for update in self.rounds:
            h = h + update(torch.cat([h, h.mean(1, keepdim=True).expand_as(h)], -1))
        return self.decode(h) * self.out_std + self.out_mean


class MujocoNextFrame:
    """A scene's prediction of the next frame's corners, restarted from the last two frames of a corner history:
    Kabsch pose, backward-difference velocity advanced by half a frame of gravity (angular velocity in the body
    frame, as MuJoCo's free joint takes it)."""

    def __init__(self, scene: Path):
        from mujoco import rollout as mj_rollout

        _, self.model = load_scene_model(scene)
        self.period_steps = round(FRAME_S / self.model.opt.timestep)
        data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, data)
        full = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
        self.template = np.empty(mujoco.mj_stateSize(self.model, full))
        mujoco.mj_getState(self.model, data, self.template, full)
        self.qpos_at, self.qvel_at = _offsets(self.model)
        self.datas = [mujoco.MjData(self.model) for _ in range(torch.get_num_threads())]
        self._rollout = mj_rollout.rollout

    def __call__(self, history_m: torch.Tensor) -> torch.Tensor:
        now_c, now_r = (a.numpy() for a in kabsch(history_m[:, -1].double()))
        before_c, before_r = (a.numpy() for a in kabsch(history_m[:, -2].double()))
        turn = np.einsum("bji,bjk->bik", before_r, now_r)
        states = np.tile(self.template, (len(now_c), 1))
        p, v = self.qpos_at, self.qvel_at
        states[:, p : p + 3] = now_c
        states[:, p + 3 : p + 7] = np.stack([quat_from_matrix(r) for r in now_r])
        states[:, v : v + 3] = (now_c - before_c) / FRAME_S + self.model.opt.gravity * FRAME_S / 2
        states[:, v + 3 : v + 6] = np.stack([quat_to_rotvec(quat_from_matrix(r)) for r in turn]) / FRAME_S
        out, _ = self._rollout(self.model, self.datas, states, nstep=self.period_steps)
        qpos = out[:, -1, p : p + 7]
        rot = np.stack([quat_to_mat(q) for q in qpos[:, 3:]])
        nxt = qpos[:, None, :3] + np.einsum("bij,kj->bki", rot, CORNERS_BODY_M)
        return torch.as_tensor(nxt, dtype=history_m.dtype)


class LearnedSimulator:
    """The network and, for the hybrid, the MuJoCo prediction it corrects."""

    def __init__(self, history: int, hidden: int, scene: Path | None):
        self.history = history
        self.mujoco = MujocoNextFrame(scene) if scene is not None else None
        self.net = CornerNet(3 * history + 5 + (3 if self.mujoco else 0), hidden)

    def inputs(self, history_m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Network inputs and the prediction its output is added to (constant velocity, or MuJoCo's)."""
        if self.mujoco is None:
            return features(history_m), 2 * history_m[:, -1] - history_m[:, -2]
        nxt = self.mujoco(history_m)
        return torch.cat([features(history_m), nxt - history_m[:, -1]], -1), nxt

    def next_frame(self, history_m: torch.Tensor) -> torch.Tensor:
        inputs, base = self.inputs(history_m)
        return rigid(base + self.net(inputs))


def training_windows(tosses: list[Trajectory], history: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Every recorded (history, next frame) pair: (N, C + 1, 8, 3) and (N, 8, 3) corner positions."""
    windows, nexts = [], []
    for toss in tosses:
        corners = corners_world_m(toss.qpos)
        for i in range(history, len(corners) - 1):
            windows.append(corners[i - history : i + 1])
            nexts.append(corners[i + 1])
    return torch.as_tensor(np.array(windows), dtype=torch.float32), torch.as_tensor(
        np.array(nexts), dtype=torch.float32
    )


def start_history_m(qpos0: np.ndarray, qvel0: np.ndarray, history: int) -> np.ndarray:
    """Corners at frames -history..0, the recorded first state flown backwards under gravity (body-frame rate)."""
    frames = []
    for k in range(history, -1, -1):
        back_s = k * FRAME_S
        centre = qpos0[:3] - qvel0[:3] * back_s + 0.5 * GRAVITY_M_S2 * back_s**2
        quat = qpos0[3:].copy()
        mujoco.mju_quatIntegrate(quat, qvel0[3:], -back_s)
        frames.append(centre + CORNERS_BODY_M @ quat_to_mat(quat).T)
    return np.array(frames)


def roll_out(sim: LearnedSimulator, tosses: list[Trajectory]) -> list[Trajectory]:
    """Every toss from its first recorded state, read back as poses at the recorded frames."""
    hist = torch.as_tensor(
        np.stack([start_history_m(t.qpos[0], t.qvel[0], sim.history) for t in tosses]), dtype=torch.float32
    )
    frames = [hist[:, -1]]
    with torch.no_grad():
        for _ in range(max(len(t.time_s) for t in tosses) - 1):
            nxt = sim.next_frame(hist)
            hist = torch.cat([hist[:, 1:], nxt[:, None]], 1)
            frames.append(nxt)
    corners = torch.stack(frames, 1).double()
    preds = []
    for i, toss in enumerate(tosses):
        n = len(toss.time_s)
        centre, rot = kabsch(corners[i, :n])
        qpos = np.concatenate([centre.numpy(), np.stack([quat_from_matrix(r) for r in rot.numpy()])], 1)
        preds.append(Trajectory(time_s=toss.time_s, qpos=qpos, qvel=np.zeros((n, 6)), name=toss.name))
    return preds


def train(sim: LearnedSimulator, tosses: list[Trajectory], steps: int, noise_m: float, lr: float, seed: int) -> None:
    windows, nexts = training_windows(tosses, sim.history)
    print(f"{len(windows)} training windows from {len(tosses)} tosses")
    net = sim.net
    with torch.no_grad():
        inputs, base = sim.inputs(windows[:8000])
        net.in_mean.copy_(inputs.reshape(-1, inputs.shape[-1]).mean(0))
        net.in_std.copy_(inputs.reshape(-1, inputs.shape[-1]).std(0) + 1e-6)
        accel = (nexts[:8000] - base).reshape(-1, 3)
        net.out_mean.copy_(accel.mean(0))
        net.out_std.copy_(accel.std(0) + 1e-9)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    gen = torch.Generator().manual_seed(seed)
    started = time.perf_counter()
    for step in range(steps):
        idx = torch.randint(len(windows), (BATCH,), generator=gen)
        yaw = random_yaw(BATCH, gen)
        hist = torch.einsum("bij,btkj->btki", yaw, windows[idx])
        nxt = torch.einsum("bij,bkj->bki", yaw, nexts[idx])
        walk = torch.randn(hist.shape, generator=gen) * (noise_m / np.sqrt(sim.history + 1))
        hist = hist + torch.cumsum(walk, 1)
        inputs, base = sim.inputs(hist)
        loss = (((net(inputs) - (nxt - base)) / net.out_std) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        schedule.step()
        if step % 2000 == 0 or step == steps - 1:
            print(f"  step {step:6d}  loss {loss.item():.4f}  ({time.perf_counter() - started:.0f} s)", flush=True)


def random_yaw(count: int, gen: torch.Generator) -> torch.Tensor:
    """``count`` rotations (count, 3, 3) about the vertical by uniform random angles."""
    angle = torch.rand(count, generator=gen) * 2 * np.pi
    c, s, zero, one = torch.cos(angle), torch.sin(angle), torch.zeros(count), torch.ones(count)
    return torch.stack(
        [torch.stack([c, -s, zero], -1), torch.stack([s, c, zero], -1), torch.stack([zero, zero, one], -1)], -2
    )


def train_on_rollouts(
    sim: LearnedSimulator, tosses: list[Trajectory], steps: int, horizon: int, batch: int, lr: float, seed: int
) -> None:
    """Fine-tunes the network on the error of its own ``horizon``-frame rollouts (see the module docstring); the
    learned simulator alone (``main`` refuses it with ``--scene``: MuJoCo is not differentiable)."""
    length = max(len(t.time_s) for t in tosses)
    corners = np.empty((len(tosses), length, 8, 3))
    for i, toss in enumerate(tosses):
        c = corners_world_m(toss.qpos)
        corners[i, : len(c)], corners[i, len(c) :] = c, c[-1]
    recorded = torch.as_tensor(corners, dtype=torch.float32)
    lengths = torch.as_tensor([len(t.time_s) for t in tosses])
    first = torch.as_tensor(
        np.stack([start_history_m(t.qpos[0], t.qvel[0], sim.history) for t in tosses]), dtype=torch.float32
    )
    opt = torch.optim.Adam(sim.net.parameters(), lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    gen = torch.Generator().manual_seed(seed + 1)
    ahead = torch.arange(horizon + 1)
    back = torch.arange(sim.history, -1, -1)
    started = time.perf_counter()
    for step in range(steps):
        toss = torch.randint(len(tosses), (batch,), generator=gen)
        latest = (lengths[toss] - 1 - horizon).clamp(min=sim.history + 1)
        start = sim.history + (torch.rand(batch, generator=gen) * (latest - sim.history).float()).long()
        from_first = torch.rand(batch, generator=gen) < 0.5
        start = torch.where(from_first, torch.zeros_like(start), start)
        truth = recorded[toss[:, None], (start[:, None] + ahead).clamp(max=length - 1)]
        hist = recorded[toss[:, None], (start[:, None] - back).clamp(min=0)]
        hist = torch.where(from_first[:, None, None, None], first[toss], hist)
        valid = ((start[:, None] + ahead) < lengths[toss][:, None]).float()[:, 1:]
        yaw = random_yaw(batch, gen)
        hist = torch.einsum("bij,btkj->btki", yaw, hist)
        truth = torch.einsum("bij,btkj->btki", yaw, truth)
        total = torch.zeros(())
        for t in range(horizon):
            inputs, base = sim.inputs(hist)
            nxt = polar_rigid(base + sim.net(inputs))
            hist = torch.cat([hist[:, 1:], nxt[:, None]], 1)
            distance_m = torch.sqrt(((nxt - truth[:, t + 1]) ** 2).sum(-1) + 1e-12).mean(-1)
            total = total + (distance_m * valid[:, t]).sum()
        loss = total / valid.sum().clamp(min=1.0) / (2 * CUBE_HALF_WIDTH_M)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(sim.net.parameters(), 1.0)
        opt.step()
        schedule.step()
        if step % 250 == 0 or step == steps - 1:
            print(
                f"  rollout step {step:5d}  mean corner error {100 * loss.item():.2f}% of the width "
                f"({time.perf_counter() - started:.0f} s)",
                flush=True,
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--history", type=int, default=3, help="frames of displacement each corner sees")
    parser.add_argument("--steps", type=int, default=20000, help="training steps (batches of 256)")
    parser.add_argument("--noise-m", type=float, default=5e-5, help="random-walk input noise at the last frame, m")
    parser.add_argument("--hidden", type=int, default=128)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--scene", type=Path, default=None, help="hybrid: correct this MuJoCo scene's prediction")
    parser.add_argument("--rollout-steps", type=int, default=0, help="then fine-tune on own rollouts (batches)")
    parser.add_argument("--rollout-horizon", type=int, default=32, help="frames per fine-tuning rollout")
    parser.add_argument("--rollout-batch", type=int, default=128, help="rollouts per fine-tuning batch")
    parser.add_argument("--rollout-lr", type=float, default=2e-4)
    args = parser.parse_args()
    if args.rollout_steps and args.scene is not None:
        parser.error("--rollout-steps fine-tunes the learned simulator alone; MuJoCo (--scene) is not differentiable")
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    train_tosses, val_tosses = split(load_dair_pll_cube(DATA))
    sim = LearnedSimulator(args.history, args.hidden, args.scene)
    started = time.perf_counter()
    train(sim, train_tosses, args.steps, args.noise_m, args.lr, args.seed)
    label = f"hybrid on {args.scene}" if args.scene else "learned simulator"
    print(f"trained in {time.perf_counter() - started:.0f} s")

    def evaluate(label: str) -> None:
        for name, tosses in (("train[:120]", train_tosses[:120]), ("validation", val_tosses)):
            pos, rot = metric(roll_out(sim, tosses), tosses)
            print(f"{name:12s} {label:40s} {fmt(pos, rot)}", flush=True)

    evaluate(label)
    if args.rollout_steps:
        started = time.perf_counter()
        train_on_rollouts(
            sim, train_tosses, args.rollout_steps, args.rollout_horizon, args.rollout_batch, args.rollout_lr, args.seed
        )
        print(f"fine-tuned on rollouts in {time.perf_counter() - started:.0f} s")
        evaluate(f"{label}, fine-tuned on rollouts")
    print("target (validation): <= 10% of cube width and <= 10 deg; calibrated MuJoCo 13.4% / 17.2 deg")


if __name__ == "__main__":
    main()
