"""The Gaussian model: raw parameters, their activations, and the random / SfM initializations (docs/method.md,
"Representation and initialisation").

Raw parameters (docs/architecture.md, "Conventions") live in `model.params`, a ParameterDict:

    means           [N, 3]       world positions
    log_scales      [N, 3]       log of the per-axis standard deviations
    quats           [N, 4]       (w, x, y, z), not necessarily normalised (the renderer normalises)
    opacity_logits  [N]          logit of the opacity
    sh0             [N, 1, 3]    SH DC coefficient per colour channel
    shN             [N, K-1, 3]  higher SH bands, K = (sh_degree + 1)^2 (15 rest coefficients at degree 3)

Activated values are read through the properties (`scales`, `opacities`, `sh`, ...), which are what
`mcsplat.render.render` consumes. Optimizers and the densification strategies change rows through mcsplat.optim.
"""

from __future__ import annotations

import math
from typing import Mapping

import numpy as np
import torch
from scipy.spatial import cKDTree

from .geometry.covariance import covariance_times
from .geometry.rotation import covariance_3d
from .geometry.sh import SH_C0, num_sh_bases

__all__ = ["GaussianModel", "PARAM_KEYS", "DEAD_OPACITY", "knn_init_scales"]

PARAM_KEYS = ("means", "log_scales", "quats", "opacity_logits", "sh0", "shN")
# Gaussians at or below this opacity are dead: MCMC relocates them (its min_opacity), exports leave them out.
DEAD_OPACITY = 0.005

# The official random init cube half-sizes.
RANDOM_CUBE_FACTOR = 3.0       # real scenes: [-3R, 3R]^3 around the world origin
BLENDER_CUBE_HALF_SIZE = 1.3   # Blender / NeRF-Synthetic: [-1.3, 1.3]^3


def _check_options(init_scale: float, init_opacity: float, sh_degree: int) -> None:
    if not (init_scale > 0 and math.isfinite(init_scale)):
        raise ValueError(f"init_scale must be a positive number, got {init_scale}")
    if not 0.0 < init_opacity < 1.0:
        raise ValueError(f"init_opacity must be strictly between 0 and 1, got {init_opacity}")
    if sh_degree not in (0, 1, 2, 3):
        raise ValueError(f"sh_degree must be 0, 1, 2 or 3, got {sh_degree}")


def knn_init_scales(points: np.ndarray, k: int = 3) -> np.ndarray:
    """sqrt(mean squared distance to the k nearest other points) per point, float64 [P].

    As in 3DGS's simple-knn, coincident points count as neighbours at distance 0, and the mean squared distance is
    floored at 1e-7 so that duplicates still get a finite log-scale. A single point gets 1.0 (there is no neighbour
    to measure against); with fewer than k + 1 points all the other points are used.
    """
    points = np.asarray(points, dtype=np.float64)
    count = points.shape[0]
    if count == 1:
        return np.ones(1)
    neighbours = min(k, count - 1)
    distances, _ = cKDTree(points).query(points, k=neighbours + 1, workers=-1)
    # Column 0 is the point itself (distance 0), unless it has a duplicate, in which case the duplicate's 0 is there
    # instead; either way the k following columns hold the k nearest other points' distances.
    mean_sq = np.mean(distances[:, 1:] ** 2, axis=1)
    return np.sqrt(np.maximum(mean_sq, 1e-7))


class GaussianModel(torch.nn.Module):
    """N 3D Gaussians with SH colour; see the module docstring for the parameter layout."""

    def __init__(self, means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                 opacity_logits: torch.Tensor, sh0: torch.Tensor, shN: torch.Tensor) -> None:
        super().__init__()
        n = means.shape[0]
        shapes = {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4), "opacity_logits": (n,), "sh0": (n, 1, 3)}
        tensors = {"means": means, "log_scales": log_scales, "quats": quats, "opacity_logits": opacity_logits,
                   "sh0": sh0, "shN": shN}
        for key, shape in shapes.items():
            if tuple(tensors[key].shape) != shape:
                raise ValueError(f"GaussianModel: {key} must have shape {list(shape)}, got {list(tensors[key].shape)}")
        if shN.dim() != 3 or shN.shape[0] != n or shN.shape[2] != 3 or shN.shape[1] + 1 not in (1, 4, 9, 16):
            raise ValueError(f"GaussianModel: shN must have shape [{n}, 0|3|8|15, 3], got {list(shN.shape)}")
        self.params = torch.nn.ParameterDict(
            {key: torch.nn.Parameter(tensors[key].detach().clone()) for key in PARAM_KEYS})
        # Drawn with Mip-Splatting's 2D filter (--antialiased): render() reads it, so every view of a scene trained
        # with the filter goes through it. Not in the state dict: a run's configuration says it.
        self.antialiased = False

    # ----------------------------------------------------------------------------------------------- construction
    @classmethod
    def empty(cls, num_gaussians: int = 0, *, sh_degree: int = 3, dtype: torch.dtype = torch.float32,
              device: torch.device | str = "cpu") -> "GaussianModel":
        """A model of `num_gaussians` zero-filled rows (identity rotations), e.g. to load a checkpoint into."""
        if num_gaussians < 0:
            raise ValueError(f"num_gaussians must be >= 0, got {num_gaussians}")
        if sh_degree not in (0, 1, 2, 3):
            raise ValueError(f"sh_degree must be 0, 1, 2 or 3, got {sh_degree}")
        n = num_gaussians
        options = {"dtype": dtype, "device": device}
        quats = torch.zeros(n, 4, **options)
        quats[:, 0] = 1.0
        return cls(torch.zeros(n, 3, **options), torch.zeros(n, 3, **options), quats, torch.zeros(n, **options),
                   torch.zeros(n, 1, 3, **options), torch.zeros(n, num_sh_bases(sh_degree) - 1, 3, **options))

    @classmethod
    def random_init(cls, scene_radius: float, *, blender: bool, num_points: int = 100_000,
                    extent: float = RANDOM_CUBE_FACTOR, init_scale: float = 0.1, init_opacity: float = 0.5,
                    sh_degree: int = 3, generator: torch.Generator | None = None,
                    device: torch.device | str = "cpu") -> "GaussianModel":
        """The official random initialization.

        Positions uniform in [-extent R, extent R]^3 around the world origin (R = `scene_radius`, extent 3 by
        default; the paper's Table 2 also tries 1), or [-1.3, 1.3]^3 for Blender scenes (R and extent unused). The
        SH DC values are uniform in [0, 1/255], i.e. an almost uniform mid-grey, as in the official code. Scale,
        opacity and rotation follow the same rules as `from_points`.
        """
        if num_points < 1:
            raise ValueError(f"num_points must be at least 1, got {num_points}")
        if not blender and not (scene_radius > 0 and math.isfinite(scene_radius)):
            raise ValueError(f"scene_radius must be a positive number, got {scene_radius}")
        if not extent > 0:
            raise ValueError(f"extent must be positive, got {extent}")
        _check_options(init_scale, init_opacity, sh_degree)
        half = BLENDER_CUBE_HALF_SIZE if blender else extent * scene_radius
        gen_device = generator.device if generator is not None else torch.device("cpu")
        means = (torch.rand(num_points, 3, generator=generator, device=gen_device) * 2.0 - 1.0) * half
        sh_dc = torch.rand(num_points, 1, 3, generator=generator, device=gen_device) / 255.0
        return cls._from_positions(means.to(device), sh_dc.to(device), init_scale=init_scale,
                                   init_opacity=init_opacity, sh_degree=sh_degree)

    @classmethod
    def from_points(cls, points: torch.Tensor | np.ndarray, colors: torch.Tensor | np.ndarray, *,
                    init_scale: float = 0.1, init_opacity: float = 0.5, sh_degree: int = 3,
                    device: torch.device | str = "cpu") -> "GaussianModel":
        """SfM initialization: one Gaussian per point, its SH DC set so that it renders `colors` (RGB in [0, 1])."""
        points = torch.as_tensor(points).to(device=device, dtype=torch.float32)
        colors = torch.as_tensor(colors).to(device=device, dtype=torch.float32)
        if points.dim() != 2 or points.shape[1] != 3 or points.shape[0] < 1:
            raise ValueError(f"points must have shape [P, 3] with P >= 1, got {list(points.shape)}")
        if tuple(colors.shape) != tuple(points.shape):
            raise ValueError(f"colors must have the shape of points {list(points.shape)}, got {list(colors.shape)}")
        if not torch.isfinite(points).all():
            raise ValueError("points contain NaN or infinite coordinates")
        _check_options(init_scale, init_opacity, sh_degree)
        sh_dc = ((colors - 0.5) / SH_C0).reshape(-1, 1, 3)
        return cls._from_positions(points, sh_dc, init_scale=init_scale, init_opacity=init_opacity,
                                   sh_degree=sh_degree)

    @classmethod
    def _from_positions(cls, means: torch.Tensor, sh_dc: torch.Tensor, *, init_scale: float, init_opacity: float,
                        sh_degree: int) -> "GaussianModel":
        n = means.shape[0]
        device = means.device
        scales = init_scale * knn_init_scales(means.detach().cpu().numpy())
        log_scales = torch.from_numpy(np.log(scales)).to(device=device, dtype=torch.float32)[:, None].expand(n, 3)
        quats = torch.zeros(n, 4, device=device)
        quats[:, 0] = 1.0
        opacity_logits = torch.full((n,), math.log(init_opacity / (1.0 - init_opacity)), device=device)
        shN = torch.zeros(n, num_sh_bases(sh_degree) - 1, 3, device=device)
        return cls(means, log_scales.contiguous(), quats, opacity_logits, sh_dc, shN)

    def subset(self, keep: torch.Tensor) -> "GaussianModel":
        """A new model of the rows `keep` selects (a bool mask or indices), detached from this one."""
        model = GaussianModel(*(self.params[key].detach()[keep] for key in PARAM_KEYS))
        model.antialiased = self.antialiased
        return model

    @classmethod
    def from_state_dict(cls, state: Mapping[str, torch.Tensor],
                        device: torch.device | str | None = None) -> "GaussianModel":
        """A model of whatever size and SH degree `state` (a `state_dict()`) holds."""
        model = cls.empty(0)
        model.load_state_dict(state)
        return model if device is None else model.to(device)

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                              error_msgs) -> None:
        """Before torch copies the values, resize the parameters to the shapes in the state (a checkpoint of another
        N or SH degree), so that `load_state_dict` works into a model of any size.

        Resizing replaces the Parameter objects: build the optimizers (mcsplat.optim.make_optimizers) after loading.
        """
        for key in PARAM_KEYS:
            saved = state_dict.get(f"{prefix}params.{key}")
            current = self.params[key]
            if saved is not None and tuple(saved.shape) != tuple(current.shape):
                self.params[key] = torch.nn.Parameter(
                    torch.empty(saved.shape, dtype=current.dtype, device=current.device))
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                                      error_msgs)

    # ------------------------------------------------------------------------------------------ activated views
    @property
    def means(self) -> torch.Tensor:
        return self.params["means"]

    @property
    def log_scales(self) -> torch.Tensor:
        return self.params["log_scales"]

    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.params["log_scales"])

    @property
    def quats(self) -> torch.Tensor:
        """The raw quaternions (w, x, y, z); render() and covariances() normalise them."""
        return self.params["quats"]

    @property
    def opacity_logits(self) -> torch.Tensor:
        return self.params["opacity_logits"]

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.params["opacity_logits"])

    @property
    def sh(self) -> torch.Tensor:
        return torch.cat([self.params["sh0"], self.params["shN"]], dim=1)

    @property
    def sh_parts(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(sh0 [N, 1, 3], shN [N, K - 1, 3]) as stored: render() reads them without concatenating."""
        return self.params["sh0"], self.params["shN"]

    @property
    def sh_degree(self) -> int:
        """The largest SH degree the model stores."""
        return math.isqrt(self.params["shN"].shape[1] + 1) - 1

    @property
    def num_gaussians(self) -> int:
        return self.params["means"].shape[0]

    def __len__(self) -> int:
        return self.num_gaussians

    def covariances(self) -> torch.Tensor:
        """The full 3D covariance Sigma = R S S^T R^T, [N, 3, 3]."""
        return covariance_3d(self.params["quats"], self.scales)

    @torch.no_grad()
    def covariance_times(self, vectors: torch.Tensor) -> torch.Tensor:
        """Sigma_i @ vectors_i [N, 3] for every Gaussian, without gradient (one Warp kernel: the MCMC noise)."""
        return covariance_times(self.params["quats"], self.scales, vectors)

    def extra_repr(self) -> str:
        return f"num_gaussians={self.num_gaussians}, sh_degree={self.sh_degree}, antialiased={self.antialiased}"
