"""The prepared GPU session (benchmarks/gpu_session.py) runs end to end on the CPU at toy sizes, so that the one
command a lent GPU machine gets is known to work before a GPU is at hand."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_the_gpu_session_dry_run_completes_every_phase(tmp_path):
    out = tmp_path / "session"
    done = subprocess.run([sys.executable, str(REPO / "benchmarks" / "gpu_session.py"), "--dry-run", "--minutes", "5",
                           "--out", str(out)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    records = {r["phase"]: r for r in map(json.loads, (out / "results.jsonl").read_text().splitlines())}
    assert list(records) == ["tests", "parity", "kernels", "profile", "update", "lego", "graph", "capture",
                             "collapse", "train", "agreement"]
    for name, record in records.items():
        assert record["dry_run"] and "skipped" not in record and "error" not in record, (name, record)
        assert record["exit_code"] == 0, (name, (out / f"{name}.log").read_text()[-2000:])
    assert "tests collected" in records["tests"]["summary"]
    assert records["kernels"]["records"][0]["composite_forward_ms"] > 0
    assert records["profile"]["wall_ms_per_step"] > 0 and records["profile"]["host_op_ms_per_step"] > 0
    assert records["profile"]["graph"]["cuda_graph"] and records["profile"]["graph"]["torch_ops_per_step"] > 0
    steps = records["update"]["step_ms"]  # the plain update, then the fused one
    assert [name.split(" (")[0] for name in steps] == ["plain", "fused"] and all(ms > 0 for ms in steps.values())
    for name in ("lego", "capture", "collapse"):
        (arm,) = records[name]["records"]
        assert arm["arm"] == "mcsplat" and arm["steps"] == (30 if name == "collapse" else 20) and arm["psnr"] > 5
    plain, graph = records["graph"]["records"]  # on the CPU the graph's arm runs its steps as they are: the same
    assert (plain["arm"], graph["arm"]) == ("mcsplat", "mcsplat-graph") and graph["psnr"] == plain["psnr"] > 5
    assert records["graph"]["graph_psnr_difference"] == 0
    dead = records["collapse"]["records"][0]["dead_share"]  # every 10 steps in the dry run
    assert list(dead) == ["10", "20", "30"] and all(0 <= share < 1 for share in dead.values())
    assert records["train"]["steps_reached"] == 30 and records["train"]["metrics"]["psnr"] > 5
    assert [e["step"] for e in records["train"]["evaluations"]] == [10, 20, 30]  # the last from metrics.json
    assert (out / "train_log.jsonl").exists()
    parity = records["parity"]
    for device in ("cuda", "cpu"):  # both on the CPU in the dry run
        assert [e["step"] for e in parity[f"on_{device}"]["evaluations"]] == [10, 20], parity
    # The dry run trains the same seed twice on one device: the two runs agree (the CPU path is deterministic).
    assert parity["psnr_cuda_minus_cpu"] == 0
    assert parity["on_cuda"]["train_psnr"] == parity["on_cpu"]["train_psnr"] and parity["on_cuda"]["train_psnr"]
    # The agreement phase compares the two runs' models on the CPU with itself: no difference at all.
    agreement = records["agreement"]
    assert [Path(run).name for run in agreement["runs"]] == ["parity_cuda", "train_run"]
    assert [s["worst_relative_error"] for s in agreement["summaries"]] == [{"cpu": 0.0}, {"cpu": 0.0}]
    assert all(r["params.means"]["only_here"] == 0 for r in agreement["records"])
    page = (out / "results.md").read_text()
    assert page.count("\n") == 13 and "| update |" in page and "| train |" in page and "| agreement |" in page
