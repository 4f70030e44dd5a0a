"""Every encoder family of the registry (fmgs.features.registry) with random weights built from its own
config: our wrapper gives the embeddings the model gives when called directly. The open_clip file is
checked against an independent forward pass of open_clip's architecture written here from its state dict
(not against our own mapping run backwards)."""

from __future__ import annotations

import json

import pytest
import torch
import torch.nn.functional as F

from fmgs.errors import ValidationError
from fmgs.features.clip import CLIP_MEAN, CLIP_STD, ClipImageEncoder
from fmgs.features.clip_tokenizer import clip_tokenizer_from_bpe_files
from fmgs.features.dino import IMAGENET_MEAN, IMAGENET_STD, DinoEncoder
from fmgs.features.registry import EncoderRef, parse_encoder_id
from fmgs.features.text import ClipTextEncoder, load_text_encoder

transformers = pytest.importorskip("transformers")
TEXTS = ["a red cube", "something to sit on", "the floor"]


def test_ids_name_their_family():
    assert parse_encoder_id("sentence-transformers/all-MiniLM-L6-v2").family == "minilm"
    assert parse_encoder_id("hf:google/siglip-base-patch16-224") == EncoderRef(
        "hf", "google/siglip-base-patch16-224"
    )
    assert parse_encoder_id("laion/CLIP-ViT-B-16-laion2B-s34B-b88K").family == "hf"
    assert parse_encoder_id("openclip-file:/m/open_clip_pytorch_model.bin") == EncoderRef(
        "openclip-file", "/m/open_clip_pytorch_model.bin"
    )
    assert parse_encoder_id("openclip-file+quickgelu:/m/x.bin").quick_gelu
    for bad in ("", "hf:", "openclip-file:", None):
        with pytest.raises(ValidationError):
            parse_encoder_id(bad)


# ---- open_clip checkpoint file -------------------------------------------------------------------------

W, LAYERS, PATCH, GRID, EMBED, CTX = 64, 2, 8, 4, 16, 77


def _openclip_state_dict(vocab: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """A random open_clip ViT CLIP state dict (open_clip's names and layouts)."""
    g = torch.Generator().manual_seed(seed)

    def r(*shape, scale=0.05):
        return torch.randn(*shape, generator=g) * scale

    def ln(prefix):
        return {f"{prefix}.weight": 1 + r(W, scale=0.1), f"{prefix}.bias": r(W)}

    def blocks(prefix):
        out = {}
        for i in range(LAYERS):
            b = f"{prefix}transformer.resblocks.{i}."
            out |= ln(b + "ln_1") | ln(b + "ln_2")
            out |= {b + "attn.in_proj_weight": r(3 * W, W), b + "attn.in_proj_bias": r(3 * W)}
            out |= {b + "attn.out_proj.weight": r(W, W), b + "attn.out_proj.bias": r(W)}
            out |= {b + "mlp.c_fc.weight": r(4 * W, W), b + "mlp.c_fc.bias": r(4 * W)}
            out |= {b + "mlp.c_proj.weight": r(W, 4 * W), b + "mlp.c_proj.bias": r(W)}
        return out

    sd = {
        "visual.class_embedding": r(W, scale=0.5),
        "visual.positional_embedding": r(GRID * GRID + 1, W, scale=0.5),
        "visual.conv1.weight": r(W, 3, PATCH, PATCH),
        "visual.proj": r(W, EMBED, scale=0.2),
        "token_embedding.weight": r(vocab, W, scale=0.5),
        "positional_embedding": r(CTX, W, scale=0.5),
        "text_projection": r(W, EMBED, scale=0.2),
        "logit_scale": torch.tensor(4.6052),
        "attn_mask": torch.full((CTX, CTX), float("-inf")).triu(1),
    }
    sd |= ln("visual.ln_pre") | ln("visual.ln_post") | ln("ln_final") | blocks("visual.") | blocks("")
    return sd


def _reference_tower(sd, prefix, x, causal, quick_gelu):
    """open_clip's residual attention blocks, from the state dict with plain torch ops. x [B,T,W]."""
    heads = W // 64 or 1
    T = x.shape[1]
    mask = torch.full((T, T), float("-inf")).triu(1) if causal else None
    for i in range(LAYERS):
        b = f"{prefix}transformer.resblocks.{i}."
        h = F.layer_norm(x, (W,), sd[b + "ln_1.weight"], sd[b + "ln_1.bias"], 1e-5)
        q, k, v = (h @ sd[b + "attn.in_proj_weight"].t() + sd[b + "attn.in_proj_bias"]).chunk(3, dim=-1)
        q, k, v = (t.reshape(x.shape[0], T, heads, -1).transpose(1, 2) for t in (q, k, v))
        att = q @ k.transpose(-1, -2) / (q.shape[-1] ** 0.5)
        if mask is not None:
            att = att + mask
        o = (att.softmax(-1) @ v).transpose(1, 2).reshape(x.shape[0], T, W)
        x = x + o @ sd[b + "attn.out_proj.weight"].t() + sd[b + "attn.out_proj.bias"]
        h = F.layer_norm(x, (W,), sd[b + "ln_2.weight"], sd[b + "ln_2.bias"], 1e-5)
        h = h @ sd[b + "mlp.c_fc.weight"].t() + sd[b + "mlp.c_fc.bias"]
        h = h * torch.sigmoid(1.702 * h) if quick_gelu else F.gelu(h)
        x = x + h @ sd[b + "mlp.c_proj.weight"].t() + sd[b + "mlp.c_proj.bias"]
    return x


def _reference_text(sd, ids, quick_gelu):
    """open_clip encode_text: ids [B,77] padded with 0, pooled at the end-of-text token (the largest id)."""
    x = sd["token_embedding.weight"][ids] + sd["positional_embedding"]
    x = _reference_tower(sd, "", x, True, quick_gelu)
    x = F.layer_norm(x, (W,), sd["ln_final.weight"], sd["ln_final.bias"], 1e-5)
    pooled = x[torch.arange(len(ids)), ids.argmax(dim=-1)] @ sd["text_projection"]
    return F.normalize(pooled, dim=-1)


def _reference_image(sd, pixels, quick_gelu):
    """open_clip encode_image of normalised pixels [B,3,32,32]."""
    x = F.conv2d(pixels, sd["visual.conv1.weight"], stride=PATCH).flatten(2).transpose(1, 2)
    cls = sd["visual.class_embedding"].expand(len(x), 1, W)
    x = torch.cat([cls, x], dim=1) + sd["visual.positional_embedding"]
    x = F.layer_norm(x, (W,), sd["visual.ln_pre.weight"], sd["visual.ln_pre.bias"], 1e-5)
    x = _reference_tower(sd, "visual.", x, False, quick_gelu)
    x = F.layer_norm(x[:, 0], (W,), sd["visual.ln_post.weight"], sd["visual.ln_post.bias"], 1e-5)
    return F.normalize(x @ sd["visual.proj"], dim=-1)


@pytest.fixture(scope="module")
def bpe(bpe_dir):
    return bpe_dir


@pytest.mark.parametrize("quick_gelu", [False, True])
def test_an_openclip_file_gives_open_clips_embeddings(bpe, tmp_path, quick_gelu):
    import shutil

    tok = clip_tokenizer_from_bpe_files(bpe / "vocab.json", bpe / "merges.txt")
    sd = _openclip_state_dict(len(tok))
    from safetensors.torch import save_file

    path = tmp_path / "open_clip_model.safetensors"
    save_file({f"module.{k}": v.contiguous() for k, v in sd.items()}, str(path))  # as saved from DDP
    for f in ("vocab.json", "merges.txt"):
        shutil.copy(bpe / f, tmp_path / f)
    eid = ("openclip-file+quickgelu:" if quick_gelu else "openclip-file:") + str(path)

    text = load_text_encoder(eid)
    assert text.id == eid and text.dim == EMBED and text.files.files[path.name]
    ids = torch.zeros(len(TEXTS), CTX, dtype=torch.long)  # open_clip pads with 0 to 77
    for i, row in enumerate(tok(TEXTS)["input_ids"]):
        ids[i, : len(row)] = torch.tensor(row)
    with torch.inference_mode():
        assert torch.allclose(text.encode_text(TEXTS), _reference_text(sd, ids, quick_gelu), atol=2e-5)
        image = ClipImageEncoder.load(eid)
        pixels = torch.rand(3, 3, GRID * PATCH, GRID * PATCH, generator=torch.Generator().manual_seed(3))
        mean, std = torch.tensor(CLIP_MEAN).view(1, 3, 1, 1), torch.tensor(CLIP_STD).view(1, 3, 1, 1)
        ref = _reference_image(sd, (pixels - mean) / std, quick_gelu)
        assert torch.allclose(image(pixels), ref, atol=2e-5)
    # The other activation gives other embeddings: the id's choice matters and is honoured.
    other = ("openclip-file:" if quick_gelu else "openclip-file+quickgelu:") + str(path)
    assert not torch.allclose(load_text_encoder(other).encode_text(TEXTS), text.encode_text(TEXTS), atol=1e-3)


def test_openclip_files_this_mapping_does_not_know_are_refused(bpe, tmp_path):
    import shutil

    from safetensors.torch import save_file

    from fmgs.features.models import ModelNotFoundError

    tok = clip_tokenizer_from_bpe_files(bpe / "vocab.json", bpe / "merges.txt")
    for f in ("vocab.json", "merges.txt"):
        shutil.copy(bpe / f, tmp_path / f)
    sd = _openclip_state_dict(len(tok))
    sd["visual.transformer.resblocks.0.ls_1.gamma"] = torch.ones(W)  # layer scale: not CLIP's ViT
    save_file(sd, str(tmp_path / "ls.safetensors"))
    with pytest.raises(ValidationError, match="ls_1"):
        load_text_encoder(f"openclip-file:{tmp_path / 'ls.safetensors'}")
    sd = _openclip_state_dict(len(tok))
    del sd["visual.proj"]
    save_file(sd, str(tmp_path / "noproj.safetensors"))
    with pytest.raises(ValidationError, match=r"visual\.proj"):
        load_text_encoder(f"openclip-file:{tmp_path / 'noproj.safetensors'}")
    with pytest.raises(ModelNotFoundError):
        load_text_encoder(f"openclip-file:{tmp_path / 'absent.safetensors'}")
    # The pickled form is never loaded: the error says how to get the safetensors form.
    (tmp_path / "open_clip_pytorch_model.bin").write_bytes(b"\x80\x04not read")
    with pytest.raises(ValidationError, match=r"never loads.*open_clip_model\.safetensors"):
        load_text_encoder(f"openclip-file:{tmp_path / 'open_clip_pytorch_model.bin'}")


# ---- SigLIP --------------------------------------------------------------------------------------------


def _word_tokenizer(folder):
    """A word-level fast tokenizer saved as tokenizer.json; like SigLIP's, it returns no attention mask."""
    from tokenizers import Tokenizer, models, pre_tokenizers

    words = ["<pad>", "<unk>", "</s>", *sorted({w for t in TEXTS for w in t.split()})]
    tk = Tokenizer(models.WordLevel({w: i for i, w in enumerate(words)}, unk_token="<unk>"))
    tk.pre_tokenizer = pre_tokenizers.Whitespace()
    fast = transformers.PreTrainedTokenizerFast(
        tokenizer_object=tk,
        pad_token="<pad>",
        unk_token="<unk>",
        eos_token="</s>",
        model_input_names=["input_ids"],
    )
    fast.save_pretrained(folder)
    return len(words)


def test_siglip_text_and_image_match_the_model_called_directly(tmp_path):
    vocab = _word_tokenizer(tmp_path)
    torch.manual_seed(4)
    small = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2)
    cfg = transformers.SiglipConfig(
        text_config=dict(small, vocab_size=vocab, max_position_embeddings=64),
        vision_config=dict(small, image_size=32, patch_size=8),
    )
    model = transformers.SiglipModel(cfg).eval()
    model.save_pretrained(tmp_path)
    (tmp_path / "preprocessor_config.json").write_text(
        json.dumps({"image_mean": [0.5] * 3, "image_std": [0.5] * 3})
    )

    text = load_text_encoder(str(tmp_path))
    assert isinstance(text, ClipTextEncoder) and text.dim == 32 and text.pad_to_max_length
    tok = transformers.AutoTokenizer.from_pretrained(str(tmp_path))
    with torch.inference_mode():
        inputs = tok(TEXTS, padding="max_length", max_length=64, return_tensors="pt")  # as SigLIP's docs
        assert set(inputs) == {"input_ids"}
        direct = model.get_text_features(**inputs)
        direct = F.normalize(getattr(direct, "pooler_output", direct), dim=-1)
        assert torch.allclose(text.encode_text(TEXTS), direct, atol=1e-5)
        image = ClipImageEncoder.load(f"hf:{tmp_path}")
        pixels = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(5))
        direct = model.get_image_features(pixel_values=(pixels - 0.5) / 0.5)
        direct = F.normalize(getattr(direct, "pooler_output", direct), dim=-1)
        assert torch.allclose(image(pixels), direct, atol=1e-5)


def test_a_model_of_another_kind_is_refused_naming_the_supported_ones(tmp_path):
    cfg = transformers.BertConfig(hidden_size=32, num_hidden_layers=1, num_attention_heads=2)
    transformers.BertModel(cfg).save_pretrained(tmp_path)
    with pytest.raises(ValidationError, match="clip, siglip"):
        load_text_encoder(str(tmp_path))
    with pytest.raises(ValidationError, match="vit, dinov2"):
        DinoEncoder.load(str(tmp_path))


# ---- DINO, DINOv2 --------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["vit", "dinov2", "dinov2_with_registers"])
def test_dense_features_match_the_model_called_directly(tmp_path, kind):
    torch.manual_seed(6)
    small = dict(
        hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2, patch_size=8
    )
    if kind == "vit":
        model = transformers.ViTModel(transformers.ViTConfig(image_size=32, **small), add_pooling_layer=False)
    elif kind == "dinov2":
        model = transformers.Dinov2Model(transformers.Dinov2Config(image_size=32, **small))
    else:
        cfg = transformers.Dinov2WithRegistersConfig(image_size=32, num_register_tokens=4, **small)
        model = transformers.Dinov2WithRegistersModel(cfg)
    model.eval().save_pretrained(tmp_path)
    enc = DinoEncoder.load(str(tmp_path), short_side=32)
    assert enc.skip == (5 if kind == "dinov2_with_registers" else 1)
    img = torch.rand(32, 48, 3, generator=torch.Generator().manual_seed(7))  # already the input size
    x = img.permute(2, 0, 1).unsqueeze(0)
    x = (x - torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)) / torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    with torch.inference_mode():
        kw = {"interpolate_pos_encoding": True} if kind == "vit" else {}
        tokens = model(pixel_values=x, **kw).last_hidden_state[0]
    direct = tokens[enc.skip :].reshape(4, 6, 32)
    assert torch.allclose(enc.dense(img, (4, 6)), direct, atol=1e-5)
