"""Process-independent seeds for the evaluation tools (benchmark, evaluate, tune).

Kept apart from the benchmark's modules so that evaluation workers import no plotting code.
"""

from __future__ import annotations

import zlib

import numpy as np


def derive_seed(*keys: int | str) -> int:
    """A 64-bit seed from integers and strings (strings hashed with CRC-32, then ``SeedSequence``):
    the same keys give the same seed in every process, whatever the executor."""
    words = [int(k) if isinstance(k, (int, np.integer)) else zlib.crc32(str(k).encode('utf-8')) for k in keys]
    state = np.random.SeedSequence(words).generate_state(2, dtype=np.uint32)
    return (int(state[0]) << 32) | int(state[1])
