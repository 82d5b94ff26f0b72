"""data/attachments/: per-view inputs (depth maps, masks)."""
