"""The feature map M^f of FDMO (section 4): keyframes with ORB features, 3D map points, and who sees what.

A feature keyframe is the twin of a direct keyframe: it carries the direct keyframe's frame index and pose,
and never a pose of its own (FDMO's design: one pose per keyframe, the direct one; ``sync_poses`` follows the
window optimization). Its ``point_ids`` say, per feature, which map point the feature observes (-1: none):
these arrays are the only record of observations, so the covisibility graph (Strasdat et al. 2011; an edge
per pair of keyframes that share points, weighted by how many) is computed from them when asked and is
always up to date, however points and keyframes come and go.

Map points live in flat arrays (position, viewing direction, representative descriptor, the keyframe that created
them, the distance and pyramid level they were seen at), indexed by point id; a removed point keeps its row,
marked dead, until most rows are dead and the map compacts itself: point ids are valid from one mapping step to
the next, not forever.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import sparse

from vo_core.features.config import OrbConfig
from vo_core.features.matcher import least_median_descriptors
from vo_core.features.orb import Features
from vo_core.features.vocabulary import BowVector, InvertedIndex
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3_inverse, sim3_pose, sim3_scale, transform_points
from vo_core.geometry.reprojection import sum_by

NO_POINT = -1
# Dead point rows are dropped once they are more than half of at least this many (ours: ids stay stable in
# between, and compaction then costs one pass over the keyframes every few hundred keyframes).
MIN_ROWS_TO_COMPACT = 4096
MIN_VIEWING_COSINE = 0.5  # ORB-SLAM2 MapPoint/Frame: mfViewingCosLimit = 0.5 (60 degrees)
MAX_DEAD_SHARE = 0.5


@dataclass
class FeatureKeyframe:
    keyframe_id: int  # order of creation in the feature map (FDMO 4.4 counts keyframes with it)
    frame_index: int  # the direct twin's frame index: the key both halves know a keyframe by
    timestamp: float
    T_world_cam: np.ndarray
    features: Features
    bow: BowVector
    nodes: np.ndarray  # (N,) vocabulary node of each feature (DBoW2's direct index)
    scene_depth: float = np.nan  # median depth of the direct twin's points (FDMO 4.4's baseline / depth rule)
    point_ids: np.ndarray = field(default=None)  # (N,) int64, map point of each feature or NO_POINT
    image: np.ndarray | None = None  # kept while the direct twin is in the window (for viewers), then dropped
    in_direct_window: bool = True
    segment: int = 0  # the map segment it belongs to (FeatureMap.begin_segment), set when it joins the map
    # (N, 3) where each feature's map point lay in this keyframe's camera frame when its pose became final (``settle``;
    # NaN where it observed none): None while its direct twin is in the window
    seen_points: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.point_ids is None:
            self.point_ids = np.full(len(self.features), NO_POINT, dtype=np.int64)

    @property
    def centre(self) -> np.ndarray:
        return self.T_world_cam[:3, 3]

    def observed(self) -> np.ndarray:
        """Feature indices that observe a map point."""
        return np.flatnonzero(self.point_ids >= 0)

    def place(self, S_world_cam: np.ndarray) -> None:
        """A loop's correction or a merge moves the keyframe by a similarity: its pose takes the rotation and the
        centre, and what it saw (``seen_points``) the scale, as the map's points do."""
        self.T_world_cam = sim3_pose(S_world_cam)
        if self.seen_points is not None:
            self.seen_points = self.seen_points * sim3_scale(S_world_cam)


class MapPoints:
    """Struct-of-arrays storage of the map points; ids are row numbers, valid until the map compacts itself.

    Rows live in arrays of doubling capacity (appending a keyframe's points costs no copy of the map); the
    attributes are views of the used rows."""

    COLUMNS = {  # name -> (shape of a row, dtype)
        "position": ((3,), np.float64),
        "normal": ((3,), np.float64),  # mean viewing direction, from the observing cameras to the point
        "descriptor": ((32,), np.uint8),  # the representative descriptor (ORB-SLAM2 distinctive descriptor)
        "first_keyframe": ((), np.int64),  # keyframe_id of the keyframe that created the point
        "reference_distance": ((), np.float64),  # camera distance at creation ...
        "reference_level": ((), np.int64),  # ... and the level it was matched at (scale prediction)
        "alive": ((), bool),
        "segment": ((), np.int64),  # the map segment the point belongs to (FeatureMap.begin_segment)
    }

    def __init__(self):
        self.active_segment = 0  # the segment new points join
        self._count = 0
        self._storage = {name: np.zeros((0, *shape), dtype) for name, (shape, dtype) in self.COLUMNS.items()}

    def __len__(self) -> int:
        return self._count

    def __getattr__(self, name: str) -> np.ndarray:
        storage = self.__dict__.get("_storage")
        if storage is None or name not in storage:
            raise AttributeError(name)
        return storage[name][: self._count]

    @property
    def num_alive(self) -> int:
        return int(self.alive.sum())

    def add(self, position, descriptor, first_keyframe: int, reference_distance, reference_level,
            normal=None) -> np.ndarray:
        """New rows; ``normal`` defaults to the direction from the origin of ``reference_distance``'s camera,
        which the caller gives when it knows it (the creating keyframe's viewing direction)."""
        count = len(position)
        self._reserve(self._count + count)
        rows = slice(self._count, self._count + count)
        values = {
            "position": position, "descriptor": descriptor, "first_keyframe": first_keyframe,
            "reference_distance": reference_distance, "reference_level": reference_level, "alive": True,
            "segment": self.active_segment,
            "normal": np.zeros((count, 3)) if normal is None else normal,
        }
        for name, value in values.items():
            self._storage[name][rows] = value
        self._count += count
        return np.arange(rows.start, rows.stop)

    def _reserve(self, needed: int) -> None:
        capacity = len(self._storage["alive"])
        if needed <= capacity:
            return
        capacity = max(needed, 2 * capacity, 1024)
        for name, column in self._storage.items():
            grown = np.zeros((capacity, *column.shape[1:]), column.dtype)
            grown[: self._count] = column[: self._count]
            self._storage[name] = grown

    def keep_only(self, rows: np.ndarray) -> None:
        """Compact the storage to ``rows`` (in order): the new id of row rows[i] is i."""
        for name, column in self._storage.items():
            self._storage[name] = column[rows].copy()
        self._count = len(rows)


@dataclass
class Observations:
    """Every observation of the keyframes asked for, as parallel arrays."""

    keyframe: np.ndarray  # (L,) frame index of the observing keyframe
    feature: np.ndarray  # (L,) feature index in that keyframe
    point: np.ndarray  # (L,) map point id

    def __len__(self) -> int:
        return len(self.point)


class FeatureMap:
    def __init__(self):
        self.keyframes: dict[int, FeatureKeyframe] = {}  # frame index -> keyframe, in order of creation
        self.points = MapPoints()
        self.index = InvertedIndex()
        self.next_keyframe_id = 0
        # The active segment: the direct map's current start. With loop closure a map started anew after a loss is a
        # new segment in its own frame and scale, and the older ones are kept until a place seen in both merges them
        # (loop_closing.py); until then nothing but the loop closer looks at them.
        self.segment = 0
        # A culled keyframe's place in the final trajectory (ORB-SLAM2's spanning tree): the keyframe that shared the
        # most points with it when it left, and its pose relative to that one (T_parent_culled).
        self.culled_parents: dict[int, tuple[int, np.ndarray]] = {}
        # The places of the loops closed, (older, newer) keyframe (ORB-SLAM2's loop edges): each stays in the pose graph
        # of every later loop, and its keyframes are never culled, so a place closed once stays closed when a later
        # loop bends the map. A merge is not one: it moves the older map rigidly, untested by a pose graph, and a
        # later loop must be free to bend a wrong one (parking, a place merged from 9.9 m apart, put a map 10 m off).
        self.loop_edges: set[tuple[int, int]] = set()

    def __len__(self) -> int:
        return len(self.keyframes)

    # ------------------------------------------------------------------------------------ keyframes

    def add_keyframe(self, keyframe: FeatureKeyframe) -> None:
        keyframe.segment = self.segment
        self.keyframes[keyframe.frame_index] = keyframe
        self.index.add(keyframe.frame_index, keyframe.bow)
        self.next_keyframe_id = keyframe.keyframe_id + 1

    def remove_keyframe(self, frame_index: int) -> None:
        """A culled keyframe takes its observations along; points left with fewer than two observations die
        (a point needs two views to have been triangulated, and one to be found again)."""
        shared = self.covisibility(frame_index)
        keyframe = self.keyframes.pop(frame_index)
        if shared:
            parent = self.keyframes[max(shared, key=shared.get)]
            T_parent_culled = se3_inverse(parent.T_world_cam) @ keyframe.T_world_cam
            self.culled_parents[frame_index] = (parent.frame_index, T_parent_culled)
        self.index.remove(frame_index)
        orphans = keyframe.point_ids[keyframe.point_ids >= 0]
        counts = self.observation_counts(orphans)
        self.points.alive[orphans[counts < 2]] = False
        self._forget_dead()

    def loop_keyframes(self) -> set[int]:
        """The keyframes at either end of a loop edge."""
        return {frame_index for edge in self.loop_edges for frame_index in edge}

    def final_poses(self) -> dict[int, np.ndarray]:
        """Every keyframe's pose as the map ends: the kept ones' own, a culled one's on its parent's final pose (ORB-
        SLAM2's SaveTrajectoryTUM follows the same links), where the chain of parents reaches a kept keyframe."""
        final = {frame_index: keyframe.T_world_cam for frame_index, keyframe in self.keyframes.items()}
        for frame_index in self.culled_parents:
            chain = []  # up the parents to one whose final pose is known (a parent was kept when its child left)
            while frame_index not in final and frame_index in self.culled_parents and frame_index not in chain:
                chain.append(frame_index)
                frame_index = self.culled_parents[frame_index][0]
            if frame_index in final:
                for culled in reversed(chain):
                    parent, T_parent_culled = self.culled_parents[culled]
                    final[culled] = final[parent] @ T_parent_culled
        return final

    def settle(self, keyframe: FeatureKeyframe) -> None:
        """The keyframe's direct twin left the window: its pose is final (until a loop moves it), its image is
        dropped, and where it sees its points now is kept (``seen_points``). The points go on being adjusted at
        the later keyframes' poses, and an old keyframe's view of them drifts off its image (fr1/desk: each keyframe's
        own points 1 px off its features, median, when it settles; 3-6 px, 15-30 px at the 90th percentile, 200
        keyframes later): what it saw then is what its pose and its features agree on (loop_closing.py measures a
        loop's similarity on it)."""
        keyframe.in_direct_window, keyframe.image = False, None
        observed = keyframe.observed()
        observed = observed[self.points.alive[keyframe.point_ids[observed]]]
        keyframe.seen_points = np.full((len(keyframe.point_ids), 3), np.nan)
        keyframe.seen_points[observed] = self.in_camera(keyframe, keyframe.point_ids[observed])

    def in_camera(self, keyframe: FeatureKeyframe, point_ids: np.ndarray) -> np.ndarray:
        """The points' positions (N, 3) in the keyframe's camera frame, where the map has them now."""
        return transform_points(se3_inverse(keyframe.T_world_cam), self.points.position[point_ids])

    def begin_segment(self) -> None:
        """The direct map starts anew at a new scale: what the map holds becomes an older segment."""
        for keyframe in self.keyframes.values():
            if keyframe.in_direct_window:
                self.settle(keyframe)
        self.segment += 1
        self.points.active_segment = self.segment

    def drop_segment(self) -> None:
        """The active segment's keyframes and points go (a start found wrong); older segments stay."""
        for frame_index in [f for f, k in self.keyframes.items() if k.segment == self.segment]:
            self.keyframes.pop(frame_index)
            self.index.remove(frame_index)
        self.loop_edges = {edge for edge in self.loop_edges if all(f in self.keyframes for f in edge)}
        self.points.alive[self.points.segment == self.segment] = False
        self._forget_dead()

    def active_keyframes(self) -> list[FeatureKeyframe]:
        """The active segment's keyframes, in order of creation."""
        return [k for k in self.keyframes.values() if k.segment == self.segment]

    def searchable(self) -> set[int] | None:
        """The keyframes a recovery may search: the active segment's (None: the map has no other)."""
        if all(k.segment == self.segment for k in self.keyframes.values()):
            return None
        return {k.frame_index for k in self.active_keyframes()}

    def reindex(self, keyframe: FeatureKeyframe) -> None:
        """The inverted index learns a keyframe's new bag of words (after features were added to it)."""
        self.index.remove(keyframe.frame_index)
        self.index.add(keyframe.frame_index, keyframe.bow)

    def newest(self) -> FeatureKeyframe | None:
        return next(reversed(self.keyframes.values())) if self.keyframes else None

    def sync_poses(self, poses: dict[int, np.ndarray]) -> None:
        """The direct keyframes' poses (after a window optimization) become the feature keyframes' own."""
        for frame_index, T_world_cam in poses.items():
            keyframe = self.keyframes.get(frame_index)
            if keyframe is not None:
                keyframe.T_world_cam = T_world_cam.copy()

    # ------------------------------------------------------------------------------------ observations

    def observations(self, frame_indices=None) -> Observations:
        keyframes = [self.keyframes[i] for i in (self.keyframes if frame_indices is None else frame_indices)]
        if not keyframes:
            empty = np.zeros(0, np.int64)
            return Observations(empty, empty, empty)
        # One pass over every keyframe's features side by side (asked for several times a keyframe, over the map).
        sizes = np.array([len(k.point_ids) for k in keyframes], np.int64)
        all_points = np.concatenate([k.point_ids for k in keyframes])
        observed = np.flatnonzero(all_points >= 0)
        owner = np.repeat(np.arange(len(keyframes)), sizes)[observed]
        frame_indices = np.array([k.frame_index for k in keyframes], np.int64)
        first_feature = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        return Observations(frame_indices[owner], observed - first_feature[owner], all_points[observed])

    def pixels_of(self, keyframe_of: np.ndarray, feature_of: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel (L, 2) and pyramid level (L,) of each observation (keyframe, feature)."""
        uv = np.zeros((len(feature_of), 2))
        level = np.zeros(len(feature_of), np.int64)
        for frame_index in np.unique(keyframe_of):
            mine = keyframe_of == frame_index
            features = self.keyframes[int(frame_index)].features
            uv[mine], level[mine] = features.uv[feature_of[mine]], features.level[feature_of[mine]]
        return uv, level

    def keyframe_ids_of(self, frame_indices: np.ndarray) -> np.ndarray:
        """The keyframe_id (creation order) of keyframes given by frame index."""
        frames = np.array(list(self.keyframes), np.int64)
        ids = np.array([k.keyframe_id for k in self.keyframes.values()], np.int64)
        return ids[positions_in(frames, frame_indices)]

    def observation_counts(self, point_ids: np.ndarray) -> np.ndarray:
        """How many keyframes observe each of ``point_ids``."""
        return self.observers_per_point()[np.asarray(point_ids, np.int64)]

    def observers_per_point(self) -> np.ndarray:
        """(points,) how many keyframes observe each point (by id; dead points none)."""
        return np.bincount(self.observations().point, minlength=len(self.points))

    def covisibility(self, frame_index: int) -> dict[int, int]:
        """Weights of the covisibility graph's edges at a keyframe: other keyframe -> shared points."""
        ids = self.keyframes[frame_index].point_ids
        mine = np.zeros(len(self.points), bool)
        mine[ids[ids >= 0]] = True
        table = self.observations()
        shared = mine[table.point] & (table.keyframe != frame_index)
        keyframes, counts = np.unique(table.keyframe[shared], return_counts=True)
        return dict(zip(keyframes.tolist(), counts.tolist()))

    def covisible_keyframes(self, frame_index: int, min_weight: int, limit: int | None = None) -> list[int]:
        """Neighbours in the covisibility graph, most shared points first (ORB-SLAM2 GetBestCovisibilityKeyFrames)."""
        return best_covisible(self.covisibility(frame_index), min_weight, limit)

    def covisibility_graph(self) -> "Covisibility":
        """The whole graph and every point's observation count at once, for many questions between two changes."""
        return Covisibility(self, self.observations())

    def points_of(self, frame_indices) -> np.ndarray:
        """Ids of the live points observed by any of the keyframes."""
        ids = [self.keyframes[i].point_ids for i in frame_indices if i in self.keyframes]
        if not ids:
            return np.zeros(0, np.int64)
        ids = np.unique(np.concatenate(ids))
        ids = ids[ids >= 0]
        return ids[self.points.alive[ids]]

    def update_normals(self, point_ids: np.ndarray) -> None:
        """Each point's viewing direction: the mean of the unit rays from the keyframes that observe it to the
        point (ORB-SLAM2 MapPoint::UpdateNormalAndDepth), for the visibility test of ``project_points``."""
        table = self.observations()
        wanted = np.isin(table.point, point_ids)
        observers, observer_of = np.unique(table.keyframe[wanted], return_inverse=True)
        centres = np.array([self.keyframes[int(k)].centre for k in observers]).reshape(-1, 3)[observer_of]
        rays = self.points.position[table.point[wanted]] - centres
        rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
        sums = sum_by(table.point[wanted], rays, len(self.points))
        norms = np.linalg.norm(sums[point_ids], axis=1, keepdims=True)
        self.points.normal[point_ids] = np.where(norms > 0, sums[point_ids] / np.maximum(norms, 1e-12), 0.0)

    def remove_points(self, point_ids: np.ndarray) -> None:
        self.points.alive[np.asarray(point_ids, np.int64)] = False
        self._forget_dead()

    def remove_observations(self, keyframe_of: np.ndarray, feature_of: np.ndarray) -> None:
        """Outlier observations leave their keyframes (their points may stay, seen elsewhere)."""
        for frame_index in np.unique(keyframe_of):
            mine = keyframe_of == frame_index
            self.keyframes[int(frame_index)].point_ids[feature_of[mine]] = NO_POINT

    def merge_points(self, duplicates: np.ndarray, survivors: np.ndarray) -> None:
        """Each duplicate's observations become its survivor's, and the duplicate dies (ORB-SLAM2 MapPoint::Replace);
        a keyframe that would then observe a survivor twice keeps one observation."""
        if len(duplicates) == 0:
            return
        new_id = np.arange(len(self.points))
        new_id[duplicates] = survivors
        for keyframe in self.keyframes.values():
            observed = keyframe.observed()
            ids = new_id[keyframe.point_ids[observed]]
            _, first = np.unique(ids, return_index=True)
            kept = np.zeros(len(ids), bool)
            kept[first] = True
            keyframe.point_ids[observed] = np.where(kept, ids, NO_POINT)
        self.points.alive[duplicates] = False

    def _forget_dead(self) -> None:
        """No keyframe keeps an observation of a dead point."""
        dead = ~self.points.alive
        for keyframe in self.keyframes.values():
            observed = keyframe.observed()
            keyframe.point_ids[observed[dead[keyframe.point_ids[observed]]]] = NO_POINT

    def compact(self) -> None:
        """Once most rows are dead, drop them and renumber the points, so that a long run's storage follows the
        live map (which culling keeps bounded). Point ids held elsewhere are invalid afterwards: the mapper calls
        this at the end of a keyframe, nothing holds ids across keyframes."""
        if len(self.points) < MIN_ROWS_TO_COMPACT or self.points.alive.mean() >= 1.0 - MAX_DEAD_SHARE:
            return
        live = np.flatnonzero(self.points.alive)
        new_id = np.full(len(self.points), NO_POINT, np.int64)
        new_id[live] = np.arange(len(live))
        self.points.keep_only(live)
        for keyframe in self.keyframes.values():
            observed = keyframe.observed()
            keyframe.point_ids[observed] = new_id[keyframe.point_ids[observed]]

    def representative_descriptors(self, point_ids: np.ndarray) -> None:
        """ORB-SLAM2 MapPoint::ComputeDistinctiveDescriptors: each point's descriptor becomes the one of its
        observations with the least median Hamming distance to the others (a compiled pass over each point's
        observations, side by side)."""
        table = self.observations()
        wanted = np.isin(table.point, point_ids)
        order = np.argsort(table.point[wanted], kind="stable")
        points = table.point[wanted][order]
        if len(points) == 0:
            return
        descriptors = self.descriptors_of(table.keyframe[wanted][order], table.feature[wanted][order])
        unique, start = np.unique(points, return_index=True)
        best = least_median_descriptors(descriptors, np.append(start, len(points)))
        self.points.descriptor[unique] = descriptors[best]

    def descriptors_of(self, keyframe_of: np.ndarray, feature_of: np.ndarray) -> np.ndarray:
        """The ORB descriptor (L, 32) of each observation (keyframe, feature)."""
        descriptors = np.zeros((len(feature_of), self.points.descriptor.shape[1]), np.uint8)
        for frame_index in np.unique(keyframe_of):
            mine = keyframe_of == frame_index
            descriptors[mine] = self.keyframes[int(frame_index)].features.descriptors[feature_of[mine]]
        return descriptors


def positions_in(keys: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Where each of ``values`` stands in ``keys`` (distinct, any order; every value among them), by a search: a
    dictionary lookup per observation cost ~1 ms each time a local map's tables were built."""
    order = np.argsort(keys)
    return order[np.searchsorted(keys[order], values)]


def best_covisible(weights: dict[int, int], min_weight: int, limit: int | None) -> list[int]:
    """The keyframes of at least ``min_weight`` shared points, most first, the newest first among equals."""
    ranked = sorted((k for k, w in weights.items() if w >= min_weight), key=lambda k: (-weights[k], -k))
    return ranked[:limit]


class Covisibility:
    """A map's covisibility graph and observation counts at one moment, from one pass over its observations: what
    FeatureMap.covisibility and observation_counts say, for the many keyframes and points asked about between two
    changes of the map (tracking asks for each local keyframe's neighbours at every frame). Built again after a
    change: it does not follow the map."""

    def __init__(self, feature_map: FeatureMap, table: Observations):
        self.table = table
        self.frames = np.array(list(feature_map.keyframes), np.int64)
        row_of = {frame_index: row for row, frame_index in enumerate(self.frames)}
        rows = positions_in(self.frames, table.keyframe)
        shape = (len(self.frames), len(feature_map.points))
        seen = sparse.csr_matrix((np.ones(len(rows), np.int64), (rows, table.point)), shape=shape)  # duplicates add
        sees = seen.copy()
        sees.data[:] = 1
        # weight (k, l): l's observations of k's points, as FeatureMap.covisibility counts them
        self.weights = (sees @ seen.T).toarray()
        np.fill_diagonal(self.weights, 0)
        self.row_of = row_of
        self.counts = np.bincount(table.point, minlength=len(feature_map.points))

    def observation_counts(self, point_ids: np.ndarray) -> np.ndarray:
        return self.counts[np.asarray(point_ids, np.int64)]

    def covisible_keyframes(self, frame_index: int, min_weight: int, limit: int | None = None) -> list[int]:
        weights = self.weights[self.row_of[frame_index]]
        shared = np.flatnonzero(weights)
        return best_covisible(dict(zip(self.frames[shared].tolist(), weights[shared].tolist())), min_weight, limit)


@dataclass
class Projection:
    """Map points seen from a camera: where they land and at which pyramid level they should be detected."""

    point_ids: np.ndarray  # (K,) the points in view
    uv: np.ndarray  # (K, 2)
    level: np.ndarray  # (K,) predicted level
    distance: np.ndarray  # (K,) from the camera centre


def project_points(points: MapPoints, point_ids: np.ndarray, T_world_cam: np.ndarray, camera: PinholeCamera,
                   orb: OrbConfig) -> Projection:
    """The points in view of a camera (ORB-SLAM2 Frame::isInFrustum): in front of it, inside the image, and at a
    distance the ORB pyramid covers (MapPoint::PredictScale: a point seen at level n from distance d appears at
    level n + log_Sf(d / distance); more than one level outside the pyramid is out of view)."""
    point_ids = np.asarray(point_ids, np.int64)
    points_cam = transform_points(se3_inverse(T_world_cam), points.position[point_ids])
    front = points_cam[:, 2] > 0
    uv = np.full((len(point_ids), 2), -1.0)
    uv[front] = camera.project(points_cam[front])
    distance = np.linalg.norm(points_cam, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.log(points.reference_distance[point_ids] / np.maximum(distance, 1e-12)) / np.log(orb.scale_factor)
    level = np.round(points.reference_level[point_ids] + shift)
    top = orb.num_levels - 1
    in_pyramid = np.isfinite(level) & (level >= -1) & (level <= top + 1)
    # Seen from more than 60 degrees off its mean viewing direction, a point's patch has changed too much to be
    # matched, and is likely on the far side of its object (ORB-SLAM2 isInFrustum: viewCos < 0.5). A point
    # without a direction yet (all zeros) passes.
    rays = points.position[point_ids] - T_world_cam[:3, 3]
    cosine = np.sum(rays * points.normal[point_ids], axis=1) / np.maximum(np.linalg.norm(rays, axis=1), 1e-12)
    facing = (cosine >= MIN_VIEWING_COSINE) | ~points.normal[point_ids].any(axis=1)
    visible = front & camera.in_image(uv) & in_pyramid & facing
    level = np.clip(np.nan_to_num(level[visible]), 0, top).astype(np.int64)
    return Projection(point_ids[visible], uv[visible], level, distance[visible])
