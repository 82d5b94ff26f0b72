"""Scoring a model on held-out views: PSNR, SSIM and LPIPS per view and their means, the renders as PNG, and the
split of that work between the processes of a multi-process run (each scores every N-th view, rank 0 gathers the
scores in view order and writes every render)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from PIL import Image
from tqdm import tqdm

from ..appearance import apply_transform, fitted_transform, split_halves
from ..data import View
from ..data.images import uint8_pixels
from ..distributed import SingleProcess, Team
from ..errors import MCSplatError
from ..gaussians import GaussianModel
from ..io.atomic import atomic_write
from ..metrics import lpips_model, masked_psnr, masked_ssim, psnr, ssim_metric
from ..render import render
from ..visibility import seen_in

RenderFile = Callable[[str], Path]  # a view's name -> the PNG its render is written to


@dataclass
class Evaluation:
    psnr: float
    ssim: float
    lpips: float | None
    lpips_net: str
    views: int
    per_view_psnr: dict[str, float] = field(default_factory=dict)  # view name -> PSNR
    # Over the pixels the masks keep (data/attachments/masks.py): the means over the views that have a mask, else None.
    masked_psnr: float | None = None
    masked_ssim: float | None = None
    masked_views: int = 0
    # 3DGS's train_test_exp protocol (appearance/heldout.py): each test view's right half, after the colour
    # transform fitted on its left half.
    compensated_psnr: float | None = None
    compensated_ssim: float | None = None

    def compensated(self) -> dict[str, float]:
        if self.compensated_psnr is None:
            return {}
        return {"compensated_psnr": self.compensated_psnr, "compensated_ssim": self.compensated_ssim}

    def masked(self) -> dict[str, float | int]:
        """The masked scores for metrics.json (nothing when no test view has a mask)."""
        if not self.masked_views:
            return {}
        return {"masked_psnr": self.masked_psnr, "masked_ssim": self.masked_ssim, "masked_views": self.masked_views}


@dataclass
class ViewScore:
    name: str
    psnr: float
    ssim: float
    lpips: float | None
    masked_psnr: float | None = None  # the view has a mask
    masked_ssim: float | None = None
    compensated_psnr: float | None = None
    compensated_ssim: float | None = None


@torch.no_grad()
def score_views(model: GaussianModel, views: list[View], background, sh_degree: int, device: torch.device,
                lpips_net: str | None = None, on_image=None, progress: bool = False) -> list[ViewScore]:
    """PSNR / SSIM / LPIPS of each view's render; `on_image(view, image)` sees each render (to save it)."""
    lp = lpips_model(lpips_net, device=device) if lpips_net else None
    scores = []
    for view in tqdm(views, desc="evaluating", disable=not progress, leave=False):
        target = view.image_float(device)
        image = render(model, view.camera.to(device), background, sh_degree).rgb.clamp(0, 1)
        keep = view.mask_float(device)
        right, right_photo = compensated_half(image, target)
        scores.append(ViewScore(view.name, psnr(image, target), ssim_metric(image, target),
                                float(lp(image, target)) if lp is not None else None,
                                masked_psnr(image, target, keep) if keep is not None else None,
                                masked_ssim(image, target, keep) if keep is not None else None,
                                psnr(right, right_photo), ssim_metric(right, right_photo)))
        if on_image is not None:
            on_image(view, image)
    return scores


def summarize(scores: list[ViewScore], lpips_net: str | None) -> Evaluation:
    """The means over the views (in the order given)."""
    lpips_values = [s.lpips for s in scores if s.lpips is not None]
    masked = [s for s in scores if s.masked_psnr is not None and np.isfinite(s.masked_psnr)]
    return Evaluation(psnr=float(np.mean([s.psnr for s in scores])), ssim=float(np.mean([s.ssim for s in scores])),
                      lpips=float(np.mean(lpips_values)) if lpips_values else None, lpips_net=lpips_net or "",
                      views=len(scores), per_view_psnr={s.name: round(s.psnr, 3) for s in scores},
                      masked_psnr=float(np.mean([s.masked_psnr for s in masked])) if masked else None,
                      masked_ssim=float(np.mean([s.masked_ssim for s in masked])) if masked else None,
                      masked_views=len(masked),
                      compensated_psnr=float(np.mean([s.compensated_psnr for s in scores])) if scores else None,
                      compensated_ssim=float(np.mean([s.compensated_ssim for s in scores])) if scores else None)


def compensated_half(image: torch.Tensor, photo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The right half of the render through the colour transform fitted on the left half, and the photo's right
    half (appearance/heldout.py)."""
    left, right = split_halves(image)
    left_photo, right_photo = split_halves(photo)
    return apply_transform(fitted_transform(left, left_photo), right).clamp(0, 1), right_photo


def require_test_views(views: list[View]) -> None:
    if not views:
        raise MCSplatError("no test views to evaluate: the scene has no test split (check --test-every)")


def evaluate(model: GaussianModel, views: list[View], background, sh_degree: int, device: torch.device,
             lpips_net: str | None = None, render_file: RenderFile | None = None, progress: bool = False,
             team: Team | None = None) -> Evaluation:
    """Mean PSNR / SSIM / LPIPS over `views`; with `render_file`, each render is written as a PNG there.

    With several processes (`team`) every process calls this: each scores every N-th view and rank 0 gathers the
    scores in view order (and writes the renders of the others)."""
    require_test_views(views)
    team = team or SingleProcess()
    mine = list(range(team.rank, len(views), team.world_size))
    sent: list[tuple[str, np.ndarray]] = []  # renders rank 0 writes for the others

    def keep(view: View, image: torch.Tensor) -> None:
        if team.is_main:
            save_png(render_file(view.name), image)
        else:
            sent.append((view.name, uint8_pixels(image)))

    scores = score_views(model, [views[i] for i in mine], background, sh_degree, device, lpips_net,
                         keep if render_file is not None else None, progress and team.is_main)
    everyone = team.gather((mine, scores))
    by_index = {i: score for indices, part in everyone for i, score in zip(indices, part)}
    if render_file is not None:
        for images in team.gather_on_main(sent)[1:]:
            for name, pixels in images:
                save_pixels(render_file(name), pixels)
    return summarize([by_index[i] for i in range(len(views))], lpips_net)


def seen_in_views(model: GaussianModel, views: list[View], background, device: torch.device,
                  team: Team | None = None) -> torch.Tensor:
    """[N] bool: composited into a pixel of some view (with several processes each renders every N-th view)."""
    team = team or SingleProcess()
    seen = seen_in(model, views[team.rank::team.world_size], background, device).to(torch.uint8)
    team.collective.max_(seen)
    return seen.bool()


def save_png(path: Path, image: torch.Tensor) -> None:
    save_pixels(path, uint8_pixels(image))


def save_pixels(path: Path, pixels: np.ndarray) -> None:
    atomic_write(path, lambda tmp: Image.fromarray(pixels).save(tmp, format="PNG"))
