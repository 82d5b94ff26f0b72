"""cli/: the `mcsplat` command itself (info, one-line errors, the console script)."""
