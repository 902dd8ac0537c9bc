"""CLI for gap diagnosis: ``image2sim diagnose`` and ``image2sim diagnose-benchmark``."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer

MAX_THREADS = 256  # each thread holds its own MjData; thousands would only exhaust memory


def _effect_names(flag: str, values: list[str] | None) -> tuple[str, ...] | None:
    """The names given (comma-separated or repeated); None when the option is left out. A value that names
    nothing (``--effects ,``) is refused rather than read as "every effect"."""
    if not values:
        return None
    names = [n.strip() for v in values for n in v.split(",") if n.strip()]
    if not names:
        from grounder.cli.common import fail

        fail(f"{flag} {','.join(values)!r} names nothing; give names separated by commas, or leave {flag} out for all")
    return tuple(names)


def register(app: typer.Typer) -> None:
    from grounder.cli.common import require, setup_logging, stage_progress, user_errors_exit_2

    @app.command("diagnose")
    def diagnose(
        scene: Annotated[
            Path, typer.Argument(help="The nominal scene you believe: its MJCF, or a scene folder with scene.xml.")
        ],
        traj_dir: Annotated[
            Path,
            typer.Argument(
                help="Folder of recorded trajectories (.npz, project format), or the folder `image2sim track` wrote "
                "(its segments; the tracker's smoothing is counted in the noise floor)."
            ),
        ],
        out: Annotated[Path, typer.Option("-o", "--out", help="Output folder (created; must be new or empty).")],
        effects: Annotated[
            list[str] | None,
            typer.Option(
                help="Effects to test, comma-separated or repeated (default: every applicable one, and on the bodies "
                "and contact pairs where the gap is largest); NAME@BODY or NAME@BODY|OTHER acts on one body or "
                "contact pair only."
            ),
        ] = None,
        holdout: Annotated[float, typer.Option(help="Share of trajectories held out for scoring.")] = 0.3,
        horizon: Annotated[float, typer.Option(help="Short-horizon window length (s).")] = 0.25,
        seed: Annotated[int, typer.Option(help="Seed of the split and the bootstrap.")] = 0,
        threads: Annotated[int | None, typer.Option(help="Rollout threads (default: all usable cores).")] = None,
        overwrite: Annotated[bool, typer.Option(help="Replace a non-empty output folder.")] = False,
        verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log each effect.")] = False,
    ) -> None:
        """Where the sim-to-real gap lies, which unmodelled effect causes it, how far it shrinks.

        Writes OUT/diagnosis.json, OUT/report.html and OUT/diagnosed.xml.
        """
        setup_logging(verbose)
        require(
            ("--threads", threads, threads is None or 1 <= threads <= MAX_THREADS, f"between 1 and {MAX_THREADS}"),
            ("--seed", seed, seed >= 0, ">= 0"),
            ("--horizon", horizon, math.isfinite(horizon) and horizon > 0, "> 0 and finite (seconds)"),
        )
        with user_errors_exit_2():
            from grounder.diagnosis.pipeline import DiagnoseOptions, diagnose_files

            options = DiagnoseOptions(
                effects=_effect_names("--effects", effects),
                holdout_fraction=holdout,
                horizon_s=horizon,
                seed=seed,
                nthread=threads,
            )
            with stage_progress() as progress:
                diag = diagnose_files(scene, traj_dir, out, options, overwrite=overwrite, progress=progress)
        held = diag.heldout
        typer.echo(
            f"gap {diag.gap['total']:.4f} (short horizon), selected: {', '.join(diag.selected) or 'none'}; held-out "
            f"{held['gap_before']:.4f} -> {held['gap_after']:.4f} ({held['reduction']:.0%} less), unexplained "
            f"{diag.unexplained_fraction:.0%}"
        )
        typer.echo(f"wrote {out}")

    @app.command("diagnose-benchmark")
    def diagnose_benchmark(
        cases: Annotated[
            list[str] | None, typer.Option(help="Case names (default: all), comma-separated or repeated.")
        ] = None,
        trajectories: Annotated[int, typer.Option(help="Trajectories per case.")] = 16,
        threads: Annotated[int, typer.Option(help="Rollout threads per case.")] = 2,
        seed: Annotated[int, typer.Option(help="Seed of the generated data.")] = 0,
        json_out: Annotated[Path | None, typer.Option("--json", help="Also write the results here.")] = None,
    ) -> None:
        """Withheld-effect benchmark: generate cases with hidden effects, diagnose them blind, print the table."""
        from grounder.diagnosis.benchmark import MAX_TRAJECTORIES, MIN_TRAJECTORIES, check_results_file, write_results

        require(
            (
                "--trajectories",
                trajectories,
                MIN_TRAJECTORIES <= trajectories <= MAX_TRAJECTORIES,
                f"between {MIN_TRAJECTORIES} and {MAX_TRAJECTORIES} (each case holds 30% out for the check; "
                "~0.7 s each per case on 2 threads)",
            ),
            ("--threads", threads, 1 <= threads <= MAX_THREADS, f"between 1 and {MAX_THREADS}"),
            ("--seed", seed, seed >= 0, ">= 0"),
        )
        if json_out is not None:  # before the benchmark's minutes, not after
            with user_errors_exit_2():
                check_results_file(json_out)
        with user_errors_exit_2():
            from grounder.diagnosis.benchmark import format_table, run_benchmark

            with stage_progress() as progress:
                results = run_benchmark(
                    names=_effect_names("--cases", cases), num_trajectories=trajectories, nthread=threads, seed=seed,
                    progress=progress,
                )  # fmt: skip
        typer.echo(format_table(results))
        if json_out is not None:
            write_results(json_out, results)
