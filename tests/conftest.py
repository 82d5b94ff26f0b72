"""Shared fixtures: where the real datasets are (../shared/data next to the repository), and writable copies."""

from __future__ import annotations

import mcsplat  # noqa: F401  (before torch: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)
import json
import os
import shutil
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The folder of real datasets that CI clones next to the repository; the test is skipped without it."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real datasets not found at {SHARED_DATA} (clone shared/ next to the repository)")
    return SHARED_DATA


def writable_copy(source: Path, target: Path) -> Path:
    """Copy a (possibly read-only) folder tree to `target` so that tests can damage the copy."""
    shutil.copytree(source, target, copy_function=shutil.copyfile)
    for folder, _, _ in os.walk(target):
        os.chmod(folder, 0o755)
    return target


@pytest.fixture
def copy_shared(shared_data: Path, tmp_path: Path):
    """copy_shared("colmap_bird") -> a writable copy of shared/data/colmap_bird under tmp_path."""

    def copy(relative: str) -> Path:
        return writable_copy(shared_data / relative, tmp_path / Path(relative).name)

    return copy


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory) -> Path:
    """A short training run of the bundled demo scene (60 steps, one evaluation on the way), shared by the tests
    of export, report and viewer."""
    from mcsplat.config import ModelConfig, TrainConfig
    from mcsplat.strategy.mcmc import MCMCConfig
    from mcsplat.train import train

    run = tmp_path_factory.mktemp("tiny") / "run"
    train(TrainConfig(data=REPO / "data" / "lego_demo", out=run, steps=60, quiet=True, lpips_net="alex",
                      eval_every=30, save_every=0, model=ModelConfig(num_init_points=2000), scale_schedule=False,
                      mcmc=MCMCConfig(cap_max=2400, refine_start=20, refine_every=20)))
    return run


@pytest.fixture(scope="session")
def mini_demo(tmp_path_factory) -> Path:
    """The demo scene cut to 12 training and 3 test views: a short run of it ends (evaluation, report) in seconds."""
    root, demo = tmp_path_factory.mktemp("mini") / "lego", REPO / "data" / "lego_demo"
    for split, count in (("train", 12), ("test", 3)):
        meta = json.loads((demo / f"transforms_{split}.json").read_text())
        meta["frames"] = meta["frames"][:count]
        (root / split).mkdir(parents=True)
        for frame in meta["frames"]:
            name = Path(frame["file_path"]).name + ".png"
            shutil.copyfile(demo / split / name, root / split / name)
        (root / f"transforms_{split}.json").write_text(json.dumps(meta))
    return root


def pytest_addoption(parser):
    parser.addoption("--device", choices=("cpu", "cuda"), default="cpu",
                     help="where the rasterizer and kernel tests put their tensors (cuda: run them on a GPU machine)")


@pytest.fixture(scope="session")
def device(request) -> torch.device:
    """The device of `pytest --device` (cpu by default); tests that take it check the kernels there."""
    name = request.config.getoption("--device")
    if name == "cuda" and not torch.cuda.is_available():
        pytest.fail("--device cuda: no CUDA device is available here", pytrace=False)
    return torch.device(name)


# The longest files (minutes of multi-process training) first: with two workers taking a file each (`make test`),
# a long file handed out last would leave one worker idle while the other finishes it.
LONGEST_FIRST = ("test_distributed.py", "test_train_e2e.py")


def pytest_collection_modifyitems(config, items):
    def rank(item):
        name = item.path.name
        return LONGEST_FIRST.index(name) if name in LONGEST_FIRST else len(LONGEST_FIRST)
    items.sort(key=rank)  # stable: the order within a file, and of the other files, is kept
    if config.getoption("--device") == "cuda":
        # On a GPU machine only the tests that take the device: the others are the CPU's, which CI runs, and a lent
        # GPU's minutes are few (16 of the 108 tests of gpu_session.py's tests phase).
        cpu_only = [item for item in items if "device" not in getattr(item, "fixturenames", ())]
        if cpu_only:
            config.hook.pytest_deselected(items=cpu_only)
            items[:] = [item for item in items if "device" in getattr(item, "fixturenames", ())]
