"""Files a run reads and writes: the 3DGS .ply layout, checkpoints, and atomic writes for both."""
