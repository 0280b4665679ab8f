"""The typed pipeline configuration: one pydantic model, with documented defaults.

Every core reads its own section (``detector``, ``yolo``, ``matcher``, ``tracker``); the
gateway validates user overrides against the same model before a session starts.
Load from YAML with :func:`load_config` and override with dotted ``key=value`` pairs.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from .errors import ConfigError


class Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class DetectorConfig(Section):
    """2HR keypoints from an R2D2/L2-Net network (paper §3.1)."""

    features: Literal["2hr", "r2d2", "orb"] = Field(
        "2hr", description="2hr = R2D2 + K-means filter; r2d2 = raw R2D2; orb = OpenCV ORB baseline"
    )
    model: str = Field("faster2d2_WASF_N16", description="registered r2d2-kind model")
    input_scale: float = Field(1.0, gt=0, le=2, description="network input size relative to the image (even sizes)")
    threads: int = Field(2, ge=1, description="onnxruntime intra-op threads")
    max_keypoints: int = Field(1500, ge=16, description="keep the top N by score")
    min_reliability: float = Field(0.7, ge=0, le=1, description="R2D2 score floor before the 2HR filter")
    min_repeatability: float = Field(0.7, ge=0, le=1, description="R2D2 score floor before the 2HR filter")
    border: int = Field(4, ge=0, description="ignore maxima this close to the image border (px)")
    reliability_clusters: int = Field(3, ge=1, le=10, description="K-means k for reliability scores (paper: 3)")
    repeatability_clusters: int = Field(2, ge=1, le=10, description="K-means k for repeatability scores (paper: 2)")
    score_threshold: float = Field(0.5, ge=0, le=1, description="T: keep keypoints with reliability*repeatability > T")


class YoloConfig(Section):
    """Dynamic-object detection and keypoint masking (paper §3.2)."""

    enabled: bool = True
    model: str = Field("yolov8n_320", description="registered yolov8- or yolov5-kind model")
    threads: int = Field(2, ge=1)
    conf_threshold: float = Field(0.25, ge=0, le=1)
    iou_threshold: float = Field(0.45, ge=0, le=1)
    dynamics_table: str | None = Field(None, description="YAML: class -> high|medium|low; None = the paper's table")
    remove_levels: list[Literal["high", "medium", "low"]] = Field(default_factory=lambda: ["high"])
    mask: Literal["box", "depth"] = Field("box", description="box = dilated boxes; depth = box pixels near its depth")
    box_margin: int = Field(8, ge=0, description="dilate boxes by this many pixels")
    every_n: int = Field(1, ge=1, description="detect every n-th frame, propagate masks between")
    border_grow: int = Field(0, ge=0, description="grow masks that touch the image border by this many pixels")


class MatcherConfig(Section):
    """Descriptor matching (paper §3.3)."""

    method: Literal["siamese", "mutual_nn", "ratio"] = "siamese"
    model: str = Field("siamese_2hr", description="registered siamese-kind model")
    candidates: int = Field(3, ge=1, le=16, description="k nearest descriptors scored by the Siamese head")
    threshold: float = Field(0.5, ge=0, le=1, description="tau: keep pairs with Siamese score >= tau")
    ratio: float = Field(0.8, gt=0, le=1, description="Lowe ratio for method=ratio")


class TrackerConfig(Section):
    """RGB-D tracking back end."""

    min_depth: float = Field(0.1, ge=0, description="metres")
    max_depth: float = Field(8.0, gt=0, description="metres")
    ransac_reprojection_px: float = Field(3.0, gt=0)
    ransac_iterations: int = Field(200, ge=10)
    min_inliers: int = Field(15, ge=6)
    keyframe_min_inlier_ratio: float = Field(0.6, ge=0, le=1)
    keyframe_max_translation: float = Field(0.15, gt=0, description="metres")
    keyframe_max_rotation_deg: float = Field(10.0, gt=0)
    local_map_keyframes: int = Field(6, ge=1)
    bundle_adjustment: bool = True


class PipelineConfig(Section):
    """The whole in-process pipeline: detector -> yolo mask -> matcher -> tracker."""

    camera: str | None = Field(None, description="camera preset; None = camera.yaml or the folder name")
    detector: DetectorConfig = Field(default_factory=DetectorConfig)
    yolo: YoloConfig = Field(default_factory=YoloConfig)
    matcher: MatcherConfig = Field(default_factory=MatcherConfig)
    tracker: TrackerConfig = Field(default_factory=TrackerConfig)


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


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | list[str] | None = None) -> PipelineConfig:
    """Defaults, then a YAML file, then overrides; any invalid or unknown key raises :class:`ConfigError`."""
    data: dict[str, Any] = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"config file not found: {path}")
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: not valid YAML: {exc}") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: expected a mapping of sections")
    merge_overrides(data, overrides or [])
    try:
        return PipelineConfig.model_validate(data)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise ConfigError(f"invalid configuration: {problems}") from None
