"""The UE's uplink buffer: bytes in arrival order with their arrival times, bounded. Pure."""

from __future__ import annotations

from collections import deque


class UeBuffer:
    def __init__(self, capacity_bytes: int) -> None:
        if capacity_bytes < 1:
            raise ValueError("capacity_bytes must be >= 1")
        self.capacity_bytes = capacity_bytes
        self._chunks: deque[tuple[int, bytes]] = deque()
        self._head_offset = 0
        self.size = 0

    @property
    def free(self) -> int:
        return max(0, self.capacity_bytes - self.size)

    def append(self, data: bytes, now_ns: int) -> None:
        """Callers read at most `free` bytes, so the bound holds; a larger append is a bug."""
        if len(data) > self.free:
            raise OverflowError(f"{len(data)} bytes do not fit in {self.free} free bytes")
        if data:
            self._chunks.append((now_ns, data))
            self.size += len(data)

    def take(self, nbytes: int) -> bytes:
        """Remove and return up to nbytes from the head."""
        parts = []
        want = min(nbytes, self.size)
        while want > 0:
            _, chunk = self._chunks[0]
            available = len(chunk) - self._head_offset
            if available <= want:
                parts.append(chunk[self._head_offset :])
                self._chunks.popleft()
                self._head_offset = 0
                want -= available
            else:
                parts.append(chunk[self._head_offset : self._head_offset + want])
                self._head_offset += want
                want = 0
        out = b"".join(parts)
        self.size -= len(out)
        return out

    def head_age_ns(self, now_ns: int) -> int | None:
        """How long the oldest byte has waited: the queueing delay right now."""
        return now_ns - self._chunks[0][0] if self._chunks else None

    def clear(self) -> int:
        dropped = self.size
        self._chunks.clear()
        self._head_offset = 0
        self.size = 0
        return dropped
