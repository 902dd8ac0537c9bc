"""`image2sim residual train SCENE TRAJ_DIR -o OUT`: a learned residual on top of a (calibrated) MuJoCo scene."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def register(app: typer.Typer) -> None:
    """Adds the ``residual`` command group to the ``image2sim`` app."""
    from grounder.cli.common import require, setup_logging, stage_progress, user_errors_exit_2

    group = typer.Typer(
        name="residual",
        help="Learned residual dynamics on top of a calibrated MuJoCo scene.",
        no_args_is_help=True,
    )

    @group.command("train")
    def train(
        scene: Annotated[Path, typer.Argument(help="A (calibrated) scene folder with scene.xml.")],
        traj_dir: Annotated[Path, typer.Argument(help="A folder of .npz trajectories recorded in that scene.")],
        out: Annotated[
            Path, typer.Option("-o", "--out", help="Output scene folder: the MJCF plus residual.pt/.json/.onnx.")
        ],
        steps: Annotated[int, typer.Option(help="Optimiser steps per training round.")] = 2000,
        rounds: Annotated[int, typer.Option(help="Data-aggregation rounds along rollouts after the first.")] = 0,
        hidden: Annotated[int, typer.Option(help="Width of the MLP's hidden layers.")] = 64,
        seed: Annotated[int, typer.Option(help="Random seed (initialisation, shuffling, k-means).")] = 0,
        ctrl_history: Annotated[
            float,
            typer.Option(
                help="Jointed scenes with actuators: seconds of earlier controls the residual sees (actuator delay)."
            ),
        ] = 0.05,
        overwrite: Annotated[
            bool, typer.Option(help="Replace a non-empty output folder once training is done.")
        ] = False,
        verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log each round.")] = False,
    ) -> None:
        """Train a bounded, gated residual on recorded trajectories; write a residual scene folder."""
        setup_logging(verbose)
        from grounder.residual.options import COUNT_LIMITS

        require(
            *(
                (flag, value, low <= value <= high, f"between {low} and {high}")
                for flag, value, (low, high) in (
                    ("--steps", steps, COUNT_LIMITS["steps"]),
                    ("--rounds", rounds, COUNT_LIMITS["dagger_rounds"]),
                    ("--hidden", hidden, COUNT_LIMITS["hidden"]),
                    ("--seed", seed, COUNT_LIMITS["seed"]),
                )
            ),
            ("--ctrl-history", ctrl_history, 0.0 <= ctrl_history <= 1.0, "between 0 and 1 (seconds)"),
        )
        with user_errors_exit_2():
            from grounder.core.trajectory import load_trajectories
            from grounder.errors import GrounderError
            from grounder.residual.options import ResidualOptions
            from grounder.residual.train import REPORT_FILE, train_residual
            from grounder.sim.scene_files import load_scene_model
            from reconstruction import check_output_dir

            check_output_dir(out, overwrite=overwrite, error=GrounderError, inputs=(scene, traj_dir))
            _xml, model = load_scene_model(scene)
            trajs = load_trajectories(traj_dir, model)
            options = ResidualOptions(
                steps=steps, dagger_rounds=rounds, hidden=hidden, seed=seed, ctrl_history_s=ctrl_history
            )
            with stage_progress() as progress:
                result = train_residual(scene, trajs, out, options, overwrite=overwrite, progress=progress)
        before, after = result.one_step_rms_before, result.one_step_rms_after
        if result.space == "free":
            errors = (
                f"one-step RMS position {before[0] * 1e3:.2f} -> {after[0] * 1e3:.2f} mm, "
                f"velocity {before[2]:.3f} -> {after[2]:.3f} m/s"
            )
        else:
            errors = (
                f"joint-space residual; one-step RMS joint position {before[0] * 1e3:.2f} -> {after[0] * 1e3:.2f} "
                f"mrad (mm for slides), joint velocity {before[2]:.3f} -> {after[2]:.3f} rad/s"
            )
        if result.gain_scores:
            gain = f"output gain chosen on held-out rollouts: {result.gain:g}" + (
                " (the residual did not help: MuJoCo alone)" if result.gain == 0 else ""
            )
        else:
            gain = (
                f"output gain {result.gain:g}, NOT checked on held-out rollouts (none held out: give at least 5 "
                "trajectories to have it checked)"
            )
        typer.echo(
            f"trained on {result.num_trajectories} trajectories ({result.num_samples} samples) in "
            f"{result.seconds:.1f} s; {errors}; {gain}"
        )
        typer.echo(f"residual scene: {result.out} (report: {result.out / REPORT_FILE})")

    app.add_typer(group, name="residual")
