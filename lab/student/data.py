"""Images for calibration and distillation: listing, the held-out split, the R2D2 input normalisation.

Only ``../shared/images`` (the data folder beside the repository, :func:`images_dir`; or another folder the caller
names) is read; never the evaluation sequence. The last ``HELD_OUT`` frames of ``7scenes/`` (sorted by name) are held
out of training and calibration, to check a network on images it did not see.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)
HELD_OUT = 200
SUFFIXES = (".jpg", ".jpeg", ".png")


def list_images(images_dir: str | Path) -> list[Path]:
    """All images under ``images_dir``, recursively, sorted by path."""
    root = Path(images_dir)
    paths = sorted(p for p in root.rglob("*") if p.suffix.lower() in SUFFIXES)
    if not paths:
        raise FileNotFoundError(f"no images under {root}")
    return paths


def split(paths: list[Path], held_out: int = HELD_OUT) -> tuple[list[Path], list[Path]]:
    """(train, held_out): the last ``held_out`` images of the ``7scenes`` folder are held out, when it exists."""
    seven = [p for p in paths if "7scenes" in p.parts]
    held = set(seven[-held_out:]) if len(seven) > held_out else set()
    return [p for p in paths if p not in held], [p for p in paths if p in held]


def spread(paths: list[Path], count: int) -> list[Path]:
    """``count`` paths evenly spread over the sorted list (every folder gets its share)."""
    if count >= len(paths):
        return list(paths)
    index = np.linspace(0, len(paths) - 1, count).round().astype(int)
    return [paths[i] for i in index]


def read_rgb(path: str | Path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise OSError(f"cannot read {path}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def normalise(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> float32 (3, H, W): RGB / 255 then ImageNet mean/std (the R2D2 contract)."""
    x = (rgb.astype(np.float32) / 255.0 - IMAGENET_MEAN) / IMAGENET_STD
    return np.ascontiguousarray(x.transpose(2, 0, 1))


def network_input(path: str | Path, width: int, height: int) -> np.ndarray:
    """The [1, 3, height, width] network input for an image file, resized like the detector does."""
    rgb = read_rgb(path)
    if rgb.shape[1::-1] != (width, height):
        shrink = width < rgb.shape[1]
        rgb = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    return normalise(rgb)[None]


def models_dir() -> Path:
    """The shared model folder (the project's mirror: $TWOHR_MODEL_MIRROR or ../shared/models beside the
    repository)."""
    from twohr.models import REPO_ROOT, mirror_dirs

    for folder in mirror_dirs():
        if (folder / "faster2d2_WASF_N16.onnx").exists():
            return folder
    return REPO_ROOT.parent / "shared" / "models"


def images_dir() -> Path:
    """The shared training/calibration images, beside the model folder."""
    return models_dir().parent / "images"
