"""A CR LF text-line channel over pyserial's ``serial_for_url``.

Shared by the line-protocol drivers (laser tracker, I++ DME CMM). The URL decides the transport:
``socket://host:port`` (raw TCP), ``/dev/ttyUSB0`` or ``COM3`` (RS-232), a pty path, or
``rfc2217://host:port``. Every read and write has a deadline; built-in errors are converted
into ours (:mod:`drivers.errors`).
"""

from __future__ import annotations

import logging
import time

import serial  # pyserial

from drivers.errors import DeviceConnectionError, DeviceTimeoutError, ProtocolError, translate_errors

log = logging.getLogger(__name__)

_POLL_S = 0.05  # the port's own read timeout; a read call never blocks longer than this


class LineLink:
    """One connection to a line-oriented device.

    ``device`` names the device in every error; ``timeout_s`` is the default deadline of a
    read or write. Lines are written with CR LF; received lines may end in CR LF or LF and
    must be printable ASCII (32-126), otherwise the read raises ``ProtocolError``.
    """

    def __init__(self, url: str, *, device: str, timeout_s: float, baudrate: int = 115200, max_line: int = 4096):
        self.url = url
        self.device = device
        self.timeout_s = float(timeout_s)
        self.baudrate = int(baudrate)
        self.max_line = int(max_line)
        self._ser = None
        self._buffer = bytearray()

    # ----------------------------------------------------------------- lifecycle

    @property
    def is_open(self) -> bool:
        return self._ser is not None

    def open(self) -> None:
        """Open the port. Raises ``DeviceConnectionError`` if it cannot be opened."""
        self.close()
        try:
            self._ser = serial.serial_for_url(
                self.url,
                baudrate=self.baudrate,
                timeout=min(_POLL_S, self.timeout_s),
                write_timeout=self.timeout_s,
            )
        except (OSError, ValueError) as exc:
            raise DeviceConnectionError(f"cannot open {self.url}: {exc}", device=self.device) from exc
        self._buffer.clear()

    def close(self) -> None:
        """Close the port; harmless when already closed."""
        ser, self._ser = self._ser, None
        self._buffer.clear()
        if ser is not None:
            try:
                ser.close()
            except Exception:  # closing a broken port must not raise
                log.debug("%s: error while closing", self.device, exc_info=True)

    # ----------------------------------------------------------------- I/O

    def write_line(self, text: str) -> None:
        """Send ``text`` followed by CR LF."""
        ser = self._require_open()
        data = text.encode("ascii") + b"\r\n"

        with translate_errors(self.device, timeout_s=self.timeout_s):
            try:
                ser.write(data)
                ser.flush()
            except serial.SerialTimeoutException as exc:
                raise DeviceTimeoutError(
                    f"could not send {text!r} within {self.timeout_s:g} s", device=self.device
                ) from exc

    def read_line(self, timeout_s: float | None = None, *, expecting: str = "a reply") -> str:
        """The next line without its terminator.

        Raises ``DeviceTimeoutError`` when no complete line arrives within ``timeout_s``
        (default: the link's timeout), ``DeviceConnectionError`` when the link drops, and
        ``ProtocolError`` for a line that is not printable ASCII or is too long.
        """
        ser = self._require_open()
        limit = self.timeout_s if timeout_s is None else float(timeout_s)
        deadline = time.monotonic() + limit
        with translate_errors(self.device, timeout_s=limit):
            while True:
                nl = self._buffer.find(b"\n")
                if nl >= 0:
                    raw = bytes(self._buffer[:nl])
                    del self._buffer[: nl + 1]
                    return self._decode(raw)
                if len(self._buffer) > self.max_line:
                    snippet = bytes(self._buffer[:40])
                    self._buffer.clear()
                    raise ProtocolError(
                        f"reply longer than {self.max_line} bytes without a line end: {snippet!r}...",
                        device=self.device,
                    )
                if time.monotonic() >= deadline:
                    partial = f" (partial: {bytes(self._buffer)!r})" if self._buffer else ""
                    raise DeviceTimeoutError(f"no {expecting} within {limit:g} s{partial}", device=self.device)
                chunk = ser.read(max(1, ser.in_waiting))
                if chunk:
                    self._buffer += chunk

    def discard_input(self) -> bytes:
        """Drop whatever has arrived but not been read (returns it, for logging)."""
        ser = self._require_open()
        dropped = bytes(self._buffer)
        self._buffer.clear()
        with translate_errors(self.device, timeout_s=self.timeout_s):
            while ser.in_waiting:
                dropped += ser.read(ser.in_waiting)
        return dropped

    # ----------------------------------------------------------------- helpers

    def _require_open(self):
        if self._ser is None:
            raise DeviceConnectionError("not connected", device=self.device)
        return self._ser

    def _decode(self, raw: bytes) -> str:
        if raw.endswith(b"\r"):
            raw = raw[:-1]
        if any(b < 32 or b > 126 for b in raw):
            raise ProtocolError(f"garbled reply (not printable ASCII): {raw!r}", device=self.device)
        return raw.decode("ascii")
