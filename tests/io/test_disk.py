"""A full disk and a read-only file system: every command ends in one line that names the folder (and the space a
full disk lacked), and nothing written before is lost. The disks are tmpfs mounts in a namespace of the test's own
(helpers.on_a_small_disk)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from tests.support.helpers import on_a_small_disk, small_disks_work

# Runs inside the namespace: each command through the CLI's main(), what it printed on stderr kept.
COMMANDS = """
import contextlib, io, json, sys
from mcsplat.cli import main
from mcsplat.io.checkpoint import load_checkpoint
disk = sys.argv[1]
results = {}
for name, args in json.loads(sys.argv[2]):
    if name == "fill":  # what the commands before left free, taken
        with contextlib.suppress(OSError), open(f"{disk}/filler", "ab") as f:
            while True:
                f.write(bytes(1 << 16))
                f.flush()
        continue
    stderr = io.StringIO()
    with contextlib.redirect_stderr(stderr):
        code = main(args)
    results[name] = [code, stderr.getvalue()]
with contextlib.suppress(Exception):
    results["checkpoint step"] = load_checkpoint(f"{disk}/run/checkpoint.pt")["step"]
import os
results["files"] = sorted(os.path.relpath(os.path.join(d, f), disk) for d, _, fs in os.walk(disk) for f in fs)
print(json.dumps(results))
"""


@pytest.fixture
def disk(tmp_path) -> Path:
    if not small_disks_work(tmp_path / "probe"):
        pytest.skip("cannot mount a tmpfs in a user namespace here (unshare --user --mount)")
    return tmp_path / "disk"


def photos(cup: Path, folder: Path) -> Path:
    folder.mkdir()
    for path in sorted(cup.glob("*.jpg"))[:3]:
        shutil.copyfile(path, folder / path.name)
    return folder


def run_commands(disk: Path, options: str, commands: list) -> dict:
    done = on_a_small_disk(disk, options, COMMANDS, str(disk), json.dumps(commands))
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.splitlines()[-1])


def assert_one_line_error(result: list, expected: str) -> None:
    code, stderr = result
    last = stderr.strip().splitlines()[-1] if stderr.strip() else ""
    assert code == 2 and "Traceback" not in stderr and "@ 0x" not in stderr, stderr[-3000:]
    assert last.startswith(f"mcsplat: error: {expected}"), stderr[-3000:]


def test_a_full_disk_ends_each_command_in_one_line_and_loses_nothing(disk, mini_demo, tiny_run, shared_data,
                                                                   tmp_path):
    """3 MB: room for the first checkpoint (2.2 MB) and not for the second; then the disk is filled."""
    train = ["train", str(mini_demo), "--out", f"{disk}/run", "--steps", "30", "--save-every", "10", "--quiet",
             "--model.num-init-points", "3000", "--lpips-net", "alex", "--save-every-minutes", "0",
             "--no-scale-schedule"]
    cup = photos(shared_data / "colmap_cup" / "images", tmp_path / "photos")
    results = run_commands(disk, "size=3m", [
        ["train", train],
        ["fill", []], ["export", ["export", str(tiny_run), "--out", f"{disk}/x.ply"]],
        ["fill", []], ["eval", ["eval", f"{disk}/run", "--save-renders"]],
        ["fill", []], ["process", ["process", str(cup), "--out", f"{disk}/scene", "--threads", "1"]]])
    assert_one_line_error(results["train"], f"no space left on the device of {disk}/run (about 2.")
    assert results["checkpoint step"] == 10, "the first checkpoint is kept whole"
    for name in ("export", "eval", "process"):
        assert_one_line_error(results[name], f"no space left on the device of {disk}")
    assert results["files"] == ["filler", "run/checkpoint.prev.pt", "run/checkpoint.pt", "run/config.json"], \
        "no half-written file, lock or partial work is left behind"


def test_a_read_only_file_system_ends_each_command_in_one_line(disk, mini_demo, shared_data, tmp_path):
    results = run_commands(disk, "ro", [
        ["process", ["process", str(photos(shared_data / "colmap_cup" / "images", tmp_path / "photos")), "--out",
                     f"{disk}/scene"]],
        ["train", ["train", str(mini_demo), "--out", f"{disk}/run", "--quiet"]]])
    for name in ("process", "train"):
        assert_one_line_error(results[name], f"cannot write to {disk}: it is on a read-only file system")
