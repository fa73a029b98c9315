"""Where the vocabulary comes from at run time: trained by slamkit on its own synthetic room, cached on disk.

Nothing is downloaded. :func:`default_vocabulary` extracts features (with the named slamkit extractor) from
every ``stride``-th frame of the embedded default sequence (:func:`slamkit.open_source` ``"default"``),
trains a :class:`Vocabulary` with a fixed seed, and caches it as ``.npz`` (no pickle) next to the default
sequence under :func:`slamkit.sources.synthetic.cache_root` (``$SLAMKIT_CACHE``, else
``$XDG_CACHE_HOME/slamkit``, else ``~/.cache/slamkit``). The file name carries the extractor, the tree shape,
the seed and a version, so a change of any of them trains a new vocabulary; the same inputs always give the
same vocabulary. :func:`train_vocabulary` trains one from any frames (e.g. the first frames of a sequence).
"""

from __future__ import annotations

import io
import logging
import zipfile
from pathlib import Path
from typing import Iterable

import numpy as np

from ..errors import ConfigError
from ..features import create_extractor
from ..io.atomic import atomic_write_bytes
from ..sources import open_source
from ..sources.synthetic import DEFAULT_VERSION, cache_root
from .vocabulary import Vocabulary, VocabularyConfig

log = logging.getLogger(__name__)

VOCABULARY_VERSION = 1
"""Part of the cache file name; change it whenever training changes."""


def train_vocabulary(grays: Iterable[np.ndarray], extractor: str = "orb",
                     config: VocabularyConfig | None = None, **extractor_options) -> Vocabulary:
    """A vocabulary trained on the descriptors the named extractor finds in ``grays`` ((H, W) uint8 images)."""
    ext = create_extractor(extractor, **extractor_options)
    return Vocabulary.train([ext.extract(g).descriptors for g in grays], config)


def vocabulary_path(extractor: str = "orb", config: VocabularyConfig | None = None, stride: int = 4) -> Path:
    """Cache file of :func:`default_vocabulary` for these arguments."""
    cfg = config or VocabularyConfig()
    name = (f"vocabulary-v{VOCABULARY_VERSION}-{extractor}-{DEFAULT_VERSION}-b{cfg.branching}d{cfg.depth}"
            f"i{cfg.iterations}-seed{cfg.seed}-stride{stride}.npz")
    return cache_root() / name


def default_vocabulary(extractor: str = "orb", config: VocabularyConfig | None = None,
                       stride: int = 4) -> Vocabulary:
    """The vocabulary of ``extractor`` trained on every ``stride``-th frame of the default sequence.

    Loaded from :func:`vocabulary_path` when cached there; else trained (tens of seconds for ORB) and
    written atomically, so concurrent first uses are safe. ConfigError for an unknown extractor or stride.
    """
    if int(stride) != stride or stride < 1:
        raise ConfigError(f"stride must be a positive integer (got {stride!r})")
    path = vocabulary_path(extractor, config, stride)
    if path.is_file():
        try:
            with np.load(path, allow_pickle=False) as arrays:
                return Vocabulary.from_arrays(arrays)
        except (OSError, ValueError, zipfile.BadZipFile, ConfigError) as e:
            log.warning("%s: unreadable cached vocabulary (%s); training it again", path, e)
    source = open_source("default", frame_skip=int(stride))
    log.info("training the %s vocabulary on %d frames of the default sequence", extractor, len(source))
    vocabulary = train_vocabulary((frame.gray for frame in source), extractor, config)
    buffer = io.BytesIO()
    np.savez(buffer, **vocabulary.to_arrays())
    atomic_write_bytes(path, buffer.getvalue())
    return vocabulary
