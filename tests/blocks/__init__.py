"""blocks/: `mcsplat blocks` (plan, train, merge) and its refusals."""
