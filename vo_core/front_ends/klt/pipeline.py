"""The classic feature-tracking baseline, ``--method klt`` (paper 003, Fig. 1), plus a windowed bundle adjustment.

Per frame:
  1. KLT-track every corner (keypoints with landmarks, and candidates) from the previous frame, starting
     from where a constant-velocity motion model predicts them.
  2. P3P RANSAC pose from the landmarks, refined on the inliers; outlier keypoints are dropped. Too few
     inliers is a tracking failure: it is reported and the pipeline bootstraps again from this frame,
     placing the new map at the predicted pose with the recent speed as its scale.
  3. At a keyframe (enough parallax or too many landmarks lost): candidates seen under a large enough
     bearing angle become landmarks, the window of recent keyframes is bundle-adjusted, and new corners
     are detected away from the existing ones.
"""

from __future__ import annotations

import time
from collections import deque
from contextlib import contextmanager

import cv2
import numpy as np

from vo_core.events import Event, EventKind, FrameResult, MapSnapshot
from vo_core.front_ends.klt.bootstrap import Bootstrap, Bootstrapper
from vo_core.front_ends.klt.config import KltConfig
from vo_core.front_ends.klt.state import Keyframe, Landmarks, Tracks
from vo_core.geometry.bundle_adjustment import WindowProblem, adjust_window
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.klt import KltTracker, detect_corners
from vo_core.geometry.lie import se3_exp, se3_inverse, se3_log, transform_points
from vo_core.geometry.multiview import bearing_angles, estimate_pose, triangulate

RECENT_SPEED_FRAMES = 10  # frames whose median translation sets the scale of a re-bootstrap


class KltOdometry:
    def __init__(self, config: KltConfig, camera: PinholeCamera, seed: int = 0):
        self.config = config
        self.camera = camera
        self.seed = seed
        self.tracker = KltTracker(config.tracker)
        self.bootstrapper = Bootstrapper(
            camera, config.bootstrap, config.corners, config.triangulation, config.ba, self.tracker, seed
        )
        self.bootstrapping = False
        self.landmarks = Landmarks()
        self.tracks = Tracks.empty()
        self.keyframes: list[Keyframe] = []  # the bundle-adjustment window
        self.keyframe_poses: dict[int, np.ndarray] = {}  # every keyframe so far, for candidates and viewers
        self.landmarks_at_keyframe = 0
        self.previous_image: np.ndarray | None = None
        self.T_world_last: np.ndarray | None = None  # pose of the last tracked frame
        self.last_tracked_index = -1
        self.velocity = np.eye(4)  # T_last_next per frame, for the constant-velocity prediction
        self.recent_steps: deque[float] = deque(maxlen=RECENT_SPEED_FRAMES)
        self._events: list[Event] = []
        self._timings: dict[str, float] = {}
        self._frame = None

    # ------------------------------------------------------------------------------------------ per frame

    def process(self, frame) -> FrameResult:
        self._events, self._timings, self._frame = [], {}, frame
        cv2.setRNGSeed(self.seed + frame.index)  # OpenCV's RANSAC draws from its global generator
        start = time.perf_counter()
        if self.previous_image is None:
            result = self._start_bootstrap(frame)
        elif self.bootstrapping:
            result = self._bootstrap_step(frame)
        else:
            result = self._track(frame)
        self.previous_image = frame.image
        self._timings["total"] = (time.perf_counter() - start) * 1000.0
        result.timings_ms = self._timings
        result.events = self._events
        return result

    def map_snapshot(self) -> MapSnapshot:
        return MapSnapshot(
            feature_points_world=self.landmarks.world_points.copy(),
            keyframe_poses={index: T.copy() for index, T in self.keyframe_poses.items()},
        )

    def final_keyframe_poses(self) -> dict[int, np.ndarray]:
        """None: the baseline's poses are never refined, and its frames hang on no keyframe."""
        return {}

    # ------------------------------------------------------------------------------------------ bootstrap

    def _start_bootstrap(self, frame) -> FrameResult:
        with self._stage("bootstrap"):
            self.bootstrapper.start(frame.index, frame.image)
        self.bootstrapping = True
        self._emit(EventKind.INITIALIZATION_STARTED, corners=len(self.bootstrapper.uv_first))
        return self._no_pose(self.bootstrapper.uv_current)

    def _bootstrap_step(self, frame) -> FrameResult:
        with self._stage("bootstrap"):
            bootstrap = self.bootstrapper.step(frame.index, frame.image)
        if bootstrap is None:
            if self.bootstrapper.should_restart(frame.index):
                self._emit(EventKind.INITIALIZATION_FAILED, first_frame=self.bootstrapper.first_index,
                           reason=self.bootstrapper.last_failure or "no parallax")
                return self._start_bootstrap(frame)
            return self._no_pose(self.bootstrapper.uv_current)
        T_world_cam = self._initialize_map(bootstrap)
        self.bootstrapping = False
        landmarks = int(bootstrap.triangulated.sum())
        self._emit(EventKind.INITIALIZATION_SUCCEEDED, first_frame=bootstrap.first_frame_index,
                   first_T_world_cam=self.keyframes[0].T_world_cam.tolist(),
                   second_frame=bootstrap.second_frame_index, landmarks=landmarks,
                   median_parallax_deg=round(bootstrap.median_parallax_deg, 3))
        for keyframe in self.keyframes:  # the bootstrap's two keyframes, announced as every later one is
            self._emit(EventKind.KEYFRAME_ADDED, keyframe=keyframe.frame_index, landmarks=landmarks)
        with self._stage("detect"):
            self._detect_new_corners(frame.image, self.keyframes[-1])
        self.landmarks_at_keyframe = landmarks
        return self._pose_result(T_world_cam, is_keyframe=True, num_inliers=landmarks)

    def _initialize_map(self, bootstrap: Bootstrap) -> np.ndarray:
        """Landmarks and the first two keyframes of a bootstrap, in the world frame.

        The first bootstrap defines the world and the scale (unit baseline). A re-bootstrap after a failure
        is placed where the motion model puts its first frame, at the scale of the recent motion."""
        gap = bootstrap.second_frame_index - bootstrap.first_frame_index
        if self.T_world_last is None:
            T_world_first, scale = np.eye(4), 1.0
        else:
            T_world_first = self._predicted_pose(bootstrap.first_frame_index)
            scale = (np.median(self.recent_steps) if self.recent_steps else 1.0) * gap
        T_first_second = bootstrap.T_first_second.copy()
        T_first_second[:3, 3] *= scale
        T_world_second = T_world_first @ T_first_second

        self.landmarks = Landmarks()
        ids = self.landmarks.new_ids(len(bootstrap.uv_first))
        triangulated = bootstrap.triangulated
        self.landmarks.set(
            ids[triangulated], transform_points(T_world_first, scale * bootstrap.points_first[triangulated])
        )
        first = Keyframe(bootstrap.first_frame_index, T_world_first, ids, bootstrap.uv_first)
        second = Keyframe(bootstrap.second_frame_index, T_world_second, ids.copy(), bootstrap.uv_second)
        self.keyframes = [first, second]
        self.keyframe_poses[first.frame_index] = T_world_first
        self.keyframe_poses[second.frame_index] = T_world_second
        self.tracks = Tracks(
            ids, bootstrap.uv_second.astype(np.float32), bootstrap.uv_first.astype(np.float32),
            np.full(len(ids), bootstrap.first_frame_index), bootstrap.uv_second.astype(np.float32),
        )
        # The motion of the bootstrap, spread evenly over its frames, starts the motion model.
        self._moved_to(bootstrap.second_frame_index, T_world_second, T_first_second, gap)
        return T_world_second

    # ------------------------------------------------------------------------------------------- tracking

    def _track(self, frame) -> FrameResult:
        T_predicted = self._predicted_pose(frame.index)
        with self._stage("klt"):
            uv, valid = self.tracker.track(
                self.previous_image, frame.image, self.tracks.uv, self._predicted_uv(T_predicted)
            )
            self.tracks.uv = uv
            self.tracks = self.tracks.select(valid)
        is_landmark = self.landmarks.is_landmark(self.tracks.ids)
        with self._stage("pnp"):
            estimate = estimate_pose(
                self.camera, self.landmarks.positions[self.tracks.ids[is_landmark]], self.tracks.uv[is_landmark],
                self.config.pose, T_world_guess=T_predicted,
            )
        if estimate is None:
            return self._fail(frame, int(is_landmark.sum()))
        keep = np.ones(len(self.tracks), bool)
        keep[np.flatnonzero(is_landmark)[~estimate.inliers]] = False
        self.tracks = self.tracks.select(keep)
        T_world_cam = estimate.T_world_cam
        frames = frame.index - self.last_tracked_index
        self._moved_to(frame.index, T_world_cam, se3_inverse(self.T_world_last) @ T_world_cam, frames)

        is_keyframe = self._wants_keyframe(frame.index, T_world_cam)
        if is_keyframe:
            T_world_cam = self._add_keyframe(frame, T_world_cam)
        return self._pose_result(T_world_cam, is_keyframe, int(estimate.inliers.sum()))

    def _predicted_uv(self, T_world_predicted: np.ndarray) -> np.ndarray:
        """Where the tracks should appear: landmarks projected with the predicted pose, candidates moved by
        the median predicted flow of the landmarks."""
        predicted = self.tracks.uv.astype(np.float64)
        is_landmark = self.landmarks.is_landmark(self.tracks.ids)
        points_cam = transform_points(
            se3_inverse(T_world_predicted), self.landmarks.positions[self.tracks.ids[is_landmark]]
        )
        in_front = points_cam[:, 2] > self.config.triangulation.min_depth
        projected = self.camera.project(points_cam[in_front])
        usable = self.camera.in_image(projected)
        rows = np.flatnonzero(is_landmark)[in_front][usable]
        if len(rows):
            flow = projected[usable] - predicted[rows]
            predicted[~is_landmark] += np.median(flow, axis=0)
            predicted[rows] = projected[usable]
        return predicted.astype(np.float32)

    def _predicted_pose(self, frame_index: int) -> np.ndarray:
        """Constant velocity from the last tracked frame, over as many frames as have passed (frames the
        player dropped included)."""
        frames = frame_index - self.last_tracked_index
        return self.T_world_last @ se3_exp(frames * se3_log(self.velocity))

    def _moved_to(self, frame_index: int, T_world_cam: np.ndarray, motion: np.ndarray, frames: int) -> None:
        """Update the motion model and the recent speed with the newest pose, reached by ``motion``
        (T_last_new) over ``frames`` frames."""
        step = se3_exp(se3_log(motion) / frames) if frames > 1 else motion
        self.last_tracked_index = frame_index
        self.T_world_last = T_world_cam
        self.velocity = step
        self.recent_steps.append(float(np.linalg.norm(step[:3, 3])))

    def _fail(self, frame, landmarks: int) -> FrameResult:
        """Report the lost pose and bootstrap again from this frame (paper 003 has no recovery)."""
        self._emit(EventKind.TRACKING_FAILED, landmarks_tracked=landmarks,
                   min_inliers=self.config.pose.min_inliers)
        self._emit(EventKind.REINITIALIZATION, from_frame=frame.index)
        self.tracks = Tracks.empty()
        self.keyframes = []
        return self._start_bootstrap(frame)

    # ------------------------------------------------------------------------------------------ keyframes

    def _wants_keyframe(self, frame_index: int, T_world_cam: np.ndarray) -> bool:
        """Enough parallax since the newest keyframe to triangulate, too many landmarks lost, or too long."""
        config = self.config.keyframes
        newest = self.keyframes[-1]
        is_landmark = self.landmarks.is_landmark(self.tracks.ids)
        if not is_landmark.any():
            return True
        parallax = bearing_angles(
            self.camera, newest.T_world_cam, self.tracks.keyframe_uv[is_landmark], T_world_cam,
            self.tracks.uv[is_landmark],
        )
        return (
            np.degrees(np.median(parallax)) >= config.min_median_parallax_deg
            or is_landmark.sum() < config.min_tracked_ratio * self.landmarks_at_keyframe
            or frame_index - newest.frame_index >= config.max_frame_gap
        )

    def _add_keyframe(self, frame, T_world_cam: np.ndarray) -> np.ndarray:
        """Make the frame a keyframe: triangulate, adjust the window, renew corners. Returns its (adjusted) pose."""
        keyframe = Keyframe(frame.index, T_world_cam, self.tracks.ids.copy(), self.tracks.uv.copy())
        self.keyframes.append(keyframe)
        self.keyframes = self.keyframes[-self.config.ba.window_keyframes :]
        self.keyframe_poses[frame.index] = T_world_cam
        with self._stage("triangulate"):
            promoted = self._triangulate_candidates(T_world_cam)
        if self.config.window_ba:
            with self._stage("ba"):
                self._adjust_window()
        with self._stage("detect"):
            self._detect_new_corners(frame.image, keyframe)
        self.landmarks_at_keyframe = int(self.landmarks.is_landmark(self.tracks.ids).sum())
        self._emit(EventKind.KEYFRAME_ADDED, new_landmarks=promoted, landmarks=self.landmarks_at_keyframe,
                   candidates=len(self.tracks) - self.landmarks_at_keyframe)
        # The adjustment may have moved this keyframe; the motion model continues from where it ended.
        self.T_world_last = keyframe.T_world_cam
        return keyframe.T_world_cam

    def _triangulate_candidates(self, T_world_cam: np.ndarray) -> int:
        """Candidates whose bearing angle since their first observation exceeds the threshold become
        landmarks (paper 003 II-B.2); those that then fail the checks are dropped as bad tracks."""
        config = self.config.triangulation
        candidates = np.flatnonzero(~self.landmarks.is_landmark(self.tracks.ids))
        if len(candidates) == 0:
            return 0
        t = self.tracks
        first_poses = np.stack([self.keyframe_poses[k] for k in t.first_keyframe[candidates]])
        angles = bearing_angles(self.camera, first_poses, t.first_uv[candidates], T_world_cam, t.uv[candidates])
        ready = candidates[angles > np.radians(config.min_bearing_angle_deg)]
        keep = np.ones(len(t), bool)
        promoted = 0
        for first_keyframe in np.unique(t.first_keyframe[ready]):
            rows = ready[t.first_keyframe[ready] == first_keyframe]
            points, valid = triangulate(
                self.camera, self.keyframe_poses[first_keyframe], t.first_uv[rows], T_world_cam, t.uv[rows],
                max_reprojection_px=config.max_reprojection_px, min_depth=config.min_depth,
            )
            self.landmarks.set(t.ids[rows[valid]], points[valid])
            keep[rows[~valid]] = False
            promoted += int(valid.sum())
        self.tracks = t.select(keep)
        return promoted

    def _adjust_window(self) -> None:
        """Bundle-adjust the keyframes of the window and the landmarks seen at least twice in it; the oldest
        keyframes are held for gauge and scale. Landmarks that still reproject badly are culled."""
        config = self.config.ba
        if len(self.keyframes) <= config.fixed_keyframes:
            return
        pose_index, ids, uv = self._window_observations()
        behind = self._behind_a_keyframe(pose_index, ids)
        if len(behind):
            self._cull(behind, reason="behind a keyframe that observes it")
            keep = ~np.isin(ids, behind)
            pose_index, ids, uv = pose_index[keep], ids[keep], uv[keep]
        problem, point_ids = self._window_problem(pose_index, ids, uv)
        if len(point_ids) == 0:
            return
        solution = adjust_window(self.camera, problem, config)
        for keyframe, T in zip(self.keyframes, solution.poses_world_cam):
            keyframe.T_world_cam = T
            self.keyframe_poses[keyframe.frame_index] = T
        self.landmarks.set(point_ids, solution.points_world)
        self._emit(EventKind.WINDOW_OPTIMIZED, keyframes=len(self.keyframes), landmarks=len(point_ids),
                   rms_before_px=_rms(solution.errors_before), rms_after_px=_rms(solution.errors_after))
        bad = np.unique(problem.observation_point[solution.errors_after > config.max_outlier_px])
        if len(bad):
            self._cull(point_ids[bad], reason="reprojection error after adjustment")

    def _window_observations(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(keyframe index in the window, point id, pixel) of every landmark observation in the window."""
        pose_index = np.concatenate([np.full(len(k.ids), i) for i, k in enumerate(self.keyframes)])
        ids = np.concatenate([k.ids for k in self.keyframes])
        uv = np.concatenate([k.uv for k in self.keyframes]).astype(np.float64)
        alive = self.landmarks.is_landmark(ids)
        return pose_index[alive], ids[alive], uv[alive]

    def _behind_a_keyframe(self, pose_index: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """Ids of landmarks behind a keyframe that saw them (as candidates, before they were triangulated):
        wrong, and a projection the adjustment cannot differentiate."""
        poses = np.stack([se3_inverse(k.T_world_cam) for k in self.keyframes])[pose_index]
        depth = np.einsum("nj,nj->n", poses[:, 2, :3], self.landmarks.positions[ids]) + poses[:, 2, 3]
        return np.unique(ids[depth <= self.config.triangulation.min_depth])

    def _window_problem(
        self, pose_index: np.ndarray, ids: np.ndarray, uv: np.ndarray
    ) -> tuple[WindowProblem, np.ndarray]:
        """The problem over the observations of landmarks seen by at least two keyframes of the window."""
        _, point_index, counts = np.unique(ids, return_inverse=True, return_counts=True)
        seen_twice = counts[point_index] >= 2
        point_ids, point_index = np.unique(ids[seen_twice], return_inverse=True)
        fixed = np.arange(len(self.keyframes)) < self.config.ba.fixed_keyframes
        problem = WindowProblem(
            np.stack([k.T_world_cam for k in self.keyframes]), fixed, self.landmarks.positions[point_ids],
            pose_index[seen_twice], point_index, uv[seen_twice],
        )
        return problem, point_ids

    def _cull(self, ids: np.ndarray, reason: str) -> None:
        """Remove landmarks from the map and stop tracking them."""
        self.landmarks.cull(ids)
        self.tracks = self.tracks.select(~np.isin(self.tracks.ids, ids))
        self._emit(EventKind.MAP_POINTS_CULLED, count=len(ids), reason=reason)

    def _detect_new_corners(self, image: np.ndarray, keyframe: Keyframe) -> None:
        """Top the tracks up to the corner budget with corners away from the tracked ones; they are observed
        in ``keyframe`` (their F and T)."""
        count = self.config.corners.max_corners - len(self.tracks)
        uv = detect_corners(image, self.config.corners, self.tracks.uv, count)
        born = Tracks.born(self.landmarks.new_ids(len(uv)), uv, keyframe.frame_index)
        self.tracks = self.tracks.extend(born)
        self.tracks.keyframe_uv = self.tracks.uv.copy()
        keyframe.ids = np.concatenate([keyframe.ids, born.ids])
        keyframe.uv = np.concatenate([keyframe.uv, born.uv])

    # ---------------------------------------------------------------------------------------------- output

    def _pose_result(self, T_world_cam: np.ndarray, is_keyframe: bool, num_inliers: int) -> FrameResult:
        is_landmark = self.landmarks.is_landmark(self.tracks.ids)
        uv = self.tracks.uv[is_landmark]
        return FrameResult(
            self._frame.index, self._frame.timestamp, T_world_cam.copy(), tracked=True, is_keyframe=is_keyframe,
            num_inliers=num_inliers, points_2d=uv.copy(),
            matches_2d=np.hstack([self.tracks.keyframe_uv[is_landmark], uv]),  # landmark tracks since the keyframe
        )

    def _no_pose(self, points_2d: np.ndarray) -> FrameResult:
        return FrameResult(self._frame.index, self._frame.timestamp, None, tracked=False,
                           points_2d=np.asarray(points_2d).copy())

    def _emit(self, kind: EventKind, **details) -> None:
        self._events.append(Event(kind, self._frame.index, self._frame.timestamp, details))

    @contextmanager
    def _stage(self, name: str):
        start = time.perf_counter()
        yield
        self._timings[name] = self._timings.get(name, 0.0) + (time.perf_counter() - start) * 1000.0


def _rms(errors: np.ndarray) -> float:
    return round(float(np.sqrt(np.mean(errors**2))), 4) if len(errors) else 0.0
