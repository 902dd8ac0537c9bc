"""`python -m grounder.cli`: the `image2sim` command line."""

from grounder.cli.entry import main

main()
