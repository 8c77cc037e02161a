"""Train the vocabulary shipped in assets/vocabulary/ and check that it generalizes.

    python benchmarks/vocabulary_train.py                      # train, save, check on frames it did not see
    python benchmarks/vocabulary_train.py --held-out           # also: leave each folder out in turn

Training images: every STRIDE-th frame of the shared sequences (TUM fr3/teddy, KITTI 00, VAMR parking, EuRoC
V1_01) and a few frames rendered by vo_core.synthetic, ORB with the default OrbConfig, k = 10, L = 4
(VocabularyConfig), seed 0. The shared folders are not part of a clone: this script is the recipe, its output
is the shipped file.

Checks (place recognition as relocalization uses it): keyframes are every KEYFRAME_STRIDE-th frame of a
sequence, indexed in an InvertedIndex; a keyframe's own image must rank it first, and a frame QUERY_OFFSET
frames after a keyframe (never a training image) must rank that keyframe first. ``--held-out`` trains
without one folder and runs the checks on it, for each folder: the real test of generalization.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from vo_core.features.config import OrbConfig, VocabularyConfig
from vo_core.features.orb import OrbExtractor
from vo_core.features.vocabulary import (
    InvertedIndex,
    Vocabulary,
    default_vocabulary_path,
    train_vocabulary_from_images,
)
from vo_core.synthetic import make_sequence

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"  # ../shared/data beside the repository
# folder name -> (images folder inside it, training stride: every 2nd-5th frame, about 50 images per folder)
FOLDERS = {
    "tum_fr3_teddy_first200": ("rgb", 4),
    "kitti00_first100": ("image_0", 2),
    "vamr_parking_first200": ("images", 4),
    "euroc_v101_micro_static": ("mav0/cam0/data", 3),
}
SYNTHETIC = [("smooth", 0), ("forward", 1), ("rotation", 2), ("planar", 3)]  # (preset, seed)
SYNTHETIC_FRAMES = (0, 20, 40, 59)  # four views along each 60-frame trajectory
KEYFRAME_STRIDE = 10
QUERY_OFFSET = 3  # closer to its keyframe (3 frames) than to the next one (7 frames)
SEED = 0


def folder_images(name: str) -> list[Path]:
    images, _ = FOLDERS[name]
    return sorted((DATA / name / images).glob("*.png"))


def training_images(folders: list[str]) -> list[Path]:
    return [path for name in folders for path in folder_images(name)[:: FOLDERS[name][1]]]


def synthetic_images(directory: Path) -> list[Path]:
    """Frames of the synthetic presets written as PNG, so that training reads files like the CLI will."""
    paths = []
    for preset, seed in SYNTHETIC:
        sequence = make_sequence(preset, num_frames=max(SYNTHETIC_FRAMES) + 1, seed=seed)
        for index in SYNTHETIC_FRAMES:
            path = directory / f"synthetic_{preset}_{seed}_{index:03d}.png"
            cv2.imwrite(str(path), sequence[index].image)
            paths.append(path)
    return paths


def train(paths: list[Path]) -> tuple[Vocabulary, float]:
    start = time.perf_counter()
    vocabulary = train_vocabulary_from_images(paths, VocabularyConfig(), SEED, OrbConfig())
    return vocabulary, time.perf_counter() - start


def place_recognition(vocabulary: Vocabulary, name: str, training: set[Path]) -> dict:
    """Keyframes every KEYFRAME_STRIDE frames of folder ``name``; rank-1 rates of their own images and of the
    frames QUERY_OFFSET after them (skipping any that were training images)."""
    extractor = OrbExtractor(OrbConfig())
    paths = folder_images(name)
    bows = {}
    transform_ms = []
    for index in range(0, len(paths)):
        if index % KEYFRAME_STRIDE in (0, QUERY_OFFSET):
            descriptors = extractor.extract(cv2.imread(str(paths[index]), cv2.IMREAD_GRAYSCALE)).descriptors
            start = time.perf_counter()
            bows[index] = vocabulary.transform(descriptors)[0]
            transform_ms.append(1000 * (time.perf_counter() - start))
    index = InvertedIndex()
    keyframes = [i for i in bows if i % KEYFRAME_STRIDE == 0]
    for keyframe in keyframes:
        index.add(keyframe, bows[keyframe])
    own = [index.query(bows[k], max_results=1)[0][0] == k for k in keyframes]
    neighbours = [
        (k, index.query(bows[k + QUERY_OFFSET], max_results=3))
        for k in keyframes
        if k + QUERY_OFFSET in bows and paths[k + QUERY_OFFSET] not in training
    ]
    top1 = [bool(result) and result[0][0] == k for k, result in neighbours]
    top3 = [any(r[0] == k for r in result) for k, result in neighbours]
    return {
        "keyframes": len(keyframes),
        "own_image_rank1": float(np.mean(own)),
        "neighbour_queries": len(neighbours),
        "neighbour_rank1": float(np.mean(top1)) if top1 else None,
        "neighbour_in_top3": float(np.mean(top3)) if top3 else None,
        "transform_ms_median": float(np.median(transform_ms)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=default_vocabulary_path())
    parser.add_argument("--held-out", action="store_true", help="also train without each folder and test on it")
    args = parser.parse_args()
    report: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        synthetic = synthetic_images(Path(tmp))
        if args.held_out:
            report["held_out"] = {}
            for held_out in FOLDERS:
                paths = training_images([n for n in FOLDERS if n != held_out])
                vocabulary, seconds = train(paths + synthetic)
                report["held_out"][held_out] = {"train_s": round(seconds, 1), "words": vocabulary.num_words}
                report["held_out"][held_out].update(place_recognition(vocabulary, held_out, set()))
                print(held_out, json.dumps(report["held_out"][held_out]), flush=True)
        paths = training_images(list(FOLDERS))
        vocabulary, seconds = train(paths + synthetic)
    vocabulary.save(args.out)
    report["shipped"] = {
        "file": str(args.out),
        "bytes": args.out.stat().st_size,
        "training_images": len(paths) + len(synthetic),
        "train_s": round(seconds, 1),
        "words": vocabulary.num_words,
        "nodes": vocabulary.num_nodes,
        "zero_idf_words": int(np.sum(vocabulary.word_weights == 0.0)),
        "checks": {name: place_recognition(vocabulary, name, set(paths)) for name in FOLDERS},
    }
    print(json.dumps(report["shipped"], indent=1))


if __name__ == "__main__":
    main()
