"""The `image2sim` command line: `main` is the console script, `app` the typer application it runs."""

from grounder.cli.app import app, main

__all__ = ["app", "main"]
