"""Foundation-model targets for the feature field: CLIP/DINO/text encoders, label targets, the feature cache.

Importing this package loads no model and does not import ``transformers``; encoders load it lazily.
"""

from fmgs.features.cache import FeatureCache, FeatureCacheWriter, FeatureMaps, TargetInfo
from fmgs.features.clip import ClipEncoders, ClipImageEncoder, ImageEncoder, load_clip
from fmgs.features.dino import DinoEncoder
from fmgs.features.extract import (
    ExtractConfig,
    extract_labels,
    extract_targets,
    feature_size,
    read_label_map,
    read_label_names,
)
from fmgs.features.labels import LabelTargets, label_embedding_map, label_map_targets
from fmgs.features.models import (
    DEFAULT_CLIP_ID,
    DEFAULT_DINO_ID,
    MINILM_ID,
    ModelNotFoundError,
    resolve_model_dir,
)
from fmgs.features.pyramid import CropGrid, PyramidConfig, crop_grid, hybrid_map
from fmgs.features.text import (
    ClipTextEncoder,
    MiniLMTextEncoder,
    TextEncoder,
    clip_tokenizer_from_bpe_files,
    load_text_encoder,
)

__all__ = [
    "DEFAULT_CLIP_ID",
    "DEFAULT_DINO_ID",
    "MINILM_ID",
    "ClipEncoders",
    "ClipImageEncoder",
    "ClipTextEncoder",
    "CropGrid",
    "DinoEncoder",
    "ExtractConfig",
    "FeatureCache",
    "FeatureCacheWriter",
    "FeatureMaps",
    "ImageEncoder",
    "LabelTargets",
    "MiniLMTextEncoder",
    "ModelNotFoundError",
    "PyramidConfig",
    "TargetInfo",
    "TextEncoder",
    "clip_tokenizer_from_bpe_files",
    "crop_grid",
    "extract_labels",
    "extract_targets",
    "feature_size",
    "hybrid_map",
    "label_embedding_map",
    "label_map_targets",
    "load_clip",
    "load_text_encoder",
    "read_label_map",
    "read_label_names",
    "resolve_model_dir",
]
