"""Local features: a registry of extractors (ORB default, SIFT; learned ones plug in) and matching."""

from . import opencv as _opencv  # noqa: F401  (registers orb and sift)
from .base import (Extractor, Features, FrameFeatures, NearestNeighborMatcher, PairMatcher, available_matchers,
                   create_matcher, register_matcher, MatchingConfig, available_extractors, create_extractor,
                   descriptor_distance, guided_match, image_signature, match_descriptors, register_extractor)
from .learned import register as _register_learned

_register_learned()  # xfeat, aliked, superpoint; lighterglue, lightglue, superglue (torch imported on creation)

__all__ = ["Extractor", "Features", "FrameFeatures", "NearestNeighborMatcher", "PairMatcher",
           "available_matchers", "create_matcher", "register_matcher", "MatchingConfig", "available_extractors", "create_extractor",
           "descriptor_distance", "guided_match", "image_signature", "match_descriptors", "register_extractor"]
