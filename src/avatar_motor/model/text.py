"""Sentence embeddings for persona text, computed on this machine (no download at run time).

WordLlama (MIT; PyPI `wordllama`) ships its 256-d token embeddings and tokenizer in its wheel: a
sentence is the pooled embedding of its tokens. Its own loader looks for the tokenizer in a folder
the wheel does not have and then downloads it, so the two files are opened from the package here.
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from .persona import TEXT_DIM

MAX_TEXT = 500  # characters of one description


@lru_cache(maxsize=1)
def _encoder():
    try:
        import wordllama
        from safetensors import safe_open
        from tokenizers import Tokenizer
        from wordllama.inference import WordLlamaInference
    except ImportError as e:  # pragma: no cover - a broken install
        raise RuntimeError(f"persona text needs the 'wordllama' package ({e}); reinstall avatar-motor: "
                           "pip install -e .") from e
    root = Path(wordllama.__file__).parent
    weights, tok = root / "weights" / "l2_supercat_256.safetensors", root / "tokenizers" / "l2_supercat_tokenizer_config.json"
    for p in (weights, tok):
        if not p.exists():
            raise RuntimeError(f"the wordllama package has no {p.name} (expected at {p}); install wordllama==0.4.0.post1")
    with safe_open(str(weights), framework="np") as f:
        emb = f.get_tensor("embedding.weight")
    if emb.shape[1] != TEXT_DIM:
        raise RuntimeError(f"wordllama embeddings are {emb.shape[1]}-d, the persona model reads {TEXT_DIM}")
    return WordLlamaInference(emb, Tokenizer.from_file(str(tok)))


def embed_texts(texts: list[str]) -> torch.Tensor:
    """Unit-length embeddings (N, TEXT_DIM) float32 of descriptions."""
    bad = [t for t in texts if not isinstance(t, str) or not t.strip() or len(t) > MAX_TEXT]
    if bad:
        raise ValueError(f"a persona description must be non-empty text of at most {MAX_TEXT} characters, "
                         f"got {str(bad[0])[:80]!r}")
    e = np.asarray(_encoder().embed([t.strip() for t in texts]), dtype=np.float32)
    e = e / np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-8)
    return torch.from_numpy(e)
