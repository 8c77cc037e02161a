"""ORB features as ORB-SLAM2 extracts them (FDMO 4.2.2 and 4.3: ORB on 8 levels, scale factor 1.2).

Per pyramid level (ORB-SLAM2 src/ORBextractor.cc, ``ComputeKeyPointsOctTree``):

1. a quota of features from a geometric series over the levels (``features_per_level``);
2. FAST corners with ``fast_threshold``, and with ``min_fast_threshold`` in the cells of ``cell_size`` pixels
   where the first threshold finds nothing, so that weakly textured parts of the image still get corners;
3. a quadtree that splits the image until it has about as many occupied regions as the quota and keeps the
   strongest corner of each (ORB-SLAM2 ``DistributeOctTree``), so that features cover the whole image;
4. orientation by the intensity centroid of a disc of radius ``patch_size // 2`` (ORB-SLAM2 ``IC_Angle``);
5. rBRIEF descriptors from OpenCV's ORB (the same 256-pair pattern and the same 7x7, sigma 2 blur of each
   level as ORB-SLAM2's ``computeDescriptors``).

FAST runs on a whole level, not per cell: once at the high threshold, and once more at the low threshold only
when some cell has no corner, keeping from that pass the corners of those cells. A corner's FAST score is the
largest threshold at which it is still a corner and non-maximum suppression compares scores, so this is
exactly ORB-SLAM2's per-cell result without a call per cell.

Coordinates: ``Features.uv`` are level-0 pixels with (0, 0) the centre of the top-left pixel, so a corner at
pixel x of level l is at (x + 0.5) s^l - 0.5 (the pixel-centre mapping of cv2.resize).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from vo_core.compiled import kernel
from vo_core.features.config import OrbConfig

DESCRIPTOR_BYTES = 32  # rBRIEF: 256 binary tests (ORB-SLAM2 ORBextractor, OpenCV ORB with WTA_K = 2)
FAST_RADIUS = 3  # the Bresenham circle of FAST-9/16: corners need this many pixels around them
# ORB-SLAM2 ComputeKeyPointsOctTree: corners are kept EDGE_THRESHOLD - 3 pixels inside each level.
BORDER_BELOW_EDGE_THRESHOLD = FAST_RADIUS
FULL_CIRCLE_DEG = 360.0
# Deepest split of the quadtree (ours): 2^16 cells a side are far below a pixel at any level of any image, so
# the split always ends before, when every corner has a cell of its own.
MAX_QUADTREE_DEPTH = 16


@dataclass
class Features:
    """Keypoints of one image with their descriptors; row i of every array is feature i."""

    uv: np.ndarray  # (N, 2) float64, level-0 pixels
    level: np.ndarray  # (N,) int, pyramid level (octave)
    angle: np.ndarray  # (N,) float64, degrees in [0, 360), intensity-centroid orientation
    response: np.ndarray  # (N,) float32, FAST score
    descriptors: np.ndarray  # (N, 32) uint8, rBRIEF

    def __len__(self) -> int:
        return len(self.uv)

    def subset(self, index_or_mask: np.ndarray) -> "Features":
        """The features selected by an index array or a boolean mask, in that order."""
        index = np.asarray(index_or_mask)
        return Features(
            uv=self.uv[index],
            level=self.level[index],
            angle=self.angle[index],
            response=self.response[index],
            descriptors=self.descriptors[index],
        )

    @staticmethod
    def empty() -> "Features":
        return Features(
            uv=np.zeros((0, 2)),
            level=np.zeros(0, dtype=int),
            angle=np.zeros(0),
            response=np.zeros(0, dtype=np.float32),
            descriptors=np.zeros((0, DESCRIPTOR_BYTES), dtype=np.uint8),
        )

    @staticmethod
    def concatenate(parts: list["Features"]) -> "Features":
        if not parts:
            return Features.empty()
        return Features(
            uv=np.concatenate([p.uv for p in parts]),
            level=np.concatenate([p.level for p in parts]),
            angle=np.concatenate([p.angle for p in parts]),
            response=np.concatenate([p.response for p in parts]),
            descriptors=np.concatenate([p.descriptors for p in parts]),
        )


# ------------------------------------------------------------------------------------------- scales


def level_scales(config: OrbConfig) -> np.ndarray:
    """s^l for every level l: a level-l pixel spans this many level-0 pixels (ORB-SLAM2 mvScaleFactor)."""
    return config.scale_factor ** np.arange(config.num_levels, dtype=float)


def level_sigma2s(config: OrbConfig) -> np.ndarray:
    """s^(2l) for every level: the variance of a keypoint's position, in level-0 pixels^2, up to a constant
    (ORB-SLAM2 mvLevelSigma2). FDMO eq. 6 weighs a residual by its inverse, ``level_inv_sigma2s``."""
    return level_scales(config) ** 2


def level_inv_sigma2s(config: OrbConfig) -> np.ndarray:
    """s^(-2l) for every level (ORB-SLAM2 mvInvLevelSigma2): the information of a level-l observation."""
    return 1.0 / level_sigma2s(config)


def features_per_level(config: OrbConfig) -> np.ndarray:
    """The quota of each level: N (1 - 1/s) / (1 - (1/s)^L) (1/s)^l, rounded, the last level taking what
    is left (ORB-SLAM2 ORBextractor constructor): the same density of features per unit area at every level."""
    shrink = 1.0 / config.scale_factor
    first = config.num_features * (1.0 - shrink) / (1.0 - shrink**config.num_levels)
    quota = np.round(first * shrink ** np.arange(config.num_levels)).astype(int)
    quota[-1] = max(config.num_features - int(quota[:-1].sum()), 0)
    return quota


# -------------------------------------------------------------------------------------------- extractor


class OrbExtractor:
    """ORB-SLAM2's ORB extractor: ``extract(image, mask=None) -> Features``. Deterministic."""

    def __init__(self, config: OrbConfig = OrbConfig()):
        self.config = config
        self.quota = features_per_level(config)
        self.scales = level_scales(config)
        self.border = config.edge_threshold - BORDER_BELOW_EDGE_THRESHOLD
        self._fast = cv2.FastFeatureDetector_create(config.min_fast_threshold, nonmaxSuppression=True,
                                                    type=cv2.FAST_FEATURE_DETECTOR_TYPE_9_16)
        # OpenCV computes the descriptors on its own pyramid of the same sizes (cvRound(size / s^l)), blurred
        # as ORB-SLAM2 does; its edge threshold only drops keypoints closer to the border than ours are.
        self._orb = cv2.ORB_create(
            nfeatures=config.num_features,
            scaleFactor=config.scale_factor,
            nlevels=config.num_levels,
            edgeThreshold=self.border,
            firstLevel=0,
            WTA_K=2,
            patchSize=config.patch_size,
            fastThreshold=config.fast_threshold,
        )

    # ---------------------------------------------------------------------------------- scales

    def level_scale(self, level: np.ndarray | int) -> np.ndarray | float:
        return self.config.scale_factor ** np.asarray(level)

    def level_sigma2(self, level: np.ndarray | int) -> np.ndarray | float:
        return self.config.scale_factor ** (2 * np.asarray(level))

    def level_inv_sigma2(self, level: np.ndarray | int) -> np.ndarray | float:
        return 1.0 / self.level_sigma2(level)

    # -------------------------------------------------------------------------------- extract

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        """ORB features of a gray uint8 image (a colour image is converted); ``mask`` (HxW, nonzero = allowed)
        keeps only corners that fall on allowed level-0 pixels."""
        gray = _gray_uint8(image)
        if mask is not None and np.shape(mask) != gray.shape:
            raise ValueError(f"mask of shape {np.shape(mask)} for an image of shape {gray.shape}")
        xy, level, response, angle = [], [], [], []
        for index, level_image in enumerate(self.pyramid(gray)):
            corners, strength = self._level_corners(index, level_image, mask)
            if len(corners):
                xy.append(corners)
                level.append(np.full(len(corners), index))
                response.append(strength)
                angle.append(self._orientation(level_image, corners))
        if not xy:
            return Features.empty()
        return self._describe(gray, *(np.concatenate(part) for part in (xy, level, angle, response)))[0]

    def pyramid(self, gray: np.ndarray) -> list[np.ndarray]:
        """Level l is level l - 1 resized to round(size / s^l) (ORB-SLAM2 ComputePyramid, bilinear)."""
        height, width = gray.shape
        levels = [gray]
        for scale in self.scales[1:]:
            size = (int(round(width / scale)), int(round(height / scale)))
            if min(size) < 1:
                break
            levels.append(cv2.resize(levels[-1], size, interpolation=cv2.INTER_LINEAR))
        return levels

    # ---------------------------------------------------------------------------- per level

    def _level_corners(self, level: int, image: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The corners kept on one level: (xy (n, 2) int level pixels, FAST response (n,) float32)."""
        height, width = image.shape
        lo, hi_x, hi_y = self.border, width - self.border, height - self.border
        if self.quota[level] <= 0 or hi_x <= lo or hi_y <= lo:
            return np.zeros((0, 2), int), np.zeros(0, np.float32)
        bounds = (lo, hi_x, hi_y)
        # One detection at minThFAST: a FAST response is the highest threshold at which the pixel is a corner, so
        # the iniThFAST corners are those responding at least that much (the same corners, non-maximum suppression
        # included: a weaker neighbour never suppresses a stronger corner), in the same raster order.
        all_xy, all_response = self._fast_corners(image, bounds, mask, self.scales[level])
        strong = all_response >= self.config.fast_threshold
        xy, response = all_xy[strong], all_response[strong]
        cell_of, cells = self._cell_grid(bounds)
        has_strong = np.zeros(cells, dtype=bool)
        has_strong[cell_of(xy)] = True
        if not has_strong.all():  # ORB-SLAM2: minThFAST in the cells where iniThFAST found nothing
            fallback = ~has_strong[cell_of(all_xy)]
            xy = np.concatenate([xy, all_xy[fallback]])
            response = np.concatenate([response, all_response[fallback]])
        keep = distribute_quadtree(xy, response, (lo, lo, hi_x, hi_y), int(self.quota[level]))
        return xy[keep], response[keep]

    def _fast_corners(
        self, image: np.ndarray, bounds: tuple[int, int, int], mask: np.ndarray | None, scale: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """FAST corners within ``bounds`` (lo, hi_x, hi_y) and on allowed mask pixels: (xy (n, 2), response)."""
        keypoints = self._fast.detect(image)
        if not keypoints:
            return np.zeros((0, 2), int), np.zeros(0, np.float32)
        xy = np.rint(cv2.KeyPoint_convert(keypoints)).astype(int)  # FAST corners are on integer pixels
        response = np.array([k.response for k in keypoints], dtype=np.float32)
        lo, hi_x, hi_y = bounds
        inside = (xy[:, 0] >= lo) & (xy[:, 0] < hi_x) & (xy[:, 1] >= lo) & (xy[:, 1] < hi_y)
        if mask is not None:
            inside &= self._allowed_by_mask(mask, xy, scale)
        return xy[inside], response[inside]

    @staticmethod
    def _allowed_by_mask(mask: np.ndarray, xy: np.ndarray, scale: float) -> np.ndarray:
        height, width = mask.shape
        uv = (xy + 0.5) * scale - 0.5
        col = np.clip(np.rint(uv[:, 0]).astype(int), 0, width - 1)
        row = np.clip(np.rint(uv[:, 1]).astype(int), 0, height - 1)
        return np.asarray(mask)[row, col] != 0

    def _cell_grid(self, bounds: tuple[int, int, int]):
        """(cell index of corners (n, 2) -> (n,), number of cells) of the FAST cells over ``bounds``."""
        lo, hi_x, hi_y = bounds
        cell_w, cols = _cells(hi_x - lo, self.config.cell_size)
        cell_h, rows = _cells(hi_y - lo, self.config.cell_size)

        def cell_of(xy: np.ndarray) -> np.ndarray:
            return ((xy[:, 1] - lo) // cell_h) * cols + (xy[:, 0] - lo) // cell_w

        return cell_of, rows * cols

    # ---------------------------------------------------------------------------- orientation

    @cached_property
    def _disc_half_widths(self) -> np.ndarray:
        """The half width of each row d = -r..r of the disc of radius r = patch_size // 2 (ORB-SLAM2 umax):
        round(sqrt(r^2 - d^2)) near the centre, and near the top and bottom the transpose of those rows, so that
        the disc is symmetric about its diagonal and its columns have the same half widths."""
        radius = self.config.patch_size // 2
        diagonal = radius * np.sqrt(2.0) / 2.0
        near = np.arange(int(np.floor(diagonal + 1)) + 1)
        half = np.zeros(radius + 1, dtype=int)
        half[near] = np.rint(np.sqrt(radius**2 - near**2)).astype(int)
        for row in range(int(np.ceil(diagonal)), radius + 1):
            half[row] = near[half[near] >= row].max()  # the widest column of the central rows reaching this row
        return half[np.abs(np.arange(-radius, radius + 1))]

    def _orientation(self, image: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """Angle in degrees of the intensity centroid (m10, m01) of the disc around each corner (Rosin 1999,
        ORB-SLAM2 IC_Angle). Corners are ``border`` >= the disc radius inside the level, so the disc fits."""
        m10, m01 = _disc_moments(image, np.ascontiguousarray(xy, dtype=np.int64), self._disc_half_widths)
        return np.degrees(np.arctan2(m01, m10)) % FULL_CIRCLE_DEG

    # ---------------------------------------------------------------------------- descriptors

    def describe(self, image: np.ndarray, uv: np.ndarray) -> tuple[Features, np.ndarray]:
        """ORB features at given level-0 pixels (points tracked by other means: the feature initializer's KLT
        tracks): orientation and descriptor at the nearest pixel, ``uv`` kept as given. Returns the features of
        the points far enough from the border to be described, and their rows in ``uv``."""
        gray = _gray_uint8(image)
        height, width = gray.shape
        xy = np.rint(np.asarray(uv, float).reshape(-1, 2)).astype(int)
        inside = ((xy >= self.border) & (xy < np.array([width, height]) - self.border)).all(axis=1)
        rows = np.flatnonzero(inside)
        if len(rows) == 0:
            return Features.empty(), rows
        xy = xy[rows]
        features, described = self._describe(
            gray, xy, np.zeros(len(rows), int), self._orientation(gray, xy), np.zeros(len(rows), np.float32)
        )
        rows = rows[described]
        features.uv = np.asarray(uv, float).reshape(-1, 2)[rows]
        return features, rows

    def _describe(
        self, gray: np.ndarray, xy: np.ndarray, level: np.ndarray, angle: np.ndarray, response: np.ndarray
    ) -> tuple[Features, np.ndarray]:
        """The features OpenCV could describe, and which of the given corners they are."""
        scale = self.scales[level][:, None]
        # OpenCV finds a keypoint's level pixel as round(pt / s^l): hand it ORB-SLAM2's x * s^l.
        pt = (xy * scale).tolist()
        sizes = (self.config.patch_size * scale[:, 0]).tolist()
        keypoints = [
            cv2.KeyPoint(x, y, size, a, r, o, i)
            for i, ((x, y), size, a, r, o) in enumerate(
                zip(pt, sizes, angle.tolist(), response.tolist(), level.tolist())
            )
        ]
        described, descriptors = self._orb.compute(gray, keypoints)
        if descriptors is None or not described:
            return Features.empty(), np.zeros(0, int)
        order = np.array([k.class_id for k in described], dtype=int)  # OpenCV may drop or reorder keypoints
        features = Features(
            uv=(xy[order] + 0.5) * scale[order] - 0.5,
            level=level[order].astype(int),
            angle=angle[order],
            response=response[order].astype(np.float32),
            descriptors=np.ascontiguousarray(descriptors, dtype=np.uint8),
        )
        return features, order


# -------------------------------------------------------------------------------------------- quadtree


def distribute_quadtree(
    xy: np.ndarray, response: np.ndarray, bounds: tuple[int, int, int, int], target: int
) -> np.ndarray:
    """Indices of about ``target`` corners spread over ``bounds`` (x0, y0, x1, y1): ORB-SLAM2's
    DistributeOctTree without a loop per node.

    The region is split into round(w / h) square-ish roots, then into quadrants depth by depth: a node of
    depth d is a cell of a 2^d grid over its root. At the first depth where the occupied cells reach
    ``target``, ORB-SLAM2 would have split only part of the previous depth's nodes, the most populated first,
    until it had enough: the same here. Each final node keeps its strongest corner; when more than ``target``
    remain, the strongest ``target`` of them.

    Corners are sorted once by their Z-order code (root, then two bits per depth, coarsest first): the cells of
    any depth are then runs of equal code prefixes, children runs nested in their parent's run."""
    count = len(xy)
    if count <= target:
        return np.argsort(-response, kind="stable")
    codes = _quadtree_codes(xy, bounds)
    order = np.argsort(codes, kind="stable")
    codes = codes[order]
    for depth in range(1, MAX_QUADTREE_DEPTH + 1):
        child = codes >> np.uint64(2 * (MAX_QUADTREE_DEPTH - depth))
        if _run_starts(child).sum() >= target:  # distinct corners have distinct codes: this ends by the last depth
            break
    parent = codes >> np.uint64(2 * (MAX_QUADTREE_DEPTH - depth + 1))
    node_starts = _split_most_populated_first(parent, child, target)
    return _strongest_per_run(order, response, node_starts, target)


def _quadtree_codes(xy: np.ndarray, bounds: tuple[int, int, int, int]) -> np.ndarray:
    """Z-order code of each corner at depth MAX_QUADTREE_DEPTH: root index, then row and column bits interleaved
    from the coarsest split down, so that code >> 2 (MAX - d) is the corner's cell at depth d."""
    x0, y0, x1, y1 = bounds
    roots = max(1, int(round((x1 - x0) / (y1 - y0))))  # ORB-SLAM2: round(width / height) roots side by side
    side = 2**MAX_QUADTREE_DEPTH
    u = (xy[:, 0] - x0) * (roots * side / (x1 - x0))
    v = (xy[:, 1] - y0) * (side / (y1 - y0))
    col = np.minimum(np.floor(u), roots * side - 1).astype(np.uint64)
    row = np.minimum(np.floor(v), side - 1).astype(np.uint64)
    root = col >> np.uint64(MAX_QUADTREE_DEPTH)
    col &= np.uint64(side - 1)
    return (root << np.uint64(2 * MAX_QUADTREE_DEPTH)) | (_spread_bits(row) << np.uint64(1)) | _spread_bits(col)


def _spread_bits(value: np.ndarray) -> np.ndarray:
    """Bits b15..b0 of 16-bit values moved to positions 30, 28, .., 0 (zeros between): Morton interleaving."""
    value = value.astype(np.uint64)
    for shift, keep in ((8, 0x00FF00FF), (4, 0x0F0F0F0F), (2, 0x33333333), (1, 0x55555555)):
        value = (value | (value << np.uint64(shift))) & np.uint64(keep)
    return value


def _run_starts(sorted_values: np.ndarray) -> np.ndarray:
    """Mask of the first element of each run of equal values."""
    starts = np.ones(len(sorted_values), dtype=bool)
    starts[1:] = sorted_values[1:] != sorted_values[:-1]
    return starts


def _split_most_populated_first(parent: np.ndarray, child: np.ndarray, target: int) -> np.ndarray:
    """Mask of the first corner of each final node (runs of the sorted codes) when only the most populated
    parents are split into their children, as many as needed for ``target`` nodes (ORB-SLAM2 splits the nodes
    with most keypoints first near the end; ties: in Z-order)."""
    parent_starts, child_starts = _run_starts(parent), _run_starts(child)
    first = np.flatnonzero(parent_starts)
    population = np.diff(np.append(first, len(parent)))
    children_per_parent = np.add.reduceat(child_starts.astype(np.int64), first)
    order = np.lexsort((np.arange(len(first)), -population))
    gained = np.cumsum(children_per_parent[order] - 1)
    needed = int(np.searchsorted(gained, target - len(first))) + 1  # parents to split
    split = np.zeros(len(first), dtype=bool)
    split[order[:needed]] = True
    parent_of_corner = np.cumsum(parent_starts) - 1
    return parent_starts | (child_starts & split[parent_of_corner])


def _strongest_per_run(order: np.ndarray, response: np.ndarray, run_starts: np.ndarray, target: int) -> np.ndarray:
    """The strongest corner of each run (ties: the first in the run), at most ``target``, strongest first.
    ``order`` maps sorted positions to corner indices."""
    strength = response[order]
    first = np.flatnonzero(run_starts)
    run_max = np.maximum.reduceat(strength, first)
    run_of = np.cumsum(run_starts) - 1
    candidates = np.flatnonzero(strength == run_max[run_of])
    best = order[candidates[_run_starts(run_of[candidates])]]
    return best[np.argsort(-response[best], kind="stable")][:target]


# ------------------------------------------------------------------------------------------------ helpers


@kernel
def _disc_moments(image: np.ndarray, xy: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(m10, m01) of each corner's disc, whose row at offset d = -r..r spans columns -half[d]..half[d]: the sums
    of u I(x + u, y + d) and d I(x + u, y + d), exact in integers (one pass over the disc's pixels, as IC_Angle)."""
    radius = (len(half) - 1) // 2
    m10, m01 = np.empty(len(xy)), np.empty(len(xy))
    for i in range(len(xy)):
        x, y = xy[i, 0], xy[i, 1]
        sum_u, sum_v = 0, 0
        for d in range(-radius, radius + 1):
            row_sum, weighted = 0, 0
            for u in range(-half[d + radius], half[d + radius] + 1):
                value = np.int64(image[y + d, x + u])
                row_sum += value
                weighted += u * value
            sum_u += weighted
            sum_v += d * row_sum
        m10[i], m01[i] = sum_u, sum_v
    return m10, m01


def _cells(length: int, cell_size: int) -> tuple[int, int]:
    """(cell length, number of cells) covering ``length`` pixels with cells of about ``cell_size``
    (ORB-SLAM2: nCols = width / W, wCell = ceil(width / nCols))."""
    number = max(1, length // cell_size)
    return int(np.ceil(length / number)), number


def _gray_uint8(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if image.dtype != np.uint8:
        raise ValueError(f"ORB needs a uint8 image, got {image.dtype}")
    return np.ascontiguousarray(image)
