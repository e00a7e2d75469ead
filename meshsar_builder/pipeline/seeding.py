"""All randomness derives from (recipe seed, stage, item id), never from order or worker."""

from __future__ import annotations

import hashlib

import numpy as np


def _words(text: str) -> list[int]:
    """Stable 32-bit words of a string (Python's hash() is salted per process)."""
    digest = hashlib.sha256(text.encode("utf-8")).digest()
    return [int.from_bytes(digest[i : i + 4], "little") for i in range(0, 16, 4)]


def seed_sequence(seed: int, stage: str, item_id: str) -> np.random.SeedSequence:
    """The SeedSequence of one item of one stage of a recipe seeded with `seed`."""
    return np.random.SeedSequence([int(seed), *_words(stage), *_words(item_id)])


def item_rng(seed: int, stage: str, item_id: str) -> np.random.Generator:
    """A Generator that depends only on (seed, stage, item_id)."""
    return np.random.default_rng(seed_sequence(seed, stage, item_id))
