"""ALIKED (Zhao et al., "ALIKED: A Lighter Keypoint and Descriptor Extraction Network via Deformable
Transformation", IEEE TIM 2023).

slamkit's implementation, loading the official ``aliked-n16.pth`` (default; 128-d descriptors, the ones
``aliked_lightglue.pth`` matches) or ``aliked-t16.pth`` (64-d), BSD-3-Clause, from ``weights_dir`` or
``$SLAMKIT_WEIGHTS``. The deformable convolutions are plain PyTorch (``grid_sample``): no torchvision.

The network: a 4-stage ResNet-like backbone (stages 3 and 4 with deformable 3x3 convolutions) whose
multi-scale features are upsampled to full resolution and concatenated into a dense feature map; a small
score head gives a keypoint score map (differentiable keypoint detection: NMS + soft-argmax refinement);
descriptors come from the SDDH head, which samples the feature map at 16 learned offsets around each
keypoint and aggregates them with learned weights.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..base import Features
from ._torch import gray_tensor, grid_cap, load_into, load_state_dict, to_features
from .weights import find_weights

CONFIGS = {
    # c1, c2, c3, c4, dim, K (offset kernel), M (sampling positions)
    "aliked-t16": (8, 16, 32, 64, 64, 3, 16),
    "aliked-n16": (16, 32, 64, 128, 128, 3, 16),
    "aliked-n16rot": (16, 32, 64, 128, 128, 3, 16),
    "aliked-n32": (16, 32, 64, 128, 128, 3, 32),
}


def deform_conv3x3(x: torch.Tensor, offset: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Deformable 3x3 convolution, stride 1, padding 1, no bias (DCNv1, torchvision's offset layout).

    x [B x C x H x W]; offset [B x 18 x H x W], (dy, dx) per kernel tap, taps row-major;
    weight [C_out x C x 3 x 3] -> [B x C_out x H x W]. Out-of-image samples are zero.
    """
    b, c, h, w = x.shape
    off = offset.view(b, 9, 2, h, w)
    ky, kx = torch.meshgrid(torch.arange(-1, 2, dtype=x.dtype), torch.arange(-1, 2, dtype=x.dtype), indexing="ij")
    ys = torch.arange(h, dtype=x.dtype).view(1, 1, h, 1) + ky.reshape(1, 9, 1, 1) + off[:, :, 0]
    xs = torch.arange(w, dtype=x.dtype).view(1, 1, 1, w) + kx.reshape(1, 9, 1, 1) + off[:, :, 1]
    # grid_sample, align_corners=True: -1 and 1 are the centres of the first and last pixels
    grid = torch.stack([2 * xs / max(w - 1, 1) - 1, 2 * ys / max(h - 1, 1) - 1], -1)  # [B x 9 x H x W x 2]
    sampled = F.grid_sample(x, grid.view(b, 9 * h, w, 2), mode="bilinear", padding_mode="zeros",
                            align_corners=True).view(b, c, 9, h * w)
    return torch.einsum("bckn,ock->bon", sampled, weight.view(weight.shape[0], c, 9)).view(b, -1, h, w)


class DeformableConv2d(nn.Module):
    """3x3 deformable convolution whose offsets come from a regular 3x3 convolution (clamped to a quarter of
    the feature map's size)."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.offset_conv = nn.Conv2d(cin, 18, 3, padding=1, bias=True)
        self.regular_conv = nn.Conv2d(cin, cout, 3, padding=1, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        m = max(x.shape[-2:]) / 4.0
        return deform_conv3x3(x, self.offset_conv(x).clamp(-m, m), self.regular_conv.weight)


def _conv(cin: int, cout: int, deformable: bool) -> nn.Module:
    return DeformableConv2d(cin, cout) if deformable else nn.Conv2d(cin, cout, 3, padding=1, bias=False)


class ConvBlock(nn.Module):
    """conv-BN-SELU twice (stage 1)."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv1, self.bn1 = _conv(cin, cout, False), nn.BatchNorm2d(cout)
        self.conv2, self.bn2 = _conv(cout, cout, False), nn.BatchNorm2d(cout)

    def forward(self, x):
        return F.selu(self.bn2(self.conv2(F.selu(self.bn1(self.conv1(x))))))


class ResBlock(nn.Module):
    """Residual block with a 1x1 projection shortcut (``downsample``), regular or deformable convolutions."""

    def __init__(self, cin: int, cout: int, deformable: bool):
        super().__init__()
        self.conv1, self.bn1 = _conv(cin, cout, deformable), nn.BatchNorm2d(cout)
        self.conv2, self.bn2 = _conv(cout, cout, deformable), nn.BatchNorm2d(cout)
        self.downsample = nn.Conv2d(cin, cout, 1)

    def forward(self, x):
        out = self.bn2(self.conv2(F.selu(self.bn1(self.conv1(x)))))
        return F.selu(out + self.downsample(x))


class SDDH(nn.Module):
    """Sparse deformable descriptor head: per keypoint, ``n_pos`` offsets predicted from the K x K patch
    around it; features sampled there, projected (``sf_conv``) and aggregated (``agg_weights``)."""

    def __init__(self, dim: int, kernel_size: int, n_pos: int):
        super().__init__()
        self.kernel_size, self.n_pos = kernel_size, n_pos
        self.offset_conv = nn.Sequential(nn.Conv2d(dim, 2 * n_pos, kernel_size, bias=True), nn.SELU(),
                                         nn.Conv2d(2 * n_pos, 2 * n_pos, 1, bias=True))
        self.sf_conv = nn.Conv2d(dim, dim, 1, bias=False)
        self.agg_weights = nn.Parameter(torch.zeros(n_pos, dim, dim))

    def forward(self, fmap: "DenseFeatures", xy: torch.Tensor) -> torch.Tensor:
        """fmap: the dense feature map (H x W, dim channels); xy [N x 2] pixels -> descriptors [N x dim],
        L2-normalised."""
        h, w, c = fmap.height, fmap.width, fmap.dim
        k, n = self.kernel_size, len(xy)
        if n == 0:
            return xy.new_zeros((0, c))
        # K x K patches with their top-left corner clamped inside the map (as upstream)
        corner = xy.long() - k // 2
        cx = corner[:, 0].clamp(0, w - 1 - k)
        cy = corner[:, 1].clamp(0, h - 1 - k)
        r = torch.arange(k)
        yy = (cy[:, None, None] + r[None, :, None]).expand(n, k, k)
        xx = (cx[:, None, None] + r[None, None, :]).expand(n, k, k)
        patches = fmap.at(xx.reshape(-1), yy.reshape(-1)).view(n, k, k, c).permute(0, 3, 1, 2)  # [N x C x K x K]
        m = max(h, w) / 4.0
        off = self.offset_conv(patches).clamp(-m, m)[:, :, 0, 0].view(n, 2, self.n_pos).transpose(1, 2)
        pos = xy[:, None, :] + off  # [N x n_pos x 2], pixels (x, y)
        f = fmap.bilinear(pos.reshape(-1, 2)).view(n, self.n_pos, c)  # [N x n_pos x C]
        f = F.selu(f @ self.sf_conv.weight[:, :, 0, 0].t())
        return F.normalize(torch.einsum("npc,pcd->nd", f, self.agg_weights), dim=1)


class DenseFeatures:
    """ALIKED's dense feature map, L2-normalised per pixel, evaluated only where it is needed.

    The network's map is ``normalize(cat(x1, up(x2), up(x3), up(x4)))`` at full resolution (x_i: the
    stage outputs projected to dim/4 channels, ``up``: bilinear, align_corners=True); computing it only at the
    pixels the descriptor head reads gives the same values without a (dim x H x W) tensor.
    ``parts`` are the four projections on the padded image; ``pad`` = (left, top).
    """

    def __init__(self, parts: list[torch.Tensor], size: tuple[int, int], pad: tuple[int, int]):
        self.parts = parts
        self.height, self.width = size
        self.pad = pad
        self.dim = sum(p.shape[1] for p in parts)
        self._padded = parts[0].shape[-2:]

    def at(self, ix: torch.Tensor, iy: torch.Tensor) -> torch.Tensor:
        """Integer pixels (x [P], y [P]) of the unpadded image -> [P x dim] unit vectors."""
        hp, wp = self._padded
        px, py = ix + self.pad[0], iy + self.pad[1]
        cols = [self.parts[0][0, :, py, px].t()]
        if len(self.parts) > 1:
            g = torch.stack([2 * px / max(wp - 1, 1) - 1, 2 * py / max(hp - 1, 1) - 1], -1).to(self.parts[0].dtype)
            for p in self.parts[1:]:
                cols.append(F.grid_sample(p, g.view(1, 1, -1, 2), mode="bilinear", align_corners=True)[0, :, 0].t())
        return F.normalize(torch.cat(cols, 1), dim=1)

    def bilinear(self, xy: torch.Tensor) -> torch.Tensor:
        """Bilinear samples at pixels xy [Q x 2] (zero outside the image, as grid_sample) -> [Q x dim]."""
        x0, y0 = xy[:, 0].floor(), xy[:, 1].floor()
        fx, fy = xy[:, 0] - x0, xy[:, 1] - y0
        x0, y0 = x0.long(), y0.long()
        corners = [(x0, y0, (1 - fx) * (1 - fy)), (x0 + 1, y0, fx * (1 - fy)), (x0, y0 + 1, (1 - fx) * fy),
                   (x0 + 1, y0 + 1, fx * fy)]
        ids, wts = [], []
        for cx, cy, wt in corners:
            ok = (cx >= 0) & (cx < self.width) & (cy >= 0) & (cy < self.height)
            ids.append(torch.where(ok, cy * self.width + cx, 0))
            wts.append(torch.where(ok, wt, 0))
        ids_all = torch.stack(ids)  # [4 x Q]
        uniq, inv = torch.unique(ids_all, return_inverse=True)
        feats = self.at(uniq % self.width, uniq // self.width)
        wts_all = torch.stack(wts)  # [4 x Q]
        return (feats[inv] * wts_all[..., None]).sum(0)


class ALIKED(nn.Module):
    """The ALIKED network.

    dense(image [1 x 3 x H x W] in [0, 1]) -> DenseFeatures (the L2-normalised dim x H x W feature map,
    evaluated lazily), score map [1 x 1 x H x W] in (0, 1). ``desc_head(features, xy [N x 2])`` ->
    [N x dim].
    """

    def __init__(self, model_name: str = "aliked-n16"):
        super().__init__()
        if model_name not in CONFIGS:
            raise ValueError(f"ALIKED: unknown model {model_name!r}; choose from {sorted(CONFIGS)}")
        c1, c2, c3, c4, dim, k, m = CONFIGS[model_name]
        self.dim = dim
        self.block1 = ConvBlock(3, c1)
        self.block2 = ResBlock(c1, c2, deformable=False)
        self.block3 = ResBlock(c2, c3, deformable=True)
        self.block4 = ResBlock(c3, c4, deformable=True)
        self.conv1 = nn.Conv2d(c1, dim // 4, 1, bias=False)
        self.conv2 = nn.Conv2d(c2, dim // 4, 1, bias=False)
        self.conv3 = nn.Conv2d(c3, dim // 4, 1, bias=False)
        self.conv4 = nn.Conv2d(c4, dim // 4, 1, bias=False)
        self.score_head = nn.Sequential(nn.Conv2d(dim, 8, 1, bias=False), nn.SELU(),
                                        nn.Conv2d(8, 4, 3, padding=1, bias=False), nn.SELU(),
                                        nn.Conv2d(4, 4, 3, padding=1, bias=False), nn.SELU(),
                                        nn.Conv2d(4, 1, 3, padding=1, bias=False))
        self.desc_head = SDDH(dim, k, m)

    def dense(self, image: torch.Tensor) -> tuple[DenseFeatures, torch.Tensor]:
        h0, w0 = image.shape[-2:]
        ph, pw = (-h0) % 32, (-w0) % 32  # pad to multiples of 32 (replicate), centred as upstream
        pad = (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2)
        x = F.pad(image, pad, mode="replicate") if ph or pw else image
        x1 = self.block1(x)
        x2 = self.block2(F.avg_pool2d(x1, 2))
        x3 = self.block3(F.avg_pool2d(x2, 4))
        x4 = self.block4(F.avg_pool2d(x3, 4))
        parts = [F.selu(conv(t)) for conv, t in ((self.conv1, x1), (self.conv2, x2), (self.conv3, x3),
                                                 (self.conv4, x4))]
        # the score head's first (1x1, linear) layer on the concatenation = the sum of its blocks applied to
        # each part, and a per-pixel linear map commutes with bilinear upsampling: upsample 8 channels, not dim
        w_first = self.score_head[0].weight[:, :, 0, 0]  # [8 x dim]
        q = self.dim // 4
        size = x1.shape[-2:]
        s = F.conv2d(parts[0], w_first[:, :q, None, None])
        for i, p in enumerate(parts[1:], 1):
            s = s + F.interpolate(F.conv2d(p, w_first[:, i * q:(i + 1) * q, None, None]), size=size,
                                  mode="bilinear", align_corners=True)
        score = torch.sigmoid(self.score_head[1:](s))
        score = score[..., pad[2]:pad[2] + h0, pad[0]:pad[0] + w0]
        return DenseFeatures(parts, (h0, w0), (pad[0], pad[2])), score


def detect_keypoints(score: torch.Tensor, radius: int, threshold: float, top_k: int,
                     grid: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable keypoint detection at inference: (2r+1)^2 NMS, border of r removed, maxima above
    ``threshold`` (all maxima if it is <= 0), the ``top_k`` best, then soft-argmax refinement (temperature
    0.1) in the (2r+1)^2 window. score [1 x 1 x H x W] -> xy [N x 2] pixels, scores [N] (bilinear)."""
    _, _, h, w = score.shape
    k = 2 * radius + 1
    nms = score == F.max_pool2d(score, k, stride=1, padding=radius)
    nms[..., :radius, :] = False
    nms[..., h - radius:, :] = False
    nms[..., :, :radius] = False
    nms[..., :, w - radius:] = False
    if threshold > 0:
        nms &= score > threshold
    yx = nms[0, 0].nonzero()
    s = score[0, 0, yx[:, 0], yx[:, 1]]
    xy_int = yx.flip(-1)
    if grid:
        keep = grid_cap(xy_int.float(), s, (h, w), top_k)
    else:
        keep = torch.argsort(s, descending=True)[:top_k] if top_k > 0 else torch.argsort(s, descending=True)
    xy_int = xy_int[keep]
    # soft-argmax over the window around each maximum
    r = torch.arange(-radius, radius + 1)
    dy, dx = torch.meshgrid(r, r, indexing="ij")
    win = score[0, 0][(xy_int[:, 1, None] + dy.reshape(1, -1)), (xy_int[:, 0, None] + dx.reshape(1, -1))]
    e = ((win - win.max(1, keepdim=True).values) / 0.1).exp()
    offs = torch.stack([dx.reshape(-1), dy.reshape(-1)], -1).to(score.dtype)
    xy = xy_int.to(score.dtype) + (e @ offs) / e.sum(1, keepdim=True)
    wh = torch.tensor([w - 1, h - 1], dtype=score.dtype)
    grid_ = (2 * xy / wh - 1).view(1, 1, -1, 2)
    scores = F.grid_sample(score, grid_, mode="bilinear", align_corners=True)[0, 0, 0]
    return xy, scores


class AlikedExtractor:
    """ALIKED keypoints and descriptors (128-d for aliked-n16; float32, L2-normalised).

    The grey image is given to the RGB network as three equal channels. Keypoints are score-map maxima
    above ``detection_threshold``, the ``num_features`` best (spread over an 8x6 grid first when ``grid``),
    refined to sub-pixel positions.
    """

    name = "aliked"
    default_conf = {
        "model_name": "aliked-n16",
        "num_features": 2000,
        "detection_threshold": 0.2,
        "nms_radius": 2,
        "grid": False,
        "weights_dir": None,
    }

    def __init__(self, **conf):
        unknown = set(conf) - set(self.default_conf)
        if unknown:
            raise ValueError(f"aliked: unknown options {sorted(unknown)}; options: {sorted(self.default_conf)}")
        self.conf = {**self.default_conf, **conf}
        name = self.conf["model_name"]
        net = ALIKED(name)
        self.weights_path = find_weights(f"{name}.pth", self.conf["weights_dir"], who="aliked")
        self.net = load_into(net, load_state_dict(self.weights_path), self.weights_path)
        self.num_features = int(self.conf["num_features"])

    @torch.inference_mode()
    def detect_and_compute(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """image [1 x 3 x H x W] in [0, 1] -> keypoints [N x 2] pixels, descriptors [N x dim], scores [N]."""
        fmap, score = self.net.dense(image)
        c = self.conf
        xy, scores = detect_keypoints(score, c["nms_radius"], c["detection_threshold"], self.num_features, c["grid"])
        return xy, self.net.desc_head(fmap, xy), scores

    def extract(self, gray: np.ndarray) -> Features:
        """gray (H, W) uint8 -> Features: keypoints (N, 2) float64 px, descriptors (N, 128) float32 unit L2,
        scores (N,) float32, N <= num_features."""
        xy, desc, scores = self.detect_and_compute(gray_tensor(gray).expand(-1, 3, -1, -1))
        return to_features(xy, desc, scores, gray.shape)
