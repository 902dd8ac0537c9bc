"""`image2sim properties ...`: train, evaluate and sample the learned physical-property model."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer

from reconstruction.errors import InputError

MAX_VARIANTS = 10_000  # each variant is a compiled scene held in memory while the folder is written


def register(app: typer.Typer) -> None:
    """Adds the `properties` command group to the `image2sim` app."""
    from grounder.cli.common import fail, require, setup_logging, stage_progress, user_errors_exit_2

    group = typer.Typer(
        name="properties",
        help="The learned prior over density, friction and contact of grounded objects.",
        no_args_is_help=True,
    )

    @group.command("train")
    def train(
        out: Annotated[
            Path | None,
            typer.Option("-o", "--out", help="Weights folder (default: the one shipped with the package)."),
        ] = None,
        num_train: Annotated[int | None, typer.Option(help="Rendered training objects (default 14000).")] = None,
        epochs: Annotated[int | None, typer.Option(help="Training epochs (default 30).")] = None,
        overwrite: Annotated[
            bool, typer.Option(help="Replace the weights in a non-empty -o folder (without -o they are replaced).")
        ] = False,
        verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log each epoch.")] = False,
    ) -> None:
        """Render synthetic objects with MuJoCo, train, calibrate the spread, write the weights (~11 min, 2 cores)."""
        setup_logging(verbose)
        from grounder.properties.training_data import MAX_EPOCHS, MAX_NUM_TRAIN, MIN_NUM_TRAIN

        require(
            (
                "--num-train",
                num_train,
                num_train is None or MIN_NUM_TRAIN <= num_train <= MAX_NUM_TRAIN,
                f"between {MIN_NUM_TRAIN} and {MAX_NUM_TRAIN} (training holds ~184 KB per object)",
            ),
            (
                "--epochs",
                epochs,
                epochs is None or 1 <= epochs <= MAX_EPOCHS,
                f"between 1 and {MAX_EPOCHS} (an epoch of the default 14000 objects takes ~15 s)",
            ),
        )
        with user_errors_exit_2():
            from grounder.properties.model_files import WEIGHTS_DIR
            from grounder.properties.network import TrainOptions
            from grounder.properties.network import train as run_train
            from reconstruction import check_output_dir

            defaults = TrainOptions()
            options = replace(
                defaults,
                num_train=defaults.num_train if num_train is None else num_train,
                epochs=defaults.epochs if epochs is None else epochs,
            )  # checked (TrainOptions) before the output folder is touched
            if out is not None:  # without -o: regenerate the shipped weights in place, the command's purpose
                check_output_dir(out, overwrite=overwrite, error=InputError)
            target = out or WEIGHTS_DIR
            with stage_progress() as progress:
                meta = run_train(target, options, progress=progress)
        val = meta["validation"]
        typer.echo(
            f"validation: ln density MAE {val['density_mae_log']:.3f} "
            f"(baseline {val['baseline_density_mae_log']:.3f}),"
            f" friction MAE {val['friction_mae']:.3f} (baseline {val['baseline_friction_mae']:.3f}); wrote {target}"
        )

    @group.command("evaluate")
    def evaluate(
        weights: Annotated[
            Path | None, typer.Option(help="Weights folder (default: the one shipped with the package).")
        ] = None,
        num_samples: Annotated[int, typer.Option(help="Held-out objects to render.")] = 1000,
        seed: Annotated[int, typer.Option(help="Held-out data seed (training used 1, calibration 2).")] = 3,
        as_json: Annotated[bool, typer.Option("--json", help="Print the figures as JSON.")] = False,
        verbose: Annotated[bool, typer.Option("--verbose", "-v")] = False,
    ) -> None:
        """Errors and 90%-interval coverage on held-out shapes and appearances, against a train-mean baseline."""
        setup_logging(verbose)
        from grounder.properties.training_data import MAX_SAMPLES, MIN_EVAL_SAMPLES

        require(
            (
                "--num-samples",
                num_samples,
                MIN_EVAL_SAMPLES <= num_samples <= MAX_SAMPLES,
                f"between {MIN_EVAL_SAMPLES} and {MAX_SAMPLES} (each object's crops take 37 KB)",
            ),
            ("--seed", seed, seed >= 0, ">= 0"),
        )
        if seed in (1, 2):
            fail(f"--seed {seed} is a training/calibration seed; pick another for held-out data")
        with user_errors_exit_2():
            from grounder.properties.model_files import WEIGHTS_DIR
            from grounder.properties.network import evaluate as run_evaluate
            from grounder.properties.prior import load_property_model

            load_property_model(weights or WEIGHTS_DIR)  # a clear error before rendering
            with stage_progress() as progress:
                figures = run_evaluate(weights or WEIGHTS_DIR, num_samples=num_samples, seed=seed, progress=progress)
        if as_json:
            typer.echo(json.dumps(figures, indent=1))
            return
        typer.echo(
            f"held-out objects: {figures['num_samples']} (seed {seed})\n"
            f"ln density MAE {figures['density_mae_log']:.3f}   baseline {figures['baseline_density_mae_log']:.3f}\n"
            f"friction MAE   {figures['friction_mae']:.3f}   baseline {figures['baseline_friction_mae']:.3f}\n"
            f"90% coverage   {figures['coverage90']:.3f}\n"
            f"material acc.  {figures['material_accuracy']:.3f}"
        )

    @group.command("sample")
    def sample(
        scene: Annotated[Path, typer.Argument(help="A scene folder written by `image2sim ground`.")],
        out: Annotated[Path, typer.Option("-o", "--out", help="Output folder for variant_NNN.xml + variants.json.")],
        n: Annotated[int, typer.Option("-n", help="Number of variants.")] = 8,
        seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
        overwrite: Annotated[bool, typer.Option(help="Replace a non-empty output folder.")] = False,
    ) -> None:
        """Scene variants with densities, frictions and solref drawn from the predicted distributions."""
        require(("-n", n, 1 <= n <= MAX_VARIANTS, f"between 1 and {MAX_VARIANTS}"), ("--seed", seed, seed >= 0, ">= 0"))
        with user_errors_exit_2():
            from grounder.properties.prior import write_scene_variants
            from reconstruction import check_output_dir

            check_output_dir(out, overwrite=overwrite, inputs=(scene,), error=InputError)  # before drawing the variants

            paths = write_scene_variants(scene, out, n, seed, overwrite=overwrite)
        typer.echo(f"wrote {len(paths)} variants to {out}")

    app.add_typer(group, name="properties")
