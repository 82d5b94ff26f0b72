"""The cut: a k-d split of the points on the ground plane into cells holding equal shares of them (VastGaussian and
CityGaussian cut on the ground too). The outer cells reach to infinity, so that the cells cover the whole plane and
every Gaussian of a merged model belongs to exactly one block."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

INF = math.inf


@dataclass(frozen=True)
class Cell:
    """A rectangle on the ground plane, low <= (u, v) < high; a side may be infinite."""

    low: tuple[float, float]
    high: tuple[float, float]

    def contains(self, uv: torch.Tensor) -> torch.Tensor:
        """[N] bool for points [N, 2] on the ground plane (the low side in, the high side out)."""
        low = torch.tensor(self.low, dtype=uv.dtype, device=uv.device)
        high = torch.tensor(self.high, dtype=uv.dtype, device=uv.device)
        return ((uv >= low) & (uv < high)).all(dim=1)

    def grown(self, pad: tuple[float, float]) -> "Cell":
        """The cell with each side moved out by `pad` (along each axis)."""
        return Cell((self.low[0] - pad[0], self.low[1] - pad[1]), (self.high[0] + pad[0], self.high[1] + pad[1]))

    def size_within(self, extent: "Cell") -> tuple[float, float]:
        """The cell's size on each axis once cut to `extent` (an outer cell's infinite sides end where the points
        do)."""
        return tuple(max(min(self.high[axis], extent.high[axis]) - max(self.low[axis], extent.low[axis]), 0.0)
                     for axis in range(2))  # type: ignore[return-value]

    def to_json(self) -> dict:
        """Infinite sides as null (JSON has no infinity)."""
        return {"low": [_finite_or_none(v) for v in self.low], "high": [_finite_or_none(v) for v in self.high]}

    @classmethod
    def from_json(cls, data: dict) -> "Cell":
        low = tuple(-INF if v is None else float(v) for v in data["low"])
        high = tuple(INF if v is None else float(v) for v in data["high"])
        if len(low) != 2 or len(high) != 2:
            raise ValueError("a cell has two low and two high bounds")
        return cls((low[0], low[1]), (high[0], high[1]))


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


def bounds(uv: torch.Tensor, share: float = 0.01) -> Cell:
    """The points' extent on each axis, between the `share` and 1 - `share` quantiles (so that a few far outliers
    do not stretch the margins)."""
    low = torch.quantile(uv, share, dim=0)
    high = torch.quantile(uv, 1.0 - share, dim=0)
    return Cell((float(low[0]), float(low[1])), (float(high[0]), float(high[1])))


def split_cells(uv: torch.Tensor, count: int) -> list[Cell]:
    """`count` cells covering the plane, each holding about 1/count of the points [N, 2]: split the longer side at
    the quantile that gives each half its share of the cells, and again within each half."""
    if count < 1:
        raise ValueError("count must be at least 1")
    return _split(uv.to(torch.float64), count, Cell((-INF, -INF), (INF, INF)))


def _split(uv: torch.Tensor, count: int, cell: Cell) -> list[Cell]:
    if count == 1:
        return [cell]
    spread = bounds(uv) if uv.shape[0] >= 2 else Cell((0.0, 0.0), (0.0, 0.0))
    axis = 0 if spread.high[0] - spread.low[0] >= spread.high[1] - spread.low[1] else 1
    left = count // 2
    at = float(torch.quantile(uv[:, axis], left / count)) if uv.shape[0] else 0.0
    below_high = list(cell.high)
    below_high[axis] = at
    above_low = list(cell.low)
    above_low[axis] = at
    below = Cell(cell.low, (below_high[0], below_high[1]))
    above = Cell((above_low[0], above_low[1]), cell.high)
    in_below = uv[:, axis] < at
    return _split(uv[in_below], left, below) + _split(uv[~in_below], count - left, above)
