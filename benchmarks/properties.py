"""Figures of the learned property model (issue 5).

    .venv/bin/python benchmarks/properties.py            # held-out figures (1000 objects, seed 3) + the sample
    .venv/bin/python benchmarks/properties.py --train    # first retrain from scratch into a temporary folder

Prints the held-out errors against the train-mean baseline, the 90% coverage, and what the shipped model says about
the grounded tabletop sample next to its truth (a sanity check, not an acceptance target).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "osmesa")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--train", action="store_true", help="retrain into a temporary folder first")
    parser.add_argument("--num-test", type=int, default=1000)
    parser.add_argument("--skip-sample", action="store_true", help="do not ground the tabletop sample")
    args = parser.parse_args()

    from grounder.properties.model_files import WEIGHTS_DIR
    from grounder.properties.network import evaluate, train

    weights = WEIGHTS_DIR
    if args.train:
        weights = Path(tempfile.mkdtemp(prefix="image2sim-properties-"))
        tick = time.perf_counter()
        meta = train(weights)
        print(f"train: {time.perf_counter() - tick:.0f} s ({meta['seconds']}) -> {weights}")
    tick = time.perf_counter()
    figures = evaluate(weights, num_samples=args.num_test)
    print(json.dumps(figures, indent=1))
    print(
        f"held-out: ln density MAE {figures['density_mae_log']:.3f} = "
        f"{figures['density_mae_log'] / figures['baseline_density_mae_log']:.0%} of baseline; friction MAE "
        f"{figures['friction_mae']:.3f} = {figures['friction_mae'] / figures['baseline_friction_mae']:.0%} of "
        f"baseline; coverage90 {figures['coverage90']:.3f} ({time.perf_counter() - tick:.0f} s)"
    )
    if args.skip_sample:
        return

    from grounder import GroundOptions, ground
    from grounder.grounding.evaluate import compare_to_truth
    from reconstruction import ReconstructOptions

    sample = REPO / "samples" / "tabletop"
    truth = {o["name"]: o for o in json.loads((sample / "truth" / "objects.json").read_text())["objects"]}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "scene"
        result = ground(sample / "video.mp4", out, GroundOptions(reconstruct=ReconstructOptions(aruco_size_m=0.12)))
        print(f"ground: properties stage {result.stage_seconds.get('properties', float('nan')):.1f} s")
        manifest = json.loads((out / "scene.json").read_text())
        for error in compare_to_truth(out, sample / "truth"):
            props = manifest["objects"][error.name]["properties"]
            mean, spread = props["mean"], props["spread"]
            true = truth[error.true_name]
            top = sorted(props["material_probs"].items(), key=lambda kv: -kv[1])[:2]
            lo, hi = spread["density_kg_m3"]
            f_lo, f_hi = spread["friction"][0]
            print(
                f"{error.true_name:5s} density {mean['density_kg_m3']:6.0f} [{lo:.0f}, {hi:.0f}] (true "
                f"{true['density_kg_m3']:.0f}) sliding {mean['friction'][0]:.2f} [{f_lo:.2f}, {f_hi:.2f}]"
                f" (true {true['friction'][0]:.2f}) material {top} (true {true['material']})"
            )


if __name__ == "__main__":
    main()
