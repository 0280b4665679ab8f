"""The typed pipeline configuration: one pydantic model, with documented defaults.

Every core reads its own section (``detector``, ``yolo``, ``matcher``, ``tracker``); the
gateway validates user overrides against the same model before a session starts.
Load from YAML with :func:`load_config` and override with dotted ``key=value`` pairs.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from .errors import ConfigError, validation_problems


class Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


#: what names a dynamics table (``yolo.dynamics_table`` over HTTP or the bus): no path, no dot
TABLE_NAME = re.compile(r"[A-Za-z0-9_-]{1,64}")


def is_table_name(value: str) -> bool:
    """Whether ``value`` names a dynamics table rather than giving a file's path."""
    return TABLE_NAME.fullmatch(value) is not None


class DetectorConfig(Section):
    """2HR keypoints from an R2D2/L2-Net network (paper §3.1)."""

    features: Literal["2hr", "r2d2", "orb", "fast", "sift"] = Field(
        "2hr", description="2hr = R2D2 + K-means filter; r2d2 = raw R2D2; orb, fast (ORB descriptors), sift = OpenCV "
        "baselines"
    )
    model: str = Field(
        "auto", description="the keyframe network: r2d2, faster2d2, faster2d2-int8 (INT8, heads in "
        "float), faster2d2-int8-coarse (its heads before the upsample: 2x faster in f32, 4 points below R2D2), "
        "student (distilled by us, 3x cheaper), a registered r2d2-kind model, or auto = the fastest on this "
        "machine of those whose measured feature quality is within 2 points of R2D2's (twohr.models.auto_candidates), "
        "timed once per host and kept in $TWOHR_CACHE/models/auto-choices.json (`twohr models auto`); the choice goes "
        "into the run's provenance")

    @property
    def descriptor_layout(self) -> tuple[int, str]:
        """The width and dtype of the descriptors these features give: what a map of them must hold."""
        return (32, "uint8") if self.features in ("orb", "fast") else (128, "float32")

    @field_validator("model")
    @classmethod
    def _known_network(cls, value: str) -> str:
        from .models import KEYFRAME_NETWORKS, registry

        names = sorted(n for n, s in registry().items() if s.kind == "r2d2")
        if value != "auto" and value not in KEYFRAME_NETWORKS and value not in names:
            raise ValueError(f"unknown keyframe network {value!r}; choose auto, {', '.join(KEYFRAME_NETWORKS)} "
                             f"or a registered one ({', '.join(names)})")
        return value

    input_scale: float = Field(0.75, gt=0, le=2, description="network input size relative to the image (even sizes); "
                               "0.75 = 480x360 for a VGA camera: keyframes cost 0.6x, at no measured loss of accuracy; "
                               "the largest scale latency_budget_ms may choose")
    latency_budget_ms: float | None = Field(
        None, gt=0, description="choose the input scale on the first image of each size: the largest of "
        "input_scale, input_scale - 1/8, ... down to min_input_scale whose latency (timed at min_input_scale, scaled "
        "by the pixel count) fits this budget (ms); None (the default) = always input_scale. Off by default: a "
        "smaller scale gives fewer keypoints and a different map (on the dev frames and their variants 0.5 cost up to "
        "9 % ATE, docs/benchmarks.md), and a slow CPU is better served by keyframe jobs that come later at the "
        "larger scale, the keyframe queue shedding the stale ones")
    min_input_scale: float = Field(0.5, gt=0, le=2, description="the smallest input scale latency_budget_ms may "
                                   "choose (on the dev frames, ATE grew by a third at 0.375)")
    backend: Literal["auto", "tensorrt", "cuda", "openvino-gpu", "openvino", "onnxruntime"] = Field(
        "auto", description="inference backend; auto = the first this machine has of tensorrt, cuda (onnxruntime-gpu "
        "on an NVIDIA GPU), openvino-gpu (an Intel GPU), openvino, onnxruntime (CPU); `twohr models backends` "
        "lists them")
    precision: Literal["auto", "bf16", "f32"] = Field(
        "auto", description="OpenVINO precision; auto = bf16 on CPUs with native bf16 (AMX), else f32; f16 on a GPU "
        "unless f32")
    threads: int = Field(1, ge=1, le=64, description="inference threads (1: the other core tracks frames)")
    subpixel: bool = Field(True, description="refine each keypoint below a pixel by a parabola through the "
                           "repeatability peak and its neighbours (else keypoints sit on the network's pixel grid, "
                           "1.33 image px apart at input_scale 0.75)")
    max_keypoints: int = Field(1500, ge=16, description="keep the top N by score")
    min_reliability: float = Field(0.7, ge=0, le=1, description="R2D2 score floor before the 2HR filter")
    min_repeatability: float = Field(0.7, ge=0, le=1, description="R2D2 score floor before the 2HR filter")
    border: int = Field(4, ge=0, description="ignore maxima this close to the image border (px)")
    reliability_clusters: int = Field(3, ge=1, le=10, description="K-means k for reliability scores (paper: 3)")
    repeatability_clusters: int = Field(2, ge=1, le=10, description="K-means k for repeatability scores (paper: 2)")
    score_threshold: float = Field(0.5, ge=0, le=1, description="T: keep keypoints with reliability*repeatability > T "
                                   "(a safety net: with the 0.7 floors the top clusters already score > ~0.8; "
                                   "see services/detector/README.md)")


class YoloConfig(Section):
    """Dynamic-object detection and keypoint masking (paper §3.2)."""

    enabled: bool = True
    model: str = Field("yolov8n_320", description="registered yolov8- or yolov5-kind model (input size from the ONNX)")
    backend: Literal["auto", "tensorrt", "cuda", "openvino-gpu", "openvino", "onnxruntime"] = Field(
        "auto", description="inference backend; auto = the first this machine has of tensorrt, cuda (onnxruntime-gpu "
        "on an NVIDIA GPU), openvino-gpu (an Intel GPU), openvino, onnxruntime (CPU); `twohr models backends` "
        "lists them")
    precision: Literal["auto", "bf16", "f32"] = Field(
        "auto", description="OpenVINO precision; auto = bf16 on CPUs with native bf16 (AMX), else f32; f16 on a GPU "
        "unless f32")
    threads: int = Field(1, ge=1, le=64, description="inference threads")
    conf_threshold: float = Field(0.25, ge=0, le=1, description="keep detections scoring at least this")
    iou_threshold: float = Field(0.45, ge=0, le=1, description="class-aware NMS overlap")
    max_detections: int = Field(100, ge=1, description="keep at most this many detections per image")
    dynamics_table: str | None = Field(
        None, description="a table's name (high/medium/low -> class names): one the stack ships or the operator put in "
        "$TWOHR_DYNAMICS_TABLES as <name>.yaml; None = the paper's table. A YAML file's path only in process "
        "(twohr run --set, the lab): POST /sessions refuses a path")
    remove_levels: list[Literal["high", "medium", "low"]] = Field(
        default_factory=lambda: ["high"], description="mask objects of these dynamics levels")
    mask: Literal["box", "depth"] = Field("depth", description="box = dilated boxes; depth = box pixels near its "
                                          "depth (leaves the background between people usable)")
    box_margin: int = Field(8, ge=0, description="dilate boxes by this many pixels")
    depth_band: float = Field(0.5, gt=0, description="depth mask: keep box pixels within this many metres of the "
                              "object's own depth (plus anything nearer); pixels without depth stay masked")
    depth_percentile: float = Field(40.0, ge=0, le=100, description="object depth = this percentile of valid "
                                    "depth in the central part of its box")
    every_n: int = Field(1, ge=1, description="detect every n-th frame, propagate masks between")
    propagate_growth: float = Field(0.08, ge=0, description="between detections, grow boxes on every side by this "
                                    "fraction of their width per elapsed frame")
    border_grow: int = Field(0, ge=0, description="grow masks that touch the image border by this many pixels")


class MatcherConfig(Section):
    """Descriptor matching (paper §3.3)."""

    method: Literal["siamese", "mutual_nn", "ratio"] = "siamese"
    model: str = Field("siamese_2hr", description="registered siamese-kind model")
    candidates: int = Field(3, ge=1, le=16, description="k nearest descriptors scored by the Siamese head")
    threshold: float = Field(0.15, ge=0, le=1, description="tau: keep pairs with Siamese score >= tau (chosen on "
                             "validation pairs by `twohr matcher train`, see services/matcher/MODEL_CARD.md)")
    ratio: float = Field(0.8, gt=0, le=1, description="Lowe ratio for method=ratio")
    threads: int = Field(1, ge=1, le=64, description="onnxruntime intra-op threads for the Siamese head")
    max_pairs_per_call: int = Field(4096, ge=64, description="one onnxruntime call scores at most this many "
                                    "candidate pairs, with as many descriptors of each side; a larger query (a "
                                    "whole-map relocalisation) runs in chunks, so memory stays flat")


class TrackerConfig(Section):
    """RGB-D tracking back end: PnP + RANSAC against a local map, pose refinement, keyframes, local BA,
    loss detection and relocalisation. Residuals are in units of one pixel of reprojection noise."""

    # depth
    min_depth: float = Field(0.1, ge=0, description="ignore depth readings nearer than this (m)")
    max_depth: float = Field(6.0, gt=0, description="ignore depth readings farther than this (m)")
    depth_edge_ratio: float = Field(0.05, gt=0, description="reject depth where the 3x3 neighbourhood spreads "
                                    "more than this fraction of the depth (object boundaries)")
    depth_noise: float = Field(0.05, gt=0, description="depth sigma = depth_noise * z^2 (m), i.e. the inverse-"
                               "depth sigma (1/m) that weighs one pixel of reprojection error. Weak on purpose: "
                               "consumer structured-light depth is biased (the Bonn sensor reads ~6 % short), and a "
                               "tight term pulls that bias into the poses; use ~0.005 for exact depth")
    # matching against the local map
    match_radius_px: float = Field(25.0, gt=0, description="accept a descriptor match only this close to the "
                                   "landmark's projection under the motion-model prediction (px)")
    lost_radius_growth_px: float = Field(15.0, ge=0, description="the radius grows by this per untracked frame")
    match_depth_gate: float = Field(0.15, gt=0, description="reject matches whose measured depth differs from the "
                                    "predicted landmark depth by more than this fraction")
    local_map_keyframes: int = Field(6, ge=1, description="keyframes whose landmarks form the local map: the "
                                     "latest plus the nearest in pose")
    keyframe_distance_per_rad: float = Field(0.5, gt=0, description="metres a radian of viewing-direction "
                                             "change counts as when ranking keyframes by nearness")
    guided_search_px: float = Field(4.0, ge=0, description="after the pose, match unmatched local-map landmarks "
                                    "to free keypoints within this distance of their projection (px); 0 = off")
    # pose estimation
    ransac_reprojection_px: float = Field(3.0, gt=0, description="RANSAC and final inlier threshold (px)")
    ransac_iterations: int = Field(200, ge=10, description="RANSAC PnP hypotheses (AP3P)")
    huber_px: float = Field(2.0, gt=0, description="Huber scale of pose refinement and BA (px)")
    motion_prior_m: float = Field(0.02, ge=0, description="sigma of the motion-model prior per frame (m); 0 = off")
    motion_prior_deg: float = Field(2.0, ge=0, description="sigma of the motion-model prior per frame (deg)")
    min_inliers: int = Field(15, ge=6, description="fewer inliers than this and the frame is lost")
    max_jump_m: float = Field(0.08, gt=0, description="a tracked pose this far from the prediction (per frame "
                              "since the last good one) is rejected as implausible (m)")
    max_jump_deg: float = Field(8.0, gt=0, description="the same for rotation (deg)")
    velocity_frames: int = Field(5, ge=1, description="motion-model velocity = mean motion of this many latest "
                                 "tracked frames")
    coast_velocity_decay: float = Field(0.7, ge=0, le=1, description="while lost, the pose coasts on the "
                                        "motion model whose velocity decays by this factor per frame")
    # per-frame optical-flow tracking between keyframes (pipeline.mode = keyframes)
    flow_window_px: int = Field(15, ge=5, le=63, description="Lucas-Kanade window (px)")
    flow_levels: int = Field(3, ge=0, le=6, description="Lucas-Kanade pyramid levels above the image")
    flow_fb_px: float = Field(1.0, gt=0, description="drop a track whose forward-backward flow misses its start "
                              "by more than this (px)")
    flow_reacquire_keyframes: int = Field(3, ge=0, description="when tracks run short, look for the landmarks "
                                          "of this many latest keyframes again by flow from the keyframe's image")
    flow_reacquire_below: int = Field(100, ge=0, description="tracks run short below this many flowed tracks")
    flow_reacquire_backoff: int = Field(4, ge=0, description="a landmark that reacquisition did not find is tried "
                                        "again only this many frames later (on the dev frames 96 % of the tries "
                                        "failed, mostly behind people, at two Lucas-Kanade passes each); 0 = on "
                                        "every frame")
    flow_max_tracks: int = Field(600, ge=16, description="follow at most this many landmarks per frame")
    reanchor_lagging_frames: bool = Field(True, description="when a keyframe job returns, the frames tracked while "
                                          "it ran keep their flow motion relative to the keyframe's new pose in the "
                                          "trajectory, instead of to the previous keyframe (no spike per keyframe)")
    refine_frames: int = Field(3000, ge=0, description="the refined trajectory re-measures the pose of each of "
                               "the latest this many frames tracked by flow against the landmarks as the final "
                               "bundle adjustment left them, from the tracks the frame was tracked with (about 4 kB "
                               "a frame kept: 3000 = 100 s at 30 Hz; about 1.2 ms a frame when the trajectory is "
                               "written, 3.5 s for 3000 on a 2-core AMD EPYC); older frames, and all with 0, keep "
                               "their pose relative to their keyframe")
    smoothing_acceleration: float = Field(1.0, ge=0, description="the refined trajectory (not the online poses) is "
                                          "smoothed under a white-noise acceleration model; the camera's "
                                          "acceleration and the pose noise are measured from the trajectory, the "
                                          "acceleration assumed at least this (m/s^2; hand-held or mobile robot: "
                                          "about 1); 0 = off")
    smoothing_angular_acceleration: float = Field(5.0, ge=0, description="the same for rotation (rad/s^2; 0 = no "
                                                  "floor, the measured angular acceleration alone)")
    # keyframes and map: the keyframe policy (services/tracker/keyframe_policy.py, docs/schedules.md)
    keyframe_tracked_ratio: float = Field(0.75, gt=0, le=1, description="a tracking frame asks for a keyframe when "
                                          "its inlier tracks, or its close ones, fall below this share of those the "
                                          "latest keyframe gave it (ORB-SLAM3's ratio for RGB-D); a waiting keyframe "
                                          "job is dropped when a newer one still tracks this share of its landmarks")
    keyframe_close_depth_m: float = Field(3.0, gt=0, description="depth of a close point (m; ORB-SLAM3's 40 "
                                          "baselines of a Kinect-class sensor, about 3 m): near points pin "
                                          "translation best, and can leave the view while far ones stay")
    keyframe_max_interval_s: float = Field(1.0, gt=0, description="a tracking frame also asks for a keyframe job "
                                           "when the latest one is this old, and a weak frame waits in the keyframe "
                                           "queue behind a busy mapping worker only then (or when tracking is very "
                                           "weak); the job adds no keyframe where the map holds the view already, so "
                                           "a still camera adds none")
    keyframe_corners: int = Field(300, ge=1, description="a tracked keyframe (pipeline.keyframes) seeds up to this "
                                  "many new landmarks at Shi-Tomasi corners with depth, outside the dynamic mask; "
                                  "they have no descriptor until the 2HR detection of a keyframe that sees them")
    corner_min_distance_px: int = Field(10, ge=1, description="new corners keep this far from each other and from "
                                        "the tracks")
    corner_depth_radius_px: int = Field(3, ge=1, description="a new corner needs valid depth that spreads by less "
                                        "than depth_edge_ratio over this many pixels around it")
    describe_radius_px: float = Field(1.5, gt=0, description="a 2HR keypoint this close to a keyframe's "
                                      "observation describes its landmark")
    init_min_points: int = Field(50, ge=6, description="keypoints with depth needed to start the map")
    landmark_max_outlier_ratio: float = Field(1.0, gt=0, description="drop a landmark once it has been "
                                              "rejected 3+ times and more often than this times accepted")
    # local bundle adjustment
    bundle_adjustment: bool = Field(True, description="local BA after every new keyframe")
    ba_window_keyframes: int = Field(5, ge=2, description="latest keyframes optimised; others that see "
                                     "their landmarks are held fixed")
    ba_max_iterations: int = Field(10, ge=1, description="Levenberg-Marquardt iterations of local BA")
    final_ba_iterations: int = Field(10, ge=0, description="when a run ends, bundle adjustment over all keyframes "
                                     "and landmarks, at most this many iterations: it refines the trajectory written "
                                     "at the end (not the online poses); 0 = off")
    final_ba_max_keyframes: int = Field(300, ge=2, description="the final bundle adjustment refines at most this "
                                        "many latest keyframes (holding older ones that share their landmarks): "
                                        "its cost grows with the cube of this (137 keyframes: about 1.5 s)")
    keyframe_culling: float = Field(0.9, ge=0, le=1, description="after each keyframe, a keyframe of the local map "
                                    "(not the first, nor one in the BA window) whose landmarks are at least this "
                                    "share seen by three other keyframes is culled: its observations and keypoints "
                                    "are dropped (its pose stays, for the frames kept relative to it); 0 = off")
    landmark_culling: bool = Field(True, description="two keyframes after a landmark is made, retire it if no "
                                   "keyframe but its own observes it (ORB-SLAM3's map-point culling for RGB-D): it "
                                   "constrains no pose, and a revisit's keyframes become redundant only without such "
                                   "landmarks")
    reuse_landmark_rows: bool = Field(True, description="new landmarks fill the rows of retired ones that neither "
                                      "the map nor the per-frame path refers to any more (its tracks, the frames kept "
                                      "for refine_frames): a long session in one place keeps its memory flat")
    # relocalisation
    relocalisation: bool = Field(True, description="when local-map tracking fails, try RANSAC PnP against "
                                 "earlier keyframes")
    relocalisation_candidates: int = Field(8, ge=1, description="keyframes tried: this many nearest to the last "
                                           "tracked pose and this many nearest to the coasted prediction; when none "
                                           "of them fits, the whole map's landmarks are tried at once")
    relocalisation_max_landmarks: int = Field(20_000, ge=0, description="the whole-map attempt matches at most "
                                              "this many landmarks, the most often matched first; 0 = no "
                                              "whole-map attempt")
    relocalisation_min_inliers: int = Field(30, ge=6, description="a relocalisation must find this many inliers "
                                            "against one keyframe (or the whole map) and again against the local map")
    reinit_after_lost_frames: int = Field(60, ge=1, description="lost this long with enough depth: start a new "
                                          "map at the coasted pose (in a map loaded from a file: look for the camera "
                                          "in it again, with no pose till then)")


class RuntimeConfig(Section):
    """How the cores are scheduled. ``keyframes`` (default) tracks every frame by optical flow and runs 2HR
    detection, matching and bundle adjustment only on keyframes, in a mapping worker, with YOLO in its own
    worker; ``every_frame`` runs every stage on every frame, as in the paper (for its ablations)."""

    mode: Literal["keyframes", "every_frame"] = "keyframes"
    synchronous: bool = Field(False, description="run the workers inline: slower, but deterministic (tests)")
    yolo_every_n: int = Field(5, ge=1, description="keyframes mode: run YOLO on every n-th frame when its "
                              "worker is free; the frames between reuse its mask (keyframes get a fresh one)")
    mask_max_age: int = Field(8, ge=0, description="keyframes mode: use a dynamic mask at most this many frames "
                              "old, as detected (not grown: grown boxes soon cover a crowded view); older = no "
                              "mask, and tracks that a person covers fail the flow check or RANSAC instead")
    max_keyframe_lag: int = Field(8, ge=0, description="replay from disk: a frame waits for the mapping worker "
                                  "when its keyframe job is more than this many frames old, so a replay faster than "
                                  "the camera sees the map as a live camera would (live streams never wait)")
    keyframe_queue: int = Field(3, ge=1, le=16, description="keyframes mode: keyframe jobs that may wait for a "
                                "busy mapping worker (ORB-SLAM3's 3); a newer job drops a waiting one it makes "
                                "redundant (tracker.keyframe_tracked_ratio), and a full queue drops its oldest, "
                                "never the newest: a short CPU sheds stale keyframe work, not density")
    keyframes: Literal["auto", "detected", "tracked"] = Field(
        "detected", description="keyframes mode: how keyframes are made while the camera tracks. detected = the 2HR "
        "detector and descriptor matching on every keyframe (the paper's design); tracked = from the optical-flow "
        "tracks and new corners, no network, with the 2HR detector describing them off the mapping path "
        "(tracker.keyframe_corners): camera rate on a CPU without AMX, but about 10 % more ATE on the dev frames and "
        "weaker against movers that no mask covers; auto = detected while the detector's measured latency fits "
        "keyframe_budget_ms, tracked when it does not")
    keyframe_budget_ms: float = Field(250.0, gt=0, description="keyframes=auto: the 2HR detector latency (median of "
                                      "the latest keyframes) above which keyframes are tracked; at 30 Hz, about the "
                                      "max_keyframe_lag frames a live map can lag")
    max_detection_lag: int = Field(30, ge=0, description="replay from disk: a frame waits for the 2HR detection of "
                                   "a tracked keyframe when it started more than this many frames ago (live streams "
                                   "never wait: the detector describes the keyframes it can)")
    max_frame_age_ms: float = Field(150.0, gt=0, description="live streams over the bus: a frame that has waited "
                                    "longer than this when its turn comes, with newer data queued behind it, is "
                                    "dropped (and counted) so that poses stay current; it bounds the latency the "
                                    "tracker absorbs when a keyframe briefly takes the CPU (on 2 cores at 30 Hz, 50 ms "
                                    "dropped 10-23 % of the frames, 150 ms 0.3-8 %, median 0.7 %)")
    max_skipped_frames: int = Field(2, ge=0, le=30, description="live streams: at most this many frames in a row "
                                    "are dropped as stale; the next one is tracked however late, so that the "
                                    "optical flow never has to bridge a long gap (while catching up after a "
                                    "slow keyframe, every 3rd frame of the backlog is tracked)")
    opencv_threads: int = Field(1, ge=0, le=64, description="OpenCV's own thread pool (0 = OpenCV's default); one "
                                "thread per stage is faster here, where the workers already fill the cores")
    prefetch: int = Field(4, ge=1, le=64, description="frames read and decoded ahead on a background thread")


#: Two keyframes whose ground-truth poses are further apart than this are not the same place: a loop between them
#: is a false accept (issue 27).
SAME_PLACE_M, SAME_PLACE_DEG = 0.3, 15.0


class LoopClosingConfig(Section):
    """Loop closing (the tracker's ``loops`` worker): place recognition with a trained vocabulary
    (``twohr vocab train``), verification by RANSAC PnP, then a pose graph, landmark fusion and bundle adjustment."""

    vocabulary: str | None = Field(None, description="name of an installed vocabulary (twohr vocab list); None = "
                                   "no loop closing", pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
    min_separation: int = Field(15, ge=1, description="a loop joins keyframes at least this many keyframes apart")
    candidates: int = Field(3, ge=1, description="place-recognition candidates verified per keyframe")
    candidate_neighbours: int = Field(2, ge=0, description="a candidate's landmarks include those of this many "
                                      "keyframes either side of it on the path")
    min_score: float = Field(0.05, ge=0, le=1, description="least bag-of-words cosine of a candidate")
    min_score_ratio: float = Field(0.75, ge=0, description="a candidate scores at least this share of the "
                                   "keyframe's best score against its 3 predecessors")
    max_shared_landmarks: float = Field(0.1, ge=0, le=1, description="a candidate whose part of the map already "
                                        "holds more than this share of the keyframe's landmarks is joined already")
    min_inliers: int = Field(60, ge=6, description="RANSAC PnP inliers a loop needs against its candidate")
    # 0.25 m and 12 deg keep a margin below SAME_PLACE_M and SAME_PLACE_DEG: the gate reads drifted estimates
    max_view_change_m: float = Field(0.25, gt=0, description="a verified loop puts the keyframe at most this far "
                                     "from its candidate (m): the same place, not the same landmarks seen from afar")
    max_view_change_deg: float = Field(12.0, gt=0, description="the same, as the angle between their views (deg)")
    chain_sigma_m: float = Field(0.01, gt=0, description="pose graph: standard deviation of a chain edge (m)")
    chain_sigma_rad: float = Field(0.01, gt=0, description="pose graph: standard deviation of a chain edge (rad)")
    unjoined_sigma_m: float = Field(1.0, gt=0, description="pose graph: standard deviation (m) of the step to a "
                                    "keyframe that shares no landmark with the one before (a new start after a loss)")
    unjoined_sigma_rad: float = Field(1.0, gt=0, description="pose graph: the same, in rad")
    loop_sigma_m: float = Field(0.003, gt=0, description="pose graph: standard deviation of the loop edge (m)")
    loop_sigma_rad: float = Field(0.003, gt=0, description="pose graph: standard deviation of the loop edge (rad)")
    ba_iterations: int = Field(5, ge=0, description="bundle adjustment over the whole map after a loop; 0 = off")


class PipelineConfig(Section):
    """The whole in-process pipeline: detector -> yolo mask -> matcher -> tracker."""

    camera: str | None = Field(None, description="camera preset; None = camera.yaml or the folder name")
    pipeline: RuntimeConfig = Field(default_factory=RuntimeConfig)
    detector: DetectorConfig = Field(default_factory=DetectorConfig)
    yolo: YoloConfig = Field(default_factory=YoloConfig)
    matcher: MatcherConfig = Field(default_factory=MatcherConfig)
    tracker: TrackerConfig = Field(default_factory=TrackerConfig)
    loop_closing: LoopClosingConfig = Field(default_factory=LoopClosingConfig)


def parse_override(item: str) -> tuple[list[str], Any]:
    """``a.b=value`` -> (["a", "b"], value parsed as YAML, so numbers, booleans and lists work)."""
    if "=" not in item:
        raise ConfigError(f"override {item!r} is not of the form key=value (e.g. tracker.min_inliers=20)")
    key, raw = item.split("=", 1)
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    return [k for k in key.strip().split(".") if k], value


def merge_overrides(data: dict[str, Any], overrides: dict[str, Any] | list[str]) -> dict[str, Any]:
    """Apply dotted overrides (a dict ``{"a.b": v}`` or a list of ``"a.b=v"``) to a nested dict."""
    items = overrides.items() if isinstance(overrides, dict) else [
        (".".join(k), v) for k, v in map(parse_override, overrides)
    ]
    for dotted, value in items:
        keys = [k for k in dotted.split(".") if k]
        if not keys:
            raise ConfigError(f"empty override key in {dotted!r}")
        node = data
        for k in keys[:-1]:
            node = node.setdefault(k, {})
            if not isinstance(node, dict):
                raise ConfigError(f"cannot override {dotted!r}: {k} is not a section")
        node[keys[-1]] = value
    return data


def read_yaml_mapping(path: str | Path, what: str) -> dict[str, Any]:
    """A YAML (or JSON) file that must hold a mapping of ``what``; raises :class:`ConfigError` in one line for a
    missing file, invalid YAML or anything but a mapping."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of {what}")
    return data


class Preset(BaseModel):
    """A named configuration of the product: overrides on top of the defaults (and of a ``--config`` file)."""

    model_config = ConfigDict(frozen=True)
    label: str = Field(description="the row of the paper's ablation table it stands for")
    overrides: dict[str, Any] = Field(description="dotted keys, as --set takes them")


_FULL = {"detector.features": "2hr", "yolo.enabled": True, "matcher.method": "siamese"}

#: The paper's ablation rows as named presets (``twohr run --preset NAME``; ``twohr bench --ablations`` runs
#: them all). ``full`` is the product's default design, spelled out.
PRESETS: dict[str, Preset] = {
    "orb": Preset(label="ORB + mutual NN",
                  overrides={"detector.features": "orb", "yolo.enabled": False, "matcher.method": "mutual_nn"}),
    "r2d2": Preset(label="R2D2 raw + mutual NN",
                   overrides={"detector.features": "r2d2", "yolo.enabled": False, "matcher.method": "mutual_nn"}),
    "2hr": Preset(label="2HR + mutual NN",
                  overrides={"detector.features": "2hr", "yolo.enabled": False, "matcher.method": "mutual_nn"}),
    "2hr-yolo": Preset(label="2HR + YOLO + mutual NN",
                       overrides={"detector.features": "2hr", "yolo.enabled": True, "matcher.method": "mutual_nn"}),
    "full": Preset(label="2HR + YOLO + Siamese (full)", overrides=_FULL),
    "full-integer-keypoints": Preset(label="full, integer keypoints", overrides={**_FULL, "detector.subpixel": False}),
    "full-no-smoothing": Preset(label="full, no trajectory smoothing",
                                overrides={**_FULL, "tracker.smoothing_acceleration": 0}),
    "full-no-final-ba": Preset(label="full, no final bundle adjustment",
                               overrides={**_FULL, "tracker.final_ba_iterations": 0}),
}


def preset_overrides(name: str) -> dict[str, Any]:
    """The overrides of preset ``name``; :class:`ConfigError` naming the presets for an unknown one."""
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}: choose one of {', '.join(PRESETS)}")
    return dict(PRESETS[name].overrides)


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | list[str] | None = None,
                preset: str | None = None) -> PipelineConfig:
    """Defaults, then a YAML file, then a named preset (:data:`PRESETS`), then overrides; any invalid or unknown
    key raises :class:`ConfigError`."""
    data: dict[str, Any] = read_yaml_mapping(path, "sections") if path is not None else {}
    if preset is not None:
        merge_overrides(data, preset_overrides(preset))
    merge_overrides(data, overrides or [])
    try:
        return PipelineConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"invalid configuration: {validation_problems(exc)}") from None
