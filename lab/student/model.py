"""The student keyframe network: an R2D2-contract net about three times cheaper than faster2d2.

Contract (the same as faster2d2's ONNX, so the detector loads it unchanged)
-------------------------------------------------------------------------
* input ``image``: float32 ``[1, 3, H, W]``, RGB / 255 then ImageNet mean/std; H and W even;
* ``descriptors``: ``[1, 128, H, W]``, L2-normalised per pixel; computed as
  ``Div(Resize2x(f), Expand(Clip(ReduceL2(Resize2x(f)))))`` on the ``[1, 128, H/2, W/2]`` feature map ``f``,
  the pattern the detector's sparse path recognises (it cuts the graph before the 2x bilinear upsample and
  normalises only the keypoints' descriptors, so the dense 128-channel full-resolution tensor disappears);
* ``reliability``: ``[1, 1, H, W]`` in [0, 1], ``sigmoid(r)`` (R2D2's ``softmax([a, b])[1]`` is ``sigmoid(b - a)``:
  the same function family, one logit instead of two, no full-resolution softmax);
* ``repeatability``: ``[1, 1, H, W]`` in [0, 1], ``softplus(s) / (1 + softplus(s))`` as in R2D2.

Design, and why
---------------
faster2d2 spends about 142 k multiply-adds per input pixel: 28 k in three full-resolution 3x3 convs
(3->32->32->64), 114 k at half resolution (64->64->128->128 3x3, then three 128->128 2x2 dilated convs),
and its heads then read the *full-resolution, 128-channel* upsampled map (x*x, two 1x1 convs, the L2 norm),
which is memory traffic the MAC count does not show. The student keeps what makes R2D2 work (half-resolution
features with a receptive field of about 50 px built by dilations, not by more downsampling, so
repeatability peaks stay pixel-accurate) and removes the cost:

* one full-resolution conv only (3->24), then a *strided* 3x3 conv (24->48) instead of full-resolution
  convs plus max-pool;
* fewer channels at half resolution: 48->64 (3x3), 64->64 (3x3, dilation 2), 64->80 (3x3, dilation 4),
  80->128 (2x2, dilation 8, linear: the descriptor features); BatchNorm after each conv, folded at export;
* one *shared light head* for both maps: a 1x1 conv projects the 128 features to 16 channels at half
  resolution, only those 16 channels are upsampled 2x, and ``[u, u*u]`` (32 channels) goes through one
  1x1 conv to 2 logits (reliability, repeatability). The square keeps R2D2's quadratic head on
  interpolated features, so peaks can fall between half-resolution samples, at 1/8 of the memory.

About 42 k multiply-adds per pixel (3.4x fewer than faster2d2's 143 k), 0.17 M parameters against 0.48 M.
Profiled in the detector's graph (onnxruntime, 1 thread, 480x360), the convolutions are 90 % of the time.

Tensor shapes (B images of H x W, both even)::

    image           [B,   3, H,   W  ]
    stem   3x3      [B,  24, H,   W  ]  ReLU
    down   3x3 s2   [B,  48, H/2, W/2]  ReLU
    b1     3x3      [B,  64, H/2, W/2]  ReLU
    b2     3x3 d2   [B,  64, H/2, W/2]  ReLU
    b3     3x3 d4   [B,  80, H/2, W/2]  ReLU
    feat   2x2 d8   [B, 128, H/2, W/2]  (no ReLU)
    descriptors     [B, 128, H,   W  ]  bilinear 2x, L2-normalised
    head   1x1      [B,  16, H/2, W/2] -> bilinear 2x [B, 16, H, W] -> cat(u, u*u) [B, 32, H, W]
    logits 1x1      [B,   2, H,   W  ] -> reliability [B, 1, H, W], repeatability [B, 1, H, W]
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

DESCRIPTOR_DIM = 128
HEAD_DIM = 16


def _conv(cin: int, cout: int, kernel: int = 3, stride: int = 1, dilation: int = 1, relu: bool = True) -> nn.Sequential:
    """Conv (no bias) + BatchNorm (+ ReLU), padded to keep the size: a 2x2 kernel with an even dilation d is
    padded by d/2 on each side (as faster2d2's last conv), a 3x3 kernel by d."""
    layers: list[nn.Module] = []
    padding = dilation // 2 if kernel == 2 else dilation * (kernel // 2)
    layers.append(nn.Conv2d(cin, cout, kernel, stride, padding, dilation, bias=False))
    layers.append(nn.BatchNorm2d(cout))
    if relu:
        layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


class StudentNet(nn.Module):
    """See the module docstring. ``forward`` returns (descriptors, reliability, repeatability), full size."""

    def __init__(self, width: float = 1.0) -> None:
        super().__init__()
        c = [max(8, int(round(n * width))) for n in (24, 48, 64, 64, 80)]
        self.backbone = nn.Sequential(
            _conv(3, c[0]),
            _conv(c[0], c[1], stride=2),
            _conv(c[1], c[2]),
            _conv(c[2], c[3], dilation=2),
            _conv(c[3], c[4], dilation=4),
            _conv(c[4], DESCRIPTOR_DIM, kernel=2, dilation=8, relu=False),
        )
        self.head_proj = nn.Conv2d(DESCRIPTOR_DIM, HEAD_DIM, 1)
        self.head_out = nn.Conv2d(2 * HEAD_DIM, 2, 1)

    def features(self, image: torch.Tensor) -> torch.Tensor:
        """The raw [B, 128, H/2, W/2] descriptor features."""
        return self.backbone(image)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        feat = self.backbone(image)
        up = F.interpolate(feat, scale_factor=2.0, mode="bilinear", align_corners=False)
        descriptors = F.normalize(up, p=2, dim=1)
        u = F.interpolate(self.head_proj(feat), scale_factor=2.0, mode="bilinear", align_corners=False)
        logits = self.head_out(torch.cat([u, u * u], dim=1))
        reliability = torch.sigmoid(logits[:, 0:1])
        s = F.softplus(logits[:, 1:2])
        repeatability = s / (1 + s)
        return descriptors, reliability, repeatability


def parameter_count(model: nn.Module) -> int:
    """Parameters at inference (BatchNorm folded into the convs: its running stats are not parameters)."""
    return sum(p.numel() for p in model.parameters())


def macs_per_pixel(model: StudentNet) -> float:
    """Multiply-adds per input pixel of the convolutions (half-resolution layers count 1/4)."""
    total = 0.0
    scale = 1.0
    for block in model.backbone:
        conv = next(m for m in block if isinstance(m, nn.Conv2d))
        scale = scale / (conv.stride[0] ** 2)
        total += conv.in_channels * conv.out_channels * conv.kernel_size[0] * conv.kernel_size[1] * scale
    total += model.head_proj.in_channels * model.head_proj.out_channels / 4
    total += model.head_out.in_channels * model.head_out.out_channels
    return total


#: faster2d2's multiply-adds per input pixel, from its ONNX weights (see the module docstring).
FASTER2D2_MACS_PER_PIXEL = (3 * 32 * 9 + 32 * 32 * 9 + 32 * 64 * 9
                            + (64 * 64 * 9 + 64 * 128 * 9 + 128 * 128 * 9 + 3 * 128 * 128 * 4) / 4
                            + 128 * 3)


def export_onnx(model: StudentNet, path, height: int = 240, width: int = 320, opset: int = 17) -> None:
    """ONNX export with faster2d2's names and layout: input ``image`` [1,3,H,W] (H, W dynamic), outputs
    ``descriptors``, ``reliability``, ``repeatability``. BatchNorm is folded (eval mode, constant folding)."""
    import copy

    model = copy.deepcopy(model).eval().cpu()
    example = torch.zeros(1, 3, height, width)
    with torch.no_grad():
        torch.onnx.export(
            model, (example,), str(path), input_names=["image"],
            output_names=["descriptors", "reliability", "repeatability"],
            dynamic_axes={"image": {2: "H", 3: "W"}, "descriptors": {2: "H", 3: "W"},
                          "reliability": {2: "H", 3: "W"}, "repeatability": {2: "H", 3: "W"}},
            opset_version=opset, do_constant_folding=True, dynamo=False,
        )
