"""io/: .ply, checkpoints, atomic writes, full and read-only disks."""
