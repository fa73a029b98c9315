"""SuperGlue (Sarlin, DeTone, Malisiewicz, Rabinovich, "SuperGlue: Learning Feature Matching with Graph
Neural Networks", CVPR 2020).

slamkit's implementation of the architecture; it loads Magic Leap's official ``superglue_indoor.pth``
(ScanNet) or ``superglue_outdoor.pth`` (MegaDepth) from ``weights_dir`` or ``$SLAMKIT_WEIGHTS``. Those
weights are licensed for non-commercial research only and may not be redistributed: slamkit neither ships nor
downloads them (github.com/magicleap/SuperGluePretrainedNetwork, ``models/weights/``).

The network: keypoint positions and scores encoded by an MLP and added to the SuperPoint descriptors; 18
alternating self/cross attention layers (4 heads); a final projection; similarity scores with a learned
"dustbin" score, normalised by 100 Sinkhorn iterations (optimal transport) in log space; mutual best matches
above ``match_threshold``.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from ...errors import ConfigError
from ..base import Features
from ._torch import image_size, load_into, load_state_dict
from .weights import find_weights


def mlp(channels: list[int]) -> nn.Sequential:
    """1x1 Conv1d layers, BatchNorm1d + ReLU between them (not after the last)."""
    layers: list[nn.Module] = []
    for i in range(1, len(channels)):
        layers.append(nn.Conv1d(channels[i - 1], channels[i], 1, bias=True))
        if i < len(channels) - 1:
            layers += [nn.BatchNorm1d(channels[i]), nn.ReLU()]
    return nn.Sequential(*layers)


class KeypointEncoder(nn.Module):
    """(x, y, score) [B x 3 x N] -> [B x D x N]."""

    def __init__(self, dim: int, layers: list[int]):
        super().__init__()
        self.encoder = mlp([3] + layers + [dim])

    def forward(self, kpts: torch.Tensor, scores: torch.Tensor) -> torch.Tensor:
        return self.encoder(torch.cat([kpts.transpose(1, 2), scores[:, None]], 1))


class MultiHeadedAttention(nn.Module):
    """Multi-head attention on [B x D x N] tensors; channel c belongs to head c % heads (Magic Leap's layout)."""

    def __init__(self, heads: int, dim: int):
        super().__init__()
        self.heads, self.head_dim = heads, dim // heads
        self.merge = nn.Conv1d(dim, dim, 1)
        self.proj = nn.ModuleList([nn.Conv1d(dim, dim, 1) for _ in range(3)])

    def forward(self, query, key, value):
        b = query.shape[0]
        q, k, v = (p(x).view(b, self.head_dim, self.heads, -1) for p, x in zip(self.proj, (query, key, value)))
        prob = torch.einsum("bdhn,bdhm->bhnm", q, k).div_(self.head_dim ** 0.5).softmax(-1)
        x = torch.einsum("bhnm,bdhm->bdhn", prob, v)
        return self.merge(x.reshape(b, self.head_dim * self.heads, -1))


class AttentionalPropagation(nn.Module):
    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.attn = MultiHeadedAttention(heads, dim)
        self.mlp = mlp([2 * dim, 2 * dim, dim])

    def forward(self, x, source):
        return self.mlp(torch.cat([x, self.attn(x, source, source)], 1))


class AttentionalGNN(nn.Module):
    def __init__(self, dim: int, layer_names: list[str]):
        super().__init__()
        self.layers = nn.ModuleList([AttentionalPropagation(dim, 4) for _ in layer_names])
        self.names = list(layer_names)

    def forward(self, d0, d1):
        for layer, name in zip(self.layers, self.names):
            s0, s1 = (d1, d0) if name == "cross" else (d0, d1)
            d0, d1 = d0 + layer(d0, s0), d1 + layer(d1, s1)
        return d0, d1


def log_optimal_transport(scores: torch.Tensor, alpha: torch.Tensor, iters: int) -> torch.Tensor:
    """Sinkhorn in log space on scores [B x M x N] augmented with a dustbin row and column of score ``alpha``;
    returns the log assignment [B x M+1 x N+1] (scaled so that a row's probabilities sum to about 1)."""
    b, m, n = scores.shape
    one = scores.new_tensor(1.0)
    ms, ns = m * one, n * one
    couplings = torch.cat([torch.cat([scores, alpha.expand(b, m, 1)], -1),
                           torch.cat([alpha.expand(b, 1, n), alpha.expand(b, 1, 1)], -1)], 1)
    norm = -(ms + ns).log()
    log_mu = torch.cat([norm.expand(m), ns.log()[None] + norm])[None].expand(b, -1)
    log_nu = torch.cat([norm.expand(n), ms.log()[None] + norm])[None].expand(b, -1)
    u, v = torch.zeros_like(log_mu), torch.zeros_like(log_nu)
    for _ in range(iters):
        u = log_mu - torch.logsumexp(couplings + v[:, None, :], dim=2)
        v = log_nu - torch.logsumexp(couplings + u[:, :, None], dim=1)
    return couplings + u[:, :, None] + v[:, None, :] - norm


class SuperGlue(nn.Module):
    """The SuperGlue network (state-dict keys ``kenc.encoder.*``, ``gnn.layers.{i}.attn.{proj,merge}``,
    ``gnn.layers.{i}.mlp.*``, ``final_proj``, ``bin_score``).

    forward(kpts0 [B x M x 2] px, scores0 [B x M], desc0 [B x D x M], size0 (w, h), and the same for image 1)
        -> matches0 [B x M] (index in image 1 or -1), matching_scores0 [B x M].
    """

    default_conf = {
        "descriptor_dim": 256,
        "keypoint_encoder": [32, 64, 128, 256],
        "GNN_layers": ["self", "cross"] * 9,
        "sinkhorn_iterations": 100,
        "match_threshold": 0.2,
    }

    def __init__(self, **conf):
        super().__init__()
        self.conf = c = {**self.default_conf, **conf}
        self.kenc = KeypointEncoder(c["descriptor_dim"], c["keypoint_encoder"])
        self.gnn = AttentionalGNN(c["descriptor_dim"], c["GNN_layers"])
        self.final_proj = nn.Conv1d(c["descriptor_dim"], c["descriptor_dim"], 1, bias=True)
        self.bin_score = nn.Parameter(torch.tensor(1.0))

    @staticmethod
    def normalize_keypoints(kpts: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        """Pixels -> centred, divided by 0.7 x the longer side (SuperGlue's normalisation)."""
        wh = kpts.new_tensor(size)
        return (kpts - wh / 2) / (wh.max() * 0.7)

    @torch.inference_mode()
    def forward(self, kpts0, scores0, desc0, size0, kpts1, scores1, desc1, size1):
        c = self.conf
        d0 = desc0 + self.kenc(self.normalize_keypoints(kpts0, size0), scores0)
        d1 = desc1 + self.kenc(self.normalize_keypoints(kpts1, size1), scores1)
        d0, d1 = self.gnn(d0, d1)
        m0, m1 = self.final_proj(d0), self.final_proj(d1)
        s = torch.einsum("bdn,bdm->bnm", m0, m1) / c["descriptor_dim"] ** 0.5
        s = log_optimal_transport(s, self.bin_score, c["sinkhorn_iterations"])[:, :-1, :-1]
        best0, best1 = s.max(2), s.max(1)
        mutual0 = torch.arange(s.shape[1])[None] == best1.indices.gather(1, best0.indices)
        p0 = torch.where(mutual0, best0.values.exp(), s.new_tensor(0.0))
        valid0 = mutual0 & (p0 > c["match_threshold"])
        return torch.where(valid0, best0.indices, -1), p0


class SuperGlueMatcher:
    """SuperGlue for SuperPoint features: ``match(a, b) -> (M, 2) int64``. ``weights``: "indoor" (default,
    superglue_indoor.pth) or "outdoor" (superglue_outdoor.pth)."""

    name = "superglue"
    default_conf = {
        "weights": "indoor",
        "weights_dir": None,
        "sinkhorn_iterations": 100,
        "match_threshold": 0.2,
    }

    def __init__(self, **conf):
        unknown = set(conf) - set(self.default_conf)
        if unknown:
            raise ValueError(f"superglue: unknown options {sorted(unknown)}; options: {sorted(self.default_conf)}")
        self.conf = c = {**self.default_conf, **conf}
        if c["weights"] not in ("indoor", "outdoor"):
            raise ConfigError(f"superglue: weights must be 'indoor' or 'outdoor' (got {c['weights']!r})")
        self.weights_path = find_weights(f"superglue_{c['weights']}.pth", c["weights_dir"], who="superglue")
        net = SuperGlue(sinkhorn_iterations=c["sinkhorn_iterations"], match_threshold=c["match_threshold"])
        self.net = load_into(net, load_state_dict(self.weights_path), self.weights_path)

    def match(self, a: Features, b: Features) -> np.ndarray:
        """(M, 2) int64 index pairs (i in a, j in b), mutual, assignment probability > match_threshold."""
        if len(a) == 0 or len(b) == 0:
            return np.empty((0, 2), np.int64)
        dim = self.net.conf["descriptor_dim"]
        for f in (a, b):
            if f.binary or f.descriptors.shape[1] != dim:
                raise ConfigError(f"matcher 'superglue' matches {dim}-d float descriptors of 'superpoint'; got "
                                  f"{f.descriptors.shape[1]}-d: use features='superpoint'")
        t = torch.from_numpy
        m0, _ = self.net(t(a.keypoints).float()[None], t(a.scores).float()[None], t(a.descriptors).float().t()[None],
                         image_size(a),
                         t(b.keypoints).float()[None], t(b.scores).float()[None], t(b.descriptors).float().t()[None],
                         image_size(b))
        m0 = m0[0].numpy()
        i = np.flatnonzero(m0 >= 0)
        return np.stack([i, m0[i]], 1).astype(np.int64)
