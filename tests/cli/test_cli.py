"""The `mcsplat` command: `info` prints the scene summary; user errors are one line on stderr with exit status 2."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from mcsplat.cli import main

REPO = Path(__file__).resolve().parents[2]
DEMO = REPO / "data" / "lego_demo"


def test_info_prints_the_summary(capsys: pytest.CaptureFixture) -> None:
    assert main(["info", str(DEMO)]) == 0
    out = capsys.readouterr().out
    assert "blender" in out and "100 train, 25 test" in out and "200x200" in out and "white" in out
    assert "radius" in out and "points" in out


def test_info_options(capsys: pytest.CaptureFixture) -> None:
    assert main(["info", str(DEMO), "--downscale", "4", "--background", "black"]) == 0
    out = capsys.readouterr().out
    assert "50x50" in out and "black" in out


def test_missing_path_is_one_line_and_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["info", str(tmp_path / "nowhere")]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("mcsplat: error: ") and captured.err.count("\n") == 1
    assert str(tmp_path / "nowhere") in captured.err


def test_bad_option_value_is_one_line(capsys: pytest.CaptureFixture) -> None:
    assert main(["info", str(DEMO), "--downscale", "0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("mcsplat: error: downscale") and err.count("\n") == 1


def test_console_script(tmp_path: Path) -> None:
    """The installed command, as a user runs it: help, a summary, an error without traceback, no banners."""
    script = Path(sys.executable).parent / "mcsplat"
    command = [str(script)] if script.exists() else [sys.executable, "-m", "mcsplat.cli"]
    helped = subprocess.run([*command, "--help"], capture_output=True, text=True, timeout=120)
    assert helped.returncode == 0 and "info" in helped.stdout and "MCMC" in helped.stdout
    ok = subprocess.run([*command, "info", str(DEMO)], capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0 and "100 train, 25 test" in ok.stdout
    assert ok.stderr == ""  # nothing else printed: no Warp banner, no warnings
    bad = subprocess.run([*command, "info", str(tmp_path / "missing")], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and bad.stdout == ""
    assert bad.stderr.startswith("mcsplat: error: ") and bad.stderr.count("\n") == 1 and "Traceback" not in bad.stderr


def test_warnings_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A transforms.json frame whose image is missing is skipped with a one-line warning naming it."""
    meta = json.loads((DEMO / "transforms_train.json").read_text())
    meta["frames"] = meta["frames"][:4]
    for i, frame in enumerate(meta["frames"]):
        if i < 3:  # the image of frame 3 is left out
            shutil.copyfile(DEMO / (frame["file_path"].removeprefix("./") + ".png"), tmp_path / f"{i}.png")
        frame["file_path"] = f"{i}.png"
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    assert main(["info", str(tmp_path), "--test-every", "0"]) == 0
    captured = capsys.readouterr()
    assert "3 train, 0 test" in captured.out
    assert captured.err.startswith("mcsplat: warning: ") and captured.err.count("\n") == 1 and "3.png" in captured.err


def test_info_says_how_train_starts_a_scene_without_points(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A capture with poses and no points is triangulated by `train`, a synthetic scene starts from random points:
    `info` says which."""
    from tests.support.helpers import demo_photos_scene

    root, _ = demo_photos_scene(tmp_path / "photos", 8)
    assert main(["info", str(root)]) == 0
    points = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("points:"))
    assert "triangulates them from the known poses" in points and "random initialisation" not in points, points
    assert main(["info", str(DEMO)]) == 0
    points = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("points:"))
    assert "random" in points and "synthetic" in points, points
