"""Every GPU check of the project in one prepared command that fits a lent GPU machine's ten minutes.

    python benchmarks/gpu_session.py --lego PATH/lego --capture PATH/colmap_bird [--minutes 9.5] [--out DIR]
    python benchmarks/gpu_session.py --phases tests kernels ...     # some of the phases only
    .venv/bin/python benchmarks/gpu_session.py --dry-run             # on the CPU at toy sizes (the test suite runs it)

A GPU is rarely at hand, so nothing here may need a second try: each phase has a share of the time, is skipped (and
says so) when too little is left, and a failing phase is recorded and does not stop the others. Nothing is
downloaded: carry the wheels of warp-lang, tyro, docstring-parser, typeguard, plyfile, trimesh, pycolmap (for a
COLMAP capture) and gsplat, and the LPIPS weights. gsplat must be installed (its CUDA extension is built in the
background from the start, with nvcc and ninja) or the gsplat arms are skipped, saying why.

    tests     pytest --device cuda: the rasterizer and tile-kernel tests against the dense reference renderer on CUDA
              tensors, the fused SSIM, and a short training run
    parity    `mcsplat train` of the capture at a quarter of its size (30,000 steps, cap 62,500) on CUDA, beside the
              same run on the CPU (same seed): the test PSNR every 2,500 steps and the training PSNR along the way.
              The CPU arm takes far longer than a session, so by default its recorded log stands in for it
              (--parity-reference, results/gpu_session/cpu_reference); --parity-cpu runs it here as well
    kernels   the compositing kernels alone on the rasterizer benchmark's scene (100k and 300k at 800x800): the
              tile kernels, the tile backward without its skip of unused pairs, and the scalar kernels before them
    profile   step_profile.py on lego 400 at 300k: the GPU's busy time per step against the wall time, and what
              takes the device's and the host's time
    update    train_speed.py on lego 400 at 300k, the plain update against the fused one (the projection's backward
              applying Adam in one Warp kernel, optim/fused_projection_warp.py), each in a fresh process: whether
              the fused update should be CUDA's default too
    lego      mcsplat against gsplat 1.5.3 (gpu_vs_gsplat.py) on lego 400, cap 300k, 150k random points
    graph     the same with a third arm, mcsplat's step replayed as a CUDA graph (`train --cuda-graph`): its step
              time against the plain step's and gsplat's, and its test PSNR beside theirs (a large share of the
              time: three arms)
    capture   the same on a capture at full resolution, cap 1M, 500k random points
    collapse  the same from the capture's SfM points, 14,000 steps (the cap is reached before the end), with the
              share of dead Gaussians every 1,000 steps on each arm: does gsplat's MCMC also end with nearly all
              dead where mcsplat's `train` at 1M does (benchmarks/README.md, "GPU")?
    train     `mcsplat train CAPTURE --steps 30000 --cap-max 1000000 --eval-every 5000`, stopped at the deadline
              (SIGTERM: the run saves and stops); the steps reached, the minutes 30,000 steps would take at the last
              logged speed, and the test PSNR at each evaluation with the Gaussians MCMC found dead at the last
              relocation before it (its log.jsonl is copied to train_log.jsonl)
    agreement device_agreement.py on the runs the parity and train phases left: the image, the loss and every
              gradient of a step on CUDA (tile and scalar kernels) against the CPU's, on the same model and views

Figures go to --out (default benchmarks/results/gpu_session): results.jsonl (one record per phase, with the
machine) and results.md; each phase's output goes to <phase>.log there, the runs themselves to --runs.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro

import _common as C

REPO = Path(__file__).resolve().parents[1]
Phase = Literal["tests", "parity", "kernels", "profile", "update", "lego", "graph", "capture", "collapse", "train",
                "agreement"]
PHASES: tuple[Phase, ...] = typing.get_args(Phase)
# Share of the whole time each phase may take (what one phase leaves is free for the next), and the least it needs.
SHARES = {"tests": 0.1, "parity": 0.2, "kernels": 0.05, "profile": 0.1, "update": 0.1, "lego": 0.12,
          "graph": 0.3, "capture": 0.18, "collapse": 0.3, "train": 0.25, "agreement": 0.05}
LEAST_SECONDS = {"tests": 30, "parity": 60, "kernels": 20, "profile": 20, "update": 40, "lego": 60, "graph": 90,
                 "capture": 90, "collapse": 90, "train": 40, "agreement": 20}
# The training PSNR the parity phase reports at these steps (the log has it every 100 steps).
PARITY_STEPS = (100, 500, 1000, 2500, 5000, 10000, 15000, 20000, 25000, 30000)
# The lego and capture phases are the end-to-end training runs on the GPU (their test PSNR beside gsplat's).
TEST_FILES = ["tests/render/test_composite_tiles.py", "tests/render/test_render.py",
              "tests/render/test_warp_kernels.py", "tests/training/test_ssim_warp.py",
              "tests/training/test_fused_projection.py", "tests/training/test_graphed_step.py"]


@dataclass(frozen=True)
class Options:
    """Every GPU check of the project in one prepared command."""

    lego: Path | None = None
    """NeRF-Synthetic lego at 400x400 (transforms_*.json)."""
    capture: Path | None = None
    """A real capture at full resolution (COLMAP)."""
    minutes: float = 9.5
    """The whole session's time."""
    phases: tuple[Phase, ...] = PHASES
    """The phases to run (in their own order, whatever the order given)."""
    lego_steps: int = 3000
    """Training steps of the lego phase."""
    capture_steps: int = 3000
    """Training steps of the capture phase."""
    collapse_steps: int = 14_000
    """Training steps of the collapse phase."""
    parity_steps: int = 30_000
    """Training steps of each parity run."""
    parity_cpu: bool = False
    """Run the parity phase's CPU arm here too."""
    parity_reference: Path = C.RESULTS / "gpu_session" / "cpu_reference"
    """A recorded CPU run of the parity phase's command (its log.jsonl and metrics.json)."""
    out: Path | None = None
    """Results folder (default benchmarks/results/gpu_session)."""
    runs: Path | None = None
    """Where the training runs go (default: OUT/runs)."""
    dry_run: bool = False
    """On the CPU at toy sizes, tests only collected, no gsplat: checks the script itself."""


class Clock:
    def __init__(self, minutes: float) -> None:
        self.end = time.monotonic() + 60.0 * minutes
        self.total = 60.0 * minutes

    def left(self) -> float:
        return self.end - time.monotonic()

    def allowance(self, phase: str, remaining_phases: list[str]) -> float:
        """This phase's share of what is left, in proportion to the shares of the phases still to come."""
        shares = sum(SHARES[p] for p in remaining_phases)
        return self.left() * SHARES[phase] / shares


def run_logged(command: list[str], log: Path, seconds: float, env: dict | None = None) -> tuple[int, float]:
    """(exit code, seconds) of a command whose output goes to `log`; SIGTERM at the limit, SIGKILL 20 s later."""
    started = time.monotonic()
    with open(log, "a") as out:
        out.write(f"$ {' '.join(command)}\n")
        out.flush()
        process = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT, cwd=REPO,
                                   env={**os.environ, **(env or {})}, start_new_session=True)
        try:
            code = process.wait(timeout=max(1.0, seconds))
        except subprocess.TimeoutExpired:
            process.send_signal(signal.SIGTERM)
            try:
                code = process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                code = process.wait()
    return code, time.monotonic() - started


def tail_line(log: Path, starts: tuple[str, ...]) -> str | None:
    """The last line of the log that starts with one of `starts` (a test summary, say)."""
    found = None
    for line in log.read_text(errors="replace").splitlines():
        if line.lstrip("= ").startswith(starts) or any(s in line for s in starts):
            found = line.strip("= ").strip()
    return found


def phase_tests(args, seconds: float, log: Path) -> dict:
    device = "cpu" if args.dry_run else "cuda"
    command = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", f"--device={device}",
               *TEST_FILES] + (["--collect-only"] if args.dry_run else [])
    code, took = run_logged(command, log, seconds)
    summary = tail_line(log, (" passed", " failed", " error", "tests collected", "no tests ran"))
    return {"exit_code": code, "seconds": round(took, 1), "summary": summary}


def phase_kernels(args, seconds: float, log: Path) -> dict:
    sizes, resolution = (["2000"], "64") if args.dry_run else (["100000", "300000"], "800")
    command = [sys.executable, "benchmarks/rasterizer.py", "--device", "cpu" if args.dry_run else "cuda",
               "--sizes", *sizes, "--resolutions", resolution, "--repeats", "3" if args.dry_run else "20",
               "--no-baseline"] + ([] if args.dry_run else ["--cuda-kernels", "tile", "tile-all", "scalar"])
    code, took = run_logged(command, log, seconds)
    records = [json.loads(line) for line in log.read_text().splitlines() if line.startswith("{")]
    return {"exit_code": code, "seconds": round(took, 1), "records": records}


def phase_profile(args, seconds: float, log: Path) -> dict:
    """The plain step's profile, then the step replayed as a CUDA graph (under "graph")."""
    sizes = ["--cap", "4000", "--warm", "20", "--profiled", "5", "--device", "cpu"] if args.dry_run else \
        ["--cap", "300000", "--warm", "400", "--profiled", "30", "--device", "cuda"]
    code, took = run_logged([sys.executable, "benchmarks/step_profile.py", "--data", str(args.lego), *sizes,
                             "--both"], log, seconds)
    records = [json.loads(line) for line in log.read_text().splitlines() if line.startswith("{")]
    plain = [r for r in records if not r.get("cuda_graph")]
    graph = [r for r in records if r.get("cuda_graph")]
    return {"exit_code": code, "seconds": round(took, 1), **(plain[-1] if plain else {}),
            "graph": graph[-1] if graph else None}


def phase_update(args, seconds: float, log: Path, out: Path) -> dict:
    sizes = ["--device", "cpu", "--sizes", "1000", "--threads", "1", "--repeats", "1", "--plain", "2", "--warmup", "1",
             "--refines", "0"] if args.dry_run else \
        ["--device", "cuda", "--sizes", "300000", "--repeats", "20", "--plain", "20"]
    command = [sys.executable, "benchmarks/train_speed.py", "--scene", str(args.lego), *sizes, "--updates", "plain",
               "fused", "--out", str(out / "update")]
    code, took = run_logged(command, log, seconds)
    records = [json.loads(line) for line in log.read_text().splitlines() if line.startswith("{")]
    return {"exit_code": code, "seconds": round(took, 1),
            "step_ms": {f"{r['update']} #{k}": r["step_ms"] for k, r in enumerate(records)}}


def gsplat_available() -> bool:
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


class GsplatBuild:
    """gsplat compiles its CUDA extension at its first use (70-85 s on 16 cores): started in the background when the
    session starts, so that the tests and kernels phases pay for it, not the first comparison's time."""

    def __init__(self, out: Path) -> None:
        self.process = None
        if gsplat_available():
            env = {**os.environ, "TORCH_CUDA_ARCH_LIST": os.environ.get("TORCH_CUDA_ARCH_LIST", "9.0"),
                   "MAX_JOBS": os.environ.get("MAX_JOBS", "12")}
            with open(out / "gsplat_build.log", "w") as log:  # the child writes through its own copy
                self.process = subprocess.Popen([sys.executable, "-c", "from gsplat.cuda._backend import _C"],
                                                stdout=log, stderr=subprocess.STDOUT, env=env)

    def wait(self, seconds: float) -> str:
        """'built', 'failed (exit N)', 'still building' after `seconds`, or 'not installed'."""
        if self.process is None:
            return "not installed"
        try:
            code = self.process.wait(timeout=max(1.0, seconds))
        except subprocess.TimeoutExpired:
            return "still building"
        return "built" if code == 0 else f"failed (exit {code})"


def phase_compare(args, build: GsplatBuild | None, seconds: float, log: Path, data: Path, cap: int, init: int,
                  steps: int, timed: int, init_method: str, *extra: str, ours: tuple[str, ...] = ("mcsplat",)) -> dict:
    started = time.monotonic()
    built = "not asked" if build is None else build.wait(seconds / 2)
    seconds -= time.monotonic() - started
    arms = list(ours) + (["gsplat"] if built == "built" else [])
    out = args.runs / log.stem
    command = [sys.executable, "benchmarks/gpu_vs_gsplat.py", "--data", str(data), "--cap", str(cap),
               "--init", str(init), "--init-method", init_method, "--steps", str(steps), "--timed", str(timed),
               "--arms", *arms, "--out", str(out), "--device", "cpu" if args.dry_run else "cuda", *extra]
    code, took = run_logged(command, log, seconds)
    records = [json.loads(line) for line in log.read_text().splitlines() if line.startswith("{")]
    result = {"exit_code": code, "seconds": round(took, 1), "arms": arms, "records": records,
              "note": None if "gsplat" in arms or args.dry_run else f"gsplat {built}: mcsplat alone"}
    by_arm = {r["arm"]: r for r in records}
    for arm, suffix in (("mcsplat", ""), ("mcsplat-graph", "_graph")):
        if arm in by_arm and "gsplat" in by_arm:
            ours, theirs = by_arm[arm], by_arm["gsplat"]
            result["step_ratio" + suffix] = round(ours["median_step_ms"] / theirs["median_step_ms"], 3)
            result["memory_ratio" + suffix] = round(ours["peak_gpu_mb"] / theirs["peak_gpu_mb"], 3)
            result["psnr_difference" + suffix] = round(ours["psnr"] - theirs["psnr"], 3)
    if "mcsplat" in by_arm and "mcsplat-graph" in by_arm:  # the graph against the plain step, same session
        plain, graph = by_arm["mcsplat"], by_arm["mcsplat-graph"]
        result["graph_step_ratio"] = round(graph["median_step_ms"] / plain["median_step_ms"], 3)
        result["graph_psnr_difference"] = round(graph["psnr"] - plain["psnr"], 3)
    return result


def train_command(args, run: Path, device: str, steps: int, cap: int, eval_every: int, *extra: str) -> list[str]:
    return [sys.executable, "-m", "mcsplat.cli", "train", str(args.capture), "--out", str(run), "--overwrite",
            "--steps", str(steps), "--cap-max", str(cap), "--eval-every", str(eval_every), "--quiet",
            "--save-every", "0", "--device", device, "--lpips-net", "alex", *extra]


def run_log(run: Path) -> list[dict]:
    log_file = run / "log.jsonl"
    if not log_file.exists():
        return []
    return [json.loads(line) for line in log_file.read_text().splitlines() if line.strip()]


def evaluations(run: Path) -> list[dict]:
    """The test PSNR at each evaluation of a run (its log, then the final one in metrics.json), with the step, the
    Gaussians then and how many of them were dead at the last relocation (MCMC moves every Gaussian below the dead
    opacity)."""
    found = [{"step": r["step"], "test_psnr": r["test_psnr"], "num_gaussians": r["num_gaussians"],
              "relocated": r.get("relocated")} for r in run_log(run) if "test_psnr" in r]
    metrics = run / "metrics.json"
    if metrics.exists():
        final = json.loads(metrics.read_text())
        found.append({"step": final["steps"], "test_psnr": round(final["psnr"], 3),
                      "num_gaussians": final["num_gaussians"], "relocated": None})
    return found


def train_psnr_at(run: Path, steps: tuple[int, ...]) -> dict[str, float]:
    """The logged training PSNR at each of `steps` the run reached."""
    logged = {r["step"]: r["train_psnr"] for r in run_log(run) if "train_psnr" in r}
    return {str(step): logged[step] for step in steps if step in logged}


def parity_arm(run: Path, code: int, took: float, steps: tuple[int, ...]) -> dict:
    return {"exit_code": code, "seconds": round(took, 1), "evaluations": evaluations(run),
            "train_psnr": train_psnr_at(run, steps)}


def phase_parity(args, seconds: float, log: Path) -> dict:
    """The CUDA path's training against the CPU's: a quarter-size run of the capture, the same seed, on each device
    (the CPU's from its recorded run unless --parity-cpu). Their test PSNR should agree to run-to-run noise (a few
    tenths of a dB), and their training PSNR early on closely; a CUDA run far below points at a kernel or a
    synchronisation that only the GPU has."""
    steps, cap, every, downscale = (20, 2000, 10, "2") if args.dry_run else (args.parity_steps, 62_500, 2500, "4")
    marks = (10, 20) if args.dry_run else PARITY_STEPS
    result: dict = {"steps": steps, "cap": cap, "downscale": int(downscale)}
    started = time.monotonic()
    devices = ("cuda", "cpu") if args.parity_cpu or args.dry_run else ("cuda",)
    for device in devices:
        run = args.runs / f"parity_{device}"
        left = seconds - (time.monotonic() - started)
        code, took = run_logged(train_command(args, run, "cpu" if args.dry_run else device, steps, cap, every,
                                              "--downscale", downscale), log, left / (len(devices) if device == "cuda"
                                                                                      else 1))
        result[f"on_{device}"] = parity_arm(run, code, took, marks)
    if "on_cpu" not in result and args.parity_reference and (args.parity_reference / "log.jsonl").exists():
        result["on_cpu"] = {**parity_arm(args.parity_reference, 0, 0.0, marks), "recorded": True}
    runs = [result[f"on_{d}"] for d in ("cuda", "cpu") if f"on_{d}" in result]
    result["exit_code"] = max(run["exit_code"] for run in runs)
    last = [run["evaluations"][-1]["test_psnr"] if run["evaluations"] else None for run in runs]
    if len(last) == 2 and None not in last:
        result["psnr_cuda_minus_cpu"] = round(last[0] - last[1], 3)
    return result


def phase_train(args, seconds: float, log: Path) -> dict:
    run = args.runs / "train_run"
    steps, cap, every = (30, 3000, 10) if args.dry_run else (30_000, 1_000_000, 5000)
    code, took = run_logged(train_command(args, run, "cpu" if args.dry_run else "cuda", steps, cap, every), log,
                            seconds)
    result = {"exit_code": code, "seconds": round(took, 1), "steps_asked": steps}
    records = run_log(run)
    if records:
        C.write_text(log.parent / "train_log.jsonl", (run / "log.jsonl").read_text())
        result["evaluations"] = evaluations(run)
        last = records[-1]
        result.update(steps_reached=last["step"], train_seconds=last["elapsed_seconds"],
                      num_gaussians=last["num_gaussians"], train_psnr=last.get("train_psnr"))
        if len(records) >= 2:
            before = records[-2]
            ms = 1000 * (last["elapsed_seconds"] - before["elapsed_seconds"]) / max(1, last["step"] - before["step"])
            result["last_ms_per_step"] = round(ms, 2)
            result["minutes_for_all_steps"] = round((last["elapsed_seconds"] + (steps - last["step"]) * ms / 1000) / 60,
                                                    1)
    metrics = run / "metrics.json"
    if metrics.exists():
        result["metrics"] = {k: v for k, v in json.loads(metrics.read_text()).items()
                             if k in ("psnr", "ssim", "lpips", "steps", "train_seconds", "num_gaussians")}
    return result


def phase_agreement(args, seconds: float, log: Path) -> dict:
    """device_agreement.py on the runs of this session that left a checkpoint."""
    runs = [run for run in (args.runs / "parity_cuda", args.runs / "train_run") if (run / "checkpoint.pt").exists()]
    if not runs:
        return {"exit_code": 0, "seconds": 0.0, "runs": []}
    command = [sys.executable, "benchmarks/device_agreement.py", *map(str, runs),
               "--views", "2" if args.dry_run else "3"]
    code, took = run_logged(command, log, seconds)
    records = [json.loads(line) for line in log.read_text().splitlines() if line.startswith("{")]
    summaries = [r for r in records if r.get("summary")]
    return {"exit_code": code, "seconds": round(took, 1), "runs": [str(r) for r in runs], "summaries": summaries,
            "records": [r for r in records if not r.get("summary")]}


def run_phase(name: str, args, build: GsplatBuild | None, seconds: float, log: Path) -> dict:
    """Run one phase (gsplat's `build` for the phases that compare with it, None in a dry run)."""
    if name == "tests":
        return phase_tests(args, seconds, log)
    if name == "parity":
        return phase_parity(args, seconds, log)
    if name == "agreement":
        return phase_agreement(args, seconds, log)
    if name == "kernels":
        return phase_kernels(args, seconds, log)
    if name == "profile":
        return phase_profile(args, seconds, log)
    if name == "update":
        return phase_update(args, seconds, log, log.parent)
    if name == "lego":
        steps, timed = (20, 10) if args.dry_run else (args.lego_steps, 1000)
        cap = 3000 if args.dry_run else 300_000
        return phase_compare(args, build, seconds, log, args.lego, cap, cap // 2, steps, timed, "auto")
    if name == "graph":
        steps, timed = (20, 10) if args.dry_run else (args.lego_steps, 1000)
        cap = 3000 if args.dry_run else 300_000
        return phase_compare(args, build, seconds, log, args.lego, cap, cap // 2, steps, timed, "auto",
                             ours=("mcsplat", "mcsplat-graph"))
    if name == "capture":
        steps, timed = (20, 10) if args.dry_run else (args.capture_steps, 500)
        cap = 3000 if args.dry_run else 1_000_000
        return phase_compare(args, build, seconds, log, args.capture, cap, cap // 2, steps, timed, "random")
    if name == "collapse":
        steps, timed = (30, 10) if args.dry_run else (args.collapse_steps, 500)
        cap = 3000 if args.dry_run else 1_000_000
        return phase_compare(args, build, seconds, log, args.capture, cap, cap // 2, steps, timed, "auto",
                             "--dead-every", "10" if args.dry_run else "1000")
    return phase_train(args, seconds, log)


def write_page(out: Path, records: list[dict]) -> str:
    lines = ["| phase | seconds | result |", "|---|---|---|"]
    for r in records:
        if r.get("skipped"):
            result = f"skipped: {r['skipped']}"
        elif r["phase"] == "tests":
            result = f"{r.get('summary')} (exit {r['exit_code']})"
        elif r["phase"] == "parity":
            result = "; ".join(f"{d}{' (recorded)' if r[f'on_{d}'].get('recorded') else ''} "
                               + ", ".join(f"{e['test_psnr']:.2f}" for e in r[f"on_{d}"]["evaluations"])
                               + " dB" for d in ("cuda", "cpu") if f"on_{d}" in r)
            if "psnr_cuda_minus_cpu" in r:
                result += f"; CUDA - CPU {r['psnr_cuda_minus_cpu']:+.2f} dB"
            result += f" (exit {r['exit_code']})"
        elif r["phase"] == "kernels":
            result = "; ".join(
                f"{k['gaussians']:,} at {k['image']}: fwd {k['composite_forward_ms']} / bwd {k['composite_backward_ms']} ms"
                + "".join(f", {v} {k.get(v + '_composite_forward_ms')} / {k.get(v + '_composite_backward_ms')}"
                          for v in ("tile-all", "scalar") if v + "_composite_forward_ms" in k)
                for k in r.get("records", []))
        elif r["phase"] == "agreement":
            result = "; ".join(f"{Path(x['run']).name} at step {x['step']}: worst relative gradient error "
                               + ", ".join(f"{path} {error:.1e}" for path, error in x["worst_relative_error"].items())
                               for x in r.get("summaries", [])) + f" (exit {r['exit_code']})"
        elif r["phase"] == "profile":
            keys = ("gaussians", "wall_ms_per_step", "gpu_busy_ms_per_step", "host_op_ms_per_step",
                    "kernel_launches_per_step", "torch_ops_per_step", "warp_launches_per_step")
            result = ", ".join(f"{k} {r[k]}" for k in keys if k in r)
            if r.get("graph"):
                result += "; as a CUDA graph: " + ", ".join(f"{k} {r['graph'][k]}" for k in keys if k in r["graph"])
            result += f" (exit {r['exit_code']})"
        elif r["phase"] == "update":
            result = ", ".join(f"{name} {ms} ms" for name, ms in r.get("step_ms", {}).items())
            result += f" (exit {r['exit_code']})"
        elif r["phase"] in ("lego", "graph", "capture", "collapse"):
            arms = "; ".join(f"{a['arm']} {a['median_step_ms']:.2f} ms, {a['peak_gpu_mb']:.0f} MB, {a['psnr']:.2f} dB"
                             + (", dead " + " ".join(f"{100 * v:.0f}%" for v in a["dead_share"].values())
                                if r["phase"] == "collapse" else "")
                             for a in r.get("records", []))
            ratio = f"; step {r['step_ratio']}x, memory {r['memory_ratio']}x, PSNR {r['psnr_difference']:+.2f} dB" \
                if "step_ratio" in r else ""
            if "graph_step_ratio" in r:
                ratio += f"; graph / plain step {r['graph_step_ratio']}x, PSNR {r['graph_psnr_difference']:+.2f} dB"
            result = arms + ratio + (f" ({r['note']})" if r.get("note") else "") + f" (exit {r['exit_code']})"
        else:
            result = ", ".join(f"{k} {r[k]}" for k in ("steps_reached", "num_gaussians", "last_ms_per_step",
                                                        "minutes_for_all_steps", "train_psnr") if k in r)
            result += "".join(f"; test {e['test_psnr']:.2f} dB at {e['step']}" for e in r.get("evaluations", []))
            result += f" (exit {r['exit_code']})"
        lines.append(f"| {r['phase']} | {r.get('seconds', 0)} | {result} |")
    table = "\n".join(lines)
    C.write_text(out / "results.md", table + "\n")
    return table


def main() -> None:
    args = tyro.cli(Options, description=__doc__)
    if args.dry_run:
        demo = REPO / "data" / "lego_demo"
        args = dataclasses.replace(args, lego=args.lego or demo, capture=args.capture or demo)
    elif not args.lego or not args.capture:
        sys.exit("gpu_session.py: error: --lego and --capture are needed (or --dry-run)")
    out = C.results_dir("gpu_session", args.out)
    args = dataclasses.replace(args, runs=args.runs or out / "runs")
    clock = Clock(args.minutes)
    # gsplat's build takes 12 cores for a minute or more: only for the phases that compare with it.
    compares = {"lego", "graph", "capture", "collapse"} & set(args.phases)
    build = GsplatBuild(out) if compares and not args.dry_run else None
    info = C.machine("cpu" if args.dry_run else "cuda")
    print(C.machine_line(info), flush=True)
    records = []
    phases = [p for p in PHASES if p in args.phases]
    for index, name in enumerate(phases):
        seconds = clock.allowance(name, phases[index:])
        record = {"phase": name, "dry_run": args.dry_run, "started": C.timestamp()}
        if seconds < LEAST_SECONDS[name] * (0.1 if args.dry_run else 1.0):
            record["skipped"] = f"{seconds:.0f} s left for it, it needs {LEAST_SECONDS[name]} s"
        else:
            log = out / f"{name}.log"
            log.write_text("")
            try:
                record.update(run_phase(name, args, build, seconds, log))
            except Exception as error:  # a broken phase is a finding; the others still run
                record["error"] = f"{type(error).__name__}: {error}"
        record.update(info)
        print(json.dumps(record), flush=True)
        records.append(record)
        C.append_jsonl(out / "results.jsonl", [record])
    print(write_page(out, records), flush=True)


if __name__ == "__main__":
    main()
