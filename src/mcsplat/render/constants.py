"""The rasterizer's fixed numbers, in one place: every kernel, the torch paths and the reference renderer read them
from here (the tests check that the fast and the reference paths agree, so they must share them)."""

TILE_SIZE = 16                     # pixels per side of a tile (one CUDA block, one CPU work item)
PIXELS_PER_TILE = TILE_SIZE * TILE_SIZE
BLOCK_SIZE = 4                     # pixels per side of the blocks a (tile, Gaussian) pair masks (bin/)
ALL_BLOCKS = 0xFFFF                # the mask of all 16 blocks of a tile

ALPHA_MIN = 1.0 / 255.0            # a Gaussian is skipped at a pixel where its alpha is below this
ALPHA_MAX = 0.99                   # alpha is clamped here (3DGS), so one Gaussian never hides all behind it
TRANSMITTANCE_MIN = 1e-4           # a pixel stops before its transmittance would fall below this
# A pixel's median Gaussian, whose depth is its median depth: the one at which its accumulated alpha first reaches 0.5,
# i.e. the last one composited while the transmittance in front of it is still above this.
MEDIAN_TRANSMITTANCE = 0.5
# alpha = o exp(power) <= exp(power), so below ln(1/255) the alpha test fails for any opacity: skipping there saves
# the exp for most of the list. The margin keeps the shortcut from deciding a case the exact test would not.
POWER_SKIP = -5.5413 - 1e-3

LOW_PASS = 0.3                     # pixels^2 added to the 2D covariance's diagonal (3DGS's screen-space filter)
NEAR_PLANE = 0.01                  # camera-space depth below which a Gaussian is culled
FAR_PLANE = 1e10
