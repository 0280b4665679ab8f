"""Small synthetic RGB-D sequences with exact ground truth, for fast tests.

The scene is a textured box-shaped room seen from inside; optional moving boxes play the
people. Everything is ray-cast analytically, so depth and poses are exact. The output is a
TUM-layout folder (``rgb/``, ``depth/``, ``rgb.txt``, ``depth.txt``, ``associations.txt``,
``groundtruth.txt``, ``camera.yaml``) plus ``dynamic/`` masks of the moving boxes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from .dataset import CameraIntrinsics
from .geometry import so3_exp_batch
from .trajectory import Trajectory, write_tum

ROOM_MIN = np.array([-2.5, -1.5, -1.5])
ROOM_MAX = np.array([2.5, 1.5, 4.0])


@dataclass
class SyntheticSpec:
    """What to generate. Defaults give a 2 s, 320x240 clip with one walking occluder."""

    frames: int = 60
    fps: float = 30.0
    width: int = 320
    height: int = 240
    occluders: int = 1
    seed: int = 0
    path_radius: float = 0.25
    depth_noise: float = 0.0
    start_stamp: float = 1000.0
    texture_px: int = 768
    distortion: tuple[float, ...] = ()
    """OpenCV lens distortion (k1 k2 p1 p2 k3) the images are rendered with; () = a pinhole camera"""
    motion: str = "loop"
    """``loop``: a hand-held loop (:func:`camera_path`); ``still``: the camera holds still; ``pan``: it turns
    ``pan_deg`` to the left and back, ``sweeps`` times (a sweep back revisits what the one before mapped)"""
    pan_deg: float = 40.0
    sweeps: int = 1

    @property
    def camera(self) -> CameraIntrinsics:
        f = 0.82 * self.width
        return CameraIntrinsics(fx=f, fy=f, cx=(self.width - 1) / 2, cy=(self.height - 1) / 2,
                                width=self.width, height=self.height, distortion=list(self.distortion))


def _texture(rng: np.random.Generator, size: int) -> np.ndarray:
    """A corner-rich texture: layered random rectangles and discs over smooth noise, RGB uint8."""
    coarse = rng.uniform(40, 215, (8, 8, 3)).astype(np.float32)
    base = cv2.resize(coarse, (size, size), interpolation=cv2.INTER_CUBIC)
    img = base.copy()
    for _ in range(size // 3):
        colour = rng.uniform(0, 255, 3).tolist()
        x, y = rng.integers(0, size, 2)
        if rng.random() < 0.6:
            w, h = rng.integers(size // 60, size // 10, 2)
            cv2.rectangle(img, (int(x), int(y)), (int(x + w), int(y + h)), colour, -1)
        else:
            cv2.circle(img, (int(x), int(y)), int(rng.integers(size // 80, size // 20)), colour, -1)
    img = cv2.GaussianBlur(img, (3, 3), 0.8)
    return np.clip(img, 0, 255).astype(np.uint8)


def camera_path(spec: SyntheticSpec) -> Trajectory:
    """A smooth hand-held-like path: a loop in x-y with gentle yaw and pitch, looking down +z (or still, or panning:
    ``spec.motion``)."""
    t = np.arange(spec.frames) / spec.fps
    if spec.motion in ("still", "pan"):
        poses = np.tile(np.eye(4), (spec.frames, 1, 1))
        if spec.motion == "pan":  # yaw 0 -> pan_deg -> 0 ... at a steady rate, sweeps legs in all
            legs = spec.sweeps * (np.arange(spec.frames) / max(spec.frames - 1, 1))
            yaw = np.radians(spec.pan_deg) * np.where(np.floor(legs) % 2 == 0, legs % 1, 1 - legs % 1)
            yaw[-1] = np.radians(spec.pan_deg) * (spec.sweeps % 2)
            poses[:, :3, :3] = so3_exp_batch(np.column_stack([np.zeros_like(yaw), yaw, np.zeros_like(yaw)]))
        return Trajectory(spec.start_stamp + t, poses)
    if spec.motion != "loop":
        raise ValueError(f"unknown synthetic motion {spec.motion!r}: loop, still or pan")
    phase = 2 * np.pi * t / max(t[-1], 1e-6) if spec.frames > 1 else np.zeros(1)
    r = spec.path_radius
    poses = np.tile(np.eye(4), (len(phase), 1, 1))
    poses[:, :3, 3] = np.stack([r * np.sin(phase), 0.5 * r * np.sin(2 * phase), 0.3 * np.sin(phase / 2)], axis=1)
    poses[:, :3, :3] = so3_exp_batch(np.stack([0.08 * np.sin(2 * phase), 0.25 * np.sin(phase), 0.05 * np.sin(phase)],
                                              axis=1))
    return Trajectory(spec.start_stamp + t, poses)


def _ray_box(origin: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray, inside: bool):
    """Ray parameter and hit axis for each ray against an axis-aligned box (exit if inside, entry if outside)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - origin) / dirs
        t2 = (hi - origin) / dirs
    t_small = np.minimum(t1, t2)
    t_big = np.maximum(t1, t2)
    if inside:
        t_big = np.where(np.isfinite(t_big), t_big, np.inf)
        axis = np.argmin(t_big, axis=1)
        return np.take_along_axis(t_big, axis[:, None], 1)[:, 0], axis
    t_small = np.where(np.isfinite(t_small), t_small, -np.inf)
    t_near = t_small.max(axis=1)
    t_far = np.where(np.isfinite(t_big), t_big, np.inf).min(axis=1)
    axis = np.argmax(t_small, axis=1)
    t_near = np.where((t_near <= t_far) & (t_near > 1e-6), t_near, np.inf)
    return t_near, axis


def _shade(points: np.ndarray, axis: np.ndarray, lo: np.ndarray, hi: np.ndarray,
           textures: list[np.ndarray]) -> np.ndarray:
    """Colour of surface points on a box: each face axis samples its own texture by the other two coordinates."""
    out = np.zeros((len(points), 3), np.uint8)
    for a in range(3):
        sel = axis == a
        if not sel.any():
            continue
        u_axis, v_axis = [k for k in range(3) if k != a]
        tex = textures[a]
        size = tex.shape[0]
        u = (points[sel, u_axis] - lo[u_axis]) / (hi[u_axis] - lo[u_axis]) * (size - 1)
        v = (points[sel, v_axis] - lo[v_axis]) / (hi[v_axis] - lo[v_axis]) * (size - 1)
        # opposite faces differ: flip the texture for the far face
        far = np.abs(points[sel, a] - hi[a]) < np.abs(points[sel, a] - lo[a])
        u = np.where(far, size - 1 - u, u)
        out[sel] = _bilinear(tex, u, v)
    return out


def _bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples of an (H, W, C) image at float coordinates, clamped to the border."""
    h, w = image.shape[:2]
    u = np.clip(u, 0, w - 1.001)
    v = np.clip(v, 0, h - 1.001)
    u0, v0 = u.astype(int), v.astype(int)
    fu, fv = (u - u0)[:, None], (v - v0)[:, None]
    img = image.astype(np.float32)
    top = img[v0, u0] * (1 - fu) + img[v0, u0 + 1] * fu
    bottom = img[v0 + 1, u0] * (1 - fu) + img[v0 + 1, u0 + 1] * fu
    return np.round(top * (1 - fv) + bottom * fv).astype(np.uint8)


class SyntheticScene:
    """Renders RGB, depth and dynamic masks of the room from any camera pose."""

    def __init__(self, spec: SyntheticSpec) -> None:
        self.spec = spec
        rng = np.random.default_rng(spec.seed)
        self.room_textures = [_texture(rng, spec.texture_px) for _ in range(3)]
        self.occluder_textures = [[_texture(rng, 128) for _ in range(3)] for _ in range(spec.occluders)]
        self.occluder_phase = rng.uniform(0, 2 * np.pi, spec.occluders)
        cam = spec.camera
        u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
        pixels = np.stack([u, v], -1).reshape(-1, 1, 2).astype(np.float64)
        # each pixel's ray, through the lens model when there is one (z = 1: the depth is the z-distance)
        normalised = cv2.undistortPoints(pixels, cam.matrix, np.array(cam.distortion or [0.0] * 5)).reshape(-1, 2)
        self.rays_cam = np.column_stack([normalised, np.ones(len(normalised))])

    def occluder_box(self, k: int, t: float) -> tuple[np.ndarray, np.ndarray]:
        """A person-sized box walking left-right through the view, 1.5-2.5 m in front of the camera."""
        x = 1.2 * np.sin(0.9 * t + self.occluder_phase[k])
        z = 1.8 + 0.4 * k
        centre = np.array([x, 0.2, z])
        half = np.array([0.25, 0.9, 0.15])
        return centre - half, centre + half

    def render(self, pose: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """RGB (H, W, 3) uint8, depth (H, W) float64 metres and dynamic mask (H, W) bool at camera pose ``pose``."""
        cam = self.spec.camera
        rotation, origin = pose[:3, :3], pose[:3, 3]
        dirs = self.rays_cam @ rotation.T
        t_room, axis = _ray_box(origin, dirs, ROOM_MIN, ROOM_MAX, inside=True)
        colour = _shade(origin + dirs * t_room[:, None], axis, ROOM_MIN, ROOM_MAX, self.room_textures)
        depth = t_room.copy()
        dynamic = np.zeros(len(depth), bool)
        for k in range(self.spec.occluders):
            lo, hi = self.occluder_box(k, t)
            t_occ, axis_occ = _ray_box(origin, dirs, lo, hi, inside=False)
            hit = t_occ < depth
            if hit.any():
                colour[hit] = _shade(origin + dirs[hit] * t_occ[hit, None], axis_occ[hit], lo, hi,
                                     self.occluder_textures[k])
                depth[hit] = t_occ[hit]
                dynamic |= hit
        shape = (cam.height, cam.width)
        return colour.reshape(shape + (3,)), depth.reshape(shape), dynamic.reshape(shape)


def generate(out_dir: str | Path, spec: SyntheticSpec | None = None) -> Path:
    """Write a synthetic TUM-layout sequence to ``out_dir`` and return it."""
    spec = spec or SyntheticSpec()
    out = Path(out_dir)
    for sub in ("rgb", "depth", "dynamic"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    scene = SyntheticScene(spec)
    gt = camera_path(spec)
    rng = np.random.default_rng(spec.seed + 1)
    rgb_lines, depth_lines, assoc_lines = [], [], []
    for stamp, pose in zip(gt.stamps, gt.poses, strict=True):
        rgb, depth, dynamic = scene.render(pose, stamp - spec.start_stamp)
        if spec.depth_noise > 0:
            depth = depth + rng.normal(0, spec.depth_noise, depth.shape) * depth**2
        depth_stamp = stamp + 0.004  # like a real sensor: depth and colour are not exactly simultaneous
        rgb_name, depth_name = f"rgb/{stamp:.6f}.png", f"depth/{depth_stamp:.6f}.png"
        cv2.imwrite(str(out / rgb_name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        depth_units = np.clip(np.round(depth * spec.camera.depth_factor), 0, 65535).astype(np.uint16)
        cv2.imwrite(str(out / depth_name), depth_units)
        cv2.imwrite(str(out / f"dynamic/{stamp:.6f}.png"), dynamic.astype(np.uint8) * 255)
        rgb_lines.append(f"{stamp:.6f} {rgb_name}")
        depth_lines.append(f"{depth_stamp:.6f} {depth_name}")
        assoc_lines.append(f"{stamp:.6f} {rgb_name} {depth_stamp:.6f} {depth_name}")
    (out / "rgb.txt").write_text("# timestamp filename\n" + "\n".join(rgb_lines) + "\n")
    (out / "depth.txt").write_text("# timestamp filename\n" + "\n".join(depth_lines) + "\n")
    (out / "associations.txt").write_text("\n".join(assoc_lines) + "\n")
    write_tum(out / "groundtruth.txt", gt, header=f"synthetic twohr sequence, seed {spec.seed}")
    (out / "camera.yaml").write_text(yaml.safe_dump(spec.camera.model_dump()))
    return out
