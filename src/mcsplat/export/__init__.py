"""`mcsplat export`: a trained run's Gaussians in a format that viewers read, or its surface as a mesh.

    formats.py    the table: every format, .ply and the mesh included, with its writer
    target.py     which format, which file (--format, --out), and what is refused
    unread.py     an option the chosen format would ignore, refused
    from_run.py   export_run(path, options): the run read back, checked, written
    selection.py  which Gaussians a Gaussian format holds, and what leaving the others out costs on the test views
    gaussians.py  a Gaussian format's file (the byte layouts are io/formats/)
    mesh.py       the mesh's file (mesh/), and the run's report made again to picture it
    options.py    ExportOptions: what the command is asked, declared once
    job.py        ExportJob: what a writer is handed

The CLI imports this package when it starts (for --format's choices): the run's heavy modules load inside functions.
"""

from .formats import DEFAULT_FORMAT, EXPORT_FORMATS, FORMAT_NAMES, ExportFormat, format_help
from .from_run import export_run
from .job import ExportJob
from .options import ExportOptions
from .selection import SelectionOptions

__all__ = ["export_run", "ExportOptions", "SelectionOptions", "ExportFormat", "ExportJob", "EXPORT_FORMATS",
           "FORMAT_NAMES", "DEFAULT_FORMAT", "format_help"]
