"""A bag-of-words vocabulary of ORB descriptors and an inverted index of keyframes (FDMO 4.2.2: the frame to
recover is "parsed into a vocabulary tree" and matched to keyframes within the tree's nodes).

After DBoW2 (Galvez-Lopez and Tardos 2012; dorian3d/DBoW2 TemplatedVocabulary, FORB, BowVector,
FeatureVector, L1Scoring) and ORB-SLAM2's KeyFrameDatabase, rewritten for numpy:

- the vocabulary is a tree of branching k and depth L whose nodes are binary descriptors: hierarchical
  k-medians (k-means++ seeding, bitwise-majority centres, Hamming distance); its leaves are the words, each
  weighted by its inverse document frequency idf = log(N / N_i) over the N training images;
- ``transform`` descends the tree for all descriptors at once, one level per step, and returns the image's
  tf-idf vector normalized to unit L1 norm (``BowVector``: sorted word ids and weights) and each feature's
  node ``direct_index_levels_up`` levels above the words (DBoW2's direct index, the FeatureVector that
  ORB-SLAM2's SearchByBoW matches within);
- ``score`` is DBoW2's L1 score 1 - |a - b|_1 / 2 of two normalized vectors, in [0, 1];
- ``InvertedIndex`` ranks keyframes by that score among those sharing enough words with a query.

A vocabulary is stored as an npz file (``save``/``load``), no pickles; the one shipped with the package is
``default_vocabulary_path()``, trained by benchmarks/vocabulary_train.py.
"""

from __future__ import annotations

import os
from collections.abc import Hashable, Iterable, Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from vo_core.assets import ASSETS_DIR
from vo_core.errors import InputError
from vo_core.features.config import OrbConfig, VocabularyConfig
from vo_core.features.matcher import hamming, hamming_rows
from vo_core.features.orb import DESCRIPTOR_BYTES, OrbExtractor

FORMAT_VERSION = 1
FILE_KIND = "fdmo-orb-vocabulary"
VOCABULARY_FILE = "vocabulary/orb_k10_l4.npz"  # under the package's assets (vo_core.assets.ASSETS_DIR)
ROOT = 0  # the root node: no descriptor of its own, parent of the first level
NO_NODE = -1  # parent of the root; padding of the children table
# Larger than any Hamming distance between 256-bit descriptors: a missing child is never the nearest.
UNREACHABLE = 8 * DESCRIPTOR_BYTES + 1
_FILE_KEYS = ("format_version", "kind", "branching", "depth", "parents", "node_descriptors", "word_weights")


# ------------------------------------------------------------------------------------------ BoW vectors


@dataclass(frozen=True)
class BowVector:
    """A sparse bag-of-words vector: ``words`` (n,) int32 strictly increasing, ``weights`` (n,) float64 > 0
    summing to 1 (tf-idf, L1-normalized, as DBoW2 with TF_IDF weighting and L1 scoring)."""

    words: np.ndarray
    weights: np.ndarray

    def __len__(self) -> int:
        return len(self.words)

    @staticmethod
    def empty() -> "BowVector":
        return BowVector(np.zeros(0, dtype=np.int32), np.zeros(0))


def bow_score(a: BowVector, b: BowVector) -> float:
    """DBoW2's L1 score 1 - |a - b|_1 / 2 of two L1-normalized vectors: in [0, 1], 1 for equal vectors. For
    unit vectors with non-negative weights it is the sum over shared words of min(a_w, b_w)."""
    _, in_a, in_b = np.intersect1d(a.words, b.words, assume_unique=True, return_indices=True)
    return min(1.0, float(np.minimum(a.weights[in_a], b.weights[in_b]).sum()))  # 1 + rounding for equal vectors


# ----------------------------------------------------------------------------------------- vocabulary


class Vocabulary:
    """A k-majority tree of ORB descriptors with idf-weighted leaves (words).

    Nodes are numbered breadth first: node 0 is the root, and every node's parent has a smaller number, so
    ``parents`` alone describes the tree. ``word_weights[w]`` is the idf of word w; words are the leaves in
    node order. Arrays are read-only: a loaded vocabulary is shared by everything in the process."""

    def __init__(
        self,
        parents: np.ndarray,
        node_descriptors: np.ndarray,
        word_weights: np.ndarray,
        branching: int,
        depth: int,
        direct_index_levels_up: int = VocabularyConfig.direct_index_levels_up,
    ):
        self.branching = int(branching)
        self.depth = int(depth)
        self.direct_index_levels_up = int(direct_index_levels_up)
        self.parents = _read_only(np.asarray(parents, dtype=np.int32))
        self.node_descriptors = _read_only(np.ascontiguousarray(node_descriptors, dtype=np.uint8))
        self.word_weights = _read_only(np.asarray(word_weights, dtype=np.float64))
        self.children = _read_only(_children_table(self.parents))
        is_leaf = _leaves(self.parents)
        if len(self.word_weights) != int(is_leaf.sum()):
            raise ValueError(f"{len(self.word_weights)} word weights for a tree of {int(is_leaf.sum())} leaves")
        self.word_of_node = np.full(len(self.parents), NO_NODE, dtype=np.int32)
        self.word_of_node[is_leaf] = np.arange(int(is_leaf.sum()), dtype=np.int32)
        _read_only(self.word_of_node)

    @property
    def num_words(self) -> int:
        return len(self.word_weights)

    @property
    def num_nodes(self) -> int:
        return len(self.parents)

    def __repr__(self) -> str:
        return f"Vocabulary(k={self.branching}, L={self.depth}, words={self.num_words}, nodes={self.num_nodes})"

    # ------------------------------------------------------------------------------ transform

    def descend(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(leaf node, node at the direct-index level) of every descriptor. All descriptors go down one level
        per step to their nearest child (the first on ties, as DBoW2); a descriptor on a leaf stays there, so
        a leaf shallower than the direct-index level is also its own direct-index node."""
        descriptors = np.ascontiguousarray(descriptors, dtype=np.uint8).reshape(-1, DESCRIPTOR_BYTES)
        node = np.zeros(len(descriptors), dtype=np.int32)
        direct_level = self.depth - self.direct_index_levels_up
        direct_node = node.copy()
        for level in range(1, self.depth + 1):
            self._step_down(descriptors, node)
            if level == direct_level:
                direct_node = node.copy()
        return node, direct_node

    def _step_down(self, descriptors: np.ndarray, node: np.ndarray) -> None:
        """Move every descriptor on an inner node to its nearest child, in place."""
        children = self.children[node]
        moving = np.flatnonzero(children[:, 0] != NO_NODE)
        if len(moving) == 0:
            return
        candidates = children[moving]  # (m, k), NO_NODE padded
        distance = _distances_to_candidates(descriptors[moving], self.node_descriptors, candidates)
        node[moving] = candidates[np.arange(len(moving)), np.argmin(distance, axis=1)]

    def transform(self, descriptors: np.ndarray) -> tuple[BowVector, np.ndarray]:
        """(the image's BowVector, the direct-index node of each feature (N,) int32).

        Weight of word w: (occurrences of w) x idf(w), then L1-normalized (DBoW2 TF_IDF: its division by the
        number of features disappears in the normalization). Words of zero idf (seen in every training image)
        stay out of the vector, as in DBoW2; their features keep their node."""
        leaf, direct_node = self.descend(descriptors)
        words, counts = np.unique(self.word_of_node[leaf], return_counts=True)
        weights = counts * self.word_weights[words]
        informative = weights > 0.0
        words, weights = words[informative], weights[informative]
        total = weights.sum()
        if total <= 0.0:
            return BowVector.empty(), direct_node
        return BowVector(words.astype(np.int32), weights / total), direct_node

    @staticmethod
    def score(a: BowVector, b: BowVector) -> float:
        """DBoW2's L1 score of two BoW vectors, in [0, 1] (see ``bow_score``)."""
        return bow_score(a, b)

    # --------------------------------------------------------------------------------- files

    def save(self, path: str | Path) -> None:
        """Write the vocabulary as a compressed npz (no pickles), with a format version."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as file:
            np.savez_compressed(
                file,
                format_version=np.int64(FORMAT_VERSION),
                kind=np.str_(FILE_KIND),
                branching=np.int64(self.branching),
                depth=np.int64(self.depth),
                parents=self.parents,
                node_descriptors=self.node_descriptors,
                word_weights=self.word_weights,
            )

    @staticmethod
    def load(
        path: str | Path, direct_index_levels_up: int = VocabularyConfig.direct_index_levels_up
    ) -> "Vocabulary":
        """Read a vocabulary written by ``save``. InputError (one line naming the file) if it is missing,
        truncated, corrupt or inconsistent; never another exception."""
        path = Path(path)
        if not path.is_file():
            raise InputError(f"{path}: no vocabulary file there")
        try:
            arrays = _read_npz(path)
        except InputError:
            raise
        except Exception as error:  # zip, zlib, npy-format and OS errors alike: the file is not usable
            raise InputError(f"{path}: not a readable vocabulary file ({_one_line(error)})") from error
        _check_consistent(path, arrays)
        return Vocabulary(
            arrays["parents"],
            arrays["node_descriptors"],
            arrays["word_weights"],
            int(arrays["branching"]),
            int(arrays["depth"]),
            direct_index_levels_up,
        )


def _read_only(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


def _leaves(parents: np.ndarray) -> np.ndarray:
    """Mask of the nodes without children (the words); the root always has children."""
    return np.bincount(parents[1:], minlength=len(parents)) == 0


def _children_table(parents: np.ndarray) -> np.ndarray:
    """(num_nodes, most children of a node) children of every node in increasing order, NO_NODE padded: as wide as
    the tree needs, which the branching bounds (a file may declare any branching)."""
    width = int(np.bincount(parents[1:], minlength=len(parents)).max())
    table = np.full((len(parents), width), NO_NODE, dtype=np.int32)
    child = np.arange(1, len(parents), dtype=np.int32)
    parent = parents[1:].astype(np.int64)
    order = np.argsort(parent, kind="stable")
    parent, child = parent[order], child[order]
    first = np.searchsorted(parent, parent, side="left")
    table[parent, np.arange(len(parent)) - first] = child
    return table


def _distances_to_candidates(descriptors: np.ndarray, node_descriptors: np.ndarray, candidates: np.ndarray):
    """(m, k) Hamming distances of descriptor i to its candidate nodes (UNREACHABLE where padded)."""
    rows, width = candidates.shape
    valid = candidates != NO_NODE
    left = np.repeat(descriptors, width, axis=0)
    right = node_descriptors[np.where(valid, candidates, ROOT).ravel()]
    distance = hamming_rows(left, right).reshape(rows, width)
    return np.where(valid, distance, UNREACHABLE)


def _is_integer_scalar(value: np.ndarray) -> bool:
    return value.shape == () and np.issubdtype(value.dtype, np.integer)


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as data:
        missing = [key for key in _FILE_KEYS if key not in data.files]
        if missing:
            raise InputError(f"{path}: not a vocabulary file (missing {', '.join(missing)})")
        return {key: data[key] for key in _FILE_KEYS}


def _one_line(error: BaseException) -> str:
    text = " ".join(str(error).split()) or type(error).__name__
    return f"{type(error).__name__}: {text}" if str(error) else text


def _check_consistent(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """InputError naming the first inconsistency of a loaded file (its arrays must describe one tree)."""

    def fail(what: str) -> None:
        raise InputError(f"{path}: inconsistent vocabulary file ({what})")

    if str(arrays["kind"]) != FILE_KIND:
        fail(f"kind {str(arrays['kind'])!r}, expected {FILE_KIND!r}")
    if not _is_integer_scalar(arrays["format_version"]) or int(arrays["format_version"]) != FORMAT_VERSION:
        fail(f"format version {arrays['format_version']}, this program reads {FORMAT_VERSION}")
    for key in ("branching", "depth"):
        if not _is_integer_scalar(arrays[key]) or int(arrays[key]) < 1:
            fail(f"{key} must be a positive integer, got {arrays[key]}")
    parents, descriptors, weights = arrays["parents"], arrays["node_descriptors"], arrays["word_weights"]
    count = len(parents) if parents.ndim == 1 else -1
    if count < 2 or not np.issubdtype(parents.dtype, np.integer):
        fail(f"parents must be integers for the root and at least one word, got {parents.dtype} {parents.shape}")
    if descriptors.dtype != np.uint8 or descriptors.shape != (count, DESCRIPTOR_BYTES):
        expected = f"uint8 ({count}, {DESCRIPTOR_BYTES})"
        fail(f"node_descriptors must be {expected}, got {descriptors.dtype} {descriptors.shape}")
    if parents[0] != NO_NODE or np.any(parents[1:] < 0) or np.any(parents[1:] >= np.arange(1, count)):
        fail("every node's parent must come before it, the root first")
    if np.any(np.bincount(parents[1:], minlength=count) > int(arrays["branching"])):
        fail(f"a node has more than branching = {int(arrays['branching'])} children")
    depth = int(arrays["depth"])
    if depth >= count:
        fail(f"depth {depth} is more than a tree of {count} nodes can have")
    level = np.zeros(count, dtype=np.int64)
    for _ in range(depth + 1):  # after d rounds every node of level <= d has its level
        level[1:] = level[parents[1:]] + 1
    if level.max() > depth:
        fail(f"the tree is deeper than the file's depth {depth}")
    leaves = int(_leaves(parents).sum())
    if weights.ndim != 1 or len(weights) != leaves or not np.issubdtype(weights.dtype, np.floating):
        fail(f"word_weights must be {leaves} floats (one per leaf), got {weights.dtype} {weights.shape}")
    if not np.all(np.isfinite(weights)) or np.any(weights < 0.0):
        fail("word weights must be finite and non-negative")


# ------------------------------------------------------------------------------------- bundled file


def default_vocabulary_path() -> Path:
    """The vocabulary shipped with the package (assets/vocabulary/, i.e. vo_core/data/vocabulary/)."""
    return ASSETS_DIR / VOCABULARY_FILE


def load_vocabulary(config: VocabularyConfig = VocabularyConfig()) -> Vocabulary:
    """The vocabulary at ``config.path`` ("" = the bundled one), loaded once per process (per file version
    and direct-index level). The file's own k and L rule; ``config.branching``/``depth`` are for training."""
    path = Path(config.path) if config.path else default_vocabulary_path()
    try:
        stat = path.stat()
        key = (str(path.resolve()), stat.st_mtime_ns, stat.st_size)
    except OSError:
        key = (str(path), 0, 0)  # load reports the missing file
    return _load_cached(key, str(path), config.direct_index_levels_up)


@lru_cache(maxsize=8)
def _load_cached(key: tuple[str, int, int], path: str, direct_index_levels_up: int) -> Vocabulary:
    return Vocabulary.load(path, direct_index_levels_up)


# ------------------------------------------------------------------------------------------- training


def train_vocabulary(
    descriptors: Sequence[np.ndarray] | np.ndarray,
    config: VocabularyConfig = VocabularyConfig(),
    seed: int = 0,
    image_ids: np.ndarray | None = None,
) -> Vocabulary:
    """Train a vocabulary (DBoW2 TemplatedVocabulary::create): hierarchical k-medians to ``config.depth``
    levels of ``config.branching`` clusters, then idf word weights from the training images.

    ``descriptors`` is a list with each image's (n_i, 32) uint8 descriptors, or one (N, 32) array with
    ``image_ids`` (N,) saying which image each row comes from (idf needs to know). Deterministic for a seed."""
    stacked, image_of_row = _stack_training_set(descriptors, image_ids)
    if len(stacked) == 0:
        raise ValueError("training a vocabulary needs at least one descriptor")
    rng = np.random.default_rng(seed)
    parents, node_descriptors = _hierarchical_kmedians(stacked, config, rng)
    unweighted = Vocabulary(
        parents, node_descriptors, np.zeros(int(_leaves(parents).sum())), config.branching, config.depth
    )
    weights = _idf_weights(unweighted, stacked, image_of_row)
    return Vocabulary(
        parents, node_descriptors, weights, config.branching, config.depth, config.direct_index_levels_up
    )


def _stack_training_set(
    descriptors: Sequence[np.ndarray] | np.ndarray, image_ids: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(descriptors, np.ndarray) and descriptors.ndim == 2:
        if image_ids is None or len(image_ids) != len(descriptors):
            raise ValueError("one descriptor array needs image_ids, one per row (idf counts images)")
        return np.ascontiguousarray(descriptors, dtype=np.uint8), np.asarray(image_ids)
    parts = [np.asarray(d, dtype=np.uint8).reshape(-1, DESCRIPTOR_BYTES) for d in descriptors]
    ids = np.repeat(np.arange(len(parts)), [len(p) for p in parts])
    stacked = np.concatenate(parts) if parts else np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
    return np.ascontiguousarray(stacked), ids


def _hierarchical_kmedians(
    descriptors: np.ndarray, config: VocabularyConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """(parents, node descriptors) of the tree, nodes numbered breadth first (DBoW2 HKmeansStep, run level by
    level instead of depth first so that the numbering is breadth first; same tree for the same draws)."""
    parents = [NO_NODE]
    node_descriptors = [np.zeros(DESCRIPTOR_BYTES, dtype=np.uint8)]
    frontier = [(ROOT, np.arange(len(descriptors)))]  # nodes of the current level to split, with their rows
    for _ in range(config.depth):
        next_frontier = []
        for node, rows in frontier:
            centres, labels = _cluster(descriptors[rows], config, rng)
            for cluster, centre in enumerate(centres):
                child = len(parents)
                parents.append(node)
                node_descriptors.append(centre)
                members = rows[labels == cluster]
                if len(members) > 1:  # DBoW2: a cluster of one descriptor is a leaf
                    next_frontier.append((child, members))
        frontier = next_frontier
    return np.array(parents, dtype=np.int32), np.array(node_descriptors, dtype=np.uint8).reshape(-1, DESCRIPTOR_BYTES)


def _cluster(
    descriptors: np.ndarray, config: VocabularyConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """(centres (c, 32), label of each descriptor): k-medians in Hamming space with k-means++ seeding
    (DBoW2 HKmeansStep); at most k descriptors are each their own cluster. Empty clusters are dropped."""
    k = config.branching
    if len(descriptors) <= k:
        return descriptors.copy(), np.arange(len(descriptors))
    centres = _kmeans_plus_plus(descriptors, k, rng)
    labels = np.argmin(hamming(descriptors, centres), axis=1)
    bits = np.unpackbits(descriptors, axis=1)
    for _ in range(config.max_kmeans_iterations):
        centres, labels = _majority_centres(bits, labels)
        new_labels = np.argmin(hamming(descriptors, centres), axis=1)
        if np.array_equal(new_labels, labels):
            break
        labels = new_labels
    return _majority_centres(bits, labels)


def _kmeans_plus_plus(descriptors: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding as DBoW2 initiateClustersKMpp: the first centre uniformly, each next one with
    probability proportional to the Hamming distance (not squared) to the nearest centre so far; stops early
    when every descriptor equals a centre."""
    chosen = [int(rng.integers(len(descriptors)))]
    nearest = hamming(descriptors, descriptors[chosen]).ravel().astype(np.float64)
    while len(chosen) < k:
        total = nearest.sum()
        if total <= 0.0:
            break
        pick = int(np.searchsorted(np.cumsum(nearest), rng.uniform(0.0, total), side="left"))
        pick = min(pick, len(descriptors) - 1)
        chosen.append(pick)
        nearest = np.minimum(nearest, hamming(descriptors, descriptors[pick : pick + 1]).ravel())
    return descriptors[chosen]


def _majority_centres(bits: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bitwise-majority centre of each non-empty cluster (DBoW2 FORB::meanValue: a bit is set when at least
    half of the members, rounded up, have it) and the labels renumbered to the kept clusters."""
    used, labels = np.unique(labels, return_inverse=True)
    order = np.argsort(labels, kind="stable")
    sizes = np.bincount(labels, minlength=len(used))
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    set_bits = np.add.reduceat(bits[order], starts, axis=0, dtype=np.int32)
    majority = set_bits >= (sizes[:, None] + 1) // 2
    return np.packbits(majority.astype(np.uint8), axis=1), labels


def _idf_weights(vocabulary: Vocabulary, descriptors: np.ndarray, image_of_row: np.ndarray) -> np.ndarray:
    """idf of each word: log(N / N_w), N training images, N_w of them with the word (DBoW2 setNodeWeights;
    a word no training image reaches keeps weight 0)."""
    leaf, _ = vocabulary.descend(descriptors)
    word = vocabulary.word_of_node[leaf]
    images, image_index = np.unique(image_of_row, return_inverse=True)
    pairs = np.unique(np.stack([word.astype(np.int64), image_index]), axis=1)
    images_with_word = np.bincount(pairs[0], minlength=vocabulary.num_words)
    weights = np.zeros(vocabulary.num_words)
    seen = images_with_word > 0
    weights[seen] = np.log(len(images) / images_with_word[seen])
    return weights


def train_vocabulary_from_images(
    paths: Iterable[str | Path],
    config: VocabularyConfig = VocabularyConfig(),
    seed: int = 0,
    orb_config: OrbConfig = OrbConfig(),
) -> Vocabulary:
    """Train on the ORB features (``orb_config``) of image files, one training image per file; InputError
    naming the first file OpenCV cannot read (what ``fdmo vocabulary train IMAGES... --out FILE`` wraps)."""
    extractor = OrbExtractor(orb_config)
    per_image = []
    for path in paths:
        image = cv2.imread(os.fspath(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise InputError(f"{path}: not an image OpenCV can read")
        per_image.append(extractor.extract(image).descriptors)
    if not per_image:
        raise InputError("training a vocabulary needs at least one image")
    if sum(len(d) for d in per_image) == 0:
        raise InputError("no ORB features in any of the training images (blank or uniform images?)")
    return train_vocabulary(per_image, config, seed)


# ------------------------------------------------------------------------------------- inverted index


class InvertedIndex:
    """Keyframes by the words they contain (ORB-SLAM2 KeyFrameDatabase, without covisibility): ``query`` finds
    the keyframes sharing words with an image, keeps those with at least ``min_common_words_ratio`` times the
    largest number of shared words (DetectRelocalizationCandidates), and ranks them by L1 score."""

    def __init__(self, min_common_words_ratio: float = VocabularyConfig.min_common_words_ratio):
        self.min_common_words_ratio = min_common_words_ratio
        self._bows: dict[Hashable, BowVector] = {}
        self._postings: tuple[np.ndarray, np.ndarray, np.ndarray, list[Hashable]] | None = None

    def __len__(self) -> int:
        return len(self._bows)

    def __contains__(self, keyframe_id: Hashable) -> bool:
        return keyframe_id in self._bows

    def add(self, keyframe_id: Hashable, bow: BowVector) -> None:
        """Index a keyframe's BoW vector (replacing what was indexed under the same id)."""
        self._bows[keyframe_id] = bow
        self._postings = None

    def remove(self, keyframe_id: Hashable) -> None:
        """Forget a keyframe; nothing happens for an id that is not indexed."""
        if self._bows.pop(keyframe_id, None) is not None:
            self._postings = None

    def query(
        self, bow: BowVector, max_results: int | None = None, restrict_to: set | None = None
    ) -> list[tuple[Hashable, float, int]]:
        """(keyframe id, score, shared words) of the candidate keyframes, best score first (ties: more shared
        words, then order of insertion). Only keyframes in ``restrict_to`` when it is given (e.g. FDMO's
        local keyframes, covisible with the last keyframe)."""
        if not self._bows or len(bow) == 0:
            return []
        words, keyframe, weight, ids = self._posting_arrays()
        position = np.minimum(np.searchsorted(bow.words, words), len(bow) - 1)
        shared = bow.words[position] == words
        common = np.bincount(keyframe[shared], minlength=len(ids))
        score = np.bincount(
            keyframe[shared], weights=np.minimum(weight[shared], bow.weights[position[shared]]), minlength=len(ids)
        )
        allowed = common > 0
        if restrict_to is not None:
            allowed &= np.array([keyframe_id in restrict_to for keyframe_id in ids], dtype=bool)
        if not allowed.any():
            return []
        allowed &= common >= self.min_common_words_ratio * common[allowed].max()
        candidates = np.flatnonzero(allowed)
        ranked = candidates[np.lexsort((candidates, -common[candidates], -score[candidates]))]
        if max_results is not None:
            ranked = ranked[:max_results]
        return [(ids[i], min(1.0, float(score[i])), int(common[i])) for i in ranked]

    def _posting_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[Hashable]]:
        """(word, keyframe index, weight) of every (keyframe, word) entry, and the keyframe ids by index;
        rebuilt after a change."""
        if self._postings is None:
            ids = list(self._bows)
            bows = [self._bows[i] for i in ids]
            lengths = [len(b) for b in bows]
            self._postings = (
                np.concatenate([b.words for b in bows]).astype(np.int64),
                np.repeat(np.arange(len(ids)), lengths),
                np.concatenate([b.weights for b in bows]),
                ids,
            )
        return self._postings
