"""`python -m visemeflow.cli`: the `visemeflow` command."""

from visemeflow.cli import main

main()
