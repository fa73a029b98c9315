"""Place recognition for loop closure: a bag of visual words trained by slamkit and a keyframe database.

:class:`Vocabulary` (hierarchical k-majority / k-means tree with TF-IDF), :class:`PlaceDatabase` (inverted
file, L1 scores, add/remove/query, arrays for saving) and :func:`default_vocabulary` (trained on the
embedded synthetic room on first use and cached on disk; nothing is downloaded).
"""

from .database import PlaceDatabase
from .training import default_vocabulary, train_vocabulary, vocabulary_path
from .vocabulary import DESCRIPTOR_KINDS, Vocabulary, VocabularyConfig, descriptor_kind

__all__ = ["DESCRIPTOR_KINDS", "PlaceDatabase", "Vocabulary", "VocabularyConfig", "default_vocabulary",
           "descriptor_kind", "train_vocabulary", "vocabulary_path"]
