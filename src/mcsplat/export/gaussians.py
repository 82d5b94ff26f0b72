"""Writing a Gaussian format (io/formats/): the Gaussians chosen (selection.py), the file, and the lines that say
what was written and what the format cannot record."""

from __future__ import annotations

from ..io.formats import GaussianFormat, write_gaussians
from .job import ExportJob
from .selection import chosen_gaussians


def export_gaussians(codec: GaussianFormat, job: ExportJob) -> None:
    model, path = job.run.model, job.path
    params = {k: v.detach().cpu().numpy() for k, v in model.params.items()}
    chosen = chosen_gaussians(job.run, params, job.selection)
    with job.writing():
        write_gaussians(codec.name, path, {k: v[chosen] for k, v in params.items()}, antialiased=model.antialiased,
                        spz_version=job.spz_version)
    if model.antialiased and not codec.records_antialiasing:
        print(f"note: this run was trained with --antialiased, which {codec.name} files cannot record: viewers "
              "draw it without the 2D filter (fine detail a little heavier); .spz and .sog record it")
    files = (path, *codec.companions(path))
    size = sum(file.stat().st_size for file in files)
    print(f"wrote {' and '.join(map(str, files))} ({chosen.size:,} of {model.num_gaussians:,} Gaussians, "
          f"{size:,} bytes)")
