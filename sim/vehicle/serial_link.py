"""The simulated vehicle's offboard link over a serial line, as a companion computer meets a Pixhawk.

`device = "pty"` makes a pseudo-terminal pair and speaks on its master side; the other side's path
(e.g. /dev/pts/7, in the ready line) is what the onboard daemon opens as its `mavlink_url`, with the
same pyserial code it would use on /dev/ttyACM0. Any other `device` is opened as it is (one end of a
`socat` pair, or a USB-serial adapter for hardware in the loop) at `baud`, raw, with RTS/CTS flow
control when asked. Bytes, not datagrams: one parser per link keeps what a read left incomplete.
Writes never block the simulation: what the line cannot take now is dropped and counted, as a UART
with a full buffer drops.
"""

from __future__ import annotations

import contextlib
import os
import termios
import tty
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

READ_BYTES = 4096
BAUD_RATES = {
    rate: getattr(termios, f"B{rate}")
    for rate in (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 921600, 1000000, 1500000)
    if hasattr(termios, f"B{rate}")
}


class SerialLink:
    stream = True  # a byte stream: messages may span reads

    def __init__(self, name: str, device: str, *, baud: int = 921600, flow_control: bool = False) -> None:
        if baud not in BAUD_RATES:
            raise ValueError(f"baud {baud} is not one of {sorted(BAUD_RATES)}")
        self.name = name
        self.device = device
        self.baud = baud
        self.flow_control = flow_control
        self.path = device  # what the peer opens
        self.fd = -1
        self._peer_fd = -1  # a pty's other side, held so that reads before the peer opens it do not fail
        self.received = 0
        self.garbage = 0
        self.dropped_bytes = 0
        self._parser: Any = None

    def open(self) -> None:
        if self.device == "pty":
            self.fd, self._peer_fd = os.openpty()
            tty.setraw(self._peer_fd)  # no echo, no line editing: MAVLink is binary
            self.path = os.ttyname(self._peer_fd)
        else:
            self.fd = os.open(self.device, os.O_RDWR | os.O_NOCTTY)
            tty.setraw(self.fd)
            attrs = termios.tcgetattr(self.fd)
            attrs[4] = attrs[5] = BAUD_RATES[self.baud]  # ispeed, ospeed
            if self.flow_control:
                attrs[2] |= termios.CRTSCTS
            else:
                attrs[2] &= ~termios.CRTSCTS
            termios.tcsetattr(self.fd, termios.TCSANOW, attrs)
        os.set_blocking(self.fd, False)

    def fileno(self) -> int:
        return self.fd

    def close(self) -> None:
        for fd in (self.fd, self._peer_fd):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self.fd = self._peer_fd = -1

    def send(self, data: bytes) -> None:
        try:
            written = os.write(self.fd, data)
        except (BlockingIOError, OSError):  # full, or the peer went: the line drops it
            written = 0
        self.dropped_bytes += len(data) - written

    def receive(self) -> list[tuple[bytes, tuple[str, int] | None]]:
        try:
            data = os.read(self.fd, READ_BYTES)
        except OSError:  # nothing waiting (EAGAIN), or no peer on a pty (EIO)
            return []
        return [(data, None)] if data else []

    def parse(self, data: bytes, signing: Any) -> list[Any]:
        if self._parser is None:
            self._parser = mavlink.MAVLink(None)
            self._parser.robust_parsing = True
            self._parser.signing = signing
        return self._parser.parse_buffer(data) or []

    def answer(self, sender: tuple[str, int] | None) -> None:
        """A serial line has one peer: nothing to redirect."""
