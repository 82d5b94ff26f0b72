"""Eq. 9 of the paper (docs/method.md, "The opacity and scale of N copies") and opacity-proportional sampling.

N identical, co-located copies of a Gaussian with opacity o and scale s should look like the original:

- the centre value of the composite must stay the same: (1 - o_new)^N = 1 - o, so o_new = 1 - (1 - o)^(1/N);
- the integral of the composited 1D profile through the centre must stay the same. With g(x) = exp(-x^2 / 2 s^2),
  the composite of N copies is 1 - (1 - o_new g_new)^N = sum_{m=1..N} (-1)^(m-1) C(N, m) o_new^m g_new^m, and the
  integral of g^m is s sqrt(2 pi) / sqrt(m). Matching o s sqrt(2 pi) gives s_new = o s / D with

      D = sum_{i=1..N} sum_{k=0..i-1} C(i-1, k) (-1)^k o_new^(k+1) / sqrt(k+1)        (the paper's form)
        = sum_{k=0..N-1} [sum_{i=k+1..N} C(i-1, k)] (-1)^k o_new^(k+1) / sqrt(k+1)   (swap the sums)

The bracket only depends on (N, k), so it is tabulated once from the binomial table C[n][k] (n < n_max) and D is a
polynomial in o_new with per-N coefficients. (The bracket is C(N, k+1) by the hockey-stick identity; the table is built
by summing, as the paper writes it.) The official CUDA kernel runs the double loop in float32; the alternating sum
cancels badly there for large N, so it is evaluated here in float64 (terms stay below ~1e6 while D is O(o), about
ten significant digits left).
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

from ..gaussians import DEAD_OPACITY

__all__ = ["DEFAULT_MAX_COPIES", "DEFAULT_COPY_FLOOR", "MAX_OPACITY", "binomial_table", "copy_capacity", "copy_opacity",
           "relocation_coefficients", "relocation_params", "sample_by_weight", "sample_hosts"]

DEFAULT_MAX_COPIES = 51                                  # gsplat's n_max; the official code clamps at 50
MAX_OPACITY = 1.0 - float(torch.finfo(torch.float32).eps)  # the official upper clamp, 1 - 1.19e-7
# Relocation "alive": every copy's Eq. 9 opacity is at least this (4x the dead threshold), so no copy is born dead.
DEFAULT_COPY_FLOOR = 4 * DEAD_OPACITY
_CHUNK = 1 << 16                                         # rows per float64 evaluation (bounds the temporary memory)


@functools.lru_cache(maxsize=None)
def binomial_table(n_max: int = DEFAULT_MAX_COPIES) -> np.ndarray:
    """C[n][k] = n choose k for 0 <= k <= n < n_max, float64 [n_max, n_max] (zeros above the diagonal)."""
    table = np.zeros((n_max, n_max), dtype=np.float64)
    for n in range(n_max):
        for k in range(n + 1):
            table[n, k] = math.comb(n, k)
    table.setflags(write=False)
    return table


@functools.lru_cache(maxsize=None)
def relocation_coefficients(n_max: int = DEFAULT_MAX_COPIES) -> np.ndarray:
    """A[N, k] = (-1)^k / sqrt(k+1) * sum_{i=k+1..N} C(i-1, k), float64 [n_max + 1, n_max]; D = sum_k A[N,k] o^(k+1)."""
    comb = binomial_table(n_max)
    coefficients = np.zeros((n_max + 1, n_max), dtype=np.float64)
    for n_copies in range(1, n_max + 1):
        for k in range(n_copies):
            inner = sum(comb[i - 1, k] for i in range(k + 1, n_copies + 1))
            coefficients[n_copies, k] = (-1) ** k * inner / math.sqrt(k + 1)
    coefficients.setflags(write=False)
    return coefficients


@functools.lru_cache(maxsize=None)
def _coefficient_tensor(n_max: int) -> torch.Tensor:
    return torch.from_numpy(relocation_coefficients(n_max).copy())


def copy_opacity(opacities: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """Eq. 9's opacity of each of `counts` copies sharing a Gaussian of opacity `opacities`: 1 - (1 - o)^(1/N), in
    float64, unclamped."""
    return 1.0 - torch.pow(1.0 - opacities.to(torch.float64), 1.0 / counts.to(torch.float64))


def relocation_params(opacities: torch.Tensor, scales: torch.Tensor, counts: torch.Tensor, *,
                      n_max: int = DEFAULT_MAX_COPIES,
                      min_opacity: float = DEAD_OPACITY) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 9: opacity [M] and scales [M, 3] that each of `counts` [M] copies of a Gaussian gets.

    `counts` is the total number of Gaussians sharing the source after the move (the source plus its copies); it is
    clamped to [1, n_max]. As in the official kernel, the new scale is computed from the unclamped new opacity, and
    the opacity is clamped to [min_opacity, 1 - 1.19e-7] afterwards. The source opacity is
    capped at 1 - 1.19e-7 before the maths (a float32 sigmoid can round to exactly 1, where the series cancels worst).
    """
    if n_max < 1 or n_max > 1000:
        raise ValueError(f"n_max must be in [1, 1000] (float64 binomials), got {n_max}")
    if opacities.dim() != 1 or scales.shape != (opacities.shape[0], 3) or counts.shape != opacities.shape:
        raise ValueError(f"relocation_params needs opacities [M], scales [M, 3], counts [M]; got "
                         f"{list(opacities.shape)}, {list(scales.shape)}, {list(counts.shape)}")
    dtype, device = opacities.dtype, opacities.device
    table = _coefficient_tensor(n_max).to(device)
    powers = torch.arange(1, n_max + 1, dtype=torch.float64, device=device)
    new_opacities = torch.empty_like(opacities)
    new_scales = torch.empty_like(scales)
    for start in range(0, opacities.shape[0], _CHUNK):
        rows = slice(start, start + _CHUNK)
        o = opacities[rows].to(torch.float64).clamp(0.0, MAX_OPACITY)
        n = counts[rows].to(device=device, dtype=torch.long).clamp(1, n_max)
        o_new = copy_opacity(o, n)
        # D = sum_k A[N, k] o_new^(k+1); the zero coefficients beyond k = N-1 drop the unused powers.
        denominator = (table[n] * o_new[:, None] ** powers).sum(dim=1)
        ratio = torch.where(denominator > 0, o / denominator, torch.ones_like(o))
        new_scales[rows] = (ratio[:, None] * scales[rows].to(torch.float64)).to(dtype)
        new_opacities[rows] = o_new.clamp(min_opacity, MAX_OPACITY).to(dtype)
    return new_opacities, new_scales


def sample_by_weight(weights: torch.Tensor, num_samples: int, generator: torch.Generator) -> torch.Tensor:
    """`num_samples` indices drawn with replacement with probability proportional to `weights` (>= 0).

    Inverse-CDF sampling on a float64 cumulative sum: unlike torch.multinomial it has no 2^24-category limit (gsplat
    #338) and draws its uniforms from `generator` (on the generator's device, so a CPU generator gives the same
    samples whatever the tensors' device). Zero weights are never drawn. Returns int64 indices on weights' device.
    """
    if weights.dim() != 1:
        raise ValueError(f"weights must be one-dimensional, got shape {list(weights.shape)}")
    if num_samples < 0:
        raise ValueError(f"num_samples must be >= 0, got {num_samples}")
    device = weights.device
    if num_samples == 0:
        return torch.zeros(0, dtype=torch.long, device=device)
    w = torch.nan_to_num(weights.detach().to(torch.float64), nan=0.0, posinf=0.0).clamp_min(0.0)
    cdf = torch.cumsum(w, dim=0)
    total = float(cdf[-1]) if cdf.numel() else 0.0
    if not total > 0:
        raise ValueError("sample_by_weight: the weights sum to zero, there is nothing to sample from")
    u = torch.rand(num_samples, dtype=torch.float64, generator=generator, device=generator.device).to(device)
    # searchsorted(right=True) returns the first i with cdf[i] > u * total: an entry of zero weight has an empty
    # interval [cdf[i-1], cdf[i]) and is skipped.
    indices = torch.searchsorted(cdf, u * total, right=True)
    indices = indices.clamp_(max=w.shape[0] - 1)
    # Rounding can land the last draws on a trailing zero-weight entry: move them to the last positive one.
    last_positive = int(torch.nonzero(w > 0)[-1])
    return torch.where(indices > last_positive, torch.full_like(indices, last_positive), indices)


def copy_capacity(opacities: torch.Tensor, floor: float, n_max: int = DEFAULT_MAX_COPIES) -> torch.Tensor:
    """How many copies each Gaussian can host (int64 [M]) so that it and every copy keep an Eq. 9 opacity of at least
    `floor`: the largest N with 1 - (1 - o)^(1/N) >= floor is log(1 - o) / log(1 - floor); N counts the host too and
    stays within n_max (Eq. 9's clamp), and the copies are N - 1. A host below the floor takes none."""
    if not 0.0 < floor < 1.0:
        raise ValueError(f"the copies' opacity floor must be in (0, 1), got {floor}")
    o = opacities.detach().to(torch.float64).clamp(0.0, MAX_OPACITY)
    # The small margin keeps a host whose N lands exactly on the floor from rounding one copy too many.
    total = torch.floor(torch.log1p(-o) / math.log1p(-floor) * (1.0 - 1e-9))
    return (total.clamp(1, n_max) - 1).to(torch.long)


def sample_hosts(weights: torch.Tensor, capacity: torch.Tensor, num_samples: int,
                 generator: torch.Generator, rounds: int = 8) -> torch.Tensor:
    """Up to `num_samples` indices drawn with replacement with probability proportional to `weights`, no index more
    often than its `capacity`: the draws past a full host are drawn again among those with room (at most `rounds`
    times). Returns the draws kept, in the order drawn (where every host has room, exactly sample_by_weight's);
    fewer than asked when the capacity runs out."""
    if weights.shape != capacity.shape or weights.dim() != 1:
        raise ValueError(f"weights and capacity must be matching vectors, got {list(weights.shape)} and "
                         f"{list(capacity.shape)}")
    device = weights.device
    counts = torch.zeros(weights.shape[0], dtype=torch.long, device=device)
    kept = []
    for _ in range(rounds):
        room = (capacity.to(device) - counts).clamp_min(0)
        open_weights = torch.where(room > 0, weights.detach().to(torch.float64),
                                   torch.zeros((), dtype=torch.float64, device=device))
        remaining = num_samples - int(counts.sum())
        if remaining <= 0 or not float(open_weights.sum()) > 0:
            break
        drawn = sample_by_weight(open_weights, remaining, generator)
        taken = drawn[_occurrence(drawn) < room[drawn]]
        counts += torch.bincount(taken, minlength=counts.shape[0])
        kept.append(taken)
    return torch.cat(kept) if kept else torch.zeros(0, dtype=torch.long, device=device)


def _occurrence(values: torch.Tensor) -> torch.Tensor:
    """For each entry, how many equal entries come before it (0 for the first of its value)."""
    order = torch.sort(values, stable=True).indices
    ordered = values[order]
    position = torch.arange(values.shape[0], device=values.device)
    starts = torch.ones_like(ordered, dtype=torch.bool)
    starts[1:] = ordered[1:] != ordered[:-1]
    first = torch.cummax(torch.where(starts, position, torch.zeros_like(position)), dim=0).values
    rank = torch.empty_like(position)
    rank[order] = position - first
    return rank
