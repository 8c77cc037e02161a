"""Direct sparse odometry (DSO's FullSystem), offered as steps that the system (vo_core/system.py) calls in
the order of FDMO's flowchart (Fig. 2), so that the decisions about a frame are taken above both halves.

    frame = odometry.prepare(raw)                 # the image pyramid (and the size check)
    odometry.initialize(frame, result)            # while not initialized: feed the initializer
    tracking = odometry.track(frame, prior)       # align against the newest keyframe; changes nothing
    keyframe = odometry.accept(frame, tracking, result)   # history, tracing, keyframe, window optimization
        # = odometry.commit(...) (the tracking thread's part) then odometry.map_frame(...) (the mapper's part)
    odometry.reinitialize(T_world_origin)         # the next frames initialize again (the old window forgotten,
                                                  # or kept and tracked against until the new map exists)

``track`` tries DSO's motion hypotheses (or only the given prior: FDMO's recovered pose) and returns the best
alignment with the RMSE at the first guess and after the optimization (FDMO's divergence test). ``accept``
records the frame, traces the immature points of the window's keyframes along their epipolar lines in it,
and makes it a keyframe when DSO's criteria say so: the window slides (DSO's marginalization choice),
converged immature points are activated where the window lacks points, the window is optimized
(photometric bundle adjustment with the marginalization prior), the leaving keyframes are marginalized,
the new keyframe selects its own immature points and becomes the tracking reference with all active points
of the window projected into it (DSO's coarse depth map).

Two watches run at every window optimization: the scale watch (scale_watch.py) reports the map's scale at every
keyframe and an event when it jumps, and a new start stays on probation (start_check.py) for its first window
optimizations: a start that fails is discarded with an event saying why, the frame gets no pose, and the
initializer starts again from it (with ``direct.initializer=auto`` the other initializer).

The initializer is handed in as a factory: the direct half does not know which one runs; the same factory makes
the start check's witness (its ORB matches are the feature half's).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from enum import Enum

import cv2
import numpy as np

from vo_core.direct.affine import relative_affine
from vo_core.direct.coarse_tracker import PATTERN, CoarseTracker, TrackingResult
from vo_core.direct.config import DirectConfig
from vo_core.direct.immature_point import (
    ActivationCandidates, ActivationTargets, ImmaturePoints, half_resolution_pixels, host_pattern,
    optimize_for_activation,
)
from vo_core.direct.initialization import InitializationResult, InitializerFactory
from vo_core.direct.keyframe_policy import fraction_in_view, keyframes_to_marginalize, needs_keyframe
from vo_core.direct.marginalization import MarginalizationPrior
from vo_core.direct.motion_model import motion_hypotheses
from vo_core.direct.pixel_selector import PixelSelector
from vo_core.direct.pyramid import ImagePyramid
from vo_core.direct.scale_watch import ScaleWatch
from vo_core.direct.start_check import StartCheck
from vo_core.direct.window import WindowOptimizer, WindowReport
from vo_core.errors import InputError
from vo_core.events import Event, EventKind, FrameResult, MapSnapshot
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3_inverse, transform_points
from vo_core.timing import ms_since

INITIAL_LAST_RMSE = 100.0  # FullSystem: lastCoarseRMSE.setConstant(100)
# activatePointsMT: currentMinActDist (half-resolution pixels) starts at 2, stays in [0, 4], and moves by these
# steps when the window holds fewer / more points than wanted (fractions of the desired density).
INITIAL_ACTIVATION_DISTANCE = 2.0
ACTIVATION_DISTANCE_RANGE = (0.0, 4.0)
ACTIVATION_DISTANCE_STEPS_DOWN = ((0.66, 0.8), (0.8, 0.5), (0.9, 0.2), (1.0, 0.1))
ACTIVATION_DISTANCE_STEPS_UP = ((1.5, 0.8), (1.3, 0.5), (1.15, 0.2), (1.0, 0.1))


@dataclass
class Keyframe:
    """A direct keyframe: its image pyramid, pose, brightness, and the points it hosts."""

    frame_index: int
    timestamp: float
    image: np.ndarray  # uint8, for the feature half
    pyramid: ImagePyramid
    T_world_cam: np.ndarray
    affine: np.ndarray  # (a, b), DSO's aff_g2l
    exposure: float | None
    keyframe_id: int = 0  # keyframes since initialization (DSO's frameID; the first is 0)
    active_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # level-0 host pixels
    active_idepth: np.ndarray = field(default_factory=lambda: np.zeros(0))  # inverse depths in the host
    active_color: np.ndarray = field(default_factory=lambda: np.zeros((0, len(PATTERN)), np.float32))
    active_grad_sq: np.ndarray = field(default_factory=lambda: np.zeros((0, len(PATTERN)), np.float32))
    # Target keyframe's frame index -> (N,) bool over the first N active points: their residual in that keyframe
    # was out of its view when the last window optimization ended, and is dropped for good (window.py).
    dropped_residuals: dict = field(default_factory=dict)
    # DSO's frameEnergyTH: the outlier threshold on a point's energy, set by the window optimization that takes the
    # keyframe as its newest (window.py); None before it.
    energy_threshold: float | None = None
    immature: ImmaturePoints | None = None
    # The tracking reference made on this keyframe: every active point of the window projected into it
    # (DSO's coarse depth map). Pixels at level 0 and inverse depths in this keyframe.
    reference_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    reference_idepth: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # The pose the keyframe was made at (tracking's, a start's or a restart's), before window optimizations moved it:
    # the one the feature map checks, beside the first of them (system.py, fdmo/decide.judge_keyframe).
    made_at: np.ndarray = field(init=False)

    def __post_init__(self):
        self.made_at = self.T_world_cam.copy()

    @property
    def camera(self) -> PinholeCamera:
        return self.pyramid[0].camera

    def active_points_cam(self) -> np.ndarray:
        """(N, 3) active points in this keyframe's camera frame."""
        return self.camera.unproject(self.active_uv) / self.active_idepth[:, None]

    def active_points_world(self) -> np.ndarray:
        return transform_points(self.T_world_cam, self.active_points_cam())

    @property
    def median_depth(self) -> float:
        """Median depth of the points the keyframe sees (its tracking reference, else its own points)."""
        idepth = self.reference_idepth if len(self.reference_idepth) else self.active_idepth
        return float(1.0 / np.median(idepth)) if len(idepth) else float("nan")

    def add_active(self, uv: np.ndarray, idepth: np.ndarray, color: np.ndarray, grad_sq: np.ndarray) -> None:
        """New active points with their host pattern (``host_pattern``: intensities, squared gradients)."""
        self.active_uv = np.concatenate([self.active_uv, uv])
        self.active_idepth = np.concatenate([self.active_idepth, idepth])
        self.active_color = np.concatenate([self.active_color, color])
        self.active_grad_sq = np.concatenate([self.active_grad_sq, grad_sq])


def _targets_of(host: Keyframe, window: list[Keyframe]) -> list[int]:
    """The window positions of a host's activation targets, in the order its activation sees them: every other
    keyframe of the window."""
    return [i for i, k in enumerate(window) if k is not host]


def _drop_residuals_not_in(host: Keyframe, targets: list[Keyframe], not_in: np.ndarray) -> None:
    """Points about to be activated in ``host`` have no residual in the targets where their activation's was not
    in (``not_in``: (new points, targets)): DSO's optimizeImmaturePoint makes a PointFrameResidual only for the
    targets where the point's residual ended in. Kept as the host's dropped residuals (window.py), which cover its
    points up to the new ones."""
    count = len(host.active_idepth)
    for target, dropped_new in zip(targets, not_in.T):
        old = host.dropped_residuals.get(target.frame_index, np.zeros(0, bool))[:count]
        host.dropped_residuals[target.frame_index] = np.concatenate(
            [old, np.zeros(count - len(old), bool), dropped_new])


@dataclass
class TrackingReference:
    """What frames are tracked against (DSO's coarse tracker with its reference): the newest keyframe's depth map
    and the keyframe's pose and brightness as they were when it was made. Once published it is never changed
    but for ``first_rmse``, so that with mapping on its own thread (mapping_thread.py) a frame is tracked
    against one consistent reference while the window optimization moves the keyframes."""

    keyframe: Keyframe
    tracker: CoarseTracker
    T_world_cam: np.ndarray  # the keyframe's pose when the reference was made
    affine: np.ndarray
    first_rmse: float = -1.0  # DSO's firstCoarseRMSE: the RMSE of the first frame accepted against it

    @property
    def frame_index(self) -> int:
        return self.keyframe.frame_index

    @property
    def exposure(self) -> float | None:
        return self.keyframe.exposure

    def points_world(self) -> np.ndarray:
        """(N, 3) the reference's points (the window's, as the keyframe sees them) where the reference put them."""
        keyframe = self.keyframe
        finite = keyframe.reference_idepth > 0
        points_cam = keyframe.camera.unproject(keyframe.reference_uv[finite]) / keyframe.reference_idepth[finite, None]
        return transform_points(self.T_world_cam, points_cam)


class _State(Enum):
    INITIALIZING = "initializing"
    TRACKING = "tracking"


@dataclass
class _Tracked:
    """A tracked frame as the motion model and the sudden-motion test need it."""

    T_world_cam: np.ndarray
    affine: np.ndarray
    timestamp: float
    image_motion_px: float | None = None  # how far the reference's points moved from the frame before (median)


@dataclass
class DirectFrame:
    """A frame prepared for the direct half: its image pyramid, built once however many steps use it."""

    frame: object  # the datasets.Frame
    pyramid: ImagePyramid

    @property
    def index(self) -> int:
        return self.frame.index

    @property
    def timestamp(self) -> float:
        return self.frame.timestamp

    @property
    def exposure(self) -> float | None:
        return getattr(self.frame, "exposure_ms", None)


@dataclass
class DirectTracking:
    """The alignment of one frame against the newest keyframe (FDMO Eq. 2), before anything is decided.

    ``rmse_before`` is the RMSE at the first guess (the motion model's, or the given prior), ``rmse_end`` the best
    hypothesis's at its final pose, measured alike (finest level, the tracker's fixed cutoff: ``CoarseTracker.rmse``):
    FDMO's divergence test compares them. ``rmse_after`` is what the alignment itself reached on its finest level,
    where DSO raises the cutoff on a level with too many residuals above it, which makes the same pose's RMSE larger
    (a handheld TUM fr1 sequence at half its frame rate: 147 frames judged diverged at RMSE after / before 1.20-1.32,
    with a Levenberg-Marquardt that accepts only steps that lower the energy). ``saturated_end``: the share of the
    terms that pose leaves beyond the cutoff. ``achieved_rmse`` (per level) is what DSO keeps as lastCoarseRMSE once
    the frame is accepted; ``last_rmse`` is the previous frame's, and
    ``good_enough`` says whether a hypothesis came within DSO's reTrackThreshold of it (trackNewCoarse stops
    trying guesses there; when none does, every motion hypothesis was worse than the last frame's fit)."""

    reference: TrackingReference
    result: TrackingResult | None  # the best hypothesis; None when none converged
    rmse_before: float
    rmse_end: float  # NaN where no hypothesis converged
    saturated_end: float  # the share of the terms beyond the cutoff at the final pose (1 where none converged)
    achieved_rmse: np.ndarray
    last_rmse: float
    good_enough: bool
    hypotheses_tried: int
    from_prior: bool  # tracked from a given pose rather than the motion model
    ms: float
    intervals_missed: float | None = None  # frame intervals since the last tracked frame, when frames were missed
    image_motion_px: float | None = None  # how far the reference's points moved from the last tracked frame (median)
    typical_motion_px: float | None = None  # the median of that over the last tracked frames (None: too few yet)

    @property
    def motion_ratio(self) -> float | None:
        """This frame's image motion over the recent frames' typical one (None where either is unknown)."""
        if self.image_motion_px is None or not self.typical_motion_px:
            return None
        return self.image_motion_px / self.typical_motion_px

    @property
    def converged(self) -> bool:
        return self.result is not None and self.result.success

    @property
    def rmse_after(self) -> float:
        return self.result.rmse_after if self.result is not None else float("nan")

    @property
    def T_world_cam(self) -> np.ndarray:
        return self.reference.T_world_cam @ se3_inverse(self.result.T_frame_ref)


class DirectOdometry:
    def __init__(self, config: DirectConfig, camera: PinholeCamera, make_initializer: InitializerFactory, seed: int):
        self.config = config
        self.camera = camera
        self.seed = seed
        self.selector = PixelSelector(config.selector, seed)
        self.reference: TrackingReference | None = None  # published by _set_tracking_reference
        # Told when a keyframe's reference is published, before its keyframe is mapped whole (a mapping thread
        # lets tracking go on then: MappingThread.release_tracking).
        self.reference_published: Callable[[], None] = lambda: None
        self.window_optimizer = WindowOptimizer(
            config.window, config.tracker.huber_threshold, config.immature.outlier_threshold,
            config.immature.outlier_sum_component,
        )
        self.make_initializer = make_initializer
        self.initializer = make_initializer(None)
        self.state = _State.INITIALIZING
        self.keyframes: list[Keyframe] = []  # the window, oldest first
        self.prior = MarginalizationPrior()  # what the keyframes that left the window still say
        self.keyframe_poses: dict[int, np.ndarray] = {}  # every keyframe ever, for viewers
        self.history: list[_Tracked] = []  # tracked frames since (re)initialization, newest last
        self.T_world_origin = np.eye(4)  # where the next initialization's first frame sits in the world
        self._reset_rmse()
        self.initializer_frames = 0
        self._first_frame: DirectFrame | None = None  # the frame the initializer started from
        self.min_activation_distance = INITIAL_ACTIVATION_DISTANCE
        self.scale_watch = ScaleWatch(config.scale_watch)
        self.start_check: StartCheck | None = None  # the current start's check (on probation until it passed)
        self.start_failure: str | None = None  # why the start on probation fails, set at a window optimization
        # Work on a thread beside the tracking thread where mapping runs on that one, whose compiled kernels release
        # the interpreter's lock as those on this one do: a frame that is no keyframe has its immature points traced
        # there while the next frame is tracked, which does not read them (whatever reads or changes them or the
        # window waits for the trace first: ``_traced``, so the order of the work is the same), and a new keyframe
        # selects its immature points there while the window is optimized. A mapping thread (system.py) is the one
        # beside tracking, and does this work itself.
        self.works_beside_tracking = True
        self._beside: ThreadPoolExecutor | None = None  # made on first use
        self._tracing: Future | None = None  # the trace running there

    @property
    def initialized(self) -> bool:
        return self.state is _State.TRACKING

    @property
    def newest_keyframe(self) -> Keyframe | None:
        return self.keyframes[-1] if self.keyframes else None

    @property
    def last_pose(self) -> np.ndarray | None:
        """T_world_cam of the last accepted frame."""
        return self.history[-1].T_world_cam if self.history else None

    # ------------------------------------------------------------------------------------ steps

    def prepare(self, frame) -> DirectFrame:
        """The frame's image pyramid (of the photometrically corrected image where there is one), packed: with a
        mapping thread this runs while the mapper may still be making the reference the frame is tracked against."""
        irradiance = getattr(frame, "irradiance", None)
        image = irradiance if irradiance is not None else frame.image
        if image.shape[:2] != (self.camera.height, self.camera.width):
            raise InputError(
                f"frame {frame.index}: image is {image.shape[1]}x{image.shape[0]}, "
                f"the camera is {self.camera.width}x{self.camera.height}"
            )
        return DirectFrame(frame, ImagePyramid(image, self.camera, self.config.pyramid).pack())

    def initialize(self, frame: DirectFrame, result: FrameResult) -> InitializationResult | None:
        """Feed the initializer; when it succeeds, the first two keyframes are made (the frame gets its pose)
        and its outcome is returned."""
        self._traced()
        start = time.perf_counter()
        if not self.initializer.started:
            self.initializer.set_first(frame.index, frame.pyramid, frame.exposure)
            self._first_frame = frame
            self.initializer_frames = 0
            result.events.append(_event(EventKind.INITIALIZATION_STARTED, frame, {"method": self.initializer.name}))
            result.timings_ms["initializer"] = ms_since(start)
            return None
        outcome = self.initializer.track(frame.index, frame.pyramid, frame.exposure)
        self.initializer_frames += 1
        result.timings_ms["initializer"] = ms_since(start)
        if outcome is None:
            if self.initializer_frames < self.initializer.max_frames:
                return None
            return self._attempt_failed(frame, result, {})  # too long without enough baseline or texture
        unusable = _unusable(outcome)
        if unusable is not None:
            return self._attempt_failed(frame, result, {"reason": unusable})
        self._start_from_initialization(frame, outcome, result)
        return outcome

    def _attempt_failed(self, frame: DirectFrame, result: FrameResult, why: dict) -> InitializationResult | None:
        """The initializer's attempt failed: reported (its status, and ``why`` over it), and a fresh initializer
        starts over from this frame."""
        details = {**self.initializer.status(), "frames": self.initializer_frames, "method": self.initializer.name,
                   **why}
        result.events.append(_event(EventKind.INITIALIZATION_FAILED, frame, details))
        self.initializer = self.make_initializer(self.initializer.name)
        return self.initialize(frame, result)

    def track(self, frame: DirectFrame, T_world_cam_prior: np.ndarray | None = None) -> DirectTracking:
        """trackNewCoarse: align the frame against the newest keyframe from DSO's motion hypotheses, or from
        ``T_world_cam_prior`` only (a pose found elsewhere, e.g. FDMO's feature-based recovery). Changes no
        state: ``accept`` commits the result."""
        start = time.perf_counter()
        reference = self.reference  # read once: a mapping thread may publish the next one meanwhile
        time_ratio = self._time_ratio(frame)
        if T_world_cam_prior is not None:
            hypotheses = [se3_inverse(T_world_cam_prior) @ reference.T_world_cam]
        else:
            previous2 = self.history[-2].T_world_cam if len(self.history) >= 2 else None
            hypotheses = motion_hypotheses(
                previous2, self.history[-1].T_world_cam, reference.T_world_cam,
                self.config.tracker.rotation_perturbation if self.config.tracker.rotation_hypotheses else None,
                time_ratio,
            )
        # After missed frames the last guess is the last motion kept up over the time that passed (motion_model.py).
        predicted = len(hypotheses) - 1 if T_world_cam_prior is None and time_ratio is not None and time_ratio > 1.0 \
            else None
        best, prior_rmse, achieved, tried = self._best_hypothesis(
            reference.tracker, frame.pyramid, hypotheses, self.history[-1].affine, frame.exposure, predicted
        )
        last_rmse = float(self.last_rmse[0])
        good_enough = bool(achieved[0] < last_rmse * self.config.tracker.retrack_threshold)
        motion_px, rmse_end, saturated_end = None, float("nan"), 1.0
        if best is not None:
            T_last_ref = se3_inverse(self.history[-1].T_world_cam) @ reference.T_world_cam
            motion_px = reference.tracker.image_motion_px(T_last_ref, best.T_frame_ref)
            rmse_end, saturated_end = reference.tracker.end_fit(frame.pyramid, best, frame.exposure)
        return DirectTracking(
            reference, best, prior_rmse, rmse_end, saturated_end, achieved, last_rmse, good_enough, tried,
            T_world_cam_prior is not None,
            ms_since(start), time_ratio if time_ratio is not None and time_ratio > 1.0 else None,
            motion_px, self._typical_motion_px(),
        )

    def _typical_motion_px(self) -> float | None:
        """The median image motion of the last tracked frames (``tracker.motion_history``), once there are
        ``tracker.min_motion_history`` of them."""
        motions = [tracked.image_motion_px for tracked in self.history if tracked.image_motion_px is not None]
        return float(np.median(motions)) if len(motions) >= self.config.tracker.min_motion_history else None

    def _time_ratio(self, frame: DirectFrame) -> float | None:
        """The time since the last tracked frame over the time between the last two, where it says frames were
        missed (outside ``tracker.time_gap_factor`` either way: a driver's drop, --drop, or the jump before the
        last frame); None otherwise, and where the timestamps cannot say (fewer than two tracked frames, time
        not going forward)."""
        if len(self.history) < 2:
            return None
        interval = self.history[-1].timestamp - self.history[-2].timestamp
        elapsed = frame.timestamp - self.history[-1].timestamp
        if interval <= 0 or elapsed <= 0:
            return None
        ratio = elapsed / interval
        factor = self.config.tracker.time_gap_factor
        return ratio if ratio > factor or ratio < 1.0 / factor else None

    def accept(self, frame: DirectFrame, tracking: DirectTracking, result: FrameResult) -> Keyframe | None:
        """Commit a converged tracking, then map the frame at once: the immature points traced in it, and a new
        keyframe when DSO's criteria ask for one (returned; None otherwise)."""
        self.commit(frame, tracking, result)
        return self.map_frame(frame, tracking, self.wants_keyframe(frame, tracking), result)

    def commit(self, frame: DirectFrame, tracking: DirectTracking, result: FrameResult) -> None:
        """The tracking half of ``accept`` (DSO's tracking thread): the frame's pose, for the motion model and the
        result."""
        reference, best = tracking.reference, tracking.result
        result.T_world_cam = tracking.T_world_cam
        result.reference_keyframe, result.T_ref_cam = reference.frame_index, se3_inverse(best.T_frame_ref)
        result.tracked = True
        if self.on_probation:
            self.start_check.posed(frame.timestamp)
        result.rmse_before, result.rmse_after = tracking.rmse_before, tracking.rmse_after
        result.num_inliers = best.num_terms
        result.points_2d = self._visible(reference.tracker.project_points(best.T_frame_ref))
        self.last_rmse = tracking.achieved_rmse
        self.history = (self.history + [_Tracked(result.T_world_cam, best.affine, frame.timestamp,
                                                 tracking.image_motion_px)])[-self.config.tracker.motion_history:]
        if reference.first_rmse < 0:
            reference.first_rmse = best.rmse_after

    def wants_keyframe(self, frame: DirectFrame, tracking: DirectTracking) -> bool:
        """DSO's criteria (needToMakeKF) for a converged tracking, before or after it is committed."""
        reference, best = tracking.reference, tracking.result
        first_rmse = reference.first_rmse if reference.first_rmse >= 0 else best.rmse_after
        factor, _ = relative_affine(reference.exposure, frame.exposure, reference.affine, best.affine)
        return needs_keyframe(
            best.flow, factor, best.rmse_after, first_rmse, self.camera.width, self.camera.height,
            self.config.keyframes,
        )

    def map_frame(self, frame: DirectFrame, tracking: DirectTracking, make_keyframe: bool, result: FrameResult,
                  discard_failed_start: bool = True) -> Keyframe | None:
        """The mapping half of ``accept`` (DSO's makeNonKeyFrame / makeKeyFrame): the window's immature points
        traced in the committed frame, and the keyframe when ``make_keyframe`` (returned; None otherwise). A start
        on probation that fails at this keyframe is discarded here, or, off the tracking thread
        (``discard_failed_start`` False), left to ``discard_failed_start`` at the next frame."""
        T_world_cam, affine = tracking.T_world_cam, tracking.result.affine
        self._traced()
        start = time.perf_counter()
        if make_keyframe or not self.works_beside_tracking:
            self._trace(frame.pyramid, T_world_cam, affine, frame.exposure)
        else:
            self._tracing = self._run_beside(self._trace, frame.pyramid, T_world_cam, affine, frame.exposure)
        result.timings_ms["trace"] = ms_since(start)
        if not make_keyframe:
            return None
        start = time.perf_counter()
        keyframe = self._add_keyframe(frame, T_world_cam, affine, result)
        result.timings_ms["keyframe"] = ms_since(start)
        if discard_failed_start and self.discard_failed_start(frame, result):
            return None
        return keyframe

    @property
    def failed_start(self) -> str | None:
        """Why the start on probation fails: at a window optimization, or by its witness beside mapping."""
        if self.start_failure is None and self.start_check is not None:
            return self.start_check.witness_failure()
        return self.start_failure

    def fail_start(self, keyframe_index: int, reason: str) -> bool:
        """A witness outside the direct half failed the start on probation at its keyframe ``keyframe_index`` (the
        feature map's check, fdmo/decide.judge_keyframe): it is discarded at the next frame (``discard_failed_start``).
        Returns whether that start is failing now. Neither a later start nor one that has passed since: with mapping
        threads the witness may answer after the start it judged is gone or proven."""
        if not self.on_probation or keyframe_index < self.start_check.first_frame_index:
            return False
        self.start_failure = self.start_failure or reason
        return True

    def discard_failed_start(self, frame: DirectFrame, result: FrameResult) -> bool:
        """Where a keyframe mapped off the tracking thread, or the witness beside mapping, failed the start on
        probation: the start is discarded and the initializer starts again from this frame (which gets no pose).
        Returns whether it was."""
        self._traced()
        if self.failed_start is None:
            return False
        self._discard_start(frame, result)
        return True

    def reinitialize(self, T_world_origin: np.ndarray, keep_window: bool = False) -> None:
        """Initialize again from the next frame given to ``initialize``; the new map's first frame sits at
        ``T_world_origin`` (the world frame is kept, the scale is the new initialization's). With
        ``keep_window`` the old window stays until the new map exists: ``track`` still aligns against it and
        ``resume`` takes it back (FDMO keeps trying its old map while the new one initializes); without, it is
        forgotten at once (DSO)."""
        self._traced()
        self.T_world_origin = np.array(T_world_origin, dtype=float)
        if not keep_window:
            self._forget_map(failed_initializer=None)
            return
        self.state = _State.INITIALIZING
        self.initializer = self.make_initializer(None)

    def _reset_rmse(self) -> None:
        """A new window has no RMSE to compare with yet."""
        self.last_rmse = np.full(1, INITIAL_LAST_RMSE)  # DSO's lastCoarseRMSE (per level)

    @property
    def on_probation(self) -> bool:
        """Whether the current start is still being checked (start_check.py): its keyframes may yet discard it."""
        return self.start_check is not None and not self.start_check.passed

    @property
    def has_window(self) -> bool:
        """Whether there is a window to track against (while initializing: the old one ``reinitialize`` kept)."""
        return bool(self.keyframes)

    def resume(self) -> None:
        """Back to the kept window: the initialization that was to replace it is dropped."""
        self._traced()
        self.state = _State.TRACKING
        self.initializer = self.make_initializer(None)

    def _forget_map(self, failed_initializer: str | None) -> None:
        self.state = _State.INITIALIZING
        self.keyframes = []
        self.reference = None
        self.prior = MarginalizationPrior()
        self.history = []
        self.initializer = self.make_initializer(failed_initializer)
        self._reset_rmse()
        self._end_start_check()
        self.scale_watch.reset()

    def restart_at(self, frame: DirectFrame, T_world_cam: np.ndarray, points_uv: np.ndarray,
                   inverse_depths: np.ndarray, result: FrameResult) -> Keyframe:
        """A new direct map at a pose found elsewhere, with depths found elsewhere (FDMO: the recovered pose and
        the feature points in view): the frame becomes the only keyframe, hosting those points, so the world
        frame and the scale go on. The window and its prior start over."""
        self._traced()
        keyframe = Keyframe(
            frame.index, frame.timestamp, frame.frame.image, frame.pyramid, np.array(T_world_cam, float),
            np.zeros(2), frame.exposure,
        )
        keyframe.add_active(np.asarray(points_uv, float), np.asarray(inverse_depths, float),
                            *host_pattern(keyframe.pyramid[0], points_uv))
        self.keyframes = [keyframe]
        self.prior = MarginalizationPrior()
        self.history = [_Tracked(keyframe.T_world_cam, keyframe.affine, keyframe.timestamp)]
        self.state = _State.TRACKING
        self.initializer = self.make_initializer(None)  # one that had started to replace a kept window
        self._reset_rmse()
        self.scale_watch.reset()  # a new window: nothing to compare its first keyframes with
        self._end_start_check()  # the feature map's points, not an initializer's start
        keyframe.immature = self._new_immature_points(frame.pyramid)
        self.keyframe_poses[keyframe.frame_index] = keyframe.T_world_cam
        self._set_tracking_reference(keyframe)
        _posed_as_keyframe(result, keyframe)
        result.tracked = True
        result.is_keyframe = True
        result.events.append(_event(
            EventKind.KEYFRAME_ADDED, frame,
            {"keyframe": keyframe.frame_index, "window": [keyframe.frame_index], "active_points": len(inverse_depths),
             "reference_points": self.reference.tracker.num_points, "immature_points": len(keyframe.immature),
             "restart": True},
        ))
        return keyframe

    # ------------------------------------------------------------------------------------ initialization

    def _start_from_initialization(self, frame: DirectFrame, outcome: InitializationResult, result: FrameResult):
        """initializeFromInitializer: the first frame with the initializer's points, the current frame as KF."""
        start = time.perf_counter()
        first_frame = self._first_frame
        first = Keyframe(
            first_frame.index, first_frame.timestamp, first_frame.frame.image, first_frame.pyramid,
            self.T_world_origin.copy(), np.zeros(2), first_frame.exposure,
        )
        first.add_active(np.asarray(outcome.points_uv, float), np.asarray(outcome.inverse_depths, float),
                         *host_pattern(first.pyramid[0], outcome.points_uv))
        self.keyframes = [first]  # a window kept by reinitialize(keep_window=True) ends here
        self.prior = MarginalizationPrior()
        self._reset_rmse()
        self.keyframe_poses[first.frame_index] = first.T_world_cam
        result.events.append(
            Event(
                EventKind.KEYFRAME_ADDED, first.frame_index, float(first.timestamp),
                {
                    "keyframe": first.frame_index,
                    "window": [first.frame_index],
                    "active_points": len(first.active_idepth),
                },
            )
        )
        T_world_cam = first.T_world_cam @ outcome.T_first_second
        self.history = [_Tracked(first.T_world_cam, np.zeros(2), first.timestamp),
                        _Tracked(T_world_cam, np.zeros(2), frame.timestamp)]
        self.state = _State.TRACKING
        method = self.initializer.name
        self._end_start_check()
        if self.config.start_check.enabled:
            self.start_check = StartCheck(self.config.start_check, first.frame_index, frame.index, method,
                                          epipolar=self.make_initializer.start_witness())
            self.start_check.posed(frame.timestamp)
        self.initializer = self.make_initializer(None)
        self.scale_watch.reset()
        result.T_world_cam = T_world_cam
        result.tracked = True
        result.events.append(
            _event(
                EventKind.INITIALIZATION_SUCCEEDED, frame,
                {**outcome.details, "method": method, "first_frame": first.frame_index,
                 "first_T_world_cam": first.T_world_cam.tolist(), "T_first_second": outcome.T_first_second.tolist()},
            )
        )
        self._add_keyframe(frame, T_world_cam, np.zeros(2), result)
        result.timings_ms["keyframe"] = ms_since(start)

    # ------------------------------------------------------------------------------------ tracking

    def _best_hypothesis(
        self, tracker: CoarseTracker, pyramid, hypotheses, affine, exposure, predicted: int | None = None
    ) -> tuple[TrackingResult | None, float, np.ndarray, int]:
        """trackNewCoarse: try guesses in order, keep the best finest-level RMSE, stop when good enough. Where the
        guess ``predicted`` (the motion over missed frames) ends within ``tracker.prediction_tie`` of the best RMSE,
        the images cannot choose, and it is kept instead (parking, 3.15 m dropped along look-alike parked cars: the
        right pose at 13.61 against a pose by the cars the camera had passed at 13.5).

        Returns the best result (None if none succeeded), the RMSE at the first guess (the motion prior), the
        best RMSE reached per level, and how many guesses were tried."""
        config = self.config.tracker
        levels = min(len(pyramid), len(tracker.levels))
        achieved = np.full(levels, np.nan)
        best: TrackingResult | None = None
        prior_rmse = float("nan")
        tried = 0
        coarse_optima: list[np.ndarray] = []
        for attempt, T_frame_ref in enumerate(hypotheses):
            tried += 1
            tracking = tracker.track(pyramid, T_frame_ref, affine, exposure, achieved, measure_start=attempt == 0,
                                     coarse_optima=coarse_optima)
            if attempt == 0:
                prior_rmse = tracking.rmse_before
            rmse = tracking.rmse_per_level
            beats_best = best is None or rmse[0] < best.rmse_per_level[0] * (
                1.0 + (config.prediction_tie if attempt == predicted else 0.0))
            if tracking.success and np.isfinite(rmse[0]) and beats_best:
                best = tracking
            if best is not None:
                # Later guesses must beat the best RMSE reached so far on every level, or they are cut short.
                better = ~np.isfinite(achieved) | (achieved > rmse[:levels])
                achieved = np.where(better & np.isfinite(rmse[:levels]), rmse[:levels], achieved)
                if achieved[0] < self.last_rmse[0] * config.retrack_threshold:
                    break
        return best, prior_rmse, achieved, tried

    # ------------------------------------------------------------------------------------ points

    def close(self) -> None:
        """The thread beside tracking ends, once the trace it may be running is done (made again if used again)."""
        self._traced()
        if self._beside is not None:
            self._beside.shutdown()
            self._beside = None

    def _run_beside(self, work: Callable, *args) -> Future:
        """``work(*args)`` on the thread beside tracking (see ``__init__``)."""
        if self._beside is None:
            self._beside = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fdmo-direct-beside")
        return self._beside.submit(work, *args)

    def _traced(self) -> None:
        """Waits for a trace running beside tracking to end (an error it raised is raised here)."""
        tracing, self._tracing = self._tracing, None
        if tracing is not None:
            tracing.result()

    def _trace(self, pyramid: ImagePyramid, T_world_cam: np.ndarray, affine: np.ndarray, exposure) -> None:
        """traceNewCoarse: every window keyframe's immature points along their epipolar lines in this frame."""
        T_cam_world = se3_inverse(T_world_cam)
        for keyframe in self.keyframes:
            if keyframe.immature is None or len(keyframe.immature) == 0:
                continue
            transfer = relative_affine(keyframe.exposure, exposure, keyframe.affine, affine)
            keyframe.immature.trace(pyramid[0], T_cam_world @ keyframe.T_world_cam, transfer, self.config.immature)

    def _add_keyframe(
        self, frame: DirectFrame, T_world_cam: np.ndarray, affine: np.ndarray, result: FrameResult
    ) -> Keyframe:
        """makeKeyFrame: slide the window, activate points, optimize, new reference, marginalize, select."""
        pyramid = frame.pyramid
        keyframe = Keyframe(
            frame.index, frame.timestamp, frame.frame.image, pyramid, T_world_cam.copy(),
            np.asarray(affine, float).copy(), frame.exposure,
            keyframe_id=self.keyframes[-1].keyframe_id + 1 if self.keyframes else 0,
        )
        # makeKeyFrame's order: flag the keyframes that will leave, optimize the window with them and the new
        # one, hand tracking the new reference (setCoarseTrackingRef: the leaving keyframes' points included), then
        # marginalize them (so the prior links them to the newest keyframe too) and select the new candidates.
        # With a mapping thread, tracking goes on from the reference on while the rest is mapped.
        # Beside tracking the candidates are selected meanwhile (nothing else draws from the selector).
        selecting = self._run_beside(self._new_immature_points, pyramid) if self.works_beside_tracking else None
        dropped = self._keyframes_to_marginalize(keyframe)
        activated = self._activate_points(keyframe)
        self.keyframes.append(keyframe)
        if self.config.window.enabled and len(self.keyframes) >= 2:
            self._optimize_window(frame, result)
        self.keyframe_poses[keyframe.frame_index] = keyframe.T_world_cam
        self._set_tracking_reference(keyframe)
        for frame_index in dropped:
            self._marginalize(next(i for i, k in enumerate(self.keyframes) if k.frame_index == frame_index),
                              frame, result)
        keyframe.immature = self._new_immature_points(pyramid) if selecting is None else selecting.result()
        for older in self.keyframes[:-1]:
            older.pyramid.release_packed()  # from here on read through their intensities
        result.is_keyframe = True
        result.events.append(
            _event(
                EventKind.KEYFRAME_ADDED, frame,
                {
                    "keyframe": keyframe.frame_index,
                    "window": [k.frame_index for k in self.keyframes],
                    "dropped": dropped,
                    "activated_points": activated,
                    "reference_points": self.reference.tracker.num_points,
                    "immature_points": len(keyframe.immature),
                    "rmse_before": result.rmse_before,
                    "rmse_after": result.rmse_after,
                },
            )
        )
        return keyframe

    def _new_immature_points(self, pyramid: ImagePyramid) -> ImmaturePoints:
        """A new keyframe's candidate points (DSO's makeMaps and its ImmaturePoints)."""
        selection = self.selector.select(pyramid, self.config.immature.density)
        return ImmaturePoints.create(pyramid, selection.uv, selection.kind, self.config.immature)

    def _optimize_window(self, frame, result: FrameResult) -> None:
        """FullSystem::optimize: the joint photometric bundle adjustment of the window; the frame that became
        the newest keyframe takes its optimized pose (for the motion model and the trajectory)."""
        report = self.window_optimizer.optimize(self.keyframes, self.prior)
        for keyframe in self.keyframes:
            self.keyframe_poses[keyframe.frame_index] = keyframe.T_world_cam
        newest = self.keyframes[-1]
        history = self.history  # with a mapping thread, tracking may have gone on: then it is not the last frame
        if history and history[-1].timestamp == newest.timestamp:
            history[-1] = replace(history[-1], T_world_cam=newest.T_world_cam, affine=newest.affine)
        _posed_as_keyframe(result, newest)
        result.timings_ms["window"] = report.ms
        result.events.append(_event(EventKind.WINDOW_OPTIMIZED, frame, report.as_details()))
        self._watch_scale(frame, result)
        if self.on_probation:
            self._check_start(report)

    def _watch_scale(self, frame, result: FrameResult) -> None:
        """The scale watch's reading of the newest keyframe, into the frame's result (and an event on a jump)."""
        newest, previous = self.keyframes[-1], self.keyframes[-2]
        step = float(np.linalg.norm(newest.T_world_cam[:3, 3] - previous.T_world_cam[:3, 3]))
        seconds = max(abs(newest.timestamp - previous.timestamp), 1e-6)  # a sequence played backward counts too
        idepth = np.concatenate([k.active_idepth for k in self.keyframes])
        reading = self.scale_watch.observe(step / seconds, float(np.mean(idepth)) if len(idepth) else float("nan"))
        result.scale_ratio, result.mean_inverse_depth = reading.step_ratio, reading.mean_inverse_depth
        if reading.jump:
            result.events.append(_event(EventKind.SCALE_JUMP, frame, {"keyframe": newest.frame_index,
                                                                       **reading.details()}))

    def _end_start_check(self) -> None:
        """The current start's check is over (its map goes, or another start replaces it)."""
        if self.start_check is not None:
            self.start_check.close()
        self.start_check, self.start_failure = None, None

    def _check_start(self, report: WindowReport) -> None:
        """One more window optimization for the start on probation: it fails (``start_failure`` says why) or,
        after enough of them, it has proven itself (``start_check.passed``). A failure already found stands."""
        failure = self.start_check.observe(report, self.keyframes)
        self.start_failure = self.start_failure or failure

    def _discard_start(self, frame: DirectFrame, result: FrameResult) -> None:
        """A start failed its check: the map goes, the frame gets no pose (it was posed in that map), the poses the
        frames before it got in that map are retracted (``retracted``: their timestamps, for the sinks that keep a
        trajectory), and the initializer starts again from this frame."""
        check = self.start_check
        result.events.append(_event(EventKind.INITIALIZATION_REJECTED, frame,
                                    {"reason": self.failed_start, **check.details(),
                                     "retracted": [t for t in check.posed_timestamps if t != frame.timestamp]}))
        result.T_world_cam, result.tracked, result.is_keyframe, result.points_2d = None, False, False, None
        self._forget_map(failed_initializer=check.initializer)
        self.initialize(frame, result)

    def _keyframes_to_marginalize(self, new_keyframe: Keyframe) -> list[int]:
        """flagFramesForMarginalization: the frame indices of the keyframes that leave the window once
        ``new_keyframe`` joins it."""
        if not self.keyframes:
            return []
        in_view = np.array([self._fraction_in_view(k, new_keyframe) for k in self.keyframes])
        log_brightness = np.array(
            [
                abs(np.log(relative_affine(new_keyframe.exposure, k.exposure, new_keyframe.affine, k.affine)[0]))
                for k in self.keyframes
            ]
        )
        drop = keyframes_to_marginalize(
            np.array([k.keyframe_id for k in self.keyframes]),
            np.array([k.T_world_cam[:3, 3] for k in self.keyframes]),
            in_view, log_brightness, self.config.keyframes,
        )
        return [self.keyframes[i].frame_index for i in drop]

    def _marginalize(self, index: int, frame, result: FrameResult) -> None:
        """Keyframe ``index`` leaves the window; with the window optimization its information (and that of the
        points it hosts) stays as the prior."""
        window = self.config.window
        leaving = self.keyframes[index]
        points = 0
        if window.enabled and window.marginalization and len(self.keyframes) >= 2:
            self.prior, points = self.window_optimizer.marginalize(self.keyframes, index, self.prior)
        del self.keyframes[index]
        result.events.append(_event(
            EventKind.KEYFRAME_MARGINALIZED, frame,
            {"keyframe": leaving.frame_index, "marginalized_points": points,
             "dropped_points": len(leaving.active_idepth) - points, "prior_keyframes": len(self.prior)},
        ))

    def _fraction_in_view(self, keyframe: Keyframe, viewer: Keyframe) -> float:
        """Share of the keyframe's active and immature points that project into ``viewer``."""
        uv = keyframe.active_uv
        idepth = keyframe.active_idepth
        if keyframe.immature is not None and len(keyframe.immature):
            traced = np.isfinite(keyframe.immature.idepth_max)
            uv = np.concatenate([uv, keyframe.immature.uv[traced]])
            idepth = np.concatenate([idepth, keyframe.immature.idepth[traced]])
        if len(idepth) == 0:
            return 1.0
        T_viewer_kf = se3_inverse(viewer.T_world_cam) @ keyframe.T_world_cam
        camera = self.camera
        return fraction_in_view(np.asarray(uv, float), np.asarray(idepth, float), T_viewer_kf, camera.intrinsics,
                                camera.width, camera.height)

    def _activate_points(self, new_keyframe: Keyframe) -> int:
        """activatePointsMT: converged immature points become active where the new keyframe has room; all hosts'
        candidates are optimized in one call."""
        self._adapt_activation_distance()
        hosts, candidates = self._activation_candidates(new_keyframe)
        activated = 0
        window = self.keyframes + [new_keyframe]
        for (keyframe, outside), chosen, (idepth, usable, inliers) in zip(
            hosts, candidates, optimize_for_activation(candidates, self.config.immature)
        ):
            immature, activating = keyframe.immature, chosen.index[usable]
            if self.config.immature.residuals_only_where_activated:
                targets = [window[i] for i in _targets_of(keyframe, window)]
                _drop_residuals_not_in(keyframe, targets, ~inliers[usable])
            keyframe.add_active(immature.uv[activating], idepth[usable], immature.color[activating],
                                immature.host_grad_sq[activating])
            activated += int(usable.sum())
            # Activated points leave the immature set; so do those that failed and the hopeless ones, and those
            # outside the new keyframe, which cannot be activated now and never will (DSO deletes them).
            remove = immature.hopeless()
            remove[chosen.index] = True
            remove[outside] = True
            keyframe.immature = immature.subset(~remove)
        return activated

    def _activation_candidates(self, new_keyframe: Keyframe) -> tuple[list, list[ActivationCandidates]]:
        """Per host with immature points: (the host, its activatable points outside the new keyframe), and its
        candidates with their targets (the window the optimization takes next).

        Room is DSO's distance map: at half resolution in the new keyframe, a candidate needs a distance of
        at least ``min_activation_distance`` x its selector type to every active point (and to the candidates
        taken before it); the distance adapts so that the window holds about ``point_density`` points."""
        camera = self.camera
        half = (camera.width + 1) // 2, (camera.height + 1) // 2
        T_new_world = se3_inverse(new_keyframe.T_world_cam)

        def half_res_pixels(host: Keyframe, uv: np.ndarray, idepth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            return half_resolution_pixels(np.asarray(uv, float), np.asarray(idepth, float),
                                          T_new_world @ host.T_world_cam, camera.intrinsics, camera.width,
                                          camera.height)

        free = np.ones((half[1], half[0]), np.uint8)
        for keyframe in self.keyframes:
            if len(keyframe.active_idepth):
                pixel, inside = half_res_pixels(keyframe, keyframe.active_uv, keyframe.active_idepth)
                free[pixel[inside, 1], pixel[inside, 0]] = 0
        distance = cv2.distanceTransform(free, cv2.DIST_L1, 3) if not free.all() else np.full(free.shape, np.inf)
        window = self.keyframes + [new_keyframe]  # the keyframes the window optimization takes next, in its order
        images = self.window_optimizer.window_images(window)
        T_cam_world = [se3_inverse(k.T_world_cam) for k in window]  # each target's, for every host below
        spacing = max(self.min_activation_distance, 1.0)
        grid_w = int(np.ceil(half[0] / spacing))
        taken = np.zeros(grid_w * int(np.ceil(half[1] / spacing)), bool)  # the cells new points hold
        hosts, candidates = [], []
        for keyframe in self.keyframes:
            immature = keyframe.immature
            if immature is None or len(immature) == 0:
                continue
            activatable = np.flatnonzero(immature.activatable(self.config.immature))
            pixel, inside = half_res_pixels(keyframe, immature.uv[activatable], immature.idepth[activatable])
            pixel = np.clip(pixel, 0, [half[0] - 1, half[1] - 1])
            far_enough = distance[pixel[:, 1], pixel[:, 0]] >= self.min_activation_distance * immature.kind[activatable]
            # New points keep the spacing among themselves: one per cell of that size (first come).
            cell = (pixel[:, 1] // spacing).astype(int) * grid_w + (pixel[:, 0] // spacing).astype(int)
            ok = inside & far_enough
            _, first = np.unique(cell[ok], return_index=True)
            fresh = np.flatnonzero(ok)[first]
            fresh = fresh[~taken[cell[fresh]]]
            taken[cell[fresh]] = True
            hosts.append((keyframe, activatable[~inside]))
            candidates.append(ActivationCandidates(immature, activatable[fresh],
                                                   self._activation_targets(keyframe, window, T_cam_world, images)))
        return hosts, candidates

    def _adapt_activation_distance(self) -> None:
        """activatePointsMT's currentMinActDist: closer spacing when the window lacks points, wider when full."""
        count = sum(len(k.active_idepth) for k in self.keyframes)
        ratio = count / self.config.point_density
        # DSO: one large step when far below, then the first matching finer step; all matching steps up.
        step = -ACTIVATION_DISTANCE_STEPS_DOWN[0][1] if ratio < ACTIVATION_DISTANCE_STEPS_DOWN[0][0] else 0.0
        step -= next((change for limit, change in ACTIVATION_DISTANCE_STEPS_DOWN[1:] if ratio < limit), 0.0)
        step += sum(change for limit, change in ACTIVATION_DISTANCE_STEPS_UP if ratio > limit)
        low, high = ACTIVATION_DISTANCE_RANGE
        self.min_activation_distance = float(np.clip(self.min_activation_distance + step, low, high))

    def _activation_targets(self, host: Keyframe, window: list[Keyframe], T_cam_world: list[np.ndarray],
                            images: tuple[np.ndarray, np.ndarray]) -> ActivationTargets:
        """Every other keyframe of the ``window`` (the new one included), as seen from ``host``; ``T_cam_world`` are
        the window's inverse poses, ``images`` its intensities in their slots (WindowOptimizer.window_images)."""
        others = _targets_of(host, window)
        store, slots = images
        return ActivationTargets(
            self.camera, store, slots[others],
            np.array([T_cam_world[i] @ host.T_world_cam for i in others]),
            np.array([relative_affine(host.exposure, window[i].exposure, host.affine, window[i].affine)
                      for i in others], dtype=float),
        )

    def _set_tracking_reference(self, keyframe: Keyframe) -> None:
        """All active points of the window, projected into the new keyframe (makeCoarseDepthL0)."""
        T_cam_world = se3_inverse(keyframe.T_world_cam)
        points = [
            transform_points(T_cam_world, k.active_points_world()) for k in self.keyframes if len(k.active_idepth)
        ]
        points = np.concatenate(points) if points else np.zeros((0, 3))
        front = points[:, 2] > 0
        points = points[front]
        uv = self.camera.project(points)
        inside = self.camera.in_image(uv)
        keyframe.reference_uv, keyframe.reference_idepth = uv[inside], 1.0 / points[inside, 2]
        tracker = CoarseTracker(self.config.tracker)
        tracker.set_reference(
            keyframe.pyramid, keyframe.reference_uv, keyframe.reference_idepth, keyframe.affine, keyframe.exposure
        )
        # One assignment publishes it whole: the tracking thread reads ``self.reference`` once per frame.
        self.reference = TrackingReference(keyframe, tracker, keyframe.T_world_cam.copy(), keyframe.affine.copy())
        self.reference_published()

    def _visible(self, uv: np.ndarray) -> np.ndarray:
        return uv[self.camera.in_image(uv)]

    # ------------------------------------------------------------------------------------ map

    def map_snapshot(self) -> MapSnapshot:
        self._traced()
        points, idepths = [], []
        for keyframe in self.keyframes:
            if len(keyframe.active_idepth):
                points.append(keyframe.active_points_world())
                idepths.append(keyframe.active_idepth)
        return MapSnapshot(
            direct_points_world=np.concatenate(points) if points else np.zeros((0, 3)),
            direct_inverse_depths=np.concatenate(idepths) if idepths else np.zeros(0),
            keyframe_poses=dict(self.keyframe_poses),
        )


def _unusable(outcome: InitializationResult) -> str | None:
    """Why an initializer's result can start no map (its optimization diverged: DSO's coarse initializer on the drone
    clip at a third of its frame rate handed over no point, its affine at 2e38 and its pose not finite), None where
    it can."""
    if len(outcome.inverse_depths) == 0:
        return "the start has no points"
    if not (np.all(np.isfinite(outcome.T_first_second)) and np.all(np.isfinite(outcome.inverse_depths))):
        return "the start's pose or depths are not finite"
    return None


def _posed_as_keyframe(result: FrameResult, keyframe: Keyframe) -> None:
    """The frame is ``keyframe``: it takes the keyframe's pose, and hangs on it (the trajectory's final pose is the
    keyframe's final one)."""
    result.T_world_cam = keyframe.T_world_cam.copy()
    result.reference_keyframe, result.T_ref_cam = keyframe.frame_index, np.eye(4)


def _event(kind: EventKind, frame, details: dict) -> Event:
    return Event(kind, frame.index, float(frame.timestamp), details)
