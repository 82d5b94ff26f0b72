"""The training masks' old address: the mask kind now lives in data/attachments/masks.py, one kind of per-view input
among others. Kept while modules outside data/ (cli.py, run_dir.py, subscribers.py) still import it from here."""

from mcsplat.data.attachments.masks import (MASK_FOLDER, NOTE_PREFIX, MaskOptions, check_something_kept, describe,
                                            mask_file, missing_error, read_keep)

__all__ = ["MASK_FOLDER", "NOTE_PREFIX", "MaskOptions", "check_something_kept", "describe", "mask_file",
           "missing_error", "read_keep"]
