"""MAVLink 2 message signing: the shared key on disk, and which unsigned messages a signed link lets in.

The signatures themselves are pymavlink's (`MAVLinkSigning`: SHA-256 over key, packet and a 48-bit
timestamp; a timestamp not above the last one from the same (link id, system, component) is a replay
and refused). What it leaves to its user, and what lives here:

- the key: 32 bytes in a file only its owner may read, as PX4 keeps it (`mavlink/mavlink-signing-key.bin`,
  mode 0600). The file holds the 32 raw bytes, or 64 hexadecimal characters (and an optional newline);
  it is never logged;
- the timestamp to start from: now, in 10 us units since 2015-01-01 UTC, so that a restarted sender is
  ahead of what the receiver last accepted from it;
- which unsigned messages a signed link still accepts: PX4's list (HEARTBEAT, RADIO_STATUS,
  ADSB_VEHICLE, COLLISION); everything else unsigned, or badly signed, or replayed, is refused.
"""

from __future__ import annotations

import os
import secrets
import stat
import time
from pathlib import Path

from dynqos.common.errors import ConfigError, DynqosError

KEY_BYTES = 32
EPOCH_2015_S = 1_420_070_400
# PX4's unsigned_messages[] (src/modules/mavlink/mavlink_sign_control.cpp): HEARTBEAT, RADIO_STATUS,
# ADSB_VEHICLE, COLLISION. Message ids, so that common/ needs no MAVLink dialect.
UNSIGNED_ALLOWED = frozenset({0, 109, 246, 247})


def load_key(path: str | Path) -> bytes:
    """The 32-byte key in `path`; a clear ConfigError (never the key) when it is missing, readable by
    others than its owner, or not 32 bytes / 64 hex characters."""
    p = Path(path)
    try:
        mode = p.stat().st_mode
        if not stat.S_ISREG(mode):
            raise ConfigError("", f"MAVLink signing key {p}: not a regular file")
        raw = p.read_bytes()
    except OSError as exc:
        raise ConfigError("", f"MAVLink signing key {p}: cannot read it ({exc.strerror})") from None
    if mode & 0o077:
        raise ConfigError(
            "",
            f"MAVLink signing key {p}: readable by others (mode {stat.S_IMODE(mode):04o}); "
            f"make it owner-only with: chmod 600 {p}",
        )
    if len(raw) == KEY_BYTES:
        return raw
    text = raw.strip()
    if len(text) == 2 * KEY_BYTES:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    raise ConfigError(
        "",
        f"MAVLink signing key {p}: expected 32 bytes or 64 hexadecimal characters, found {len(raw)} bytes "
        "(make one with: dynqos signing-key --out FILE)",
    )


def write_key(path: str | Path, *, force: bool = False) -> Path:
    """A new random key as 64 hex characters in a new file of mode 0600 (through O_EXCL: never through
    a link, never over an existing key unless `force`)."""
    p = Path(path)
    try:
        if p.exists() or p.is_symlink():
            if not force:
                raise DynqosError(f"{p} exists: keep it, or give --force to replace the key")
            p.unlink()
        p.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o600)
        with os.fdopen(fd, "w") as out:
            out.write(secrets.token_bytes(KEY_BYTES).hex() + "\n")
    except OSError as exc:
        raise DynqosError(f"cannot write the signing key {p}: {exc.strerror}") from None
    return p


def timestamp_now(now_s: float | None = None) -> int:
    """The signing timestamp for `now_s` (wall clock, default now): 10 us units since 2015."""
    now = time.time() if now_s is None else now_s
    return max(0, int((now - EPOCH_2015_S) * 100_000))


def accepts_unsigned(message_id: int) -> bool:
    return message_id in UNSIGNED_ALLOWED


def signed_frame(data: bytes | bytearray) -> bool:
    """Whether a MAVLink frame (starting at its magic byte) carries a signature: MAVLink 2, flag bit 0."""
    return len(data) > 2 and data[0] == 0xFD and bool(data[2] & 0x01)
