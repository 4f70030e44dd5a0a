"""open_clip checkpoint files on the transformers CLIP architecture (``openclip-file:PATH`` ids).

Many users hold LAION's models as open_clip checkpoints (``open_clip_model.safetensors``; the
``open_clip_pytorch_model.bin`` beside it is pickled data, which this project never loads). open_clip's
ViT CLIP and transformers' ``CLIPModel`` compute the same
function, so the weights map one to one (the attention's packed q/k/v split in three, the projections
transposed) and the sizes follow from the tensors' shapes: widths, layers, patch, image size, context,
vocabulary, embedding size; heads are width / 64 (open_clip's head width). The blocks' activation is not
in the weights: GELU for LAION-trained checkpoints, QuickGELU for OpenAI-trained ones
(``openclip-file+quickgelu:``). Checkpoints with parts this mapping does not know (layer scale,
attentional pooling, a text tower other than CLIP's) are refused by name.

CLIP's tokenizer files (``tokenizer.json``, or ``vocab.json`` and ``merges.txt``) must lie beside the
checkpoint, as they do in the hub repositories that ship it.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import torch

from fmgs.errors import ValidationError
from fmgs.features.clip_tokenizer import load_clip_tokenizer
from fmgs.features.models import ModelFiles, ModelNotFoundError, require_transformers, sha256_file
from fmgs.features.registry import EncoderRef

HEAD_WIDTH = 64
"""open_clip's attention head width: heads = width / 64 in both towers."""
_BLOCK = re.compile(r"(visual\.)?transformer\.resblocks\.(\d+)\.(.+)")
_BLOCK_PARTS = {
    "ln_1.weight": "layer_norm1.weight",
    "ln_1.bias": "layer_norm1.bias",
    "ln_2.weight": "layer_norm2.weight",
    "ln_2.bias": "layer_norm2.bias",
    "attn.out_proj.weight": "self_attn.out_proj.weight",
    "attn.out_proj.bias": "self_attn.out_proj.bias",
    "mlp.c_fc.weight": "mlp.fc1.weight",
    "mlp.c_fc.bias": "mlp.fc1.bias",
    "mlp.c_proj.weight": "mlp.fc2.weight",
    "mlp.c_proj.bias": "mlp.fc2.bias",
}
_DIRECT = {
    "visual.class_embedding": "vision_model.embeddings.class_embedding",
    "visual.conv1.weight": "vision_model.embeddings.patch_embedding.weight",
    "visual.positional_embedding": "vision_model.embeddings.position_embedding.weight",
    "visual.ln_pre.weight": "vision_model.pre_layrnorm.weight",
    "visual.ln_pre.bias": "vision_model.pre_layrnorm.bias",
    "visual.ln_post.weight": "vision_model.post_layernorm.weight",
    "visual.ln_post.bias": "vision_model.post_layernorm.bias",
    "token_embedding.weight": "text_model.embeddings.token_embedding.weight",
    "positional_embedding": "text_model.embeddings.position_embedding.weight",
    "ln_final.weight": "text_model.final_layer_norm.weight",
    "ln_final.bias": "text_model.final_layer_norm.bias",
    "logit_scale": "logit_scale",
}
_TRANSPOSED = {"visual.proj": "visual_projection.weight", "text_projection": "text_projection.weight"}
_IGNORED = {"attn_mask", "visual.attn_mask"}
"""Buffers older open_clip versions saved (the causal mask): rebuilt by the model."""


def read_checkpoint(path: Path) -> dict[str, torch.Tensor]:
    """The state dict of an open_clip checkpoint in safetensors form (``open_clip_model.safetensors``).

    The ``.bin`` form is pickled data, and nothing in this project unpickles: such a file is refused with how
    to get or make the safetensors form. ``module.`` prefixes are removed."""
    if path.suffix != ".safetensors":
        raise ValidationError(
            str(path),
            "open_clip .bin/.pt checkpoints are pickles, which FMGS never loads; use the safetensors "
            "file the model's repository ships beside it (open_clip_model.safetensors), or convert the .bin "
            "once, on a machine where you trust it, with safetensors.torch.save_file",
        )
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    try:
        sd = load_file(str(path))
    except (SafetensorError, OSError) as e:
        raise ValidationError(str(path), f"not a readable safetensors checkpoint ({e})") from e
    return {k.removeprefix("module."): v for k, v in sd.items()}


def _layers(sd: dict[str, torch.Tensor], prefix: str) -> int:
    ids = {int(m.group(2)) for k in sd if (m := _BLOCK.fullmatch(k)) and (m.group(1) or "") == prefix}
    if not ids or ids != set(range(len(ids))):
        raise ValidationError("open_clip checkpoint", f"no contiguous {prefix or 'text '}transformer blocks")
    return len(ids)


def clip_config(sd: dict[str, torch.Tensor], quick_gelu: bool) -> Any:
    """The ``transformers.CLIPConfig`` an open_clip ViT CLIP state dict describes."""
    need = ["visual.conv1.weight", "visual.positional_embedding", "visual.proj", "token_embedding.weight",
            "positional_embedding", "text_projection", "visual.transformer.resblocks.0.mlp.c_fc.weight",
            "transformer.resblocks.0.mlp.c_fc.weight"]  # fmt: skip
    missing = [k for k in need if k not in sd]
    if missing:
        raise ValidationError("open_clip checkpoint", f"not an open_clip ViT CLIP: missing {missing}")
    width, _, patch, _ = sd["visual.conv1.weight"].shape
    tokens = sd["visual.positional_embedding"].shape[0]
    grid = math.isqrt(tokens - 1)
    if grid * grid != tokens - 1:
        raise ValidationError("open_clip checkpoint", f"{tokens - 1} patch positions are not a square grid")
    vocab, t_width = sd["token_embedding.weight"].shape
    act = "quick_gelu" if quick_gelu else "gelu"
    mlp_v = int(sd["visual.transformer.resblocks.0.mlp.c_fc.weight"].shape[0])
    mlp_t = int(sd["transformer.resblocks.0.mlp.c_fc.weight"].shape[0])
    vision = dict(
        hidden_size=int(width), intermediate_size=mlp_v,
        num_hidden_layers=_layers(sd, "visual."), num_attention_heads=int(width) // HEAD_WIDTH,
        patch_size=int(patch), image_size=int(grid * patch), hidden_act=act, layer_norm_eps=1e-5,
    )  # fmt: skip
    text = dict(
        hidden_size=int(t_width), intermediate_size=mlp_t,
        num_hidden_layers=_layers(sd, ""), num_attention_heads=int(t_width) // HEAD_WIDTH,
        max_position_embeddings=int(sd["positional_embedding"].shape[0]), vocab_size=int(vocab),
        hidden_act=act, layer_norm_eps=1e-5,
        # open_clip pools the text at the end-of-text token, the largest id: the same position.
        eos_token_id=int(vocab) - 1, bos_token_id=int(vocab) - 2, pad_token_id=int(vocab) - 1,
    )  # fmt: skip
    transformers = require_transformers()
    return transformers.CLIPConfig(
        vision_config=vision, text_config=text, projection_dim=int(sd["text_projection"].shape[1])
    )


def to_transformers(sd: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """open_clip parameter names and layouts -> ``CLIPModel``'s; unknown parameters are refused by name."""
    out: dict[str, torch.Tensor] = {}
    unknown = []
    for k, v in sd.items():
        if k in _IGNORED:
            continue
        if k in _DIRECT:
            out[_DIRECT[k]] = v
        elif k in _TRANSPOSED:
            out[_TRANSPOSED[k]] = v.t().contiguous()
        elif m := _BLOCK.fullmatch(k):
            tower = "vision_model" if m.group(1) else "text_model"
            base = f"{tower}.encoder.layers.{m.group(2)}."
            part = m.group(3)
            if part in ("attn.in_proj_weight", "attn.in_proj_bias"):
                kind = part.rsplit("_", 1)[1]  # weight or bias
                for name, chunk in zip(("q", "k", "v"), v.chunk(3, dim=0), strict=True):
                    out[f"{base}self_attn.{name}_proj.{kind}"] = chunk.contiguous()
            elif part in _BLOCK_PARTS:
                out[base + _BLOCK_PARTS[part]] = v
            else:
                unknown.append(k)
        else:
            unknown.append(k)
    if unknown:
        raise ValidationError(
            "open_clip checkpoint", f"parameters this mapping does not know: {sorted(unknown)[:8]}"
        )
    return out


def load_openclip_file(ref: EncoderRef) -> tuple[Any, Any, ModelFiles]:
    """(``CLIPModel`` in eval mode, its tokenizer, the files) of an ``openclip-file:`` id."""
    path = Path(ref.ref).expanduser()
    if not path.is_file():
        raise ModelNotFoundError(ref.ref, [f"open_clip checkpoint {path} (absent)"])
    sd = read_checkpoint(path)
    cfg = clip_config(sd, ref.quick_gelu)
    weights = to_transformers(sd)
    model = require_transformers().CLIPModel(cfg)
    missing, unexpected = model.load_state_dict(weights, strict=False)
    missing = [k for k in missing if not k.endswith("position_ids")]
    if missing or unexpected:
        raise ValidationError(
            str(path), f"weights do not fit CLIP: missing {missing[:5]}, extra {unexpected[:5]}"
        )
    tokenizer = load_clip_tokenizer(path.parent)
    prefix = "openclip-file+quickgelu:" if ref.quick_gelu else "openclip-file:"
    files = ModelFiles(prefix + ref.ref, path.parent, "local", files={path.name: sha256_file(path)})
    return model.eval(), tokenizer, files
