"""Writing the mesh (mesh/): the surface the training views see, its file, and the run's report made again when the
mesh is the run's own RUN/mesh.ply (the report pictures it).

mesh/ and report/ load inside the functions: the CLI imports this package for --format's choices, and
`mcsplat --help` stays quick.
"""

from __future__ import annotations

import time
from pathlib import Path

from .job import ExportJob


def check_mesh_file(path: Path) -> None:
    """A one-line error unless `path` ends in a mesh format's ending."""
    from ..mesh import check_mesh_path

    check_mesh_path(path)


def export_mesh(job: ExportJob) -> None:
    from ..mesh import extract, write_mesh

    run, path = job.run, job.path
    started = time.perf_counter()
    mesh = extract(run.model, run.scene.train, job.mesh, sh_degree=run.sh_degree, progress=True)
    with job.writing():
        write_mesh(path, mesh)
    made = mesh.metadata["mcsplat"]
    print(f"wrote {path} ({len(mesh.vertices):,} vertices, {len(mesh.faces):,} faces; {made['views']} views fused "
          f"in {made['grid'].describe()}, {made['fused_share']:.0%} of their surface pixels confirmed by their "
          f"neighbours, {time.perf_counter() - started:.0f} s)")
    folder = run.folder
    if path == folder.mesh_file and folder.report_file.is_file():
        _remake_report(folder, job.device)


def _remake_report(folder, device_name: str) -> None:
    from ..report import make_report
    from ..report.views import saved_run_views

    test_views, render_view = saved_run_views(folder.path, device_name)
    with folder.lock("mcsplat export"):
        print(f"wrote {make_report([folder.path], test_views=test_views, render_view=render_view)}")
