"""The image plumbing every detector shares: the check of an input image and the network input size it is scaled
to. The lowest module of the room: it imports nothing of the room."""

from __future__ import annotations

import numpy as np


def check_image(rgb: np.ndarray) -> None:
    """Raise a clear ValueError unless ``rgb`` is an (H, W, 3) uint8 image of at least 16x16 pixels."""
    if not isinstance(rgb, np.ndarray):
        raise ValueError(f"expected an RGB uint8 numpy image of shape (H, W, 3), got {type(rgb).__name__}")
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"expected an RGB uint8 image of shape (H, W, 3), got shape {rgb.shape} dtype {rgb.dtype}")
    if min(rgb.shape[:2]) < 16:
        raise ValueError(f"image too small for keypoint detection: {rgb.shape[1]}x{rgb.shape[0]} (need 16x16)")


def network_size(width: int, height: int, scale: float) -> tuple[int, int]:
    """Network input (width, height): the image scaled by ``scale`` and rounded to even numbers."""
    return max(2, int(round(width * scale / 2)) * 2), max(2, int(round(height * scale / 2)) * 2)
