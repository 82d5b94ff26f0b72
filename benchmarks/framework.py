"""The benchmarks as one small framework: an experiment declares its arms, runs one, and writes a page from the
records; one runner does the rest.

An experiment is a module of benchmarks/ (its name is its subcommand and, unless its RESULTS says otherwise, its
results folder) that defines what `Experiment` lists. The runner (`python -m benchmarks NAME ...`, or the module's
own `python benchmarks/NAME.py ...`):

- parses the experiment's `Options` with tyro, as `mcsplat` parses its commands (`Common` holds the options every
  experiment takes: --out, --report, --rerun, --threads, --jobs, --data-root);
- runs every arm that results.jsonl does not hold yet (all of them with --rerun), each in a fresh process (a worker:
  its own memory, its own environment, a crash stops that arm only) that answers with one JSON line;
- runs an arm that needs other arms' results (`Arm.after`: a shared voxel size, a count to match) only once those
  are recorded, and leaves it out when one of them is not; its run() reads their records with `recorded()`;
- appends a record per arm: the common fields (SCHEMA_FIELDS), the arm's labels and the figures `run()` returned
  (one record per row where it returned a list of rows: an experiment's ROW_KEY tells them apart);
- writes results.md from the last record of every arm (`report()`), also with --report alone.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import dataclasses
import importlib
import json
import os
import subprocess
import sys
import time
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol, Sequence

import tyro

import _common as C

# The converted experiments, by module name (each module's docstring says what it measures).
EXPERIMENTS = ("antialiasing", "appearance", "auto_cap", "budget", "collapse", "defaults_before_after",
               "depth_accuracy", "fusion_gap", "masks", "mesh_chamfer", "mesh_quality", "pose_refinement", "sfm_depth",
               "sparse_depth", "time_to_quality")
SCHEMA = 1
SCHEMA_FIELDS = ("name", "script", "schema", "date", "commit", "machine", "load_average_before", "options", "worker")
NOT_READY = 3  # a worker's exit status for NotReady
WORKER_ENV = ("OMP_NUM_THREADS", "CUDA_VISIBLE_DEVICES")  # besides every MCSPLAT_* variable, recorded per arm
MAIN = Path(__file__).resolve().with_name("__main__.py")


@dataclass(frozen=True)
class Common:
    """Options of every experiment."""

    out: Path | None = None
    """Results folder (default: benchmarks/results/<experiment>/)."""
    report: bool = False
    """Run nothing: only write results.md (and its pictures) again from results.jsonl."""
    rerun: bool = False
    """Run again the arms results.jsonl already holds (the last record of an arm is the one reported)."""
    threads: int | None = None
    """CPU threads of each arm's process (default: all cores)."""
    jobs: int = 1
    """Arms run at a time, each in its own process."""
    data_root: Path = C.DATA_ROOT
    """The shared data folder."""


@dataclass(frozen=True)
class Arm:
    """One configuration of an experiment: what its run() needs, as plain JSON values."""

    name: str
    """Unique within the experiment; the run folder's name where it trains one."""
    labels: dict[str, Any]
    """Recorded with the figures; they hold the experiment's KEY fields, which tell its records apart."""
    config: dict[str, Any] = field(default_factory=dict)
    """TrainConfig options as config.json names them, the nested groups' with a dot (C.make_config)."""
    env: dict[str, str] = field(default_factory=dict)
    """Environment variables of the arm's process (MCSPLAT_CPU_TARGET, ...)."""
    after: tuple[str, ...] = ()
    """Names of arms declared with it whose records its run() reads (`recorded()`): it starts once they are
    recorded (earlier, or in this run), and is left out when one of them is not."""


class NotReady(Exception):
    """An arm that cannot run with this checkout or at this point (the message says why): left out, not failed."""


class Experiment(Protocol):
    """What an experiment module defines."""

    Options: type
    """A frozen dataclass parsed by tyro, with a field `common: Annotated[Common, tyro.conf.OmitArgPrefixes]`."""
    KEY: tuple[str, ...]
    """The record fields that tell one arm's records from another's (old records too: they may lack `name`)."""

    def arms(self, options: Any) -> list[Arm]:
        """The arms these options ask for, declared (nothing is run or read here)."""

    def run(self, arm: Arm, options: Any, folder: Path) -> dict:
        """Run one arm in this (worker) process; its figures, JSON values. Raise NotReady to leave it out."""

    def report(self, records: list[dict], folder: Path) -> str:
        """results.md's text from the last record of every arm (pictures may be written into `folder`)."""

    # Optional:
    # - ROW_KEY: tuple[str, ...], the figures' fields that tell apart the records of one arm: its rows where run()
    #   returns a list of figures (one record each), or runs kept side by side. The last record of each KEY + ROW_KEY
    #   is reported; an arm is recorded when any record has its KEY values.
    # - RESULTS: str, "FOLDER/STEM": the records and page are results/FOLDER/STEM.jsonl and .md (by default
    #   "<name>/results"; with --out, OUT/STEM.jsonl and .md), for one that measures another's runs beside them.
    # - finish(arms, options, folder) runs in the runner after the arms (pictures across arms).


class Records:
    """A JSON-lines file of records, appended; the last record of a key wins (in the place of its first)."""

    def __init__(self, path: Path, key: Sequence[str] = ("name",)) -> None:
        self.path, self.key = path, tuple(key)
        self.by_key = {self.key_of(r): r for r in C.read_jsonl(path)}

    def key_of(self, record: dict) -> tuple:
        return tuple(record.get(k) for k in self.key)

    def add(self, record: dict) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        C.append_jsonl(self.path, [record])
        self.by_key[self.key_of(record)] = record

    def get(self, *values: Any) -> dict | None:
        return self.by_key.get(tuple(values))

    def of(self, *values: Any) -> list[dict]:
        """The last records whose key starts with `values` (an arm's rows, by its KEY values)."""
        return [record for key, record in self.by_key.items() if key[:len(values)] == values]

    def latest(self) -> list[dict]:
        return list(self.by_key.values())


# ------------------------------------------------------------------------------------------------ the runner
def experiment(name: str) -> Experiment:
    """The experiment module `name` (a module of benchmarks/, or any on the path: the tests' toy one)."""
    return importlib.import_module(name)


def places(name: str, out: Path | None = None) -> tuple[Path, Path, Path]:
    """Experiment `name`'s (folder, records file, page): RESULTS's, or in `out` (--out) when given."""
    place, stem = getattr(experiment(name), "RESULTS", f"{name}/results").rsplit("/", 1)
    folder = Path(out) if out else C.RESULTS / place
    return folder, folder / f"{stem}.jsonl", folder / f"{stem}.md"


def recorded(name: str, folder: Path) -> Records:
    """Experiment `name`'s records in `folder` (run()'s folder): run() finds those of the arms it waits for."""
    module = experiment(name)
    return Records(places(name, folder)[1], module.KEY + getattr(module, "ROW_KEY", ()))


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m benchmarks NAME [OPTIONS]`: one subcommand per experiment."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--worker"]:
        return worker(json.loads(argv[1]))
    modules = {name: experiment(name) for name in EXPERIMENTS}
    options = tyro.extras.subcommand_cli_from_dict(
        {name: module.Options for name, module in modules.items()}, prog="python -m benchmarks", args=argv,
        description="Run a benchmark experiment (benchmarks/README.md): its arms not yet recorded, then its page.")
    name = next(name for name, module in modules.items() if type(options) is module.Options)
    return run_experiment(name, options, argv[argv.index(name) + 1:])


def script(name: str, argv: Sequence[str] | None = None) -> int:
    """`python benchmarks/NAME.py [OPTIONS]`: the experiment's options without a subcommand."""
    argv = list(sys.argv[1:] if argv is None else argv)
    module = experiment(name)
    options = tyro.cli(module.Options, args=argv, prog=f"benchmarks/{name}.py", description=module.__doc__)
    return run_experiment(name, options, argv)


def run_experiment(name: str, options: Any, args: list[str]) -> int:
    """Run the arms not yet recorded (each in a worker given `args`, the experiment's own options), then write
    results.md; 1 when an arm failed."""
    module = experiment(name)
    folder, _, page = places(name, options.common.out)
    records = recorded(name, folder)
    failed = 0
    if not options.common.report:
        try:
            arms = ordered(module.arms(options))
        except ValueError as error:
            print(f"{name}: {error}", file=sys.stderr)
            return 2
        todo = [arm for arm in arms if options.common.rerun or not records.of(*keys(module, arm))]
        for arm in arms:
            if arm not in todo:
                print(f"{name}: {arm.name} is recorded (--rerun runs it again)", file=sys.stderr)
        common = {"script": name, "schema": SCHEMA, "load_average_before": C.warn_if_busy() if todo else None,
                  "machine": C.machine(getattr(options, "device", "cpu")) if todo else None,
                  "commit": C.git_commit(), "options": json.loads(json.dumps(dataclasses.asdict(options), default=str))}

        def keep(arm: Arm, answer: dict) -> None:
            figures = answer["figures"]
            for row in figures if isinstance(figures, list) else [figures]:
                record = {"name": arm.name, **common, "date": C.timestamp(), **arm.labels, **row,
                          "worker": answer["worker"]}
                records.add(record)
                C.emit({k: v for k, v in record.items() if k not in ("machine", "options")})

        folder.mkdir(parents=True, exist_ok=True)
        failed = run_arms(name, todo, options.common.jobs, lambda arm: run_worker(name, arm, args, folder), keep)
        if hasattr(module, "finish"):
            module.finish(arms, options, folder)
    if not records.latest():
        hint = ": run it without --report first" if options.common.report else ""
        print(f"{name}: nothing yet in {records.path}{hint}", file=sys.stderr)
        return 1 if failed else 0
    C.write_text(page, module.report(records.latest(), folder))
    print(f"{name}: wrote {page}", file=sys.stderr)
    if failed:
        print(f"{name}: {failed} arm(s) failed (see above)", file=sys.stderr)
    return 1 if failed else 0


def ordered(arms: list[Arm]) -> list[Arm]:
    """The arms in their declared order, each moved after the arms it waits for (Arm.after); ValueError for a name
    not declared or a cycle."""
    names = {arm.name for arm in arms}
    if len(names) < len(arms):
        twice = sorted({arm.name for arm in arms if [a.name for a in arms].count(arm.name) > 1})
        raise ValueError(f"two arms are named {', '.join(twice)}: give each run its own folder name")
    for arm in arms:
        if unknown := [other for other in arm.after if other not in names]:
            raise ValueError(f"arm {arm.name} waits for {', '.join(unknown)}, which the experiment does not declare")
    placed: list[Arm] = []
    while len(placed) < len(arms):
        done = {arm.name for arm in placed}
        ready = [arm for arm in arms if arm.name not in done and done.issuperset(arm.after)]
        if not ready:
            raise ValueError("arms wait for each other in a cycle: "
                             + ", ".join(arm.name for arm in arms if arm.name not in done))
        placed.append(ready[0])
    return placed


def run_arms(name: str, todo: list[Arm], jobs: int, start: Callable[[Arm], dict],
             keep: Callable[[Arm, dict], None]) -> int:
    """Run the arms of `todo` (ordered()) `jobs` at a time, each once the arms it waits for are recorded, and keep()
    each answer as it comes; an arm that waits for one not recorded (failed, left out) is left out. How many failed."""
    unfinished = {arm.name for arm in todo}
    missing: set[str] = set()  # finished without a record
    pending, running, failed = list(todo), {}, 0
    with ThreadPoolExecutor(max(1, jobs)) as pool:
        while pending or running:
            for arm in list(pending):
                if lost := missing.intersection(arm.after):
                    print(f"{name}: {arm.name} left out: {', '.join(sorted(lost))} not recorded", file=sys.stderr)
                    pending.remove(arm)
                    unfinished.discard(arm.name)
                    missing.add(arm.name)
                elif len(running) < max(1, jobs) and not unfinished.intersection(arm.after):
                    pending.remove(arm)
                    running[pool.submit(start, arm)] = arm
            if pending and not running:
                raise RuntimeError(f"{name}: arms wait for arms not run before them (give run_arms ordered() arms)")
            finished: set[Future] = wait(running, return_when=FIRST_COMPLETED).done if running else set()
            for future in finished:
                arm, answer = running.pop(future), future.result()
                unfinished.discard(arm.name)
                if "error" in answer:
                    failed += answer["error"] != "not ready"
                    missing.add(arm.name)
                else:
                    keep(arm, answer)
    return failed


def keys(module: Experiment, arm: Arm) -> list:
    """The arm's KEY values (its labels must hold every KEY field)."""
    missing = [k for k in module.KEY if k not in arm.labels]
    if missing:
        raise ValueError(f"arm {arm.name}: its labels lack the key fields {missing}")
    return [arm.labels[k] for k in module.KEY]


def run_worker(name: str, arm: Arm, args: list[str], folder: Path) -> dict:
    """Run `arm` in a fresh process; its answer ({"figures", "worker"}), or {"error": ...}."""
    print(f"{name}: {arm.name}", file=sys.stderr, flush=True)
    payload = {"experiment": name, "args": args, "folder": str(folder), "arm": dataclasses.asdict(arm)}
    done = subprocess.run([sys.executable, str(MAIN), "--worker", json.dumps(payload)], stdout=subprocess.PIPE,
                          text=True, env=dict(os.environ, **arm.env))
    if done.returncode == NOT_READY:
        print(f"{name}: {arm.name} left out (see above)", file=sys.stderr)
        return {"error": "not ready"}
    lines = done.stdout.strip().splitlines()
    if done.returncode != 0 or not lines:
        print(f"{name}: {arm.name} failed (exit status {done.returncode}; its output is above)", file=sys.stderr)
        return {"error": f"exit status {done.returncode}"}
    return json.loads(lines[-1])


def worker(payload: dict) -> int:
    """In the arm's own process: run it and print one JSON line, its figures and the process's own facts."""
    module = experiment(payload["experiment"])
    options = tyro.cli(module.Options, args=payload["args"])
    arm = Arm(**{**payload["arm"], "after": tuple(payload["arm"]["after"])})
    if options.common.threads is not None:
        C.set_threads(options.common.threads)
    answer, sys.stdout = sys.stdout, sys.stderr  # what the run prints goes to stderr: stdout carries the answer
    started = time.perf_counter()
    try:
        figures = module.run(arm, options, Path(payload["folder"]))
    except NotReady as error:
        print(f"{payload['experiment']}: {arm.name}: {error}", file=sys.stderr)
        return NOT_READY
    finally:
        sys.stdout = answer
    facts = {"seconds": round(time.perf_counter() - started, 1), "peak_rss_mb": round(C.peak_rss_mb()),
             "env": {k: v for k, v in os.environ.items() if k.startswith("MCSPLAT_") or k in WORKER_ENV}}
    print(json.dumps({"figures": figures, "worker": facts}, default=_plain), flush=True)
    return 0


def _plain(value: Any) -> Any:
    """JSON for the values figures often hold: numpy scalars and arrays, paths."""
    if hasattr(value, "tolist"):
        return value.tolist()
    return str(value)
