"""The `image2sim` command line: `main` is the console script, `app` the typer application it runs.

- `entry`: `app`, `main` and the handling of every way a command ends (one line, the exit code).
- `common`: what every command shares (one-line errors, option checks, progress lines, logging).
- `scan` (reconstruct, ground), `properties`, `calibrate` (calibrate, rollout, import-trajectories, batch),
  `residual`, `diagnose`, `track`: one module per command group, each adding itself with ``register(app)``.

The module holding `app` and `main` is `entry`, not `app` or `main`: a submodule of those names would be shadowed
by the names this package re-exports.
"""

from grounder.cli.entry import app, main

__all__ = ["app", "main"]
