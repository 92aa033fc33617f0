"""Facade: the text encoders live in :mod:`common.text`; import them from here or there."""
from common.text import (  # noqa: F401
    IMAGENET_TEMPLATES,
    SINGLE_TEMPLATE,
    TEXT_MODELS,
    CachedTextEncoder,
    ModelFileError,
    TextEncoder,
    make_text_encoder,
)
from common.text.minilm import MiniLMText, minilm_model_dir  # noqa: F401
from common.text.siglip import SiglipText, canonicalize  # noqa: F401
