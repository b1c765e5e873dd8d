"""The root of Recal's exception tree.

Every exception Recal raises on purpose derives from :class:`RecalError` and also from the
built-in that matches it (``ValueError`` for bad input, ``ConnectionError`` for a lost link,
``RuntimeError`` for a result that cannot be had), so a caller can catch either. The root lives
here, in the calibration core, because every other package may import the core and the core
imports nothing of ours (drivers/errors.py holds the device branch of the tree)::

    RecalError
    ├── calibration: ModelFormatError (ValueError), SweepError (ValueError),
    │                CovarianceError (ValueError), NotEnoughData (ValueError)
    ├── drivers:     DeviceError and its branch (drivers/errors.py)
    ├── fakes:       CellError (ValueError), IppError, DropConnection
    └── service:     InputError, DeviceConfigError, SettingsError, UnsafePlan, RegionError,
                     CompensationInputError, FleetConfigError (ValueError); AnalysisError,
                     ApiError, ServiceError (RuntimeError); DeviceOpenError,
                     ServiceUnreachableError (ConnectionError); SessionStopped; Fail (the CLI's
                     one-line exit)
"""

from __future__ import annotations


class RecalError(Exception):
    """Base of every exception Recal raises on purpose."""
