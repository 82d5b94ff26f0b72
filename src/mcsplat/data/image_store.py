"""Images decoded on demand: a bounded cache and a background prefetch, so memory does not grow with the image count.

When all of a scene's images fit in the cache budget (the usual case) they are decoded once, in parallel, at load
time and kept, exactly as before. Otherwise each image is decoded when first asked for, kept in a least-recently-used
cache of at most the budget, and the trainer asks for the next views ahead of time so that decoding overlaps training.
The budget is MCSPLAT_IMAGE_CACHE_MB (MiB) when set, else a quarter of the machine's memory.
"""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from . import images
from ..errors import DataError

BUDGET_ENV = "MCSPLAT_IMAGE_CACHE_MB"
PREFETCH_WORKERS = 2


def default_budget_bytes() -> int:
    value = os.environ.get(BUDGET_ENV)
    if value:
        try:
            megabytes = float(value)
        except ValueError:
            raise DataError(f"{BUDGET_ENV}={value!r} is not a number; give the image cache size in MiB") from None
        if megabytes <= 0:
            raise DataError(f"{BUDGET_ENV}={value!r} must be positive (MiB)")
        return int(megabytes * 2**20)
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        total = 8 * 2**30
    return total // 4


class ImageStore:
    """The uint8 [H, W, 3] images of one scene, by index; `resident` when they all fit the budget and are decoded."""

    def __init__(self, paths: Sequence[Path], sizes: Sequence[images.Size], background: Sequence[float],
                 budget_bytes: int | None = None):
        if len(paths) != len(sizes):
            raise ValueError("ImageStore needs one size per path")
        self.paths, self.sizes = list(paths), [tuple(s) for s in sizes]
        self.background = tuple(background)
        self.budget = default_budget_bytes() if budget_bytes is None else budget_bytes
        self.total_bytes = sum(w * h * 3 for w, h in self.sizes)
        self.resident = self.total_bytes <= self.budget
        self._cache: OrderedDict[int, torch.Tensor] = OrderedDict()
        self._cached_bytes = 0
        self._pending: dict[int, Future] = {}
        self._lock = threading.Lock()
        self._pool: ThreadPoolExecutor | None = None
        if self.resident:
            for index, pixels in enumerate(images.load_images(self.paths, self.sizes, self.background)):
                self._cache[index] = pixels

    def __len__(self) -> int:
        return len(self.paths)

    def handle(self, index: int) -> "LazyImage":
        return LazyImage(self, index)

    def get(self, index: int) -> torch.Tensor:
        with self._lock:
            pixels = self._cache.get(index)
            if pixels is not None:
                self._cache.move_to_end(index)
                return pixels
            future = self._pending.pop(index, None)
        pixels = future.result() if future is not None else self._decode(index)
        self._keep(index, pixels)
        return pixels

    def prefetch(self, index: int) -> None:
        """Start decoding `index` in the background if it is not cached (a no-op for a resident store)."""
        if self.resident:
            return
        with self._lock:
            if index in self._cache or index in self._pending:
                return
            if self._pool is None:
                self._pool = ThreadPoolExecutor(PREFETCH_WORKERS, thread_name_prefix="mcsplat-prefetch")
            self._pending[index] = self._pool.submit(self._decode, index)

    @property
    def cached_bytes(self) -> int:
        return self._cached_bytes if not self.resident else self.total_bytes

    def _decode(self, index: int) -> torch.Tensor:
        background = np.asarray(self.background, dtype=np.float32) * 255.0
        return images._load_one(self.paths[index], self.sizes[index], background)

    def _keep(self, index: int, pixels: torch.Tensor) -> None:
        if self.resident:
            return
        size = pixels.numel()
        with self._lock:
            if index in self._cache:
                return
            # Evict the least recently used images until this one fits (one image always stays: the one asked for).
            while self._cache and self._cached_bytes + size > self.budget:
                _, old = self._cache.popitem(last=False)
                self._cached_bytes -= old.numel()
            self._cache[index] = pixels
            self._cached_bytes += size


class LazyImage:
    """One image of an ImageStore: what a View holds instead of the pixels."""

    __slots__ = ("store", "index")

    def __init__(self, store: ImageStore, index: int):
        self.store, self.index = store, index

    def get(self) -> torch.Tensor:
        return self.store.get(self.index)

    def prefetch(self) -> None:
        self.store.prefetch(self.index)

    @property
    def size(self) -> images.Size:
        return self.store.sizes[self.index]

    @property
    def path(self) -> Path:
        return self.store.paths[self.index]


def store_note(store: ImageStore) -> list[str]:
    """A line for Scene.notes when the images do not all stay in memory."""
    if store.resident:
        return []
    return [f"{store.total_bytes / 2**20:,.0f} MiB of images > the {store.budget / 2**20:,.0f} MiB cache "
            f"({BUDGET_ENV}): decoded on demand with prefetch"]
