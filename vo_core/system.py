"""The odometry: one object that takes frames in order and emits results and events to its sinks.

``Odometry.track`` runs FDMO's per-frame flowchart (paper Fig. 2). It alone knows both halves: it gathers what they
say about a frame (fdmo/evidence.py), has it decided (fdmo/decide.py, pure functions of that evidence) and carries the
decision out (``_carry_out``, ``_continue_from``); each half offers steps and decides nothing:

    direct tracking from the motion model                  DirectOdometry.track (changes nothing)
    divergence test                                        direct/divergence.py: trusted, suspect, diverged, lost
    if not trusted: feature-based recovery (Fig. 3)        FeatureOdometry.recover: a pose from the feature map
        a suspect pose the feature map agrees with is kept, and one it is too weakly anchored to overrule
            (reported as unverified)
        else direct alignment from the recovered pose: where it ends where the motion model's did, the direct
            pose was right and the same window goes on
        else the direct map restarts at the recovered pose (refined by that alignment where it converged and
            agrees with the feature map) with the feature points' depths (same scale)
        else the frame gets the feature pose and feature tracking takes the next frames
        no pose at all: the frame is lost; after a while the direct map initializes anew (a new scale), while
            the old window is still tracked against and recovered from: the first frame it takes back ends the
            new initialization, so that the map goes on at its scale
    accept: immature points, keyframe decision, window      DirectOdometry.accept
    at a new direct keyframe: the feature map grows (Fig. 4)  FeatureOdometry.add_keyframe

``--method direct`` runs the same flow without the feature half: a lost frame reinitializes at once (DSO)
and a diverged one is reported and kept. The KLT baseline is a pipeline of its own and only passes through.

With ``mapping.threaded`` (mapping_thread.py) a trusted frame of a proven map is only committed here; its tracing
and, at a keyframe, the direct mapping run on the direct mapping thread, and the feature map grows on a thread of
its own. Every other branch of the flowchart waits for both first and then runs here, as in synchronous mode; live
(``mapping.wait_for_keyframes`` off), the feature map's check of a suspect frame waits only for the feature mapper.
"""

from __future__ import annotations

import dataclasses
import sys
import threading
import time
from dataclasses import dataclass
from enum import Enum

import numpy as np

from vo_core.config import Config
from vo_core.direct.divergence import Judgement, Verdict, judge, rounded_rmse
from vo_core.geometry.motion_model import extrapolate
from vo_core.direct.odometry import DirectFrame, DirectOdometry, DirectTracking, Keyframe
from vo_core.features.config import FeatureConfig
from vo_core.features.loop_closing import LoopReport
from vo_core.features.mapping import MappingReport
from vo_core.events import Event, EventBus, EventKind, FrameResult, MapSnapshot, Sink
from vo_core.fdmo.decide import Decision, Next, Outcome, after_recovery, decide, judge_keyframe
from vo_core.fdmo.evidence import Evidence, gather, gather_recovered
from vo_core.front_ends import IMPLEMENTED_METHODS, make_front_end  # noqa: F401 (app reads IMPLEMENTED_METHODS here)
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3_inverse, transform_points
from vo_core.geometry.multiview import project_world
from vo_core.init.registry import initializer_factory, start_witness
from vo_core.mapping_thread import MappingThread
from vo_core.timing import ms_since

def maps_features_in_a_process(config: Config) -> bool:
    """Whether the odometry's feature half maps in a process of its own: FDMO with mapping threads."""
    return config.method == "fdmo" and config.mapping.threaded


def _feature_half(config: FeatureConfig, camera: PinholeCamera, process_priority: tuple[int, bool] | None):
    """FDMO's feature half: with mapping threads in a process of its own (its Python would hold the GIL the tracking
    and the direct mapping threads need) at ``process_priority`` (niceness, idle scheduling class), else (None)
    here."""
    if process_priority is not None:
        from vo_core.features.feature_process import FeatureProcess

        return FeatureProcess(config, camera, *process_priority)
    from vo_core.features.feature_odometry import FeatureOdometry

    return FeatureOdometry(config, camera)


class _Mode(Enum):
    DIRECT = "direct"  # the direct half tracks (or initializes)
    FEATURES = "features"  # feature-based tracking until the direct map can restart
    FOLLOWING = "following"  # the same, growing the feature map (features.mapping.own_poses: features/following.py)


class Odometry:
    def __init__(self, config: Config, camera: PinholeCamera, sinks: list[Sink] | None = None):
        self.config = config
        self.camera = camera
        self.bus = EventBus(sinks)
        self.front_end = make_front_end(config, camera, lambda: start_witness(config.direct.start_check.epipolar))
        self.features = None
        if self.front_end is None:
            make_initializer = initializer_factory(config.direct, config.init, camera, config.seed)
            self.direct = DirectOdometry(config.direct, camera, make_initializer, config.seed)
        mapping = config.mapping
        threaded = mapping.threaded and self.front_end is None
        if config.method == "fdmo":
            priority = (mapping.feature_niceness, mapping.feature_idle_scheduling) if mapping.wait_for_keyframes \
                else (mapping.live_feature_niceness, False)
            in_a_process = maps_features_in_a_process(config)
            self.features = _feature_half(config.features, camera, priority if in_a_process else None)
        # Offline the mapper never leaves a frame untraced: with the waits below, the run is the synchronous one.
        catch_up = None if mapping.wait_for_keyframes else mapping.max_queued_frames
        self.mapper = MappingThread(catch_up, "direct-mapping") if threaded else None
        self.switch_interval_before = sys.getswitchinterval()  # Python's, given back at close
        if self.mapper is not None:
            self.direct.reference_published = self.mapper.release_tracking
            self.direct.works_beside_tracking = False
            sys.setswitchinterval(mapping.switch_interval_s)
        # The feature map grows beside the direct mapping, from the keyframes the direct mapper hands it (FDMO runs
        # its feature mapping in a thread of its own too); the thread waits while the feature half's process maps.
        has_features = self.features is not None
        self.feature_mapper = MappingThread(None, "feature-mapping") if threaded and has_features else None
        # Held by the feature mapper's jobs, and by the tracking thread where it checks a pose against the feature
        # map while the mappers work on (_stands_beside_mapping).
        self.feature_map_lock = threading.Lock()
        self.queued_frame: int | None = None  # the last frame handed to the mapping thread
        self.feature_keyframes_given: set[int] = set()  # direct keyframes handed to the feature map since it started
        # Feature keyframes the feature half maps beside the next frames (synchronous mapping): keyframe -> (the frame
        # and timestamp that added it, the check's details), until their reports are taken (_feature_keyframes_grown).
        self.feature_keyframes_growing: dict[int, tuple[int, float, dict]] = {}
        # The feature map's segments (FeatureMap.begin_segment: with loop closure a map started anew after a loss is
        # kept as a segment of its own) in time, [first keyframe's time, the next segment's or None], by segment; and
        # those the active map holds (more than one once older ones merged into it): a loop moves their poses.
        self.segment_times: list[list[float | None]] = []
        self.segment = 0
        self.map_segments: list[int] = []
        self.snapshots: dict[str, MapSnapshot] = {}  # the newest of each mapper ("direct", "features")
        self.mode = _Mode.DIRECT
        # Why the feature map holds still (judge_keyframe): it overruled a direct keyframe, and takes none until it
        # agrees with one again, the view leaves it, or a direct map goes on from its pose (_continue_from).
        self.held: str | None = None
        self.lost_frames = 0  # frames in a row without a pose
        self.lost_since: int | None = None  # the first of them (its index in the sequence)
        # The current map's last poses (timestamp, T_world_cam): the motion model, and how well it predicted them.
        self.posed: list[tuple[float, np.ndarray]] = []
        self.previous_image: np.ndarray | None = None
        self.repeated_since = -1  # the frame whose image the following ones repeat

    def track(self, frame) -> FrameResult:
        """Process the next frame, then tell the sinks what happened. A frame that repeats the previous image is no
        measurement, whatever the method (``_repeats_previous``)."""
        result = FrameResult(frame.index, frame.timestamp, None, tracked=False)
        if not self._repeats_previous(frame, result):
            result = self.front_end.process(frame) if self.front_end is not None else self._track_hybrid(frame)
        snapshots = self._deliver_mapped(result)
        for event in result.events:
            self.bus.event(event)
        self.bus.frame(frame, result)
        for snapshot in snapshots:
            self.bus.map(snapshot)
        if result.is_keyframe and result.frame_index != self.queued_frame:  # a keyframe mapped here, at once
            self.bus.map(self._snapshot() if self.mapper is None else self._with_mapped_features(
                self.direct.map_snapshot()))
        return result

    def _deliver_mapped(self, result: FrameResult | None) -> list[MapSnapshot]:
        """With a mapping thread: what it finished since the last frame goes out with this frame (sinks hear only
        from the tracking thread). Its events go to the sinks first, with their own frames; its timings are added
        to this frame's, and a keyframe's scale reading is this frame's. Returns the newest map snapshot."""
        if self.mapper is None:
            return []
        finished = self.mapper.take_finished()
        if self.feature_mapper is not None:
            finished += self.feature_mapper.take_finished()
        maps_changed = False
        for mapped in finished:
            for event in mapped.result.events:
                self.bus.event(event)
            if mapped.snapshot is not None:
                half = "features" if mapped.snapshot.direct_points_world is None else "direct"
                self.snapshots[half], maps_changed = mapped.snapshot, True
            if result is None:
                continue
            for stage, ms in mapped.result.timings_ms.items():
                result.timings_ms[stage] = result.timings_ms.get(stage, 0.0) + ms
            if mapped.result.scale_ratio is not None:
                result.scale_ratio = mapped.result.scale_ratio
                result.mean_inverse_depth = mapped.result.mean_inverse_depth
        if not maps_changed or "direct" not in self.snapshots:
            return []
        return [self._with_mapped_features(self.snapshots["direct"])]

    def _with_mapped_features(self, direct: MapSnapshot) -> MapSnapshot:
        """With mapping threads: the direct map with the feature map as its mapper last reported it (the feature
        half's process is not asked: it may still be mapping, or starting). The direct map is kept as the newest,
        which the feature maps reported later join."""
        self.snapshots["direct"] = direct
        features = self.snapshots.get("features", MapSnapshot())
        return dataclasses.replace(direct, feature_points_world=features.feature_points_world,
                                   feature_keyframe_poses=features.feature_keyframe_poses)

    def report(self, event: Event) -> None:
        """Tell the sinks about something that happened outside the odometry (a frame the loader skipped,
        frames the player dropped), on the same channel as the odometry's own events."""
        self.bus.event(event)

    def map_snapshot(self) -> MapSnapshot:
        """The maps as they stand once the mapping thread (if any) has mapped every frame it was given."""
        self.flush()
        return self._snapshot()

    def final_keyframe_poses(self) -> dict[int, np.ndarray]:
        """The keyframes' poses as the run ends, which the final trajectory hangs each frame on
        (FrameResult.reference_keyframe): the direct keyframes', or a front end's (the features method's culled
        keyframes included); with ``features.mapping.own_poses`` the feature map's twins' (the map kept consistent
        where the direct one drifted: TUM fr1/desk, seed 0, 0.026 -> 0.020 m; parking 0.058 -> 0.037)."""
        self.flush()
        if self.front_end is not None:
            return self.front_end.final_keyframe_poses()
        poses = dict(self.direct.keyframe_poses)
        if self.config.features.mapping.own_poses:  # the feature map's, where it kept a pose of its own for one
            poses.update({f: T for f, T in self.features.final_poses().items() if f in poses})
        return poses

    def flush(self) -> None:
        """With a mapping thread: map what is queued and pass on what that produced, so that the maps and what the
        sinks heard are complete (before a snapshot, at the end of a pass). Synchronously, the feature keyframe grown
        beside the last frames is waited for and reported."""
        if self.feature_keyframes_growing:
            for event in self._feature_keyframes_grown(wait=True)[0]:
                self.bus.event(event)
        if self.mapper is None:
            return
        self._own_the_maps()
        for snapshot in self._deliver_mapped(None):
            self.bus.map(snapshot)

    def _snapshot(self) -> MapSnapshot:
        if self.front_end is not None:
            return self.front_end.map_snapshot()
        snapshot = self.direct.map_snapshot()
        if self.features is not None:  # while a keyframe grows the feature map beside tracking, as it was before it
            snapshot.feature_points_world, snapshot.feature_keyframe_poses = self.features.map_view()
        return snapshot

    def close(self) -> None:
        """The mapper maps what it has and stops; what it produced reaches the sinks; the threads beside tracking end;
        then the sinks close."""
        self.flush()
        if self.mapper is not None:
            self.mapper.close()
            if self.feature_mapper is not None:
                self.feature_mapper.close()
            sys.setswitchinterval(self.switch_interval_before)
        if self.features is not None:
            self.features.close()
        if self.front_end is None:
            self.direct.close()
        self.bus.close()

    # ------------------------------------------------------------------------------------ FDMO Fig. 2

    def _track_hybrid(self, raw_frame) -> FrameResult:
        start = time.perf_counter()
        result = FrameResult(raw_frame.index, raw_frame.timestamp, None, tracked=False)
        frame = self.direct.prepare(raw_frame)
        result.timings_ms["pyramid"] = ms_since(start)
        if self.mode is _Mode.FEATURES:
            self._own_the_maps()
            self._track_features(frame, result)
        elif self.mode is _Mode.FOLLOWING:
            self._own_the_maps()
            self._follow(frame, result)
        elif self.direct.initialized and not self._start_failed(frame, result):
            if self.mapper is not None and self.config.mapping.wait_for_keyframes:
                self.mapper.wait_reference()  # tracked against the newest keyframe, as synchronously
            self._track_direct(frame, result)
        else:
            self._own_the_maps()
            self._initialize(frame, result)
        self._forget_rejected_start(result)
        self._count_lost(frame, result)
        if result.T_world_cam is not None:
            self.posed = (self.posed + [(frame.timestamp, result.T_world_cam)])[-self.config.fdmo.prior_frames:]
        if self.feature_keyframes_growing:
            events, ms = self._feature_keyframes_grown(wait=False)
            if events:
                result.events += events
                result.timings_ms["feature_mapping"] = result.timings_ms.get("feature_mapping", 0.0) + ms
        result.timings_ms["total"] = ms_since(start)
        return result

    def _start_failed(self, frame: DirectFrame, result: FrameResult) -> bool:
        """Whether a keyframe mapped on a mapping thread, or the start's witness beside mapping, failed the start on
        probation (start_check.py); the start is then discarded here and the frame begins the next one. (A keyframe
        mapped here discards a start it fails at once.)"""
        if self.direct.failed_start is None:
            return False
        self._own_the_maps()
        return self.direct.discard_failed_start(frame, result)

    def _forget_rejected_start(self, result: FrameResult) -> None:
        """A start the direct half rejected (start_check.py) takes its feature map with it: that map holds the
        rejected start's keyframes only, at its wrong structure, and a recovery from it would bring the start back
        (TUM fr1/desk: a start refused at frame 39 was recovered from at frame 40, its scale kept)."""
        if self.features is not None and any(e.kind is EventKind.INITIALIZATION_REJECTED for e in result.events):
            self._forget_feature_map(keep=False)

    def _repeats_previous(self, raw_frame, result: FrameResult) -> bool:
        """A frame whose image is the previous frame's, bit for bit, is a camera or driver that stalled: it says
        nothing new about the motion, and a pose for it (the previous one) would be wrong by however far the
        camera went meanwhile. It gets no pose, with the reason; the frames after it are a jump."""
        image = raw_frame.image
        previous, self.previous_image = self.previous_image, image
        # Compared as buffers: pixel by pixel up to the first difference (in a frame's first row, unless the camera
        # stalled), holding the interpreter's lock. np.array_equal compared every pixel with the lock released, and
        # the frame-reading thread took it meanwhile: teddy's frames waited 1.2 ms each to get it back.
        if previous is None or previous.shape != image.shape or memoryview(previous) != memoryview(image):
            self.repeated_since = raw_frame.index
            return False
        _emit(result, EventKind.FRAME_REPEATED, {"same_as_frame": self.repeated_since})
        return True

    def _track_direct(self, frame: DirectFrame, result: FrameResult) -> None:
        """Fig. 2: track directly and judge; a trusted frame is accepted, any other is decided on the feature map's
        evidence (``_recover``: gather, decide, carry out), or by DSO's rules without a feature half."""
        if self.held is not None:
            self._go_on_from_features(frame, result)
            return
        tracking, judgement = self._track_and_judge(frame, result)
        if self.mapper is not None and judgement.verdict is not Verdict.TRUSTED:
            if self._stands_beside_mapping(frame, tracking, judgement, result):
                return
            # What follows may change the maps (a recovery, a restart): the mapper finishes first, and where it
            # published a newer reference meanwhile, the frame is tracked against that one.
            self._own_the_maps()
            if self.direct.reference is not tracking.reference:
                tracking, judgement = self._track_and_judge(frame, result)
        if judgement.verdict is Verdict.TRUSTED:
            self._accept(frame, tracking, result)
        elif self.features is None:
            self._without_recovery(frame, tracking, judgement, result)
        else:
            self._recover(frame, tracking, judgement, result)

    def _go_on_from_features(self, frame: DirectFrame, result: FrameResult) -> None:
        """While the feature map holds still (it overruled a direct keyframe, ``_add_feature_keyframes``), a frame is
        not tracked against the window it contradicted: where the feature map recovers it, it goes on from the
        recovered pose as after feature tracking (the direct map restarts there from the feature depths in view, or
        feature tracking takes the next frames, the hold kept: where it loses the view, the frames come back here, not
        to the contradicted window); where it does not, the frame gets no pose, reported, as any frame no
        half can place (lost: after ``fdmo.lost_frames_before_reinitialization`` of them a new map begins, while the
        held window is still recovered from). TUM fr1/desk: tracked on in the contradicted window, the ~140 blurred
        frames of a fast sweep were posed 10-70x off in scale until one was recognized; lost instead, a new map begins
        ten frames in and holds through the sweep (stride 1, seeds 0-2, each map aligned alone: 0.21 -> 0.05 m)."""
        self._own_the_maps()
        reference = self.features.newest_keyframe  # an overruled direct keyframe did not join the feature map
        outcome = self.features.recover(frame.frame.image, reference, self._predicted_pose(frame))
        result.timings_ms["recovery"] = result.timings_ms.get("recovery", 0.0) + outcome.ms
        _emit(result, EventKind.RECOVERY_TRIED, {"candidates": outcome.candidates, "reason": self.held,
                                                 "reference_keyframe": reference})
        if not outcome.succeeded:
            _emit(result, EventKind.RECOVERY_FAILED, outcome.details())
            return
        _emit(result, EventKind.RECOVERY_SUCCEEDED, outcome.details())
        self._continue_from(frame, outcome, None, result)

    @property
    def _live_mapping(self) -> bool:
        """Mapping threads that do not hold tracking back (live input); offline they are waited for."""
        return self.mapper is not None and not self.config.mapping.wait_for_keyframes

    def _stands_beside_mapping(self, frame: DirectFrame, tracking: DirectTracking, judgement: Judgement,
                               result: FrameResult) -> bool:
        """Live (mapping that does not hold tracking back), ``_recover``'s check of a suspect pose against the feature
        map runs while the mappers work on: only the feature map must hold still meanwhile. Waiting for all the
        mapping first made the next frame later still after missed frames, and so suspect in turn (teddy at 30 Hz:
        four frames in a row 9-10 frame intervals apart, each waiting ~300 ms for the mappers). Where the pose stands,
        the frame is accepted. Where it does not, ``_recover`` checks again once the mappers are done (the feature map
        may lack keyframes the direct mapper has not handed it yet); offline it is only checked there, after the
        mappers, so that the run is the synchronous one."""
        if self.features is None or judgement.verdict is not Verdict.SUSPECT or not self._live_mapping:
            return False
        with self.feature_map_lock:
            outcome = self._feature_pose(frame, tracking, result)
            decision = decide(self._evidence(frame, tracking, judgement, outcome), self.config)
        if decision.kept:
            self._carry_out(decision, frame, tracking, judgement, outcome, result)
        return decision.kept

    def _track_and_judge(self, frame: DirectFrame, result: FrameResult) -> tuple[DirectTracking, Judgement]:
        tracking = self.direct.track(frame)
        result.timings_ms["track"] = result.timings_ms.get("track", 0.0) + tracking.ms
        judgement = judge(tracking, self.config.fdmo.divergence)
        result.divergence_ratio = judgement.ratio if np.isfinite(judgement.ratio) else None
        result.divergence_threshold = judgement.threshold
        return tracking, judgement

    def _accept(self, frame: DirectFrame, tracking: DirectTracking, result: FrameResult) -> None:
        """The direct half accepts the frame and maps it; at a new direct keyframe the feature map grows
        (Fig. 4). With a mapping thread, a trusted frame is mapped there; anything else is mapped here, at once."""
        # Offline, a start on probation is mapped here too: one that fails is discarded at the frame it fails at.
        inline = not self.direct.initialized or (self.direct.on_probation and self.config.mapping.wait_for_keyframes)
        if self.mapper is None or inline:
            self._describe_ahead(frame, tracking)
            self._grow_feature_map(self.direct.accept(frame, tracking, result), result)
            return
        # Offline the frame is accepted while the last keyframe is still being mapped: its tracing, or the keyframe it
        # asks for, waits behind that one in the mapper's queue. Live, no keyframe is asked for while one is pending.
        self.direct.commit(frame, tracking, result)
        make_keyframe = self.direct.wants_keyframe(frame, tracking) and not (
            self._live_mapping and self.mapper.keyframe_pending)
        result.is_keyframe = make_keyframe

        def map_direct(mapped: FrameResult) -> MapSnapshot | None:
            self.direct.map_frame(frame, tracking, make_keyframe, mapped, discard_failed_start=False)
            if not make_keyframe:
                return None
            if self.feature_mapper is not None:
                self._submit_feature_keyframes(frame.index, frame.timestamp)
            return self.direct.map_snapshot()

        self.queued_frame = frame.index
        self.mapper.submit(frame.index, frame.timestamp, map_direct, keyframe=make_keyframe, may_skip=not make_keyframe)

    def _submit_feature_keyframes(self, frame_index: int, timestamp: float, initialization=None) -> None:
        """Hand the feature mapping thread the direct keyframes the feature map does not have yet."""
        new, window_poses = self._new_feature_keyframes()
        self.feature_mapper.submit(frame_index, timestamp,
                                   lambda grown: self._grow_features_beside(new, window_poses, grown, initialization))

    def _grow_features_beside(self, new: list[_NewFeatureKeyframe], window_poses: dict[int, np.ndarray],
                              result: FrameResult, initialization=None) -> MapSnapshot:
        """The feature mapping thread's job: the feature map grows at the keyframes the direct mapper handed it."""
        with self.feature_map_lock:
            self._add_feature_keyframes(new, window_poses, result, initialization)
            return MapSnapshot(feature_points_world=self.features.points_world(),
                               feature_keyframe_poses=self.features.keyframe_poses())

    def _own_the_maps(self) -> None:
        """Before the tracking thread changes the maps (a recovery, a restart, an initialization): the mapping
        thread maps what it has and waits."""
        if self.mapper is not None:
            self.mapper.wait_idle()  # first: the direct mapper may still hand keyframes to the feature mapper
        if self.feature_mapper is not None:
            self.feature_mapper.wait_idle()

    def _initialize(self, frame: DirectFrame, result: FrameResult) -> None:
        """Feed the direct initializer. After a reinitialization, first try to go on in the old map, so that it
        keeps its scale instead of a new one: its window, which a reinitialization keeps (with its feature map)
        until the new map exists. (Without a window there is no old map to go on in: the direct half drops its
        window only with a rejected start, which takes its feature map with it.)"""
        if self.features is not None and self.direct.has_window:
            self._track_old_window(frame, result)
            if result.T_world_cam is not None:
                return
        outcome = self.direct.initialize(frame, result)
        if outcome is not None and self.features is not None:
            self._forget_feature_map(keep=True)  # the new map has a new scale: the old feature map cannot serve it
            self._map_features(result, initialization=outcome)

    def _forget_feature_map(self, keep: bool) -> None:
        """The feature map starts over with the direct map's next start, and so does the motion it predicts from.
        With loop closure, a map to ``keep`` (not a start found wrong) stays as an older segment a place seen again
        merges with the new map."""
        self._own_the_maps()
        if not self._feature_map_empty:
            self.features.reset(keep)
            self.segment += keep  # with loop closure the feature map's segment ids follow (FeatureMap.begin_segment)
        self.feature_keyframes_given.clear()
        self.posed = []
        self.held = None

    @property
    def _feature_map_empty(self) -> bool:
        """Whether the feature map has no keyframe: asked of it only where it was given some since its last reset (so
        that the first frames need not wait for the feature half's process to start)."""
        return not self.feature_keyframes_given or self.features.empty

    def _track_old_window(self, frame: DirectFrame, result: FrameResult) -> None:
        """A frame while a new map initializes: the old window is tracked and recovered from as before the
        reinitialization, so that frames that come back after a long failure (KITTI: 10 noise frames, 11 m on)
        go on in the old map at its scale. Where direct tracking is back, the new initialization is dropped."""
        self._track_direct(frame, result)
        if result.T_world_cam is not None and not self.direct.initialized and self.mode is _Mode.DIRECT:
            self.direct.resume()
            _emit(result, EventKind.REINITIALIZATION_ABANDONED, {"keyframe": self.direct.newest_keyframe.frame_index})

    # ------------------------------------------------------------------------------------ FDMO Fig. 3

    def _recover(self, frame: DirectFrame, tracking: DirectTracking, judgement: Judgement,
                 result: FrameResult) -> None:
        """FDMO Fig. 3: the feature map checks a suspect pose, and recovers where the direct pose is not kept: its
        evidence gathered, decided on (fdmo/decide.py), and carried out."""
        outcome = self._feature_pose(frame, tracking, result)
        decision = decide(self._evidence(frame, tracking, judgement, outcome), self.config)
        self._carry_out(decision, frame, tracking, judgement, outcome, result)

    def _feature_pose(self, frame: DirectFrame, tracking: DirectTracking, result: FrameResult):
        """The feature map's pose for the frame: blind, then around the direct pose (or the motion model's)."""
        estimate = tracking.T_world_cam if tracking.converged else self._predicted_pose(frame)
        outcome = self.features.recover(frame.frame.image, tracking.reference.frame_index, estimate)
        result.timings_ms["recovery"] = result.timings_ms.get("recovery", 0.0) + outcome.ms
        return outcome

    def _evidence(self, frame: DirectFrame, tracking: DirectTracking, judgement: Judgement, outcome) -> Evidence:
        """What the two halves and the motion prior say about a frame direct tracking did not trust."""
        return gather(self.features, self.camera, tracking, judgement, outcome, self.posed,
                      self._predicted_pose(frame), self.config)

    def _carry_out(self, decision: Decision, frame: DirectFrame, tracking: DirectTracking, judgement: Judgement,
                   outcome, result: FrameResult) -> None:
        """The one place a decision about an untrusted frame changes the halves and tells the sinks: a kept direct
        pose is accepted (checked or unverified); one not kept is reported with the decision's reason, and the frame
        goes on from the recovered pose, or is lost (the recovery failed or was refused)."""
        if decision.kept:
            checked = decision.outcome is Outcome.ACCEPT
            _emit(result, EventKind.TRACKING_CHECKED if checked else EventKind.TRACKING_UNVERIFIED,
                  {**judgement.details(tracking), **outcome.details(), **decision.details})
            self._accept(frame, tracking, result)
            return
        self._report_failure(frame, tracking, dataclasses.replace(judgement, reason=decision.reason), result)
        _emit(result, EventKind.RECOVERY_TRIED,
              {"candidates": outcome.candidates, "reference_keyframe": tracking.reference.frame_index})
        if decision.outcome is Outcome.LOST:
            details = outcome.details() if decision.refusal is None else {**outcome.details(),
                                                                          "reason": decision.refusal}
            _emit(result, EventKind.RECOVERY_FAILED, details)
            self._set_matches(result, outcome, tracking.reference)
            return
        _emit(result, EventKind.RECOVERY_SUCCEEDED, outcome.details())
        self._set_matches(result, outcome, tracking.reference)
        self._continue_from(frame, outcome, tracking, result)

    def _continue_from(self, frame: DirectFrame, outcome, direct: DirectTracking | None,
                       result: FrameResult) -> None:
        """Back to direct from a recovered pose (FDMO 4.2.2): the pose seeds direct alignment against the window
        (``retracked``), the feature map says how that and the motion model's alignment (``direct``, where there was
        one) compare with the recovery, fdmo/decide.after_recovery chooses (the same window goes on with one of them,
        the direct map restarts at the recovered pose with the feature points' depths, or feature tracking), and
        this carries it out.

        Why restart where the alignment from the recovered pose fits better: the motion model's had locked onto a
        worse optimum, so the window's points fit the new view poorly, and carrying its scale through them drifted it
        (teddy, 20 frames dropped at 100: RMSE 13.2 against 12.1; ATE 0.017 m in the same window, 0.009 m
        restarted). Why not where it fits no better: the feature pose's disagreement is then the feature map's own
        error, and a restart trades a window of ~2,000 points for the few dozen feature points in view, at a young
        feature map's depths (teddy, 13 frames missed right after the start, live under load: 75 points from the
        start's 3-frame baseline, the optima 1.3 px apart, RMSE 13.62 against the motion model's 13.59; the restarted
        map's scale collapsed 10x, unreported, and the run ended 0.135 m off, against 0.006 m in the same window)."""
        retracked = None
        if direct is not None:
            retracked = self.direct.track(frame, outcome.T_world_cam)
            result.timings_ms["track"] = result.timings_ms.get("track", 0.0) + retracked.ms
        choice = after_recovery(gather_recovered(self.features, outcome, direct, retracked, self.config), self.config)
        if choice.next is not Next.FEATURE_TRACKING:
            self.held = None  # a direct map goes on from the feature map's pose: the map follows the direct half again
        if choice.next is Next.RESUME:
            alignment = direct if choice.alignment == "direct" else retracked
            self._resume_window(frame, outcome, direct, retracked, alignment, choice.why, result)
            return
        T_world_cam = retracked.T_world_cam if choice.refined else outcome.T_world_cam
        if choice.next is Next.RESTART:
            uv, inverse_depths = self.features.depths_in_view(outcome.pose, T_world_cam,
                                                              self.config.fdmo.min_restart_observations)
            fits = _alignment_fits(direct, retracked) if direct is not None else {}
            _emit(result, EventKind.DIRECT_RESTARTED,
                  {"points": len(uv), "keyframe": outcome.keyframe, "stage": outcome.stage, "refined": choice.refined,
                   **fits})
            self.mode = _Mode.DIRECT
            self._grow_feature_map(self.direct.restart_at(frame, T_world_cam, uv, inverse_depths, result), result)
            return
        if self.config.features.mapping.own_poses and self.mode is not _Mode.FOLLOWING:
            self.features.begin_following(frame.index, frame.timestamp, outcome)
        self._pose_from_features(T_world_cam, outcome.pose.num_inliers, result)

    def _resume_window(self, frame: DirectFrame, outcome, direct: DirectTracking, retracked: DirectTracking,
                       alignment: DirectTracking, why: str, result: FrameResult) -> None:
        """After a recovery, the same window goes on with ``alignment`` (the motion model's, ``direct``, or the one
        from the recovered pose, ``retracked``), reported with both fits and why."""
        _emit(result, EventKind.DIRECT_RESUMED,
              {"keyframe": direct.reference.frame_index, "rmse": rounded_rmse(alignment.rmse_after),
               "last_rmse": rounded_rmse(alignment.last_rmse), "stage": outcome.stage, "why": why,
               **_alignment_fits(direct, retracked)})
        self._accept(frame, alignment, result)

    def _track_features(self, frame: DirectFrame, result: FrameResult) -> None:
        """Fig. 3's feature-based tracking: motion model, guided search in the local map, pose-only BA; the
        direct map restarts as soon as enough feature depths are in view."""
        anchor = self.features.newest_keyframe
        outcome = self.features.track(frame.frame.image, self._predicted_pose(frame), anchor)
        if not outcome.succeeded:
            outcome = self.features.recover(frame.frame.image, anchor)
            result.timings_ms["recovery"] = outcome.ms
            if not outcome.succeeded:
                self.mode = _Mode.DIRECT  # lost: the next frames go through the recovery
                _emit(result, EventKind.RECOVERY_FAILED, outcome.details())
                return
            _emit(result, EventKind.RECOVERY_SUCCEEDED, outcome.details())
        self._continue_from(frame, outcome, None, result)

    def _follow(self, frame: DirectFrame, result: FrameResult) -> None:
        """With ``features.mapping.own_poses``: Fig. 3's feature-based tracking as ORB-SLAM2 tracks, growing the
        feature map at keyframes of its own (features/following.py), until the direct map can restart: at each of those
        keyframes, from its fresh depths, as after a recovery (fdmo/decide.after_recovery); between them the frame gets
        the feature pose. Where it loses the camera, the frame gets no pose and the next ones go through the recovery
        (the hold's, where the feature map holds still)."""
        followed = self.features.follow(frame.index, frame.timestamp, frame.frame.image)
        outcome = followed.outcome
        result.timings_ms["feature_tracking"] = outcome.ms
        if not outcome.succeeded:
            self.mode = _Mode.DIRECT
            _emit(result, EventKind.RECOVERY_FAILED, outcome.details())
            return
        if not followed.is_keyframe:
            self._pose_from_features(outcome.T_world_cam, outcome.pose.num_inliers, result)
            return
        self.feature_keyframes_given.add(frame.index)  # a direct map restarted here has its feature twin already
        self._continue_from(frame, outcome, None, result)

    def _follow_from_check(self, keyframe: _NewFeatureKeyframe) -> None:
        """With ``features.mapping.own_poses``, an overruled keyframe: feature tracking goes on from the feature map's
        pose for it (its check), with the direct motion into it moved to that pose, rather than from a recovery of the
        frames after it: a recovery searches the map held still, which a fast sweep leaves within a few frames."""
        outcome = self.features.checked_outcome(keyframe.frame_index)
        if outcome is None:
            return
        before = [(t, T) for t, T in self.posed if t < keyframe.timestamp]
        previous = None
        if before:
            T_feature_direct = outcome.T_world_cam @ se3_inverse(keyframe.T_world_cam)
            previous = (before[-1][0], T_feature_direct @ before[-1][1])
        self.features.begin_following(keyframe.frame_index, keyframe.timestamp, outcome, previous)
        self.mode = _Mode.FOLLOWING

    def _predicted_pose(self, frame: DirectFrame) -> np.ndarray | None:
        """Where the map's last motion, kept up over the time that passed, puts the camera: the feature map is
        searched around it where direct alignment gives no pose (ORB-SLAM2's TrackWithMotionModel)."""
        return extrapolate(self.posed, frame.timestamp)

    def _pose_from_features(self, T_world_cam: np.ndarray, inliers: int, result: FrameResult) -> None:
        self.mode = _Mode.FOLLOWING if self.config.features.mapping.own_poses else _Mode.FEATURES
        result.T_world_cam = T_world_cam
        result.reference_keyframe, result.T_ref_cam = None, None  # the feature map's pose hangs on no direct keyframe
        result.tracked = True
        result.num_inliers = inliers
        _emit(result, EventKind.FEATURE_TRACKING, {"inliers": inliers})

    # ------------------------------------------------------------------------------------ without recovery

    def _without_recovery(self, frame: DirectFrame, tracking: DirectTracking, judgement: Judgement,
                          result: FrameResult) -> None:
        """--method direct: DSO's behaviour, reported. A lost frame reinitializes at once; a diverged one is
        reported and kept (there is nothing to recover from), and so is one after missed frames or a sudden motion
        (nothing can check it: teddy with 20-45 frames dropped ends 0.09-0.23 m off, and would say nothing) or one
        that leaves most residuals beyond the cutoff (a black frame); another suspect one is kept (DSO's retrack
        threshold: 4 % of teddy's frames, nearly all right)."""
        if judgement.verdict is Verdict.LOST:
            self._report_failure(frame, tracking, judgement, result)
            origin = self.direct.last_pose.copy()
            _emit(result, EventKind.REINITIALIZATION, {"origin_from_frame_pose": origin.tolist()})
            self.direct.reinitialize(origin)
            self.direct.initialize(frame, result)
            return
        if judgement.verdict is Verdict.DIVERGED or judgement.jump or judgement.saturated:
            _emit(result, EventKind.DIVERGENCE_DETECTED,
                  {**judgement.details(tracking), "recovery": "none (--method direct keeps the pose)"})
        self._accept(frame, tracking, result)

    def _report_failure(self, frame: DirectFrame, tracking: DirectTracking, judgement: Judgement,
                        result: FrameResult) -> None:
        result.rmse_before = tracking.rmse_before
        if judgement.verdict is Verdict.LOST:
            details = {
                "reason": judgement.reason,
                "reference_keyframe": tracking.reference.frame_index,
                "rmse_before": tracking.rmse_before if np.isfinite(tracking.rmse_before) else None,
            }
            _emit(result, EventKind.TRACKING_FAILED, details)
        else:
            result.rmse_after = tracking.rmse_after
            _emit(result, EventKind.DIVERGENCE_DETECTED, judgement.details(tracking))

    def _count_lost(self, frame: DirectFrame, result: FrameResult) -> None:
        """After ``lost_frames_before_reinitialization`` frames without a pose, the direct map starts over from
        scratch (the last resort: a new scale); the old window is tracked against and recovered from until the new
        map exists (``_track_old_window``). The frames are the camera's, counted by their indices: live, the frames
        that arrived while a lost frame was being processed were lost too (teddy at 30 Hz: 10 lost frames processed
        took 106 camera frames, 3.5 s, before the new map was begun)."""
        if result.T_world_cam is not None or not self.direct.initialized:
            if result.T_world_cam is not None:
                self.lost_frames, self.lost_since = 0, None
            return
        self.lost_frames += 1
        self.lost_since = frame.index if self.lost_since is None else self.lost_since
        lost = max(self.lost_frames, frame.index - self.lost_since + 1)  # a jump back counts what was processed
        if self.features is None or lost < self.config.fdmo.lost_frames_before_reinitialization:
            return
        self._own_the_maps()
        origin = self.direct.last_pose.copy()
        _emit(result, EventKind.REINITIALIZATION,
              {"origin_from_frame_pose": origin.tolist(), "from_scratch": True, "lost_frames": lost,
               "lost_frames_processed": self.lost_frames})
        self.direct.reinitialize(origin, keep_window=True)
        self.lost_frames, self.lost_since = 0, None

    # ------------------------------------------------------------------------------------ FDMO Fig. 4

    def _describe_ahead(self, frame: DirectFrame, tracking: DirectTracking) -> None:
        """Synchronously, a frame that becomes a direct keyframe has its ORB features extracted, and its tracked pose
        checked against the feature map, on a thread of the feature half while the direct half maps it, for the
        feature keyframe that follows (with mapping threads the feature half maps in a process of its own, beside the
        direct mapper)."""
        if self.mapper is None and self.features is not None and self.direct.wants_keyframe(frame, tracking):
            self.features.describe_ahead(frame.index, frame.timestamp, frame.frame.image, tracking.T_world_cam)

    def _grow_feature_map(self, keyframe: Keyframe | None, result: FrameResult) -> None:
        if self.features is not None and (keyframe is not None or result.is_keyframe):
            self._map_features(result)

    def _map_features(self, result: FrameResult, initialization=None) -> None:
        """Every direct keyframe the feature map does not have yet becomes a feature keyframe (at initialization
        both of the initializer's keyframes, and the initializer's feature tracks their first points), at its
        direct pose. With mapping threads, on the feature mapping thread: live, the start and a restart made them
        here, and the frames that came meanwhile were missed (two feature keyframes at the start: 41-57 ms of
        teddy's); offline the tracking thread waited for them (the feature map grows in the same order either way,
        and whatever reads it waits for the feature mapper first)."""
        if self.feature_mapper is not None:
            self._submit_feature_keyframes(result.frame_index, result.timestamp, initialization)
            return
        self._add_feature_keyframes(*self._new_feature_keyframes(), result, initialization)

    def _new_feature_keyframes(self) -> tuple[list[_NewFeatureKeyframe], dict[int, np.ndarray]]:
        """The direct keyframes the feature map has not been given yet, and the window's poses, read now, where the
        direct map is not changing: with mapping threads the feature map grows from them beside the direct map."""
        window_poses = {k.frame_index: k.T_world_cam for k in self.direct.keyframes}
        probation = self.direct.on_probation
        new = [_NewFeatureKeyframe(k.frame_index, k.timestamp, k.image, k.T_world_cam, k.median_depth, probation,
                                   k.made_at)
               for k in self.direct.keyframes if k.frame_index not in self.feature_keyframes_given]
        if not self.feature_keyframes_given and new:
            self._start_segment(new[0].timestamp)
        self.feature_keyframes_given.update(k.frame_index for k in new)
        return new, window_poses

    def _add_feature_keyframes(self, new: list[_NewFeatureKeyframe], window_poses: dict[int, np.ndarray],
                               result: FrameResult, initialization=None) -> None:
        """The feature map grows at each new direct keyframe it does not overrule (fdmo/decide.judge_keyframe). After
        one it overrules it holds still (``held``): the poses of the keyframes after it, and the points they would
        make, are the drifted direct map's, and would pull the feature map with it. Each is checked, and joins where
        the feature map agrees with it again or no longer sees the view; a direct map going on from the feature map's
        pose ends the hold too (``_continue_from``: resumed or restarted there, not feature tracking). A keyframe of a
        start on probation that the feature map contradicts fails the start instead (its feature map is that start's
        own)."""
        for keyframe in new:
            start = time.perf_counter()
            check = self.features.check_keyframe(keyframe.frame_index, keyframe.timestamp, keyframe.image,
                                                 keyframe.made_at, keyframe.median_depth)
            checked = {} if check is None else {"check": check.details()}
            refused = judge_keyframe(check, keyframe.start_on_probation, self.held is not None, self.config)
            if (refused is not None and keyframe.start_on_probation
                    and self.direct.fail_start(keyframe.frame_index, f"at keyframe {keyframe.frame_index}, {refused}")):
                break  # the start goes at the next frame, and its feature map with it (_forget_rejected_start)
            if refused is not None:
                _emit(result, EventKind.KEYFRAME_OVERRULED,
                      {"keyframe": keyframe.frame_index, "reason": refused, **checked})
                self.held = refused
                if self.config.features.mapping.own_poses:
                    self._follow_from_check(keyframe)
                continue
            self.held = None
            if self._grows_beside(initialization):
                self.features.add_keyframe_beside(keyframe.frame_index, keyframe.timestamp, keyframe.image,
                                                  keyframe.T_world_cam, keyframe.median_depth, window_poses)
                self.feature_keyframes_growing[keyframe.frame_index] = (result.frame_index, result.timestamp, checked)
                continue
            report = self.features.add_keyframe(keyframe.frame_index, keyframe.timestamp, keyframe.image,
                                                keyframe.T_world_cam, keyframe.median_depth, window_poses)
            if initialization is not None and keyframe.frame_index == initialization.second_frame_index:
                report.tracked_points = self._add_initial_tracks(initialization, window_poses)
            result.timings_ms["feature_mapping"] = (result.timings_ms.get("feature_mapping", 0.0)
                                                    + ms_since(start))
            result.events += _feature_keyframe_events(report, checked, result.frame_index, result.timestamp)
            if report.loop is not None:
                self._report_loop(report.loop, result)
            if keyframe.frame_index == result.frame_index and len(report.new_matches):
                result.matches_2d = report.new_matches
                result.matches_inlier = None

    def _grows_beside(self, initialization) -> bool:
        """Synchronously, the feature map grows at a keyframe on the feature half's worker while the next frames are
        tracked; whatever reads the feature map waits for it first, so the trajectory is the one of growing it in turn
        (BENCHMARKS.md, Speed). Not at a start (its tracks join the map next), nor with loop closing, whose loops move
        the window at once. With mapping threads it grows on their feature mapper."""
        return self.mapper is None and initialization is None and not self.config.features.loop_closing.enabled

    def _feature_keyframes_grown(self, wait: bool) -> tuple[list[Event], float]:
        """The events, at the frames that added them, and the mapping time of the feature keyframes grown beside
        tracking and waited for since the last call (all of them, the last waited for here, where ``wait``)."""
        events, ms = [], 0.0
        for report in self.features.settle() if wait else self.features.take_grown():
            frame_index, timestamp, checked = self.feature_keyframes_growing.pop(report.frame_index)
            events += _feature_keyframe_events(report, checked, frame_index, timestamp)
            ms += report.ms
        return events, ms

    def _start_segment(self, timestamp: float) -> None:
        """The feature map's active segment begins at ``timestamp``: an older one still open ends there."""
        for times in self.segment_times:
            times[1] = timestamp if times[1] is None else times[1]
        self.segment_times[self.segment:] = [[timestamp, None]]
        self.map_segments = [self.segment]

    def _report_loop(self, loop: LoopReport, result: FrameResult) -> None:
        """Every place recognised at a keyframe, taken or refused and why; a closed loop with the correction of each
        keyframe of the map, and a merge with the one of the older segment's poses, which move the poses tracked
        from them (vo_core.trajectory.loop_corrected)."""
        for candidate in loop.candidates:
            _emit(result, EventKind.LOOP_CANDIDATE, {"keyframe": loop.keyframe, **candidate.as_details()})
        if loop.loop is not None:
            times, corrections = zip(*loop.loop.corrections)
            _emit(result, EventKind.LOOP_CLOSED, {
                **loop.loop.as_details(), "ms": round(loop.ms, 1), "segments": self._times_of(self.map_segments),
                "keyframe_times": list(times), "corrections": [C.reshape(-1).tolist() for C in corrections]})
        if loop.merge is not None:
            merged = self._times_of([loop.merge.segment])
            self.map_segments.append(loop.merge.segment)
            _emit(result, EventKind.MAPS_MERGED, {
                **loop.merge.as_details(), "ms": round(loop.ms, 1), "segments": merged,
                "keyframe_times": [merged[0][0]], "corrections": [loop.merge.S_active_old.reshape(-1).tolist()]})

    def _times_of(self, segments: list[int]) -> list[list[float | None]]:
        return [list(self.segment_times[i]) for i in segments]

    def map_segments_summary(self) -> list[dict]:
        """The maps the run made, in time (metrics.json): each one's span, and whether it is in the final map (an
        older one merged into it) or stayed apart (its poses are at a scale of their own)."""
        return [{"segment": i, "first_keyframe_time": start, "ends_at": end, "in_final_map": i in self.map_segments}
                for i, (start, end) in enumerate(self.segment_times)]

    def _add_initial_tracks(self, initialization, window_poses: dict[int, np.ndarray]) -> int:
        """The initializer's feature tracks (its first points) between its two keyframes join the feature map, at
        the first keyframe's pose in ``window_poses``."""
        if initialization.tracks_second is None:
            return 0
        first = initialization.first_frame_index
        count = len(initialization.tracks_second)
        uv, inverse_depths = initialization.points_uv[:count], initialization.inverse_depths[:count]
        points_world = transform_points(window_poses[first], self.camera.unproject(uv) / inverse_depths[:, None])
        return self.features.add_initial_tracks(first, initialization.second_frame_index, uv,
                                                initialization.tracks_second, points_world)

    def _set_matches(self, result: FrameResult, outcome, reference: Keyframe) -> None:
        """A recovery's matches for the viewers: from where each matched map point was in the last direct
        keyframe (the image before the jump) to the feature it matched in this frame; outliers flagged."""
        pose = outcome.pose
        if pose is None or outcome.features is None or len(pose.point_ids) == 0:
            return
        points = self.features.point_positions(pose.point_ids)
        uv_from, depth = project_world(self.camera, reference.T_world_cam, points)
        front = depth > 0
        uv_to = outcome.features.features.uv[pose.feature_ids[front]]
        result.matches_2d = np.hstack([uv_from[front], uv_to])
        result.matches_inlier = pose.inlier[front]


@dataclass(frozen=True)
class _NewFeatureKeyframe:
    """A direct keyframe as the feature map takes it (FDMO Fig. 4)."""

    frame_index: int
    timestamp: float
    image: np.ndarray
    T_world_cam: np.ndarray
    median_depth: float
    start_on_probation: bool  # the direct map's start was still on probation (start_check.py)
    made_at: np.ndarray  # the pose the direct keyframe was made at (Keyframe.made_at): the one the feature map checks


def _alignment_fits(direct: DirectTracking, retracked: DirectTracking) -> dict:
    """The RMSE of the motion model's alignment and of the one from the recovered pose, for the events."""
    return {"motion_model_rmse": rounded_rmse(direct.rmse_after),
            "recovered_pose_rmse": rounded_rmse(retracked.rmse_after)}


def _feature_keyframe_events(report: MappingReport, checked: dict, frame_index: int, timestamp: float) -> list[Event]:
    """A feature keyframe's events, at the frame that added it."""
    events = [(EventKind.FEATURE_KEYFRAME_ADDED, {**report.as_details(), **checked})]
    events += [(EventKind.FEATURE_KEYFRAME_CULLED, {"keyframe": culled}) for culled in report.culled_keyframes]
    return [Event(kind, frame_index, float(timestamp), details) for kind, details in events]


def _emit(result: FrameResult, kind: EventKind, details: dict) -> None:
    """An event of the frame being processed."""
    result.events.append(Event(kind, result.frame_index, float(result.timestamp), details))
