"""Subcommands of the `hairwarp` command line, one module each."""
