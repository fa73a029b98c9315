"""SuperPoint (DeTone, Malisiewicz, Rabinovich, "SuperPoint: Self-Supervised Interest Point Detection and
Description", CVPRW 2018).

slamkit's implementation of the architecture; it loads Magic Leap's official ``superpoint_v1.pth`` from
``weights_dir`` or ``$SLAMKIT_WEIGHTS``. Those weights are licensed by Magic Leap for non-commercial research
only and may not be redistributed: slamkit neither ships nor downloads them (get them from
github.com/magicleap/SuperGluePretrainedNetwork, ``models/weights/``).

The network: a VGG-style encoder (8 3x3 convolutions, 3 max-pools: 1/8 resolution), a detector head giving 65
logits per 8x8 cell (64 positions + "no keypoint") and a descriptor head giving a 256-d map, interpolated
at the keypoints.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..base import Features
from ._torch import gray_tensor, grid_cap, load_into, load_state_dict, to_features
from .weights import find_weights


class SuperPoint(nn.Module):
    """The SuperPoint network (state-dict keys ``conv1a`` ... ``conv4b``, ``convPa``, ``convPb``, ``convDa``,
    ``convDb``).

    forward(image [B x 1 x H x W] in [0, 1], H and W multiples of 8) ->
        keypoint probabilities [B x H x W] (softmax over each cell, "no keypoint" dropped),
        descriptors [B x 256 x H/8 x W/8] (L2-normalised).
    """

    def __init__(self, descriptor_dim: int = 256):
        super().__init__()
        c1, c2, c3, c4, c5 = 64, 64, 128, 128, 256
        for name, cin, cout in (("conv1a", 1, c1), ("conv1b", c1, c1), ("conv2a", c1, c2), ("conv2b", c2, c2),
                                ("conv3a", c2, c3), ("conv3b", c3, c3), ("conv4a", c3, c4), ("conv4b", c4, c4),
                                ("convPa", c4, c5), ("convDa", c4, c5)):
            setattr(self, name, nn.Conv2d(cin, cout, 3, padding=1))
        self.convPb = nn.Conv2d(c5, 65, 1)
        self.convDb = nn.Conv2d(c5, descriptor_dim, 1)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = image
        for i, (a, b) in enumerate((("conv1a", "conv1b"), ("conv2a", "conv2b"), ("conv3a", "conv3b"),
                                    ("conv4a", "conv4b"))):
            x = F.relu(getattr(self, b)(F.relu(getattr(self, a)(x))))
            if i < 3:
                x = F.max_pool2d(x, 2)
        prob = F.softmax(self.convPb(F.relu(self.convPa(x))), 1)[:, :-1]
        b, _, h, w = prob.shape
        prob = prob.permute(0, 2, 3, 1).reshape(b, h, w, 8, 8).permute(0, 1, 3, 2, 4).reshape(b, h * 8, w * 8)
        desc = F.normalize(self.convDb(F.relu(self.convDa(x))), dim=1)
        return prob, desc


def simple_nms(scores: torch.Tensor, radius: int) -> torch.Tensor:
    """Non-maximum suppression of a score map [B x H x W] in (2r+1)^2 windows (SuperPoint's two-pass
    version: maxima suppress their window, then maxima of what remains are added)."""
    def max_pool(x):
        return F.max_pool2d(x, 2 * radius + 1, stride=1, padding=radius)

    zeros = torch.zeros_like(scores)
    is_max = scores == max_pool(scores)
    for _ in range(2):
        suppressed = max_pool(is_max.float()) > 0
        rest = torch.where(suppressed, zeros, scores)
        is_max = is_max | ((rest == max_pool(rest)) & ~suppressed)
    return torch.where(is_max, scores, zeros)


def sample_descriptors(xy: torch.Tensor, desc: torch.Tensor, s: int = 8) -> torch.Tensor:
    """Bilinear descriptors [N x D] at pixels xy [N x 2] from the cell map desc [1 x D x h x w] (SuperPoint's
    cell-centre convention), L2-normalised."""
    _, d, h, w = desc.shape
    g = (xy - s / 2 + 0.5) / torch.tensor([w * s - s / 2 - 0.5, h * s - s / 2 - 0.5], dtype=xy.dtype)
    out = F.grid_sample(desc, (g * 2 - 1).view(1, 1, -1, 2), mode="bilinear", align_corners=True)
    return F.normalize(out.reshape(d, -1).t(), dim=1)


class SuperPointExtractor:
    """SuperPoint keypoints and 256-d descriptors (float32, L2-normalised).

    Options as Magic Leap's: ``nms_radius`` 4, ``keypoint_threshold`` 0.005, ``remove_borders`` 4; the
    ``num_features`` best are kept (spread over an 8x6 grid first when ``grid``).
    """

    name = "superpoint"
    default_conf = {
        "num_features": 2000,
        "nms_radius": 4,
        "keypoint_threshold": 0.005,
        "remove_borders": 4,
        "grid": False,
        "weights": "superpoint_v1.pth",
        "weights_dir": None,
    }

    def __init__(self, **conf):
        unknown = set(conf) - set(self.default_conf)
        if unknown:
            raise ValueError(f"superpoint: unknown options {sorted(unknown)}; options: {sorted(self.default_conf)}")
        self.conf = {**self.default_conf, **conf}
        self.weights_path = find_weights(self.conf["weights"], self.conf["weights_dir"], who="superpoint")
        self.net = load_into(SuperPoint(), load_state_dict(self.weights_path), self.weights_path)
        self.num_features = int(self.conf["num_features"])

    @torch.inference_mode()
    def detect_and_compute(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """image [1 x 1 x H x W] in [0, 1] -> keypoints [N x 2] pixels, descriptors [N x 256], scores [N]."""
        c = self.conf
        h0, w0 = image.shape[-2:]
        ph, pw = (-h0) % 8, (-w0) % 8
        x = F.pad(image, (0, pw, 0, ph)) if ph or pw else image  # zeros right and bottom
        prob, desc = self.net(x)
        scores = simple_nms(prob[:, :h0, :w0], c["nms_radius"])[0]
        b = c["remove_borders"]
        scores[:b] = 0
        scores[h0 - b:] = 0
        scores[:, :b] = 0
        scores[:, w0 - b:] = 0
        yx = (scores > c["keypoint_threshold"]).nonzero()
        s = scores[yx[:, 0], yx[:, 1]]
        xy = yx.flip(-1).to(torch.float32)
        if c["grid"]:
            keep = grid_cap(xy, s, (h0, w0), self.num_features)
        else:
            keep = torch.argsort(s, descending=True)[: self.num_features]
        xy, s = xy[keep], s[keep]
        return xy, sample_descriptors(xy, desc), s

    def extract(self, gray: np.ndarray) -> Features:
        """gray (H, W) uint8 -> Features: keypoints (N, 2) float64 px, descriptors (N, 256) float32 unit L2,
        scores (N,) float32, N <= num_features."""
        xy, desc, scores = self.detect_and_compute(gray_tensor(gray))
        return to_features(xy, desc, scores, gray.shape)
