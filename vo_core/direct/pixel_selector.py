"""DSO's pixel selection (PixelSelector2.cpp, DSO paper section 3.2 / FDMO 4.2.1), vectorized.

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

from vo_core.direct.config import SelectorConfig
from vo_core.direct.pyramid import ImagePyramid

# The level a selected pixel was found on is stored as DSO's type: 1, 2 or 4 (the cell factor).
LEVEL_TYPES = (1, 2, 4)


@dataclass
class Selection:
    uv: np.ndarray  # (N, 2) integer pixel coordinates at level 0
    kind: np.ndarray  # (N,) 1, 2 or 4: pixel found at level 0, 1 or 2 (DSO's my_type)


def _block_view(array: np.ndarray, cell: int) -> np.ndarray:
    """(H, W) with H, W multiples of cell -> (H/cell, W/cell, cell*cell)."""
    h, w = array.shape
    return array.reshape(h // cell, cell, w // cell, cell).transpose(0, 2, 1, 3).reshape(h // cell, w // cell, -1)


def _sum_3x3(values: np.ndarray) -> np.ndarray:
    padded = np.pad(values, 1)
    h, w = values.shape
    return sum(padded[dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3))


def gradient_thresholds(grad_sq: np.ndarray, config: SelectorConfig) -> np.ndarray:
    """Per-pixel threshold on |grad|^2 from the smoothed per-block median (+7) of |grad| (makeHists)."""
    h, w = grad_sq.shape
    block = config.block_size
    h_blocks, w_blocks = max(h // block, 1), max(w // block, 1)
    magnitude = np.minimum(np.sqrt(grad_sq).astype(np.int32), config.hist_max_gradient).astype(float)
    magnitude[0, :] = magnitude[-1, :] = magnitude[:, 0] = magnitude[:, -1] = np.nan  # DSO skips the border
    covered = np.full((h_blocks * block, w_blocks * block), np.nan)
    rows, cols = min(h, covered.shape[0]), min(w, covered.shape[1])
    covered[:rows, :cols] = magnitude[:rows, :cols]
    blocks = np.sort(_block_view(covered, block), axis=2)  # NaN sorts last
    count = np.sum(~np.isnan(blocks), axis=2)
    # computeHistQuantil: the first histogram bin whose cumulative count exceeds count * q + 0.5.
    rank = np.minimum((count * config.hist_quantile + 0.5).astype(int), np.maximum(count - 1, 0))
    quantile = np.take_along_axis(blocks, rank[:, :, None], axis=2)[:, :, 0]
    block_threshold = np.nan_to_num(quantile, nan=config.hist_max_gradient) + config.hist_add
    smoothed = _sum_3x3(block_threshold) / _sum_3x3(np.ones_like(block_threshold))
    block_rows = np.minimum(np.arange(h) // block, h_blocks - 1)
    block_cols = np.minimum(np.arange(w) // block, w_blocks - 1)
    return (smoothed**2)[np.ix_(block_rows, block_cols)]


class PixelSelector:
    def __init__(self, config: SelectorConfig, seed: int):
        self.config = config
        self.potential = config.initial_potential
        self.rng = np.random.default_rng(seed)

    def select(self, pyramid: ImagePyramid, density: float, threshold_factor: float = 1.0) -> Selection:
        """About ``density`` well-spread pixels with high gradient (makeMaps)."""
        config = self.config
        thresholds = gradient_thresholds(pyramid[0].grad_sq, config)
        selection = self._select_at_potential(pyramid, thresholds, self.potential, threshold_factor)
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
            selection = self._select_at_potential(pyramid, thresholds, self.potential, threshold_factor)
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
        self, pyramid: ImagePyramid, thresholds: np.ndarray, pot: int, threshold_factor: float
    ) -> Selection:
        config = self.config
        level0 = pyramid[0]
        h, w = level0.intensity.shape
        big = 4 * pot
        height, width = -(-h // big) * big, -(-w // big) * big

        def padded(values: np.ndarray, fill: float) -> np.ndarray:
            out = np.full((height, width), fill, dtype=float)
            out[:h, :w] = values
            return out

        ys, xs = np.arange(h), np.arange(w)
        inside = np.zeros((h, w), dtype=bool)
        inside[config.border : h - config.border, config.border : w - config.border - 1] = True
        grad_sq_levels = [level0.grad_sq]
        for level, scale in ((1, 0.5), (2, 0.25)):
            if level < len(pyramid):
                gl = pyramid[level].grad_sq
                rows = np.minimum((ys * scale + scale / 2).astype(int), gl.shape[0] - 1)
                cols = np.minimum((xs * scale + scale / 2).astype(int), gl.shape[1] - 1)
                grad_sq_levels.append(gl[np.ix_(rows, cols)])
            else:
                grad_sq_levels.append(np.zeros((h, w)))
        gx = padded(level0.packed[:, :, 1], 0.0)
        gy = padded(level0.packed[:, :, 2], 0.0)
        taken = np.zeros((height, width), dtype=bool)
        uv_parts, kind_parts = [], []
        for level, kind in enumerate(LEVEL_TYPES):
            cell = pot * kind
            weight = config.grad_downweight_per_level ** (level * (level + 1) // 2)  # 1, 0.75, 0.75^3 as DSO
            passes = grad_sq_levels[level] > thresholds * weight * threshold_factor
            candidate = padded(passes & inside, False).astype(bool)
            # A random direction per cell spreads the gradient directions of the selected pixels.
            angle = self.rng.uniform(0.0, np.pi, size=(height // cell, width // cell))
            direction_u = np.repeat(np.repeat(np.cos(angle), cell, 0), cell, 1)
            direction_v = np.repeat(np.repeat(np.sin(angle), cell, 0), cell, 1)
            score = np.where(candidate, np.abs(gx * direction_u + gy * direction_v), 0.0)
            blocked = _block_view(taken, cell).any(axis=2)  # a finer level already chose in this cell
            cells = _block_view(score, cell)
            best = cells.argmax(axis=2)
            chosen = (np.take_along_axis(cells, best[:, :, None], axis=2)[:, :, 0] > 0.0) & ~blocked
            cell_rows, cell_cols = np.nonzero(chosen)
            within = best[cell_rows, cell_cols]
            rows = cell_rows * cell + within // cell
            cols = cell_cols * cell + within % cell
            taken[rows, cols] = True
            uv_parts.append(np.stack([cols, rows], axis=1))
            kind_parts.append(np.full(len(rows), kind))
        uv = np.concatenate(uv_parts)
        kind = np.concatenate(kind_parts)
        order = np.lexsort((uv[:, 0], uv[:, 1]))
        return Selection(uv[order], kind[order])
