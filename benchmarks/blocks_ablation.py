"""What the choices of a block plan cost, on a small run: the share of outside points a block starts from
(partition/scene.py OUTSIDE_SHARE), the margin, and the number of blocks, against one run at the same cap.

    .venv/bin/python benchmarks/blocks_ablation.py              # the cup at a quarter size, 1,500 steps, cap 30k

Each arm trains in this process, the blocks one after another (all the cores each), and is scored as merged on all
the scene's test views. Columns: psnr (merged), gaussians (merged), own_psnr (each block's run on its own test
views, with all its Gaussians), seconds. Writes results/blocks_ablation/results.{jsonl,md}.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import json
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

import _common as C

ARMS = [  # (blocks, margin, outside share); 1 block is the one run
    (1, None, None), (2, 0.2, 0.1), (2, 0.2, 0.0), (2, 0.2, 1.0), (4, 0.2, 0.1), (4, 0.4, 0.1)]


@dataclass(frozen=True)
class Options:
    """What the choices of a block plan cost."""

    run: Annotated[C.BlockRuns, tyro.conf.OmitArgPrefixes] = C.BlockRuns(downscale=4, steps=1500, cap=30_000)


def main() -> None:
    runs = tyro.cli(Options, description=__doc__).run

    from mcsplat.blocks import plan_blocks, train_blocks
    from mcsplat.config import config_of
    from mcsplat.partition import BlocksFolder
    import mcsplat.partition.scene as block_scene
    from mcsplat.train import train

    options = dict(data=C.scene_path(runs.scene), downscale=runs.downscale, steps=runs.steps, cap_max=runs.cap,
                   quiet=True, lpips_net="alex", save_renders=False, save_every=0)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for number, (count, margin, outside) in enumerate(ARMS):
            out, start = Path(tmp) / f"arm{number}", time.perf_counter()
            if count == 1:
                merged, own = train(config_of(out=out, **options)), []
            else:
                block_scene.OUTSIDE_SHARE = outside
                plan_blocks(config_of(**options), out, count=count, margin=margin)
                folder = BlocksFolder(out)
                merged = train_blocks(folder, quiet=True)
                own = [json.loads((folder.block_run(i) / "metrics.json").read_text())["psnr"] for i in range(count)]
            rows.append({"scene": runs.scene, "blocks": count, "margin": margin, "outside_share": outside,
                         "psnr": merged["psnr"], "gaussians": merged["num_gaussians"],
                         "own_psnr": " ".join(f"{value:.2f}" for value in own),
                         "seconds": time.perf_counter() - start})
            C.emit(rows[-1])
    folder = C.results_dir("blocks_ablation")
    C.write_text(folder / "results.jsonl", "".join(json.dumps(row) + "\n" for row in rows))
    columns = [("blocks", "blocks", ""), ("margin", "margin", ""), ("outside share", "outside_share", ""),
               ("test PSNR (merged)", "psnr", ".2f"), ("Gaussians (merged)", "gaussians", ","),
               ("each block's own PSNR", "own_psnr", ""), ("s", "seconds", ".0f")]
    C.write_results_page(folder, f"Block plans against one run ({runs.scene}, downscale {runs.downscale}, "
                         f"{runs.steps:,} steps, cap {runs.cap:,})", "blocks_ablation.py", rows, columns)


if __name__ == "__main__":
    main()
