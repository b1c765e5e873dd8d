"""Exceptions raised by device drivers.

The device branch of Recal's exception tree (its root, ``RecalError``, is in calibration/errors.py;
each class also inherits the matching built-in, so callers can catch either)::

    RecalError
    └── DeviceError
        ├── DeviceConnectionError (ConnectionError)   cannot connect, or the link dropped
        ├── DeviceTimeoutError    (TimeoutError)      no (complete) answer in time
        ├── ProtocolError                             garbled or unexpected reply; carries the
        │                                             protocol's own code where it has one
        ├── DeviceFaultError                          the device answered and reports a fault
        │   ├── MeasurementError                      this measurement cannot be taken
        │   │                                         (beam broken, no touch, out of range)
        │   └── RobotStoppedError                     protective or emergency stop
        └── DeviceUnavailableError (RuntimeError)     the client library is missing here

Every message names the device (its address) and what was expected.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from calibration.errors import RecalError  # the root of the tree, re-exported here for drivers' callers


class DeviceError(RecalError):
    """A device could not do what was asked.

    ``device`` names the device (for example ``"tracker socket://127.0.0.2:10001"``); ``code`` is
    the protocol's own error code when it gave one (a Modbus exception code, an I++ error number,
    a tracker ``ERR`` code), else ``None``.
    """

    # what a protocol may add to its errors (I++ DME: the error's severity, the method it named
    # and its text); None where the protocol says nothing of it
    severity: int | None = None
    method: str | None = None
    text: str | None = None

    def __init__(self, message: str, *, device: str = "", code: int | str | None = None):
        self.device = device
        self.code = code
        prefix = f"{device}: " if device else ""
        suffix = f" (code {code})" if code is not None else ""
        super().__init__(f"{prefix}{message}{suffix}")


class DeviceConnectionError(DeviceError, ConnectionError):
    """The connection could not be made, or it dropped."""


class DeviceTimeoutError(DeviceError, TimeoutError):
    """The device did not answer (completely) within the timeout."""


class ProtocolError(DeviceError):
    """The device answered something the protocol does not allow here (garbled, unexpected)."""


class DeviceFaultError(DeviceError):
    """The device answered properly and reports a fault."""


class MeasurementError(DeviceFaultError):
    """This measurement cannot be taken (beam broken, no touch, target out of range)."""


class RobotStoppedError(DeviceFaultError):
    """The robot is in a protective or emergency stop, or its program stopped."""


class DeviceUnavailableError(DeviceError, RuntimeError):
    """The client library this driver needs is not installed on this machine."""


@contextlib.contextmanager
def translate_errors(device: str, *, timeout_s: float | None = None) -> Iterator[None]:
    """Convert built-in socket and serial exceptions raised inside the block into ours.

    Our own exceptions pass through unchanged; the original is chained with ``from``.
    """
    try:
        yield
    except DeviceError:
        raise
    except TimeoutError as exc:  # socket.timeout is TimeoutError since 3.10
        limit = f" within {timeout_s:g} s" if timeout_s is not None else ""
        raise DeviceTimeoutError(f"no answer{limit}", device=device) from exc
    except ConnectionError as exc:
        raise DeviceConnectionError(f"connection lost: {exc}", device=device) from exc
    except OSError as exc:
        raise DeviceConnectionError(f"I/O error: {exc}", device=device) from exc
