"""An alternative to the impacts calibration's sampled start-error covariance, measured here and not in the tool:
each grid point's start state fitted to the frames after the contact.

The default (`grounder.interaction.impacts.fit_impacts`) rolls every grid point out from the flight's fitted start
and carries the start's uncertainty to the compared frames as the sample covariance of 64 rollouts; a tumbling
can's landings are chaotic, so that covariance, and the fit with it, moves with the last digits of the tracks
(`benchmarks/impacts_stability.py`). Here each point of a coarser grid (every `--coarse`-th friction and restitution,
every second time constant) gets its own start: the offset from the flight's start that minimises
|L^-1 [r; delta]|^2, where r is the compared frames' residual (centre of mass and orientation, as the default), delta
the start's offset, and L L^T their joint covariance: the frames' noise, the flight's start covariance and the
drifting depth and orientation error, which moves both (`Impact.drift_start`, `drift_after`). The minimum is found by
a batched Levenberg-Marquardt (forward differences of 2% of each start standard deviation, `--iters` steps, every
point of a chunk in one `mujoco.rollout` call). Ranges and "resolved" as the default: grid points within 4 x
max(1, chi-square per dof) of the best, within 20% of it and inside the grid.

Run: `.venv/bin/python benchmarks/impacts_start_fit.py --scene out/det/scene --tracks out/tracks/toss [--clip
samples/toss] [--objects object_2] [--seeds saved 3 4 5]` (seed N: the tracks moved by 0.1 um per axis as in
`benchmarks/impacts_stability.py`; about 70 s per impact on 2 cores).
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from impacts_stability import true_contacts  # noqa: E402

from grounder.calibration.parameters import collision_geoms, contact_priority, resolve_parameters  # noqa: E402
from grounder.interaction.flights import find_impacts  # noqa: E402
from grounder.interaction.impacts import (  # noqa: E402
    _CONTACT_FIELDS,
    _compared,
    _compared_size,
    _frames_cov,
    _moved,
    _resolved,
    _start_variant,
    profile_range,
    widened,
)
from grounder.interaction.options import ImpactOptions  # noqa: E402
from grounder.interaction.per_object import single_body_scene  # noqa: E402
from grounder.interaction.tracks import camera_poses_of, view_point_of  # noqa: E402
from grounder.sim.restitution import contact_solref, simulated_restitution  # noqa: E402
from grounder.sim.rollout import initial_state, prepare  # noqa: E402
from grounder.tracking.output import load_object_trajectories  # noqa: E402


def joint_chol(impact, rotation=True):
    D = _compared_size(impact, rotation)
    F = _frames_cov(impact, rotation)
    P0 = impact.start_cov
    if impact.drift_cov.size:
        A = impact.drift_after[:D]
        S = impact.drift_start
        Sig = impact.drift_cov
        J = np.block([[F + A @ Sig @ A.T, A @ Sig @ S.T], [S @ Sig @ A.T, P0 + S @ Sig @ S.T]])
    else:
        J = np.block([[F, np.zeros((D, 12))], [np.zeros((12, D)), P0]])
    J = J + 1e-18 * np.eye(len(J))
    return np.linalg.cholesky(J), D


def fit_grid(model, contact, body, impact, grid, iters=10, chunk=64, fd=0.02, nthread=2):
    """Per grid point: min over the start offset delta of |L^-1 [r(theta, s0 + delta); delta]|^2."""
    L, D = joint_chol(impact)
    std = np.sqrt(np.clip(np.diag(impact.start_cov), 1e-14, None))
    solimp = model.geom_solimp[collision_geoms(model, model.body(body).id)[0]]
    by_field = {p.name.split(".", 1)[1]: p for p in contact}
    priority = contact_priority(model)
    pool = [copy.copy(model) for _ in range(chunk)]
    for m in pool:
        for p in contact:
            m.geom_priority[list(p.contact_geoms)] = priority
    datas = [mujoco.MjData(model) for _ in range(nthread)]
    base_batch = prepare(model, [_start_variant(model, body, impact, np.zeros(12))])
    steps = base_batch.sample_steps[0]
    nstep = base_batch.nstep
    data0 = mujoco.MjData(model)

    def costs_and_w(models, deltas):
        """models: list (R,), deltas: (R, 12) -> whitened residuals (R, D + 12)."""
        trajs = [_start_variant(model, body, impact, d) for d in deltas]
        states0 = np.stack([initial_state(model, t.qpos[0], t.qvel[0], data0) for t in trajs])
        state, _ = mj_rollout.rollout(list(models), datas, states0, nstep=nstep)
        full = np.concatenate([states0[:, None, :], state], axis=1)
        qpos = full[:, steps[1:], 1 : 1 + model.nq]
        r = np.stack([_compared(model, body, impact, q, True) for q in qpos])
        z = np.concatenate([r, deltas], axis=1)
        w = np.linalg.solve(L, z.T).T
        return w

    out = np.zeros(len(grid))
    for start in range(0, len(grid), chunk):
        pts = grid[start : start + chunk]
        ms = pool[: len(pts)]
        for m, (mu, e, tc) in zip(ms, pts, strict=True):
            t, d = contact_solref(e, tc, solimp=tuple(solimp))
            by_field["friction.sliding"].set_model(m, mu)
            by_field["solref.timeconst"].set_model(m, t)
            by_field["solref.dampratio"].set_model(m, d)
        G = len(pts)
        delta = np.zeros((G, 12))
        lam = np.full(G, 1e-2)
        w = costs_and_w(ms, delta)
        cost = np.sum(w**2, 1)
        for _ in range(iters):
            # FD Jacobian at delta (12 rows per point)
            rows_m, rows_d = [], []
            for g in range(G):
                for k in range(12):
                    dd = delta[g].copy()
                    dd[k] += fd * std[k]
                    rows_m.append(ms[g])
                    rows_d.append(dd)
            wf = costs_and_w(rows_m, np.array(rows_d)).reshape(G, 12, -1)
            jac = (wf - w[:, None, :]) / (fd * std)[None, :, None]  # (G, 12, n)
            steps_d = np.zeros((G, 12))
            for g in range(G):
                Jg = jac[g].T  # (n, 12)
                H = Jg.T @ Jg
                grad = Jg.T @ w[g]
                steps_d[g] = -np.linalg.solve(H + lam[g] * np.diag(np.diag(H) + 1e-12), grad)
            trial = delta + steps_d
            wt = costs_and_w(ms, trial)
            ct = np.sum(wt**2, 1)
            better = ct < cost
            delta[better], w[better], cost[better] = trial[better], wt[better], ct[better]
            lam = np.where(better, lam / 3, lam * 4)
        out[start : start + G] = cost
    return out, D


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", type=Path, default=ROOT / "out/det/scene")
    ap.add_argument("--tracks", type=Path, default=ROOT / "out/tracks/toss")
    ap.add_argument("--clip", type=Path, default=ROOT / "samples/toss")
    ap.add_argument("--objects", nargs="*", default=None, help="grounded bodies (default: all)")
    ap.add_argument("--seeds", nargs="*", default=["saved"], help="saved, or N: copies moved by 0.1 um")
    ap.add_argument("--iters", type=int, default=10)
    ap.add_argument("--fd", type=float, default=0.02)
    ap.add_argument("--coarse", type=int, default=2)
    args = ap.parse_args()
    tj = json.loads((args.tracks / "track.json").read_text())
    view = view_point_of(camera_poses_of(tj["world_from_cam"]))
    own = load_object_trajectories(args.tracks / "track.json")
    truth_opt, truths = true_contacts(args.scene, args.clip)
    options = ImpactOptions()
    fr = options.friction_grid[:: args.coarse]
    re = options.restitution_grid[:: args.coarse]
    tcs = options.timeconst_grid[::2]
    grid = [(mu, e, tc) for tc in tcs for e in re for mu in fr]
    pts = np.array(grid)
    print(f"grid: {len(fr)} frictions x {len(re)} restitutions x {len(tcs)} time constants = {len(grid)} points")
    for body, body_runs in own.items():
        if args.objects and body not in args.objects:
            continue
        true = truths[body]
        tname, mu_true, e_true = true.name, true.friction, true.restitution
        with single_body_scene(args.scene / "scene.xml", body) as sub:
            model = mujoco.MjModel.from_xml_path(str(sub))
            contact = resolve_parameters(model, [f"{body}.{f}" for f in _CONTACT_FIELDS])
            solimp = model.geom_solimp[collision_geoms(model, model.body(body).id)[0]]
            for s in args.seeds:
                tick = time.time()
                runs = body_runs if s == "saved" else _moved(body_runs, 1e-7, int(s))
                impacts = find_impacts(model, body, runs, options, view)
                if not impacts:
                    print(f"{body} ({tname}) {s}: no impact")
                    continue
                total = np.zeros(len(grid))
                dsum = 0
                for imp in impacts:
                    cost, dim = fit_grid(model, contact, body, imp, grid, iters=args.iters, fd=args.fd)
                    total += cost
                    dsum += dim
                best = int(np.argmin(total))
                dof = max(1, dsum - 3)
                thr = options.delta_chi2 * max(1.0, total[best] / dof)
                mu_b, e_b, tc_b = grid[best]
                mspan = widened(profile_range(pts[:, 0], total, thr), fr)
                espan = widened(profile_range(pts[:, 1], total, thr), re)
                mres = _resolved(mu_b, mspan, fr, options.resolution_fraction)
                eres = _resolved(e_b, espan, re, options.resolution_fraction)
                e_fit = simulated_restitution(contact_solref(e_b, tc_b, solimp=tuple(solimp)), true.solimp, truth_opt)
                print(
                    f"{body} ({tname}) {s}: chi2 {total[best]:.0f} / {dof}; friction {mu_b:.3f} "
                    f"({100 * (mu_b / mu_true - 1):+.0f}%, range {mspan[0]:.3f}..{mspan[1]:.3f}, "
                    f"{'resolved' if mres else 'unresolved'}); restitution {e_fit:.3f} "
                    f"({100 * (e_fit / e_true - 1):+.0f}%, {'resolved' if eres else 'unresolved'}); "
                    f"{len(impacts)} impacts, {time.time() - tick:.0f} s",
                    flush=True,
                )


if __name__ == "__main__":
    main()
