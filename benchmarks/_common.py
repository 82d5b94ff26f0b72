"""Helpers shared by the benchmark scripts: data paths, the results folder, JSON lines, markdown tables, plots,
training options (make_config, test_subset), timing and a description of the machine. Not part of the package; the
scripts import it as `_common` (they run as `python benchmarks/<script>.py`, which puts this folder on sys.path)."""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import torch

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
DATA_ROOT = REPO.parent / "shared" / "data"  # ../shared/data from the repository root
LEGO = "nerf_synthetic_lego_400/lego"         # NeRF-Synthetic lego at 400x400 (Blender: white background)
SFM_SCENES = {"bird": "colmap_bird", "cup": "colmap_cup"}  # real captures with a COLMAP sparse model
MATPLOTLIB_HINT = "matplotlib is missing: `.venv/bin/pip install -c constraints.txt matplotlib` (the bench extra)"


# ------------------------------------------------------------------------------------------------ paths and data
def scene_path(name_or_path: str, data_root: str | os.PathLike = DATA_ROOT) -> Path:
    """'lego', 'bird', 'cup' (under the shared data folder) or any scene folder."""
    named = {"lego": LEGO, **SFM_SCENES}
    if name_or_path in named:
        return Path(data_root) / named[name_or_path]
    return Path(name_or_path)


def results_dir(script: str, out: str | os.PathLike | None = None) -> Path:
    """benchmarks/results/<script>/ (or `out`, a script's --out, when given), created on demand."""
    path = Path(out) if out else RESULTS / script
    path.mkdir(parents=True, exist_ok=True)
    return path


def load(path: str | os.PathLike, downscale: int = 1):
    """load_scene with a readable exit when the data is not there."""
    from mcsplat.data import load_scene
    path = Path(path)
    if not path.exists():
        sys.exit(f"scene folder {path} not found (the shared data lives in {DATA_ROOT}; pass --data-root or a path)")
    return load_scene(path, downscale=downscale)


# ------------------------------------------------------------------------------------------------- output files
def train_with_tree(tree: Path, args: Sequence[str], log: Path, script: str) -> None:
    """`mcsplat train ARGS` with the package of checkout `tree` (its src/ first on the path), output to `log`;
    `script` names the benchmark in the error when training fails."""
    env = dict(os.environ, PYTHONPATH=str(tree / "src"))
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as out:
        done = subprocess.run([sys.executable, "-m", "mcsplat.cli", "train", *args], env=env, stdout=out,
                              stderr=subprocess.STDOUT)
    if done.returncode != 0:
        sys.exit(f"{script}: training failed, see {log}")


def write_results(folder: Path, records: Sequence[dict], page: str, show: bool = False) -> None:
    """Append `records` to folder/results.jsonl and write `page` as folder/results.md (also on stdout with `show`)."""
    append_jsonl(folder / "results.jsonl", records)
    write_text(folder / "results.md", page)
    if show:
        print(page, end="")
    print(f"wrote {folder / 'results.md'}", file=sys.stderr)


def logged_step_seconds(run: Path) -> float:
    """Seconds per step between a run's first and last log.jsonl records (the first at step 100: past the first
    steps' one-time costs)."""
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    first, last = log[0], log[-1]
    return (last["elapsed_seconds"] - first["elapsed_seconds"]) / (last["step"] - first["step"])


def emit(record: dict) -> None:
    """One JSON line on stdout (the figures of a configuration)."""
    print(json.dumps(record), flush=True)


def append_jsonl(path: Path, records: Iterable[dict]) -> None:
    with open(path, "a") as f:
        for record in records:
            f.write(json.dumps(record) + "\n")


def read_jsonl(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def fmt(value: Any, spec: str = "") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if spec:
        return format(value, spec)
    return f"{value:,}" if isinstance(value, int) else str(value)


def markdown_table(rows: Sequence[dict], columns: Sequence[tuple[str, str, str | Callable[[dict], str]]]) -> str:
    """columns: (header, key, format spec or a function of the row)."""
    lines = ["| " + " | ".join(header for header, _, _ in columns) + " |",
             "|" + "|".join("---" for _ in columns) + "|"]
    for row in rows:
        cells = [spec(row) if callable(spec) else fmt(row.get(key), spec) for _, key, spec in columns]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)


def results_page(title: str, script: str, rows: Sequence[dict], columns) -> str:
    """A results.md: a title, the command that made the figures, and their table."""
    return "\n".join([f"# {title}", "", f"`.venv/bin/python benchmarks/{script}` (the module docstring says what each "
                      "column is).", "", markdown_table(rows, columns), ""])


def write_results_page(folder: Path, title: str, script: str, rows: Sequence[dict], columns) -> None:
    """folder/results.md: results_page()."""
    write_text(folder / "results.md", results_page(title, script, rows, columns))


def pyplot():
    """matplotlib.pyplot on the Agg backend, or None (with a hint on stderr) when matplotlib is not installed."""
    try:
        import matplotlib
    except ImportError:
        print(MATPLOTLIB_HINT + "; no plot written", file=sys.stderr)
        return None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def human(n: int) -> str:
    """10000 -> '10k', 1500000 -> '1.5M'."""
    for div, suffix in ((1_000_000, "M"), (1_000, "k")):
        if n >= div:
            return f"{n / div:g}{suffix}"
    return str(n)


# ------------------------------------------------------------------------------------------------ training runs
@dataclasses.dataclass(frozen=True)
class BlockRuns:
    """Options of the blocks benchmarks (blocks.py, blocks_ablation.py): what the one run and every block train."""

    downscale: int
    """Image downscale factor of the scene."""
    steps: int
    """Training steps of the one run and of each block."""
    cap: int
    """--cap-max of the one run; the blocks' caps add up to it."""
    scene: str = "cup"
    """cup, bird, lego (under the shared data folder) or a scene folder."""


def make_config(**options: Any):
    """A TrainConfig from options named as config.json names them, the nested groups' with a dot:
    make_config(data=scene, steps=500, surface=True, **{"mcmc.refine_every": 10, "model.init": "random"})."""
    from mcsplat.config import TrainConfig, config_of

    top: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {}
    for key, value in options.items():
        group, _, name = key.rpartition(".")
        if group:
            nested.setdefault(group, {})[name] = value
        else:
            top[key] = value
    factories = {f.name: f.default_factory for f in dataclasses.fields(TrainConfig)}
    for group, values in nested.items():
        if group not in factories:
            raise ValueError(f"TrainConfig has no group of options {group!r} (in {sorted(values)})")
        top[group] = dataclasses.replace(top.get(group) or factories[group](), **values)
    return config_of(**top)


@contextlib.contextmanager
def test_subset(stride: int, max_views: int):
    """Evaluate train()'s final metrics on every `stride`-th test view (at most max_views; 0 = all): wraps the
    scene loader the run calls. Training views are untouched."""
    import importlib
    import importlib.util

    # The module through which a run loads its scene (run/scene.py; run_scene.py or run_dir.py in older checkouts).
    names = [name for name in ("mcsplat.run.scene", "mcsplat.run_scene", "mcsplat.run_dir")
             if importlib.util.find_spec(name.rpartition(".")[0]) and importlib.util.find_spec(name)]
    loader = next(module for module in map(importlib.import_module, names) if hasattr(module, "load_scene"))
    original = loader.load_scene

    def load_with_subset(*args, **kwargs):
        scene = original(*args, **kwargs)
        views = scene.test[::stride]
        scene.test = views[:max_views] if max_views else views
        return scene

    loader.load_scene = load_with_subset
    try:
        yield
    finally:
        loader.load_scene = original


# ----------------------------------------------------------------------------------------------- timing, memory
def sync(device: torch.device | str) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def now(device: torch.device | str) -> float:
    """perf_counter after the device has finished its queued work."""
    sync(device)
    return time.perf_counter()


def median(values: Sequence[float]) -> float:
    return float(statistics.median(values)) if values else float("nan")


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (Linux reports KiB, macOS bytes)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2 ** 20 if sys.platform == "darwin" else peak / 1024.0


def current_rss_mb() -> float | None:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20
    except (OSError, ValueError, IndexError):
        return None


def set_threads(threads: int | None) -> None:
    """Threads for torch's CPU ops and for the CPU compositing launcher together."""
    from mcsplat.render import set_cpu_threads
    if threads is not None:
        torch.set_num_threads(threads)
    set_cpu_threads(threads)


def cuda_or_exit(device: str, script: str) -> None:
    """With --device cuda on a machine without CUDA, say so in one JSON line and exit 0 (skip cleanly)."""
    if device.startswith("cuda") and not torch.cuda.is_available():
        emit({"benchmark": script, "skipped": "no CUDA device available", "device": device})
        sys.exit(0)


def warn_if_busy(threshold: float = 0.5) -> float | None:
    """Warn on stderr when the machine is already busy (1-minute load average above `threshold`): timings taken
    next to another job are not comparable (with 2 cores, torch's threads slow down many times over)."""
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):
        return None
    if load > threshold:
        print(f"warning: load average {load:.2f} before starting: another job is running, the timings will be "
              f"unreliable", file=sys.stderr)
    return round(load, 2)


# ---------------------------------------------------------------------------------------------------- machine
def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def memory_gb() -> float | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return round(int(line.split()[1]) / 2 ** 20, 1)
    except OSError:
        pass
    return None


def machine(device: str = "cpu") -> dict:
    import warp
    info = {"cpu": cpu_name(), "cores": os.cpu_count(), "memory_gb": memory_gb(), "os": platform.platform(terse=True),
            "python": platform.python_version(), "torch": torch.__version__, "warp": warp.__version__}
    if str(device).startswith(("cuda", "auto")) and torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name()
    return info


def machine_line(info: dict) -> str:
    text = f"{info['cpu']}, {info['cores']} cores, {info.get('memory_gb')} GB RAM, {info['os']}; " \
           f"Python {info['python']}, torch {info['torch']}, warp {info['warp']}"
    return text + (f"; GPU {info['gpu']}" if info.get("gpu") else "")


def git_commit() -> str | None:
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                                check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "src"], cwd=REPO,
                               capture_output=True, text=True, check=True).stdout.strip()
        return commit + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return None


def timestamp() -> str:
    return datetime.datetime.now().astimezone().isoformat(timespec="seconds")
