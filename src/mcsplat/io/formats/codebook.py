"""Codebooks for quantised formats (SOG): the 256 values that stand for a column of numbers (1D k-means), and a
palette of vectors (k-means) that stands for the SH coefficients of many Gaussians. Both are deterministic: the
same numbers give the same codebook, byte for byte, on the same machine.
"""

from __future__ import annotations

import numpy as np


def scalar_codebook(values: np.ndarray, size: int = 256, iterations: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """(codebook: `size` values ascending, labels: the index of the nearest codebook value for each of `values`,
    uint8 when `size` <= 256, in `values`' shape). Lloyd's algorithm in one dimension on the sorted values (each
    step costs `size` binary searches), started halfway between even quantiles and even steps of the range, so that
    the sparse tails (the largest scales, the brightest colours) keep codes of their own."""
    flat = values.astype(np.float64).ravel()
    ordered = np.sort(flat)
    fractions = (np.arange(size) + 0.5) / size
    centres = 0.5 * (np.quantile(ordered, fractions) + ordered[0] + (ordered[-1] - ordered[0]) * fractions)
    prefix = np.concatenate([[0.0], np.cumsum(ordered)])
    for _ in range(iterations):
        cuts = np.searchsorted(ordered, 0.5 * (centres[:-1] + centres[1:]))
        starts, ends = np.concatenate([[0], cuts]), np.concatenate([cuts, [ordered.size]])
        counts = ends - starts
        means = np.where(counts > 0, (prefix[ends] - prefix[starts]) / np.maximum(counts, 1), centres)
        means.sort()
        if np.array_equal(means, centres):
            break
        centres = means
    labels = np.searchsorted(0.5 * (centres[:-1] + centres[1:]), flat)
    return centres, labels.astype(np.uint8 if size <= 256 else np.uint16).reshape(values.shape)


def vector_palette(rows: np.ndarray, size: int, weights: np.ndarray | None = None, iterations: int = 10,
                   seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(centroids [k, d] float32, labels [n] int64) with k = min(size, n): Lloyd's k-means from k distinct rows drawn
    with a fixed seed, each centroid the `weights`-weighted mean of its rows (SOG weighs the SH of a Gaussian by its
    opacity: a faint one's colour matters little; the rows are drawn in proportion too). With as many centroids as
    rows each row is its own. Runs in torch, on the GPU when there is one (the distances of n rows to k centroids are
    most of the work of writing a large scene)."""
    import torch

    n = len(rows)
    k = min(size, n)
    if k == n:
        return rows.astype(np.float32), np.arange(n)
    weights = np.ones(n) if weights is None else np.maximum(weights.astype(np.float64), 1e-12)
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    data = torch.from_numpy(np.ascontiguousarray(rows, dtype=np.float32)).to(device)
    weight = torch.from_numpy(weights.astype(np.float32)).to(device)
    chosen = np.sort(np.random.default_rng(seed).choice(n, size=k, replace=False, p=weights / weights.sum()))
    centroids = data[torch.from_numpy(chosen).to(device)].clone()
    for _ in range(iterations):
        labels = _nearest(data, centroids)
        sums = torch.zeros_like(centroids).index_add_(0, labels, data * weight[:, None])
        totals = torch.zeros(k, device=device).index_add_(0, labels, weight).unsqueeze(1)
        centroids = torch.where(totals > 0, sums / totals.clamp(min=1e-30), centroids)  # an empty cluster stays put
    labels = _nearest(data, centroids)
    return centroids.cpu().numpy(), labels.cpu().numpy()


def _nearest(data, centroids):
    """The index of each row's nearest centroid, in blocks of rows that keep the distance matrix near 64 MB."""
    import torch

    squared = (centroids * centroids).sum(dim=1)
    labels = torch.empty(len(data), dtype=torch.int64, device=data.device)
    step = max(1, (1 << 24) // len(centroids))
    for start in range(0, len(data), step):
        block = data[start:start + step]
        labels[start:start + step] = torch.argmin(squared - 2.0 * block @ centroids.T, dim=1)
    return labels
