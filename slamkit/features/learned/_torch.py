"""Small torch helpers shared by the learned models: loading state dicts, image tensors, Features."""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np
import torch
from torch import nn

from ...errors import ConfigError
from ..base import Features
from .weights import check_weight_file, load_error_reason


def load_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """``torch.load(path, weights_only=True)`` on the CPU; ConfigError naming the file if it is not a state dict."""
    check_weight_file(Path(path))  # a damaged file: one line naming it, not torch's advice
    try:
        sd = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as e:  # corrupt file, pickle with code, not a torch file
        raise ConfigError(f"{path}: not a loadable torch state dict ({load_error_reason(e)})") from e
    if not isinstance(sd, Mapping):
        raise ConfigError(f"{path}: expected a state dict (mapping of tensors), got {type(sd).__name__}")
    return dict(sd)


def load_into(module: nn.Module, state_dict: Mapping[str, torch.Tensor], source: str | Path) -> nn.Module:
    """``module.load_state_dict(state_dict, strict=True)`` with an error that names the file and the keys."""
    own = module.state_dict()
    missing = sorted(set(own) - set(state_dict))
    unexpected = sorted(set(state_dict) - set(own))
    wrong = sorted(k for k in set(own) & set(state_dict) if tuple(own[k].shape) != tuple(state_dict[k].shape))
    if missing or unexpected or wrong:
        parts = []
        if missing:
            parts.append(f"missing {missing[:5]}{' ...' if len(missing) > 5 else ''}")
        if unexpected:
            parts.append(f"unexpected {unexpected[:5]}{' ...' if len(unexpected) > 5 else ''}")
        if wrong:
            k = wrong[0]
            parts.append(f"shape of {k} is {tuple(state_dict[k].shape)}, expected {tuple(own[k].shape)}")
        raise ConfigError(f"{source}: not a {type(module).__name__} state dict ({'; '.join(parts)})")
    module.load_state_dict(state_dict, strict=True)
    return module.eval()


def gray_tensor(gray: np.ndarray) -> torch.Tensor:
    """(H, W) uint8 -> (1, 1, H, W) float32 in [0, 1]."""
    if gray.ndim != 2:
        raise ValueError(f"expected a (H, W) grey image, got shape {gray.shape}")
    return torch.from_numpy(np.ascontiguousarray(gray)).to(torch.float32).div_(255.0)[None, None]


def to_features(keypoints: torch.Tensor, descriptors: torch.Tensor, scores: torch.Tensor,
                shape: tuple[int, ...]) -> Features:
    """Tensors (N, 2) pixels, (N, D), (N,) -> Features (float64 keypoints, float32 L2-normalised descriptors)."""
    d = descriptors.shape[-1]
    kp = keypoints.detach().to(torch.float64).numpy().reshape(-1, 2)
    desc = np.ascontiguousarray(descriptors.detach().to(torch.float32).numpy().reshape(-1, d))
    sc = scores.detach().to(torch.float32).numpy().reshape(-1)
    return Features(np.ascontiguousarray(kp), desc, np.ascontiguousarray(sc), False, None,
                    (int(shape[1]), int(shape[0])))


def image_size(f: Features) -> tuple[int, int]:
    """(width, height) of the image of ``f``; from the keypoints' extent when the extractor did not say."""
    if f.image_size is not None:
        return int(f.image_size[0]), int(f.image_size[1])
    if len(f) == 0:
        return 1, 1
    mx = np.ceil(f.keypoints.max(axis=0)) + 1
    return int(mx[0]), int(mx[1])


def grid_cap(xy: torch.Tensor, scores: torch.Tensor, shape: tuple[int, int], total: int,
             cells: tuple[int, int] = (8, 6)) -> torch.Tensor:
    """Indices (sorted by descending score) of at most ``total`` keypoints spread over a grid of cells:
    the strongest ``total / cells`` of every cell first, then the strongest of the rest (as ORB's cap)."""
    n = len(scores)
    order = torch.argsort(scores, descending=True)
    if total <= 0 or n <= total:
        return order
    h, w = shape
    gx, gy = cells
    per_cell = int(np.ceil(total / (gx * gy)))
    cx = (xy[order, 0] * gx / w).long().clamp_(0, gx - 1)
    cy = (xy[order, 1] * gy / h).long().clamp_(0, gy - 1)
    cell = (cy * gx + cx).numpy()
    # rank of each keypoint within its cell (order is by descending score)
    o = np.argsort(cell, kind="stable")
    c = cell[o]
    rank = np.empty(n, np.int64)
    rank[o] = np.arange(n) - np.searchsorted(c, c, side="left")
    first = np.flatnonzero(rank < per_cell)[:total]
    if len(first) < total:
        rest = np.flatnonzero(rank >= per_cell)[: total - len(first)]
        first = np.sort(np.concatenate([first, rest]))
    return order[torch.from_numpy(first)]
