"""A library of nominal robot models, by name (``nominal("ur10e")``).

- Universal Robots e-Series (UR3e, UR5e, UR10e, UR16e): the DH tables Universal Robots
  publishes for its robots (standard DH, mm and degrees).
- PUMA 560 of the book's case study (Mooring, Roth & Driels, ch. 6), in inches and degrees as
  printed: ``puma560`` is the modified-DH model of Table 6.1 (standard DH links, Hayati's form
  for the parallel joints 2-3, the base transform B->0 and the 6-parameter tool transform folded
  exactly into ``base`` and joint 6), and ``puma560-zrp`` the zero-reference-position model of
  Table 6.2 with T0 of eq. 6.11 as ``home``.
"""

from __future__ import annotations

from typing import Any

from .model import KinematicModel, model_from_dict

_UR_DH = {
    # name: (d1, a2, a3, d4, d5, d6) in mm, from Universal Robots' published DH parameters.
    "ur3e": (151.85, -243.55, -213.2, 131.05, 85.35, 92.1),
    "ur5e": (162.5, -425.0, -392.2, 133.3, 99.7, 99.6),
    "ur10e": (180.7, -612.7, -571.55, 174.15, 119.85, 116.55),
    "ur16e": (180.7, -478.4, -360.0, 174.15, 119.85, 116.55),
}


def _ur(name: str) -> dict[str, Any]:
    d1, a2, a3, d4, d5, d6 = _UR_DH[name]
    rows = [(d1, 0.0, 90.0), (0.0, a2, 0.0), (0.0, a3, 0.0), (d4, 0.0, 90.0), (d5, 0.0, -90.0), (d6, 0.0, 0.0)]
    return {
        "format": "recal.model/1",
        "name": f"{name}-nominal",
        "units": {"length": "mm", "angle": "deg"},
        "convention": "dh",
        "base": [0, 0, 0, 0, 0, 0],
        "joints": [
            {"name": f"j{i + 1}", "type": "revolute", "theta": 0.0, "d": d, "a": a, "alpha": alpha,
             "lower": -360.0, "upper": 360.0}
            for i, (d, a, alpha) in enumerate(rows)
        ],
        "tool": [0, 0, 0, 0, 0, 0],
        "targets": {},
    }


# Joint ranges of the PUMA 560 (degrees), as commonly published for the arm.
_PUMA_LIMITS = [(-160, 160), (-225, 45), (-45, 225), (-110, 170), (-100, 100), (-266, 266)]


def _puma_dh() -> dict[str, Any]:
    """Table 6.1 (inches, degrees). B->0 (Type 1, no joint variable):
    Rz(0)·Tz(32.878)·Tx(-15.591)·Rx(-90) = pose [-15.591, 0, 32.878, -90, 0, 0].
    1->2 is Hayati's Type 2 (``beta``). 5->6 (Type 3, eq. 6.4):
    Rz(Θ6 + 90)·Ry(0)·Rx(0)·T(0, 0, 2.213) = a DH link with theta = 90, d = 2.213 and an
    identity tool."""
    links = [
        {"theta": 0.0, "d": 14.681, "a": 0.0, "alpha": -90.0},
        {"theta": 0.0, "a": 17.000, "alpha": 0.0, "beta": 0.0},
        {"theta": 0.0, "d": 5.870, "a": -0.800, "alpha": 90.0},
        {"theta": 0.0, "d": 17.050, "a": 0.0, "alpha": -90.0},
        {"theta": 0.0, "d": 0.0, "a": 0.0, "alpha": 90.0},
        {"theta": 90.0, "d": 2.213, "a": 0.0, "alpha": 0.0},
    ]
    return {
        "format": "recal.model/1",
        "name": "puma560-nominal",
        "units": {"length": "in", "angle": "deg"},
        "convention": "dh",
        "base": [-15.591, 0.0, 32.878, -90.0, 0.0, 0.0],
        "joints": [
            {"name": f"j{i + 1}", "type": "revolute", **link, "lower": lo, "upper": hi}
            for i, (link, (lo, hi)) in enumerate(zip(links, _PUMA_LIMITS))
        ],
        "tool": [0, 0, 0, 0, 0, 0],
        "targets": {},
    }


def _puma_zrp() -> dict[str, Any]:
    """Table 6.2 (u dimensionless, p in inches) with T0 of eq. 6.11 as ``home``:
    T0 = [[0,-1,0,1.2],[0,0,1,33.96],[-1,0,0,27.73]] = pose [1.2, 33.96, 27.73, 0, 90, 90]."""
    axes = [(0, 1, 0), (0, 0, -1), (0, 0, -1), (0, 1, 0), (0, 0, -1), (0, 1, 0)]
    points = [(-15.00, 14.70, 33.60), (-15.00, 14.70, 27.73), (2.00, 14.70, 27.73),
              (1.20, 31.75, 27.73), (1.20, 31.75, 27.73), (1.20, 31.75, 27.73)]
    return {
        "format": "recal.model/1",
        "name": "puma560-zrp-nominal",
        "units": {"length": "in", "angle": "deg"},
        "convention": "poe",
        "base": [0, 0, 0, 0, 0, 0],
        "joints": [
            {"name": f"j{i + 1}", "type": "revolute", "axis": list(u), "point": list(p), "theta": 0.0,
             "lower": lo, "upper": hi}
            for i, (u, p, (lo, hi)) in enumerate(zip(axes, points, _PUMA_LIMITS))
        ],
        "home": [1.2, 33.96, 27.73, 0.0, 90.0, 90.0],
        "tool": [0, 0, 0, 0, 0, 0],
        "targets": {},
    }


_LIBRARY = {**{name: (lambda n=name: _ur(n)) for name in _UR_DH}, "puma560": _puma_dh, "puma560-zrp": _puma_zrp}


def names() -> tuple[str, ...]:
    """The names ``nominal`` accepts."""
    return tuple(sorted(_LIBRARY))


def nominal_document(name: str) -> dict[str, Any]:
    """The ``recal.model/1`` document of a library robot (its published units)."""
    try:
        return _LIBRARY[name.lower()]()
    except KeyError:
        raise KeyError(f"unknown robot {name!r}; known: {', '.join(names())}") from None


def nominal(name: str) -> KinematicModel:
    """The nominal model of a library robot."""
    return model_from_dict(nominal_document(name))
