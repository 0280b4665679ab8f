"""TUM-layout RGB-D sequences (TUM RGB-D, Bonn RGB-D Dynamic, and our synthetic ones).

A sequence folder holds ``rgb.txt``, ``depth.txt`` (``timestamp filename``), the images they
name, optionally ``associations.txt`` (``rgb_ts rgb_file depth_ts depth_file``),
``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``) and ``camera.yaml`` (intrinsics that
override the preset chosen from the folder name).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml
from pydantic import BaseModel, Field, ValidationError

from .errors import DatasetError
from .geometry import nearest_rotation
from .trajectory import Trajectory, read_tum

log = logging.getLogger(__name__)

#: The TUM tools' default association window, in seconds.
DEFAULT_MAX_DT = 0.02


class CameraIntrinsics(BaseModel):
    """Pinhole intrinsics of the RGB-D camera; depth is registered to the colour image."""

    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    width: int = Field(640, gt=0)
    height: int = Field(480, gt=0)
    depth_factor: float = Field(5000.0, gt=0, description="depth PNG units per metre")
    distortion: list[float] = Field(default_factory=list, description="OpenCV k1 k2 p1 p2 k3; empty = none")

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def distorted(self) -> bool:
        """Whether the lens distorts (any non-zero coefficient): images must be undistorted before use."""
        return any(c != 0 for c in self.distortion)


#: Published intrinsics of the TUM RGB-D (fr1, fr2, fr3) and Bonn RGB-D Dynamic cameras, with the published lens
#: distortion where there is one (the images of both datasets are stored as the camera took them).
CAMERA_PRESETS: dict[str, CameraIntrinsics] = {
    "tum_fr1": CameraIntrinsics(fx=517.3, fy=516.5, cx=318.6, cy=255.3,
                                distortion=[0.2624, -0.9531, -0.0054, 0.0026, 1.1633]),
    "tum_fr2": CameraIntrinsics(fx=520.9, fy=521.0, cx=325.1, cy=249.7,
                                distortion=[0.2312, -0.7849, -0.0033, -0.0001, 0.9172]),
    "tum_fr3": CameraIntrinsics(fx=535.4, fy=539.2, cx=320.1, cy=247.6),
    "bonn": CameraIntrinsics(fx=542.822841, fy=542.576870, cx=315.593520, cy=237.756098,
                             distortion=[0.039903, -0.099343, -0.000730, -0.000144, 0.0]),
}

_T_ROS = np.array([[-1.0, 0, 0, 0], [0, 0, 1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])
_T_MARKER_CAMERA = np.array(
    [
        [1.0157, 0.1828, -0.2389, 0.0113],
        [0.0009, -0.8431, -0.6413, -0.0098],
        [-0.3009, 0.6147, -0.8085, 0.0111],
        [0, 0, 0, 1],
    ]
)


def undistorted(image: np.ndarray, camera: CameraIntrinsics, depth: bool = False) -> np.ndarray:
    """``image`` as a pinhole camera with ``camera.matrix`` and no lens distortion would see it; the image itself
    when the camera has no distortion. Every stage undistorts what it decodes, so keypoints, flow and depth all
    live in the pinhole model the tracker assumes. ``depth`` resamples nearest-neighbour: blending two depths
    across an object's edge would invent a surface between them (pixels that fall outside read 0 = no depth)."""
    if not camera.distorted:
        return image
    height, width = image.shape[:2]
    maps = _undistortion_maps(camera.fx, camera.fy, camera.cx, camera.cy, width, height,
                              tuple(camera.distortion))
    return cv2.remap(image, *maps, cv2.INTER_NEAREST if depth else cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def depth_in_metres(raw: np.ndarray, camera: CameraIntrinsics) -> np.ndarray:
    """A depth image as the sensor sends it (``camera.depth_factor`` units per metre, 0 = no reading) as float32
    metres in the pinhole model: undistorted like the colour image."""
    return undistorted(raw, camera, depth=True).astype(np.float32) / np.float32(camera.depth_factor)


@functools.lru_cache(maxsize=8)
def _undistortion_maps(fx: float, fy: float, cx: float, cy: float, width: int, height: int,
                       coefficients: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    k = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    return cv2.initUndistortRectifyMap(k, np.array(coefficients, np.float64), None, k, (width, height), cv2.CV_16SC2)


def _bonn_extrinsic() -> tuple[np.ndarray, np.ndarray]:
    # Bonn's calibration: camera = T_ros · marker · T_ros · T_m. T_m's 3x3 block carries a
    # uniform scale of ~1.059, so it is projected onto the nearest rotation.
    t_m = _T_MARKER_CAMERA.copy()
    t_m[:3, :3] = nearest_rotation(t_m[:3, :3])
    return _T_ROS, _T_ROS @ t_m


#: Fixed transforms that turn ground-truth poses into camera poses: camera = left · gt · right.
GT_EXTRINSIC_PRESETS: dict[str, tuple[np.ndarray, np.ndarray]] = {
    "none": (np.eye(4), np.eye(4)),
    "bonn": _bonn_extrinsic(),
}


def load_gt_extrinsic(spec: str) -> tuple[str, np.ndarray, np.ndarray]:
    """Resolve ``none``, a preset name, or a file holding a 4x4 right-hand extrinsic (whitespace separated)."""
    if spec in GT_EXTRINSIC_PRESETS:
        left, right = GT_EXTRINSIC_PRESETS[spec]
        return spec, left, right
    path = Path(spec)
    if not path.is_file():
        raise DatasetError(
            f"unknown ground-truth extrinsic {spec!r}: use one of {sorted(GT_EXTRINSIC_PRESETS)} "
            "or a file with a 4x4 matrix"
        )
    try:
        right = np.loadtxt(path, dtype=np.float64).reshape(4, 4)
    except ValueError as exc:
        raise DatasetError(f"{path}: expected a 4x4 matrix ({exc})") from None
    right[:3, :3] = nearest_rotation(right[:3, :3])
    return str(path), np.eye(4), right


def guess_camera_preset(root: Path) -> str | None:
    """The camera preset implied by a sequence folder name (TUM ``freiburgN``, Bonn ``rgbd_bonn``)."""
    name = root.resolve().name.lower()
    if "bonn" in name:
        return "bonn"
    for n in (1, 2, 3):
        if f"freiburg{n}" in name or f"fr{n}_" in name:
            return f"tum_fr{n}"
    return None


@dataclass
class FrameRecord:
    """One associated RGB-D pair of a sequence, before its images are read."""

    index: int
    stamp: float
    rgb_path: Path
    depth_stamp: float
    depth_path: Path


class Frame:
    """One RGB-D frame, as every stage sees it: ``rgb`` (H, W, 3) uint8 in RGB order, ``depth`` (H, W) float32
    metres (0 = no reading) and ``gray`` (H, W) uint8, all undistorted.

    A frame read from disk holds its arrays. A frame that came over the bus holds ``message``, the bytes as the
    source sent them (for a stage in another service), and decodes each image on first use (``decoders``:
    image name -> function), so that a stage pays only for the images it reads."""

    def __init__(self, index: int, stamp: float, rgb: np.ndarray | None = None, depth: np.ndarray | None = None,
                 *, message: bytes | None = None, decoders: dict[str, Callable[[], np.ndarray]] | None = None) -> None:
        self.index = index
        self.stamp = stamp
        self.message = message
        self._images: dict[str, np.ndarray | None] = {"rgb": rgb, "depth": depth, "gray": None}
        self._decoders = decoders or {}

    def _image(self, name: str) -> np.ndarray | None:
        if self._images[name] is None and name in self._decoders:
            self._images[name] = self._decoders[name]()
        return self._images[name]

    @property
    def rgb(self) -> np.ndarray:
        return self._image("rgb")

    @property
    def depth(self) -> np.ndarray:
        return self._image("depth")

    @property
    def gray(self) -> np.ndarray:
        """The grayscale image; decoded straight to grey where the frame came encoded (3x faster than colour)."""
        if self._image("gray") is None:
            self._images["gray"] = cv2.cvtColor(self.rgb, cv2.COLOR_RGB2GRAY)
        return self._images["gray"]


def _read_list(path: Path) -> list[tuple[float, str]]:
    if not path.is_file():
        raise DatasetError(f"missing file: {path}")
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        try:
            rows.append((float(fields[0]), fields[1]))
        except (ValueError, IndexError):
            raise DatasetError(f"{path}:{lineno}: expected 'timestamp filename', got {line!r}") from None
    return rows


def associate_stamps(first: np.ndarray, second: np.ndarray, max_dt: float) -> list[tuple[int, int]]:
    """One-to-one pairs (i, j) of closest stamps within ``max_dt``, chosen greedily by |Δt| as in TUM's associate.py."""
    first = np.asarray(first, dtype=np.float64)
    second = np.asarray(second, dtype=np.float64)
    if len(first) == 0 or len(second) == 0:
        return []
    order = np.argsort(second)
    sorted_second = second[order]
    candidates = []
    for i, t in enumerate(first):
        lo = np.searchsorted(sorted_second, t - max_dt, side="left")
        hi = np.searchsorted(sorted_second, t + max_dt, side="right")
        for k in range(lo, hi):
            candidates.append((abs(sorted_second[k] - t), i, int(order[k])))
    candidates.sort()
    used_i, used_j, pairs = set(), set(), []
    for _, i, j in candidates:
        if i not in used_i and j not in used_j:
            used_i.add(i)
            used_j.add(j)
            pairs.append((i, j))
    return sorted(pairs)


class RGBDSequence:
    """A TUM-layout RGB-D sequence on disk. Images are read lazily, frame by frame."""

    def __init__(self, root: str | Path, camera: str | CameraIntrinsics | None = None,
                 max_dt: float = DEFAULT_MAX_DT) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"sequence folder not found: {self.root}")
        self.camera = self._load_camera(camera)
        self.records = self._load_records(max_dt)
        if not self.records:
            raise DatasetError(f"no RGB-D pairs within {max_dt} s in {self.root}")
        self.skipped: list[int] = []

    @property
    def name(self) -> str:
        return self.root.resolve().name

    def __len__(self) -> int:
        return len(self.records)

    def _load_camera(self, camera: str | CameraIntrinsics | None) -> CameraIntrinsics:
        if isinstance(camera, CameraIntrinsics):
            return camera
        if camera is not None:
            if camera not in CAMERA_PRESETS:
                raise DatasetError(f"unknown camera preset {camera!r}; known: {sorted(CAMERA_PRESETS)}")
            return CAMERA_PRESETS[camera]
        camera_file = self.root / "camera.yaml"
        if camera_file.is_file():
            try:
                return CameraIntrinsics(**(yaml.safe_load(camera_file.read_text()) or {}))
            except (yaml.YAMLError, TypeError, ValidationError) as exc:
                raise DatasetError(f"{camera_file}: invalid intrinsics: {exc}") from None
        preset = guess_camera_preset(self.root)
        if preset is None:
            raise DatasetError(
                f"cannot tell the camera of {self.root}: add a camera.yaml (fx, fy, cx, cy, width, height, "
                f"depth_factor) or choose a preset: {sorted(CAMERA_PRESETS)}"
            )
        return CAMERA_PRESETS[preset]

    def _load_records(self, max_dt: float) -> list[FrameRecord]:
        assoc = self.root / "associations.txt"
        rows: list[tuple[float, str, float, str]] = []
        if assoc.is_file():
            for lineno, line in enumerate(assoc.read_text().splitlines(), 1):
                fields = line.split()
                if not fields or fields[0].startswith("#"):
                    continue
                try:
                    rows.append((float(fields[0]), fields[1], float(fields[2]), fields[3]))
                except (ValueError, IndexError):
                    raise DatasetError(f"{assoc}:{lineno}: expected 'rgb_ts rgb_file depth_ts depth_file'") from None
        else:
            rgb = _read_list(self.root / "rgb.txt")
            depth = _read_list(self.root / "depth.txt")
            pairs = associate_stamps([r[0] for r in rgb], [d[0] for d in depth], max_dt)
            rows = [(rgb[i][0], rgb[i][1], depth[j][0], depth[j][1]) for i, j in pairs]
        rows.sort(key=lambda r: r[0])
        return [
            FrameRecord(k, t_rgb, self.root / f_rgb, t_depth, self.root / f_depth)
            for k, (t_rgb, f_rgb, t_depth, f_depth) in enumerate(rows)
        ]

    @property
    def stamps(self) -> np.ndarray:
        return np.array([r.stamp for r in self.records])

    def has_ground_truth(self) -> bool:
        return (self.root / "groundtruth.txt").is_file()

    def ground_truth(self, extrinsic: str = "none") -> Trajectory:
        """Ground truth, optionally turned into camera poses by a fixed extrinsic preset or file."""
        gt = read_tum(self.root / "groundtruth.txt")
        _, left, right = load_gt_extrinsic(extrinsic)
        return gt.transformed(left, right)

    def default_gt_extrinsic(self) -> str:
        """The extrinsic preset that matches this sequence (``bonn`` for Bonn sequences)."""
        return "bonn" if guess_camera_preset(self.root) == "bonn" else "none"

    def check(self, index: int) -> tuple[int, int]:
        """Check frame ``index`` from its image headers only (about 30x cheaper than :meth:`read`): both files
        readable, colour with 3 channels, 16-bit depth, equal sizes. Returns (height, width); raises
        :class:`DatasetError` naming the file. Pixel data is not decoded, so damage past the header shows
        only when a consumer decodes the image."""
        from PIL import Image, UnidentifiedImageError

        rec = self.records[index]
        sizes = {}
        for kind, path in (("colour", rec.rgb_path), ("depth", rec.depth_path)):
            try:
                with Image.open(path) as image:
                    sizes[kind], mode = image.size, image.mode
            except (OSError, UnidentifiedImageError):
                raise DatasetError(f"unreadable {kind} image: {path}") from None
            if kind == "colour" and mode != "RGB":
                raise DatasetError(f"colour images must have 3 channels, got mode {mode}: {path}")
            if kind == "depth" and mode not in ("I;16", "I;16B", "I"):
                raise DatasetError(f"depth must be a single-channel 16-bit PNG, got mode {mode}: {path}")
        if sizes["colour"] != sizes["depth"]:
            raise DatasetError(f"depth size {sizes['depth']} differs from colour size {sizes['colour']}: "
                               f"{rec.depth_path}")
        width, height = sizes["colour"]
        return height, width

    def read(self, index: int) -> Frame:
        """Read frame ``index``; raises :class:`DatasetError` naming the file if it is missing or corrupt."""
        rec = self.records[index]
        try:
            encoded = np.fromfile(rec.rgb_path, np.uint8)
        except OSError:
            raise DatasetError(f"unreadable colour image: {rec.rgb_path}") from None
        # imdecode, not imread: imread pads a truncated JPEG with grey and only prints a warning
        bgr = cv2.imdecode(encoded, cv2.IMREAD_COLOR) if encoded.size else None
        if bgr is None:
            raise DatasetError(f"unreadable colour image: {rec.rgb_path}")
        raw = cv2.imread(str(rec.depth_path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise DatasetError(f"unreadable depth image: {rec.depth_path}")
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise DatasetError(
                f"depth must be a single-channel 16-bit PNG, got {raw.dtype} with shape {raw.shape}: {rec.depth_path}"
            )
        if raw.shape != bgr.shape[:2]:
            raise DatasetError(
                f"depth size {raw.shape[::-1]} differs from colour size {bgr.shape[1::-1]}: {rec.depth_path}"
            )
        rgb = cv2.cvtColor(undistorted(bgr, self.camera), cv2.COLOR_BGR2RGB)
        return Frame(rec.index, rec.stamp, rgb, depth_in_metres(raw, self.camera))

    def frame_range(self, start: int = 0, frames: int | None = None, step: int = 1) -> range:
        """The indices that ``start``, ``frames`` (a count, None = to the end) and ``step`` select; raises
        :class:`DatasetError` when they select nothing or are out of range."""
        if step < 1:
            raise DatasetError(f"step must be at least 1, got {step}")
        if frames is not None and frames < 1:
            raise DatasetError(f"frames must be at least 1, got {frames}")
        if not 0 <= start < len(self):
            raise DatasetError(f"start frame {start} is out of range: {self.root} has frames 0 to {len(self) - 1}")
        return range(start, len(self) if frames is None else min(len(self), start + frames * step), step)

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1) -> Iterator[Frame]:
        """Frames in order; a corrupt frame is skipped with a warning and recorded in ``self.skipped``."""
        for index in range(start, len(self) if stop is None else min(stop, len(self)), step):
            try:
                yield self.read(index)
            except DatasetError as exc:
                log.warning("skipping frame %d: %s", index, exc)
                self.skipped.append(index)
