"""DSO's pixel selection (PixelSelector2.cpp, DSO paper section 3.2 / FDMO 4.2.1), per-block and per-cell loops
compiled (numba).

1. Region-adaptive threshold: per 32x32 block the median gradient magnitude + 7, smoothed over the 3x3
   neighbouring blocks (makeHists).
2. Selection in cells of ``pot`` x ``pot`` pixels: in each cell the pixel above the level-0 threshold with the
   largest gradient along a random direction; a 2pot cell with no level-0 pixel may take one whose level-1
   gradient passes a 0.75x lower threshold, a 4pot cell with neither may take a level-2 one (select()).
3. The cell size is adapted so that the count reaches the requested density; surplus pixels are thinned
   randomly (makeMaps). The cell size is remembered between calls, as DSO's currentPotential.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vo_core.compiled import kernel
from vo_core.direct.config import SelectorConfig
from vo_core.direct.pyramid import ImagePyramid

# The level a selected pixel was found on is stored as DSO's type: 1, 2 or 4 (the cell factor).
LEVEL_TYPES = (1, 2, 4)
# A cell scores its candidates by |gradient . d| along one of DSO's 16 directions (PixelSelector2's directions[16],
# k pi / 16 up to sign), drawn at random per cell: an index a cell instead of an angle and its cosine and sine
# (0.8 ms a keyframe at 640x480).
DIRECTIONS = np.stack([np.cos(np.arange(16) * np.pi / 16), np.sin(np.arange(16) * np.pi / 16)], axis=1)


@dataclass
class Selection:
    uv: np.ndarray  # (N, 2) integer pixel coordinates at level 0
    kind: np.ndarray  # (N,) 1, 2 or 4: pixel found at level 0, 1 or 2 (DSO's my_type)


def _sum_3x3(values: np.ndarray) -> np.ndarray:
    padded = np.pad(values, 1)
    h, w = values.shape
    return sum(padded[dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3))


def block_thresholds(grad_sq: np.ndarray, config: SelectorConfig) -> np.ndarray:
    """Per block of ``block_size`` pixels, the threshold on |grad|^2: the smoothed block median (+7) of |grad|, squared
    (makeHists). Pixels past the last whole block belong to it (``_take_best_in_cells``)."""
    h, w = grad_sq.shape
    block = config.block_size
    h_blocks, w_blocks = max(h // block, 1), max(w // block, 1)
    quantile = _block_quantiles(grad_sq, block, h_blocks, w_blocks, config.hist_max_gradient, config.hist_quantile)
    block_threshold = quantile + config.hist_add
    smoothed = _sum_3x3(block_threshold) / _sum_3x3(np.ones_like(block_threshold))
    return smoothed**2


@kernel
def _block_quantiles(grad_sq, block, h_blocks, w_blocks, max_gradient, quantile):
    """makeHists: per block the ``quantile`` of the integer gradient magnitudes min(int(|grad|), max_gradient) by
    histogram, the image border skipped, ``max_gradient`` for a block without pixels. computeHistQuantil: the first
    bin whose cumulative count exceeds count * q + 0.5 (at most the last pixel's)."""
    h, w = grad_sq.shape
    out = np.empty((h_blocks, w_blocks))
    histogram = np.zeros(max_gradient + 1, np.int64)
    for block_row in range(h_blocks):
        for block_col in range(w_blocks):
            histogram[:] = 0
            for y in range(max(block_row * block, 1), min((block_row + 1) * block, h - 1)):
                for x in range(max(block_col * block, 1), min((block_col + 1) * block, w - 1)):
                    histogram[min(int(np.sqrt(grad_sq[y, x])), max_gradient)] += 1
            count = histogram.sum()
            out[block_row, block_col] = max_gradient
            if count == 0:
                continue
            rank = min(int(count * quantile + 0.5), count - 1)
            cumulative = 0
            for value in range(max_gradient + 1):
                cumulative += histogram[value]
                if cumulative > rank:
                    out[block_row, block_col] = value
                    break
    return out


class PixelSelector:
    def __init__(self, config: SelectorConfig, seed: int):
        self.config = config
        self.potential = config.initial_potential
        self.rng = np.random.default_rng(seed)

    def select(self, pyramid: ImagePyramid, density: float, threshold_factor: float = 1.0) -> Selection:
        """About ``density`` well-spread pixels with high gradient (makeMaps)."""
        config = self.config
        grad_sq = [pyramid[level].grad_sq if level < len(pyramid) else None for level in range(len(LEVEL_TYPES))]
        thresholds = block_thresholds(grad_sq[0], config)
        selection = self._select_at_potential(pyramid, grad_sq, thresholds, self.potential, threshold_factor)
        for _ in range(config.max_resample_rounds):
            have = max(len(selection.kind), 1)
            ratio = density / have
            ideal = self._ideal_potential(have, density)
            if ratio > config.resample_more_above and self.potential > 1:
                self.potential = min(ideal, self.potential - 1)
            elif ratio < config.resample_less_below:
                self.potential = max(ideal, self.potential + 1)
            else:
                break
            selection = self._select_at_potential(pyramid, grad_sq, thresholds, self.potential, threshold_factor)
        have = max(len(selection.kind), 1)
        self.potential = self._ideal_potential(have, density)
        ratio = density / have
        if ratio < config.subsample_below:
            keep = self.rng.random(len(selection.kind)) < ratio
            selection = Selection(selection.uv[keep], selection.kind[keep])
        return selection

    def _ideal_potential(self, have: int, want: float) -> int:
        # The count behaves as K / (pot + 1)^2 with a scene-dependent K (makeMaps).
        k = have * (self.potential + 1) ** 2
        return max(int(np.sqrt(k / want) - 1), 1)

    def _select_at_potential(
        self, pyramid: ImagePyramid, grad_sq: list, thresholds: np.ndarray, pot: int, threshold_factor: float
    ) -> Selection:
        """``grad_sq``: |grad|^2 of levels 0-2 (None past the pyramid); ``thresholds``: ``block_thresholds``."""
        config = self.config
        level0 = pyramid[0]
        h, w = level0.intensity.shape
        big = 4 * pot
        height, width = -(-h // big) * big, -(-w // big) * big  # whole cells of the coarsest type
        chosen = np.zeros((h, w), dtype=np.int8)  # the type of the pixel taken there, 0 where none
        for level, kind in enumerate(LEVEL_TYPES):
            cell = pot * kind
            weight = config.grad_downweight_per_level ** (level * (level + 1) // 2)  # 1, 0.75, 0.75^3 as DSO
            # A random direction per cell spreads the gradient directions of the selected pixels. Drawn for every
            # level, one the pyramid lacks included, so that the seed's later draws stay the same.
            direction = self.rng.integers(0, len(DIRECTIONS), size=(height // cell, width // cell))
            if grad_sq[level] is None:  # a pyramid this short has no pixel of this type
                continue
            _take_best_in_cells(grad_sq[level], 0.5**level, thresholds, config.block_size, weight, threshold_factor,
                                config.border, level0.packed, direction, DIRECTIONS, cell, kind, chosen)
        rows, cols = np.nonzero(chosen.view(np.bool_))  # row-major: sorted by (v, u); on bools 0.6 against 0.8 ms
        return Selection(np.stack([cols, rows], axis=1), chosen[rows, cols].astype(np.int64))


@kernel
def _take_best_in_cells(grad_sq, scale, thresholds, block, weight, factor, border, packed, direction, directions, cell,
                        kind, chosen):
    """select() for one cell size: in each cell where no finer level chose a pixel, the candidate with the
    largest |gradient . d| (the first one in row-major order on ties) is chosen as ``kind``; d is the cell's
    ``directions[direction[cell]]``. A candidate is a level-0 pixel at least ``border`` inside the image (one more
    on the right) whose level's |grad|^2 (``grad_sq``, the level's pixel under it: ``scale`` = 2^-level) passes its
    block's threshold times ``weight`` and ``factor``.

    One compiled pass over the cells: the numpy version built a dozen full-resolution temporaries per size. Each
    row's and column's pixel on the level and threshold block are looked up once per call."""
    h, w = chosen.shape
    level_row, block_row = _level_and_block(h, scale, grad_sq.shape[0], block, thresholds.shape[0])
    level_col, block_col = _level_and_block(w, scale, grad_sq.shape[1], block, thresholds.shape[1])
    scaled_thresholds = thresholds * weight * factor
    x_lo, x_hi = border, w - border - 1
    for cell_row in range(direction.shape[0]):
        y0 = cell_row * cell
        y1 = min(y0 + cell, h)
        for cell_col in range(direction.shape[1]):
            x0 = cell_col * cell
            x1 = min(x0 + cell, w)
            if _any_chosen(chosen, y0, y1, x0, x1):
                continue
            best, best_y, best_x = 0.0, -1, -1
            cos_a, sin_a = directions[direction[cell_row, cell_col]]
            for y in range(max(y0, border), min(y1, h - border)):
                level_y, block_y = level_row[y], block_row[y]
                for x in range(max(x0, x_lo), min(x1, x_hi)):
                    if grad_sq[level_y, level_col[x]] > scaled_thresholds[block_y, block_col[x]]:
                        score = abs(packed[y, x, 1] * cos_a + packed[y, x, 2] * sin_a)
                        if score > best:
                            best, best_y, best_x = score, y, x
            if best_y >= 0:
                chosen[best_y, best_x] = kind


@kernel
def _level_and_block(length, scale, level_length, block, num_blocks):
    """For each level-0 index 0..``length``-1 along one axis: its pixel on the level (``scale`` = 2^-level, the
    level's pixel under it) and its threshold block."""
    level = np.empty(length, np.int64)
    blocks = np.empty(length, np.int64)
    for i in range(length):
        level[i] = min(int(i * scale + scale / 2), level_length - 1)
        blocks[i] = min(i // block, num_blocks - 1)
    return level, blocks


@kernel
def _any_chosen(chosen, y0, y1, x0, x1):
    for y in range(y0, y1):
        for x in range(x0, x1):
            if chosen[y, x] != 0:
                return True
    return False
