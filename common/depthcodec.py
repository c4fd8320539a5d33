"""A fast lossless codec for 16-bit depth images: byte shuffle, then zstd.

Why not PNG: PNG's deflate on noisy 16-bit depth costs ~15 ms per 640 x 480 frame here; splitting
the image into its high-byte and low-byte planes (the high bytes are smooth and compress well) and
compressing with zstd level 1 costs ~1-2 ms for a similar size. The `zstandard` package is the
well-kept binding of the reference zstd library.
"""

from __future__ import annotations

import numpy as np
import zstandard
from numpy.typing import NDArray

from dynqos.common.errors import DecodeError

_COMPRESSOR = zstandard.ZstdCompressor(level=1)
MAX_PIXELS = 8192 * 8192


def encode_zstd16(depth: NDArray[np.uint16]) -> bytes:
    if depth.dtype != np.uint16 or depth.ndim != 2:
        raise ValueError("depth must be a 2-D uint16 array")
    planes = depth.astype("<u2").view(np.uint8).reshape(-1, 2).T  # [low bytes, high bytes]
    compressed: bytes = _COMPRESSOR.compress(np.ascontiguousarray(planes).tobytes())
    return compressed


def decode_zstd16(data: bytes, width: int, height: int) -> NDArray[np.uint16]:
    """Raises DecodeError for anything but a valid frame of exactly width x height."""
    size = width * height
    if not 0 < size <= MAX_PIXELS:
        raise DecodeError("payload", f"{width}x{height} is not a valid depth size")
    try:
        raw = zstandard.ZstdDecompressor().decompress(data, max_output_size=2 * size)
    except zstandard.ZstdError as exc:
        raise DecodeError("payload", f"not zstd16 data ({exc})") from None
    if len(raw) != 2 * size:
        raise DecodeError("payload", f"zstd16 holds {len(raw)} bytes, expected {2 * size}")
    planes = np.frombuffer(raw, np.uint8).reshape(2, size)
    depth: NDArray[np.uint16] = np.ascontiguousarray(planes.T).view("<u2").reshape(height, width)
    return depth
