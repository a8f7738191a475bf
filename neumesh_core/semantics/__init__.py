"""Semantic codes: distill 2D image features into per-vertex codes, and select parts from one click.

* :mod:`.extractors` - pluggable 2D feature extractors (weight-free "colour-texture"; DINO ViTs with
  local weights).
* :mod:`.distill` - :func:`distill_semantics` fits the field's semantic codes and decoder.
* :mod:`.select` - :func:`select_region`: click -> surface seeds -> DBSCAN -> region growing over the
  mesh (colour + shape, never across a concave crease) -> vertex indices.
* :mod:`.geometry` - :func:`geometric_features`: the scaffold's shape features for selection
  (crease-aware heat embedding, concave creases, optional shape diameter), cached per scaffold.
"""
from .distill import DistillConfig, DistillProgress, DistillResult, distill_semantics, semantics_record
from .geometry import (GeometricFeatures, GeometryConfig, GeometryUnavailable, compute_geometric_features,
                       geometric_features)
from .select import SelectConfig, Selection, SelectionContext, select_at_point, select_region
from .segment import FeatureSegmenter, SamSegmenter, make_segmenter
from .extractors import (EXTRACTORS, ColourTextureConfig, ColourTextureExtractor, DinoExtractor, FeatureExtractor,
                         find_dino_weights, make_extractor)

__all__ = ["EXTRACTORS", "ColourTextureConfig", "ColourTextureExtractor", "DinoExtractor", "DistillConfig",
           "DistillProgress", "DistillResult", "FeatureExtractor", "FeatureSegmenter", "GeometricFeatures",
           "GeometryConfig", "GeometryUnavailable", "SamSegmenter", "compute_geometric_features",
           "geometric_features",
           "SelectConfig", "Selection", "SelectionContext", "distill_semantics", "find_dino_weights",
           "make_extractor", "make_segmenter", "select_at_point", "select_region", "semantics_record"]
