"""Foundation-model targets for the feature field: CLIP/DINO/text encoders, label targets, the feature cache.

Importing this package loads no model and imports neither torch nor ``transformers``: exports resolve
on first use, and encoders load their models lazily.
"""

from fmgs.lazy import lazy_exports

_EXPORTS = {
    "ClipEncoders": "fmgs.features.clip",
    "ClipImageEncoder": "fmgs.features.clip",
    "ClipTextEncoder": "fmgs.features.text",
    "CropGrid": "fmgs.features.pyramid",
    "DEFAULT_CLIP_ID": "fmgs.features.models",
    "DEFAULT_DINO_ID": "fmgs.features.models",
    "DinoEncoder": "fmgs.features.dino",
    "ExtractConfig": "fmgs.features.extract",
    "FeatureCache": "fmgs.features.cache",
    "FeatureCacheWriter": "fmgs.features.cache",
    "FeatureMaps": "fmgs.features.cache",
    "ImageEncoder": "fmgs.features.clip",
    "LabelTargets": "fmgs.features.labels",
    "MINILM_ID": "fmgs.features.models",
    "MiniLMTextEncoder": "fmgs.features.text",
    "ModelNotFoundError": "fmgs.features.models",
    "PyramidConfig": "fmgs.features.pyramid",
    "TargetInfo": "fmgs.features.cache",
    "TextEncoder": "fmgs.features.text",
    "clip_tokenizer_from_bpe_files": "fmgs.features.clip_tokenizer",
    "crop_grid": "fmgs.features.pyramid",
    "extract_labels": "fmgs.features.extract",
    "extract_targets": "fmgs.features.extract",
    "feature_size": "fmgs.features.extract",
    "hybrid_map": "fmgs.features.pyramid",
    "label_embedding_map": "fmgs.features.labels",
    "label_map_targets": "fmgs.features.labels",
    "load_clip": "fmgs.features.clip",
    "load_text_encoder": "fmgs.features.text",
    "read_label_map": "fmgs.features.extract",
    "read_label_names": "fmgs.features.extract",
    "resolve_model_dir": "fmgs.features.models",
}
__all__ = sorted(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
