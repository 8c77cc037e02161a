"""The bag-of-words vocabulary: training, the tree descent against a per-descriptor reference, tf-idf and the L1
score, files (round trip, and every kind of broken file as an InputError), the inverted index, the bundled file."""

from __future__ import annotations

import zipfile

import cv2
import numpy as np
import pytest

from vo_core.errors import InputError
from vo_core.features.config import OrbConfig, VocabularyConfig
from vo_core.features.matcher import hamming
from vo_core.features.orb import OrbExtractor
from vo_core.features.vocabulary import (
    BowVector,
    InvertedIndex,
    Vocabulary,
    bow_score,
    default_vocabulary_path,
    load_vocabulary,
    train_vocabulary,
    train_vocabulary_from_images,
)
from vo_core.synthetic import make_sequence

TINY = VocabularyConfig(branching=4, depth=2, direct_index_levels_up=1)  # 16 words, 4 direct-index nodes
SMALL = VocabularyConfig(branching=16, depth=3, direct_index_levels_up=1)  # 4096 words: enough to tell places
TRAINING_VIEWS = [("smooth", 1), ("planar", 1), ("forward", 2), ("smooth", 2)]  # (preset, seed), frames 0 and 10
# Places never trained on: each scene's frame 0 is a keyframe, its frame QUERY_OFFSET a later visit.
PLACES = [("smooth", 5), ("smooth", 6), ("smooth", 7), ("planar", 5), ("planar", 6), ("forward", 5)]
QUERY_OFFSET = 4


def _descriptors_of(preset: str, seed: int, frames) -> list[np.ndarray]:
    sequence = make_sequence(preset, max(frames) + 1, seed=seed)
    extractor = OrbExtractor(OrbConfig())
    return [extractor.extract(sequence[i].image).descriptors for i in frames]


@pytest.fixture(scope="module")
def training_set() -> list[np.ndarray]:
    """ORB descriptors of two views of four synthetic scenes: training images only."""
    return [d for preset, seed in TRAINING_VIEWS for d in _descriptors_of(preset, seed, (0, 10))]


@pytest.fixture(scope="module")
def small(training_set) -> Vocabulary:
    return train_vocabulary(training_set, SMALL, seed=0)


@pytest.fixture(scope="module")
def tiny(training_set) -> Vocabulary:
    return train_vocabulary(training_set, TINY, seed=0)


@pytest.fixture(scope="module")
def places() -> dict[tuple[str, int], tuple[np.ndarray, np.ndarray]]:
    """(keyframe descriptors, later-visit descriptors) of every place."""
    return {place: tuple(_descriptors_of(*place, (0, QUERY_OFFSET))) for place in PLACES}


# ------------------------------------------------------------------------------------------ training


def test_training_is_deterministic_per_seed(training_set, tiny):
    again = train_vocabulary(training_set, TINY, seed=0)
    np.testing.assert_array_equal(again.parents, tiny.parents)
    np.testing.assert_array_equal(again.node_descriptors, tiny.node_descriptors)
    np.testing.assert_array_equal(again.word_weights, tiny.word_weights)
    other = train_vocabulary(training_set, TINY, seed=1)
    assert not np.array_equal(other.node_descriptors, tiny.node_descriptors)


def test_tree_has_the_configured_shape(small):
    assert small.branching == 16 and small.depth == 3
    assert small.num_words > 0.9 * 16**3  # a full tree, up to a few small clusters
    children_per_node = np.bincount(small.parents[1:], minlength=small.num_nodes)
    assert children_per_node.max() <= 16
    assert np.all(small.parents[1:] < np.arange(1, small.num_nodes))


def test_clusters_are_bitwise_majorities_of_their_members():
    """Two groups of noisy copies of two descriptors: k = 2, L = 1 recovers both exactly (the majority of
    copies with 10 % of their bits flipped is the original)."""
    rng = np.random.default_rng(3)
    centres = rng.integers(0, 256, (2, 32), dtype=np.uint8)
    flips = np.packbits(rng.random((400, 256)) < 0.1, axis=1)
    noisy = centres[np.arange(400) % 2] ^ flips
    vocabulary = train_vocabulary(noisy, VocabularyConfig(branching=2, depth=1), seed=0, image_ids=np.arange(400) % 7)
    words = vocabulary.node_descriptors[1:]
    assert sorted(map(bytes, words)) == sorted(map(bytes, centres))


def test_idf_is_zero_for_words_in_every_image_and_log_n_over_ni_otherwise():
    rng = np.random.default_rng(4)
    common, rare = rng.integers(0, 256, (2, 32), dtype=np.uint8)
    images = [np.stack([common, rare]), np.stack([common]), np.stack([common]), np.stack([common])]
    vocabulary = train_vocabulary(images, VocabularyConfig(branching=2, depth=1), seed=0)
    common_word = vocabulary.word_of_node[vocabulary.descend(common[None])[0][0]]
    rare_word = vocabulary.word_of_node[vocabulary.descend(rare[None])[0][0]]
    assert vocabulary.word_weights[common_word] == 0.0
    assert vocabulary.word_weights[rare_word] == pytest.approx(np.log(4 / 1))
    bow, _ = vocabulary.transform(np.stack([common, rare, rare]))
    np.testing.assert_array_equal(bow.words, [rare_word])  # a word of zero idf says nothing about an image


def test_one_array_needs_image_ids(training_set):
    with pytest.raises(ValueError, match="image_ids"):
        train_vocabulary(np.concatenate(training_set), TINY)


# ------------------------------------------------------------------------------------------ transform


def _reference_descent(vocabulary: Vocabulary, descriptor: np.ndarray, direct_level: int) -> tuple[int, int]:
    """One descriptor down the tree the slow way: nearest child (first on ties) until a leaf."""
    node, level, direct = 0, 0, 0
    while True:
        children = [c for c in vocabulary.children[node] if c >= 0]
        if not children:
            return node, (node if level < direct_level else direct)
        distances = hamming(descriptor[None], vocabulary.node_descriptors[children])[0]
        node, level = children[int(np.argmin(distances))], level + 1
        if level == direct_level:
            direct = node


def test_vectorized_descent_matches_the_reference(small, places):
    descriptors = places[PLACES[0]][0][:200]
    leaves, direct = small.descend(descriptors)
    expected = [_reference_descent(small, d, small.depth - small.direct_index_levels_up) for d in descriptors]
    np.testing.assert_array_equal(leaves, [leaf for leaf, _ in expected])
    np.testing.assert_array_equal(direct, [node for _, node in expected])
    # The direct-index node is the leaf's ancestor one level up (direct_index_levels_up = 1 here).
    np.testing.assert_array_equal(small.parents[leaves], direct)


def test_bow_vector_is_sorted_l1_normalized_tf_idf(small, places):
    descriptors = places[PLACES[0]][0]
    bow, nodes = small.transform(descriptors)
    assert nodes.shape == (len(descriptors),)
    assert np.all(np.diff(bow.words) > 0) and np.all(bow.weights > 0)
    assert bow.weights.sum() == pytest.approx(1.0)
    words = small.word_of_node[small.descend(descriptors)[0]]
    expected = np.bincount(words, minlength=small.num_words) * small.word_weights
    np.testing.assert_allclose(bow.weights, expected[bow.words] / expected.sum())
    empty, no_nodes = small.transform(np.zeros((0, 32), np.uint8))
    assert len(empty) == 0 and no_nodes.shape == (0,)


def test_score_is_dbow2_l1(small, places):
    a, _ = small.transform(places[PLACES[0]][0])
    b, _ = small.transform(places[PLACES[0]][1])
    c, _ = small.transform(places[PLACES[3]][0])

    def dense(v: BowVector) -> np.ndarray:
        out = np.zeros(small.num_words)
        out[v.words] = v.weights
        return out

    assert small.score(a, b) == pytest.approx(1.0 - 0.5 * np.abs(dense(a) - dense(b)).sum())
    assert small.score(a, a) == pytest.approx(1.0) and small.score(a, b) == pytest.approx(small.score(b, a))
    assert 0.0 <= small.score(a, c) < small.score(a, b) < 1.0  # a later view of the same place is more alike
    assert bow_score(a, BowVector.empty()) == 0.0


# ---------------------------------------------------------------------------------------------- files


def test_save_load_round_trip_gives_identical_transforms(tmp_path, small, places):
    path = tmp_path / "vocabulary.npz"
    small.save(path)
    assert zipfile.is_zipfile(path)
    loaded = Vocabulary.load(path, direct_index_levels_up=SMALL.direct_index_levels_up)
    for name in ("parents", "node_descriptors", "word_weights", "children", "word_of_node"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(small, name))
    for descriptors in places[PLACES[0]] + places[PLACES[3]]:
        (bow_a, nodes_a), (bow_b, nodes_b) = small.transform(descriptors), loaded.transform(descriptors)
        np.testing.assert_array_equal(bow_a.words, bow_b.words)
        np.testing.assert_array_equal(bow_a.weights, bow_b.weights)
        np.testing.assert_array_equal(nodes_a, nodes_b)


def test_load_vocabulary_honours_the_path_and_caches(tmp_path, tiny):
    path = tmp_path / "tiny.npz"
    tiny.save(path)
    config = VocabularyConfig(path=str(path), direct_index_levels_up=1)
    first = load_vocabulary(config)
    assert load_vocabulary(config) is first
    np.testing.assert_array_equal(first.node_descriptors, tiny.node_descriptors)
    assert first.direct_index_levels_up == 1
    assert load_vocabulary(VocabularyConfig(path=str(path), direct_index_levels_up=2)).direct_index_levels_up == 2


def _write_npz(path, **arrays):
    with open(path, "wb") as file:
        np.savez(file, **arrays)


def _saved_arrays(vocabulary: Vocabulary, path) -> dict[str, np.ndarray]:
    vocabulary.save(path)
    with np.load(path) as data:
        return {key: data[key] for key in data.files}


def _broken_files(tmp_path, tiny):
    """(name, writer) of every kind of broken vocabulary file."""
    good = tmp_path / "good.npz"
    arrays = _saved_arrays(tiny, good)
    content = good.read_bytes()

    def write(name, data: bytes):
        (tmp_path / name).write_bytes(data)

    def edited(name, **changes):
        _write_npz(tmp_path / name, **{**arrays, **changes})

    def without(name, key):
        _write_npz(tmp_path / name, **{k: v for k, v in arrays.items() if k != key})

    bad_parents = arrays["parents"].copy()
    bad_parents[3] = len(bad_parents) - 1  # a parent after its child
    return {
        "zero.npz": lambda: write("zero.npz", b""),
        "truncated.npz": lambda: write("truncated.npz", content[: len(content) // 2]),
        "garbage.npz": lambda: write("garbage.npz", np.random.default_rng(0).bytes(4096)),
        "flipped.npz": lambda: write("flipped.npz", content[:200] + bytes([content[200] ^ 0xFF]) + content[201:]),
        "missing_key.npz": lambda: without("missing_key.npz", "word_weights"),
        "version.npz": lambda: edited("version.npz", format_version=np.int64(99)),
        "parents.npz": lambda: edited("parents.npz", parents=bad_parents),
        "weights.npz": lambda: edited("weights.npz", word_weights=arrays["word_weights"][:-1]),
        "nan.npz": lambda: edited("nan.npz", word_weights=np.full_like(arrays["word_weights"], np.nan)),
        "descriptors.npz": lambda: edited("descriptors.npz", node_descriptors=arrays["node_descriptors"][:, :16]),
        "pickled.npz": lambda: edited("pickled.npz", kind=np.array([{"a": 1}], dtype=object)),
    }


@pytest.mark.parametrize(
    "name",
    [
        "zero.npz",
        "truncated.npz",
        "garbage.npz",
        "flipped.npz",
        "missing_key.npz",
        "version.npz",
        "parents.npz",
        "weights.npz",
        "nan.npz",
        "descriptors.npz",
        "pickled.npz",
        "absent.npz",
    ],
)
def test_broken_files_raise_one_line_input_errors_naming_the_file(tmp_path, tiny, name):
    writers = _broken_files(tmp_path, tiny)
    if name in writers:
        writers[name]()
    with pytest.raises(InputError) as caught:
        Vocabulary.load(tmp_path / name)
    message = str(caught.value)
    assert name in message and "\n" not in message
    with pytest.raises(InputError):
        load_vocabulary(VocabularyConfig(path=str(tmp_path / name)))


def test_unreadable_training_images_raise_input_errors(tmp_path):
    image = make_sequence("planar", 1, seed=0, width=320, height=240)[0].image
    good, bad = tmp_path / "good.png", tmp_path / "bad.png"
    cv2.imwrite(str(good), image)
    bad.write_bytes(b"not a png")
    with pytest.raises(InputError, match="bad.png"):
        train_vocabulary_from_images([good, bad], TINY)
    vocabulary = train_vocabulary_from_images([good, good], TINY, seed=0)
    assert vocabulary.num_words > 1


# ------------------------------------------------------------------------------------- inverted index


def _place_recognition(vocabulary: Vocabulary, places: dict) -> tuple[InvertedIndex, dict, dict]:
    """An index of every place's keyframe; returns it with the keyframes' and the later visits' BoW vectors."""
    keyframes = {place: vocabulary.transform(views[0])[0] for place, views in places.items()}
    visits = {place: vocabulary.transform(views[1])[0] for place, views in places.items()}
    index = InvertedIndex()
    for place, bow in keyframes.items():
        index.add(place, bow)
    return index, keyframes, visits


def test_keyframes_rank_first_for_their_own_image_and_a_later_visit(small, places):
    index, keyframes, visits = _place_recognition(small, places)
    for place, bow in keyframes.items():
        results = index.query(bow)
        assert results[0][0] == place and results[0][1] == pytest.approx(1.0)
        assert [r[1] for r in results] == sorted((r[1] for r in results), reverse=True)
        assert index.query(visits[place], max_results=1)[0][0] == place


def test_index_remove_restrict_and_max_results(small, places):
    index, _, visits = _place_recognition(small, places)
    first, others = PLACES[0], set(PLACES[1:3])
    query = visits[first]
    assert len(index.query(query, max_results=2)) <= 2
    restricted = index.query(query, restrict_to=others)
    assert restricted and {r[0] for r in restricted} <= others
    index.remove(first)
    assert first not in index and all(r[0] != first for r in index.query(query))
    index.remove(first)  # twice: nothing happens
    assert index.query(BowVector.empty()) == [] and InvertedIndex().query(query) == []


def test_candidates_share_at_least_eight_tenths_of_the_most_common_words():
    def bow(words):
        return BowVector(np.array(words, dtype=np.int32), np.full(len(words), 1.0 / len(words)))

    index = InvertedIndex()
    index.add("ten", bow(range(10)))
    index.add("eight", bow(range(8)))  # 8 of 10 shared words: kept
    index.add("seven", bow(list(range(7)) + [50, 51, 52, 53]))  # 7: dropped, though a candidate by score
    results = index.query(bow(range(10)))
    assert [r[0] for r in results] == ["ten", "eight"]
    assert [r[2] for r in results] == [10, 8]


# ---------------------------------------------------------------------------------------- bundled file


def test_bundled_vocabulary_is_small_and_recognizes_places_it_never_saw(places):
    path = default_vocabulary_path()
    assert path.is_file() and path.stat().st_size < 1_000_000
    vocabulary = load_vocabulary(VocabularyConfig())
    assert (vocabulary.branching, vocabulary.depth) == (10, 4) and vocabulary.num_words > 5000
    assert load_vocabulary(VocabularyConfig()) is vocabulary
    index, keyframes, visits = _place_recognition(vocabulary, places)
    for place in keyframes:
        assert index.query(visits[place], max_results=1)[0][0] == place
