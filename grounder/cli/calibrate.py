"""CLI commands ``calibrate``, ``rollout``, ``randomize``, ``import-trajectories`` and ``batch`` (registered by
``grounder.cli``)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer


def _split_params(params: list[str] | None) -> tuple[str, ...]:
    out: list[str] = []
    for item in params or []:
        out += [p.strip() for p in item.split(",") if p.strip()]
    return tuple(out)


def _check_new_dir(path: Path, *, inputs: tuple[Path, ...] = ()) -> None:
    """For the commands without --overwrite: `path` must be a new or empty folder, outside the inputs."""
    from grounder.errors import GrounderError
    from reconstruction import check_output_dir

    check_output_dir(path, error=GrounderError, inputs=inputs, offers_overwrite=False)


_FLAG_OF_OPTION = {
    "validation_fraction": "--validation-fraction",
    "split_seed": "--split-seed",
    "max_train_trajectories": "--max-train",
    "global_search_trajectories": "--global-search-trajectories",
    "generations": "--generations",
    "popsize": "--popsize",
    "local_iterations": "--local-iterations",
    "rotation_weight": "--rotation-weight",
    "seed": "--seed",
    "params": "--params",
    "distribution_params": "--distribution-params",
    "distribution_samples": "--distribution-samples",
    "distribution_iterations": "--distribution-iterations",
    "distribution_centre": "--distribution-centre",
}


def _as_flag(message: str) -> str:
    """``calibrate option FIELD must be ...`` (CalibrateOptions' wording, for Python and jobs files) as ``--flag``."""
    for field_name, flag in _FLAG_OF_OPTION.items():
        prefix = f"calibrate option {field_name} must be "
        if message.startswith(prefix):
            return f"{flag} must be {message[len(prefix) :].replace(' or null', '')}"
    return message


def register(app: typer.Typer) -> None:
    """Adds the calibration commands to the ``image2sim`` app."""
    _add_calibrate(app)
    _add_rollout(app)
    _add_randomize(app)
    _add_import_trajectories(app)
    _add_batch(app)


def _add_calibrate(app: typer.Typer) -> None:
    """Adds ``calibrate``: fit a scene's parameters to recorded trajectories."""
    from grounder.cli.common import fail, setup_logging, stage_progress, user_errors_exit_2

    @app.command()
    def calibrate(
        scene: Annotated[Path, typer.Argument(help="An MJCF file or a scene folder (with scene.xml).")],
        traj_dir: Annotated[Path, typer.Argument(help="Folder of recorded trajectories (.npz, the project format).")],
        out: Annotated[Path, typer.Option("-o", "--out", help="Calibrated scene folder to write (new or empty).")],
        params: Annotated[
            list[str] | None,
            typer.Option(
                "--params",
                help="Parameter NAME or NAME=LOW:HIGH (repeat or comma-separate), e.g. cube.friction.sliding, "
                "cube.solref.timeconst=0.002:0.05, opt.gravity_scale. Default: the scene kind's defaults.",
            ),
        ] = None,
        mode: Annotated[
            str, typer.Option(help="raw (parameters within bounds) or embedding (property embedding).")
        ] = "raw",
        validation_fraction: Annotated[float, typer.Option(help="Share of trajectories held out.")] = 0.3,
        split_seed: Annotated[int, typer.Option(help="Seed of the train/validation shuffle.")] = 0,
        max_train: Annotated[
            int | None, typer.Option(help="Fit on at most this many training trajectories (seeded subset).")
        ] = None,
        global_search_trajectories: Annotated[
            int,
            typer.Option(
                help="The global search scores candidates on a seeded subset of this many fitting trajectories; "
                "the local refinement uses them all (0: all throughout)."
            ),
        ] = 48,
        generations: Annotated[
            int, typer.Option(help="Differential-evolution generations (0: no global search).")
        ] = 20,
        popsize: Annotated[int, typer.Option(help="Differential-evolution population per parameter.")] = 8,
        local_iterations: Annotated[int, typer.Option(help="mujoco.minimize least-squares iterations.")] = 10,
        rotation_weight: Annotated[float, typer.Option(help="Loss weight: percent of size per degree.")] = 0.0,
        seed: Annotated[int, typer.Option(help="Seed of the global search.")] = 0,
        distribution: Annotated[
            bool,
            typer.Option(
                "--distribution",
                help="Also fit a distribution over the parameters (Monte Carlo EM): distribution.json, for "
                "`rollout --samples` and `randomize`.",
            ),
        ] = False,
        distribution_params: Annotated[
            list[str] | None,
            typer.Option(
                "--distribution-params",
                help="Parameters given a spread (names among --params; default: every continuous one).",
            ),
        ] = None,
        distribution_samples: Annotated[
            int, typer.Option(help="Parameter draws per iteration of the distribution fit.")
        ] = 64,
        distribution_iterations: Annotated[int, typer.Option(help="Iterations of the distribution fit.")] = 6,
        distribution_centre: Annotated[
            str,
            typer.Option(
                help="fitted: fit the distribution's mean and covariance; point: centre it on the calibrated values "
                "and fit its spread only (raw mode)."
            ),
        ] = "fitted",
        verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log each step.")] = False,
    ) -> None:
        """Fit a scene's physical parameters to recorded trajectories: scene.xml, calibration.json, report.html
        (and with --distribution, distribution.json)."""
        setup_logging(verbose)
        with user_errors_exit_2():
            from grounder.calibration.fit import calibrate as run_calibrate
            from grounder.calibration.options import CalibrateOptions
            from grounder.core.trajectory import load_trajectories
            from grounder.errors import GrounderError
            from grounder.sim.scene_files import load_scene_spec

            if mode not in ("raw", "embedding"):
                fail(f"--mode must be raw or embedding, got {mode!r}")
            _check_new_dir(out, inputs=(scene, traj_dir))
            try:
                options = CalibrateOptions(
                    params=_split_params(params),
                    mode=mode,  # type: ignore[arg-type]
                    validation_fraction=validation_fraction,
                    split_seed=split_seed,
                    max_train_trajectories=max_train,
                    global_search_trajectories=global_search_trajectories or None,
                    generations=generations,
                    popsize=popsize,
                    local_iterations=local_iterations,
                    rotation_weight=rotation_weight,
                    seed=seed,
                    distribution=distribution,
                    distribution_params=_split_params(distribution_params),
                    distribution_samples=distribution_samples,
                    distribution_iterations=distribution_iterations,
                    distribution_centre=distribution_centre,  # type: ignore[arg-type]
                )
            except GrounderError as exc:  # named by the option's field: say the flag the user typed
                fail(_as_flag(str(exc)))
            _, model = load_scene_spec(scene)
            trajs = load_trajectories(traj_dir, model)
            from grounder.calibration.parameters import resolve_parameters

            resolve_parameters(model, options.params)  # unknown names fail before any work
            with stage_progress() as progress:
                result = run_calibrate(scene, trajs, options=options, out=out, progress=progress)
        for p in result.parameters:
            interval = f"[{p.interval_low:.4g}, {p.interval_high:.4g}]"
            typer.echo(f"{p.name:32s} {p.nominal:10.4g} -> {p.value:10.4g}  {interval} {p.unit}")
        for split, after in result.after.items():
            before = result.before[split]
            typer.echo(
                f"{split}: position {before.position_pct.mean():.1f}% -> {after.position_pct.mean():.1f}% of size, "
                f"rotation {before.rotation_deg.mean():.1f} -> {after.rotation_deg.mean():.1f} deg "
                f"({len(after.names)} trajectories)"
            )
        if result.distribution is not None:
            dist = result.distribution
            for row in dist.summary(dist.parameters(result.model)):
                typer.echo(
                    f"{row['name']:32s} distribution: mean {row['mean']:.4g}, std {row['std']:.4g} "
                    f"(90%: {row['p05']:.4g} to {row['p95']:.4g}) {row['unit']}"
                )
        typer.echo(f"wrote {out}")


def _add_rollout(app: typer.Typer) -> None:
    """Adds ``rollout``: re-simulate recorded trajectories (`grounder.sim.rollout_files.run_rollout`)."""
    from grounder.cli.common import require, setup_logging, user_errors_exit_2

    @app.command()
    def rollout(
        scene: Annotated[Path, typer.Argument(help="An MJCF file or a scene folder (with scene.xml).")],
        traj_dir: Annotated[Path, typer.Argument(help="Folder of recorded trajectories (.npz).")],
        out: Annotated[Path, typer.Option("-o", "--out", help="Folder for the predicted trajectories.")],
        no_residual: Annotated[
            bool, typer.Option("--no-residual", help="Plain MuJoCo even when the scene folder has a residual.")
        ] = False,
        overwrite: Annotated[
            bool,
            typer.Option(help="Replace a non-empty output folder (its files are removed) once the rollouts are done."),
        ] = False,
        samples: Annotated[
            int | None,
            typer.Option(
                "--samples",
                help="Simulate each trajectory K times from the scene's distribution.json (parameters and start "
                "noise): NAME.npz is the median, NAME.samples.npz the K samples.",
            ),
        ] = None,
        seed: Annotated[int, typer.Option(help="Seed of the draws (with --samples).")] = 0,
        verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log each step.")] = False,
    ) -> None:
        """Simulate every trajectory from its first state with its controls; same file names in the output."""
        setup_logging(verbose)
        require(("--seed", seed, 0 <= seed < 2**32, "between 0 and 2^32 - 1"))
        with user_errors_exit_2():
            from grounder.sim.rollout_files import MAX_SAMPLES, run_rollout, run_sampled_rollout

            if samples is not None:
                require(("--samples", samples, 1 <= samples <= MAX_SAMPLES, f"between 1 and {MAX_SAMPLES}"))
                medians, _ = run_sampled_rollout(
                    scene, traj_dir, out, samples=samples, seed=seed, overwrite=overwrite, use_residual=not no_residual
                )
                typer.echo(f"simulated {len(medians)} trajectories x {samples} samples; wrote {out}")
                return
            preds, used_residual = run_rollout(scene, traj_dir, out, use_residual=not no_residual, overwrite=overwrite)
        what = "MuJoCo + residual" if used_residual else "MuJoCo"
        typer.echo(f"simulated {len(preds)} trajectories with {what}; wrote {out}")


def _add_randomize(app: typer.Typer) -> None:
    """Adds ``randomize``: domain-randomisation variants drawn from a calibrated scene's distribution.json."""
    from grounder.cli.common import require, setup_logging, user_errors_exit_2

    @app.command()
    def randomize(
        scene: Annotated[Path, typer.Argument(help="A scene folder written by `calibrate --distribution`.")],
        out: Annotated[Path, typer.Option("-o", "--out", help="Output folder for variant_NNN.xml + variants.json.")],
        n: Annotated[int, typer.Option("-n", help="Number of variants.")] = 8,
        seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
        overwrite: Annotated[bool, typer.Option(help="Replace a non-empty output folder.")] = False,
        verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log each step.")] = False,
    ) -> None:
        """Scene variants with the calibrated parameters drawn from the fitted distribution (distribution.json)."""
        from grounder.calibration.randomize import MAX_VARIANTS

        setup_logging(verbose)
        require(
            ("-n", n, 1 <= n <= MAX_VARIANTS, f"between 1 and {MAX_VARIANTS}"),
            ("--seed", seed, 0 <= seed < 2**32, "between 0 and 2^32 - 1"),
        )
        with user_errors_exit_2():
            from grounder.calibration.randomize import write_randomized_variants

            paths = write_randomized_variants(scene, out, n, seed, overwrite=overwrite)
        typer.echo(f"wrote {len(paths)} variants to {out}")


def _add_import_trajectories(app: typer.Typer) -> None:
    """Adds ``import-trajectories``: convert recorded motion into the project's format."""
    from grounder.cli.common import setup_logging, user_errors_exit_2

    @app.command("import-trajectories")
    def import_trajectories_cmd(
        src: Annotated[Path, typer.Argument(help="The recorded data (for dair-pll-cube: the folder with tosses/).")],
        out: Annotated[Path, typer.Option("-o", "--out", help="Trajectory folder to write (new or empty).")],
        fmt: Annotated[str, typer.Option("--format", help="Input format: dair-pll-cube.")] = "dair-pll-cube",
        verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log each step.")] = False,
    ) -> None:
        """Convert recorded motion into the project's trajectory format."""
        setup_logging(verbose)
        with user_errors_exit_2():
            from grounder.core.importers import import_trajectories
            from grounder.core.trajectory import save_trajectories

            _check_new_dir(out, inputs=(src,))
            trajs = import_trajectories(fmt, src)
            if out.is_dir():
                out.rmdir()  # empty: let save_trajectories build it atomically
            save_trajectories(trajs, out)
        steps = sum(t.num_steps for t in trajs)
        typer.echo(f"imported {len(trajs)} trajectories ({steps} samples) from {src}; wrote {out}")


def _add_batch(app: typer.Typer) -> None:
    """Adds ``batch``: many calibrations from a jobs file, on Ray."""
    from grounder.cli.common import require, setup_logging, stage_progress, user_errors_exit_2

    @app.command()
    def batch(
        jobs_file: Annotated[Path, typer.Argument(help="JOBS.yaml: scenes x datasets x settings.")],
        out: Annotated[
            Path | None,
            typer.Option(
                "-o",
                "--out",
                help="Output folder: new, empty, or an earlier batch output to resume (default: JOBS_results next "
                "to the file).",
            ),
        ] = None,
        address: Annotated[
            str | None,
            typer.Option(
                help="Ray cluster: the head node's host:port (e.g. head:6379), auto, or ray://host:10001 (needs "
                "ray[client]); default: a local Ray."
            ),
        ] = None,
        num_cpus: Annotated[int | None, typer.Option(help="CPUs of the local Ray (jobs at a time).")] = None,
        inline: Annotated[bool, typer.Option(help="Run the jobs one by one in this process, without Ray.")] = False,
        verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log each step.")] = False,
    ) -> None:
        """Run many calibrations on Ray; re-running skips finished jobs. Results in results.csv / results.json.

        Exit code 1 when some job failed (the others still ran), 2 for a bad jobs file or output folder, 130 after
        Ctrl-C and 143 after SIGTERM (the table is true of what finished; re-running resumes).
        """
        import signal
        import threading

        class Terminated(BaseException):
            """SIGTERM during the run: a BaseException, so that no ``except Exception`` on the way swallows it."""

        def terminated(signum: int, frame: object) -> None:
            raise Terminated

        setup_logging(verbose)
        require(("--num-cpus", num_cpus, num_cpus is None or 1 <= num_cpus <= 256, "between 1 and 256"))
        out_dir: Path | None = None
        # SIGTERM as this command's own exception while it runs, not `grounder.cli.entry._Terminated`: the batch
        # says how far it got before it exits 143 (the handler before is put back at the end).
        on_main = threading.current_thread() is threading.main_thread()
        before = signal.signal(signal.SIGTERM, terminated) if on_main else None
        try:
            with user_errors_exit_2():
                from grounder.calibration.batch import run_batch
                from grounder.calibration.batch_jobs import load_jobs
                from grounder.calibration.batch_output import check_batch_output, read_table

                jobs = load_jobs(jobs_file)
                out_dir = out if out is not None else jobs_file.with_name(f"{jobs_file.stem}_results")
                check_batch_output(out_dir)  # run_batch checks again; this fails before the progress bar appears
                from grounder.errors import GrounderError
                from image2sim_common.outdir import claim_output

                claim_output(out_dir, error=GrounderError)  # a second batch on this folder is refused while this runs
                with stage_progress() as progress:
                    summary = run_batch(
                        jobs, out_dir, address=address, num_cpus=num_cpus, inline=inline, progress=progress
                    )
        except (KeyboardInterrupt, Terminated) as exc:  # run_batch has rewritten the table on its way out
            signum = signal.SIGINT if isinstance(exc, KeyboardInterrupt) else signal.SIGTERM
            rows = read_table(out_dir) if out_dir is not None else None
            if out_dir is None or rows is None:
                where = "before any job ran"
            else:
                finished = sum(row.get("status") == "ok" for row in rows)
                where = f"with {finished} of {len(rows)} jobs finished (table: {out_dir / 'results.csv'})"
            typer.echo(
                f"image2sim: batch stopped ({signum.name}) {where}; run the same command again to resume", err=True
            )
            # sys.exit, not typer.Exit: typer returns 130 for an Exit as it does for a Ctrl-C it caught itself, and
            # main() prints the stopped line for that one; this stop has said its own.
            sys.exit(128 + signum)
        finally:
            if on_main:
                signal.signal(signal.SIGTERM, before)
        for row in summary.rows:
            if row["status"] == "failed":
                typer.echo(f"job {row['id']} failed: {row['error']}", err=True)
        typer.echo(
            f"{summary.total} jobs: {len(summary.skipped)} already finished, {len(summary.ran)} run now, "
            f"{len(summary.failed)} failed; table: {out_dir / 'results.csv'}"
        )
        if summary.failed:
            raise typer.Exit(1)  # the other jobs finished; re-running retries only the failed ones
