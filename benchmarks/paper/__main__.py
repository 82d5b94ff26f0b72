"""Run every experiment of the paper's claims at one scale, then write docs/paper.md.

    .venv/bin/python -m benchmarks.paper --scale cpu             # everything (hours on 2 cores); resumable
    .venv/bin/python -m benchmarks.paper --scale gpu             # on a machine with an NVIDIA GPU (mcsplat takes it)
    .venv/bin/python -m benchmarks.paper --scale cpu --list      # the runs and whether they are done
    .venv/bin/python -m benchmarks.paper --report                # docs/paper.md from the records, train nothing

Runs are trained one at a time, in this process: run nothing else on the machine (the time claim compares step
times). After the seed-0 pass, every comparison closer than 0.3 dB, or closer than its baseline's own seeds are to
each other, is run again with seeds 1 and 2 (--no-extra-seeds skips that); the page reports the mean over the seeds a
comparison has.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import argparse
import sys

import _common as C

from .experiments import SCALES, Run, comparisons, runs
from .runner import NotReady, Records, short, train_run


def results_folder(scale: str):
    return C.results_dir(f"paper/{scale}")


def seed_spread(records: Records, run: Run, seeds) -> float:
    """How far apart the PSNRs of a run's seeds are (0 until it has more than one)."""
    found = [r["psnr"] for r in (records.get(run.with_seed(seed).name) for seed in (0, *seeds)) if r]
    return max(found) - min(found) if len(found) > 1 else 0.0


def extra_seed_runs(scale, records: Records) -> list[Run]:
    """Seeds 1 and 2 of both sides of every comparison whose seed-0 PSNRs are closer than scale.close_db, or closer
    than the baseline's own seeds are to each other (then one seed of the variant settles nothing)."""
    out: dict[str, Run] = {}
    for row in comparisons(scale):
        base, variant = records.get(row.baseline.name), records.get(row.variant.name)
        close = max(scale.close_db, seed_spread(records, row.baseline, scale.extra_seeds))
        if base and variant and abs(base["psnr"] - variant["psnr"]) < close:
            for run in (row.baseline, row.variant):
                for seed in scale.extra_seeds:
                    out.setdefault(run.with_seed(seed).name, run.with_seed(seed))
    return list(out.values())


def train_all(todo: list[Run], scale, records: Records, machine: dict) -> int:
    """Train the runs not yet recorded; returns how many were left out (NotReady: an option this checkout lacks, or
    a cap that comes from a run not trained yet)."""
    left_out = 0
    for i, run in enumerate(todo, 1):
        if records.get(run.name):
            continue
        print(f"[{i}/{len(todo)}] {run.name}", file=sys.stderr, flush=True)
        try:
            record = train_run(run, scale, results_folder(scale.name), records, machine)
        except NotReady as error:
            print(f"  left out: {error}", file=sys.stderr)
            left_out += 1
            continue
        print("  " + short(record), file=sys.stderr, flush=True)
    return left_out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scale", choices=sorted(SCALES), default="cpu")
    parser.add_argument("--only", nargs="*", default=None, help="run only the runs whose name contains one of these")
    parser.add_argument("--list", action="store_true", help="list the runs and whether they are recorded")
    parser.add_argument("--report", action="store_true", help="only write docs/paper.md from the records")
    parser.add_argument("--no-extra-seeds", action="store_true", help="no seeds 1 and 2 for close comparisons")
    parser.add_argument("--threads", type=int, default=None, help="CPU threads (default: all cores)")
    args = parser.parse_args()
    from .page import write_page

    scale = SCALES[args.scale]
    records = Records(results_folder(scale.name))
    todo = runs(scale)
    if args.only is not None:
        todo = [r for r in todo if any(part in r.name for part in args.only)]
    if args.list:
        for run in todo + extra_seed_runs(scale, records):
            record = records.get(run.name)
            print(f"{run.name:48s} {'-' if record is None else short(record)}")
        return
    if not args.report:
        C.warn_if_busy()
        C.set_threads(args.threads)
        machine = C.machine("cuda" if scale.name == "gpu" else "cpu")
        left_out = train_all(todo, scale, records, machine)
        if not args.no_extra_seeds:
            extra = [r for r in extra_seed_runs(scale, records)
                     if args.only is None or any(part in r.name for part in args.only)]
            left_out += train_all(extra, scale, records, machine)
        if left_out:
            print(f"{left_out} runs left out (see above)", file=sys.stderr)
    print(f"wrote {write_page()}", file=sys.stderr)


if __name__ == "__main__":
    main()
