"""Which format `mcsplat export` writes, and to which file: --format, else the one --out's name ends with, else
ply; --out, else the format's own file in the run folder. What it refuses, in one line each: an --out that is a
folder, one of the run's own files or inside a scene folder, a name that says no format or another than --format;
the same of each file written beside it (a .gltf's .bin), which moreover never replaces a file it did not write."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import MCSplatError
from .formats import DEFAULT_FORMAT, EXPORT_FORMATS, ExportFormat

if TYPE_CHECKING:
    from ..run.folder import RunDir


def export_target(folder: RunDir, format_name: str | None, out: Path | None) -> tuple[ExportFormat, Path]:
    """(the format, the file to write)."""
    if format_name is not None and format_name not in EXPORT_FORMATS:
        raise MCSplatError(f"--format {format_name}: not a format mcsplat writes; choose one of "
                           f"{', '.join(EXPORT_FORMATS)}")
    chosen = EXPORT_FORMATS.get(format_name)
    if out is None:
        chosen = chosen or EXPORT_FORMATS[DEFAULT_FORMAT]
        path = chosen.default_file(folder)
    else:
        path = _checked_out(folder, out)
        if chosen is None or chosen.ending is not None:
            chosen = _named_by(path, chosen)
    for companion in chosen.companions(path):
        _check_companion(folder, companion, path)
    if chosen.check_path is not None:
        chosen.check_path(path)
    return chosen, path


def _checked_out(folder: RunDir, out: Path) -> Path:
    """--out, unless it is a folder, one of the run's own files or inside a scene folder."""
    if out.is_dir():
        raise MCSplatError(f"--out {out} is a folder; give the file to write")
    _refuse_run_file_or_scene(folder, out, f"--out {out}")
    return out


def _check_companion(folder: RunDir, companion: Path, path: Path) -> None:
    """A file written beside `path` is held to --out's rules: the user named only `path`."""
    what = f"{companion} (written beside {path.name})"
    if companion.is_dir():
        raise MCSplatError(f"{what} is a folder; export to another name")
    _refuse_run_file_or_scene(folder, companion, what)


def _refuse_run_file_or_scene(folder: RunDir, file: Path, what: str) -> None:
    from ..run.scene import refuse_writing_into_scene

    if folder.is_own_file(file):
        raise MCSplatError(f"{what} would replace the run's own {file.name}; choose another name")
    refuse_writing_into_scene(file, folder.read_config())


def _named_by(out: Path, asked: ExportFormat | None) -> ExportFormat:
    """The format --out's name ends with (the longest ending that matches: x.compressed.ply is compressed-ply, x.ply
    ply), which must be --format's when it is given."""
    by_ending = [entry for entry in EXPORT_FORMATS.values() if entry.ending is not None]
    matching = [(len(entry.ending), entry.name) for entry in by_ending if out.name.lower().endswith(entry.ending)]
    if not matching:
        endings = ", ".join(sorted({entry.ending for entry in by_ending}))
        hint = "".join(f" (a {entry.name}: --format {entry.name})" for entry in EXPORT_FORMATS.values()
                       if entry.ending is None and _takes(entry, out))
        raise MCSplatError(f"--out {out}: the name must end in {endings}, which says the format{hint}")
    named = EXPORT_FORMATS[max(matching)[1]]
    if asked is not None and asked is not named:
        raise MCSplatError(f"--out {out} names a {named.name} file but --format is {asked.name}; name it "
                           f"*{asked.ending} or leave --format out")
    return named


def _takes(entry: ExportFormat, path: Path) -> bool:
    """Whether a format that only --format chooses could be written as `path` (for the hint of a refusal)."""
    try:
        entry.check_path(path)
    except MCSplatError:
        return False
    return True
