"""Fanuc TP programs in ASCII (``.ls``).

Targets are the positions of the ``/POS`` section, each ``P[n]`` or ``P[n:"comment"]`` with its
group 1 (``GP1:``; other groups are left untouched):

- Cartesian: ``UF : u, UT : t, CONFIG : 'N U T, 0, 0, 0', X = .. mm, Y, Z, W = .. deg, P, R``
  (W, P, R Fanuc's fixed angles about X, Y, Z of the user frame; the configuration: flip F/N,
  up U/D, front T/B and the turn numbers of J1, J4, J6);
- joint: ``UF : u, UT : t, J1 = .. deg, ..., J6`` (Fanuc's readings: J3 from the horizon, which
  the model's coupling matrix turns into joint angles, contracts §2).

The form stays as written. Positions span several lines; ``/MN`` (the instructions, their ``!``
comments and continuation lines) is not read: every position of ``/POS`` is compensated. User
frame ``u`` and tool frame ``t`` come from ``--base-frame u=X,Y,Z,W,P,R`` and
``--tool-frame t=...`` (or the unnumbered option for every number), or a backup's frame data
(service.programs.fanuc_frames); ``UF : 0`` is the robot's world frame (taken as its base frame)
and ``UT : 0`` the faceplate. ``F`` (the frame active at run time) is the number ``/MN`` selects
with ``UFRAME_NUM=n`` / ``UTOOL_NUM=n`` when it fixes one statically (:func:`selected_frames`);
else, or for a number not given, the program is refused, naming the line.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from calibration.transforms import homogeneous
from calibration.vendors import fanuc_wpr_to_matrix

from ..files import InputError
from .base import Number, Program, Target, read_text
from .frames import Frames
from .tokens import FANUC_TP, SIGNED_NUMBER, Source

_POS_RE = re.compile(r"^/POS\b", re.MULTILINE)
_END_RE = re.compile(r"^/END\b", re.MULTILINE)
_P_RE = re.compile(r'P\[\s*(\d+)\s*(?::\s*"([^"\r\n]*)")?\s*\]\s*\{(.*?)\}\s*;', re.DOTALL)
_GP_RE = re.compile(r"GP(\d+)\s*:")
_FRAME_RE = re.compile(r"\b(UF|UT)\s*:\s*([^\s,]+)")
_CONFIG_RE = re.compile(r"CONFIG\s*:\s*'([^']*)'")
_CONF_VALUE_RE = re.compile(
    r"^\s*([NF])\s*([UD])\s*([TB])\s*,\s*(-?\d+)\s*,\s*(-?\d+)\s*,\s*(-?\d+)\s*$", re.IGNORECASE
)
_COMP_RE = re.compile(rf"\b([XYZWPR]|J[1-9]|E[1-9])\s*=\s*({SIGNED_NUMBER})\s*(mm|deg)?")


def _frame(values) -> np.ndarray:
    x, y, z, w, p, r = values
    return homogeneous(fanuc_wpr_to_matrix(np.radians([w, p, r])), np.array([x, y, z]) * 1e-3)


def parse(path, data: bytes | None = None, *, n_joints: int = 6, frames: Frames | None = None) -> Program:
    """Parse the ``/POS`` section of an ``.ls`` program (see the module docstring)."""
    if n_joints != 6:
        raise InputError(path, f"TP programs are compensated for six-axis arms; the model has {n_joints} joints")
    frames = frames or Frames()
    src = Source(FANUC_TP, path, read_text(path, data))
    m = _POS_RE.search(src.code)
    if m is None:
        raise InputError(path, "expected a /POS section (an ASCII .ls program); none found")
    end = _END_RE.search(src.code, m.end())
    stop = end.start() if end else len(src.code)
    active = selected_frames(src.code[: m.start()])
    out = []
    for p in _P_RE.finditer(src.code, m.end(), stop):
        position = _group1(src, p, frames, active)
        if position is not None:
            out.append(_KINDS[position.kind](src, position))
    return Program((src.path,), (src.text,), "fanuc", out, [])


@dataclass(frozen=True)
class _Position:
    """A position's group 1 as read: ``label`` (``P[n]``), ``line``, the offset ``at`` and code
    ``seg`` of its text after ``GP1:``, its components (``comps``) and resolved frames."""

    label: str
    line: int
    at: int
    seg: str
    comps: dict[str, Number]
    T_work: np.ndarray
    T_tool: np.ndarray
    frames: str

    @property
    def kind(self) -> str:
        return "joints" if any(k.startswith("J") for k in self.comps) else "pose"


def _group1(src: Source, p: re.Match, frames: Frames, active: dict) -> _Position | None:
    """Position ``p``'s group 1 (``None`` when it has none: other groups are left untouched)."""
    label = f"P[{p.group(1)}]"
    body_at = p.start(3)
    body = p.group(3)
    gps = list(_GP_RE.finditer(body))
    if not gps:
        src.fail(p.start(), f"{label}: expected a group 'GP1:'")
    gp1 = [g for g in gps if g.group(1) == "1"]
    if not gp1:
        return None
    g = gp1[0]
    nxt = [x.start() for x in gps if x.start() > g.start()]
    seg_s, seg_e = body_at + g.end(), body_at + (nxt[0] if nxt else len(body))
    seg = src.code[seg_s:seg_e]
    fr = {k.upper(): (v, seg_s + mm.start(2)) for mm in _FRAME_RE.finditer(seg) for k, v in [mm.groups()]}
    for key in ("UF", "UT"):
        if key not in fr:
            src.fail(seg_s, f"{label}: expected '{key} : n'")
    comps = {}
    for c in _COMP_RE.finditer(seg):
        a, e = seg_s + c.start(2), seg_s + c.end(2)
        comps[c.group(1).upper()] = Number(0, a, e, src.text[a:e])
    last = max((n.start for n in comps.values()), default=seg_s)  # a missing component: named at the last
    _components(src.fail, label, comps, last)
    T_work, uf_name = _resolve(src.fail, label, "UF", *fr["UF"], frames.bases, "--base-frame", active)
    T_tool, ut_name = _resolve(src.fail, label, "UT", *fr["UT"], frames.tools, "--tool-frame", active)
    names = f"UF {uf_name}, UT {ut_name}"
    return _Position(label, src.line(p.start()), seg_s, seg, comps, T_work, T_tool, names)


def _joints(src: Source, pos: _Position) -> Target:
    """A joint position: ``J1`` .. ``J6`` (deg)."""
    need = [f"J{i}" for i in range(1, 7)]
    missing = [k for k in need if k not in pos.comps]
    if missing:
        src.fail(pos.at, f"{pos.label}: expected component {missing[0]}")
    nums = tuple(pos.comps[k] for k in need)
    q = np.radians([n.value for n in nums])
    return Target(
        "joints", 0, pos.line, pos.label, "P", q=q, joints=nums, T_work=pos.T_work, T_tool=pos.T_tool, frames=pos.frames
    )


def _pose(src: Source, pos: _Position) -> Target:
    """A Cartesian position: ``X``, ``Y``, ``Z`` (mm), ``W``, ``P``, ``R`` (deg) and its ``CONFIG``."""
    need = list("XYZWPR")
    missing = [k for k in need if k not in pos.comps]
    if missing:
        src.fail(pos.at, f"{pos.label}: expected component {missing[0]} (Cartesian X, Y, Z, W, P, R or joints J1..J6)")
    cm = _CONFIG_RE.search(pos.seg)
    if cm is None:
        src.fail(pos.at, f"{pos.label}: expected CONFIG : 'N U T, 0, 0, 0' in a Cartesian position")
    config_text = src.text[pos.at + cm.start(1) : pos.at + cm.end(1)]
    cv = _CONF_VALUE_RE.match(config_text)
    if cv is None:
        src.fail(
            pos.at + cm.start(1),
            f"{pos.label}: CONFIG: expected 'F|N U|D T|B, turn1, turn4, turn6', got {config_text!r}",
        )
    config = (
        int(cv.group(1).upper() == "F"),
        int(cv.group(2).upper() == "U"),
        int(cv.group(3).upper() == "T"),
        int(cv.group(4)),
        int(cv.group(5)),
        int(cv.group(6)),
    )
    return Target(
        "pose",
        0,
        pos.line,
        pos.label,
        "P",
        P=_frame([pos.comps[k].value for k in need]),
        rotation="fanuc_wpr",
        position=tuple(pos.comps[k] for k in "XYZ"),
        orientation=tuple(pos.comps[k] for k in "WPR"),
        config=config,
        config_text=config_text,
        T_work=pos.T_work,
        T_tool=pos.T_tool,
        frames=pos.frames,
    )


# a position's kind (:attr:`_Position.kind`) -> how its target is read
_KINDS = {"joints": _joints, "pose": _pose}


def _components(fail, label, comps, offset):
    if any(k.startswith("J") for k in comps):
        missing = [f"J{i}" for i in range(1, 7) if f"J{i}" not in comps]
        if missing:
            fail(offset, f"{label}: expected component {missing[0]}")
        return
    missing = [k for k in "XYZWPR" if k not in comps]
    if missing:
        fail(offset, f"{label}: expected component {missing[0]} (Cartesian X, Y, Z, W, P, R or joints J1..J6)")


# /MN: UFRAME_NUM=n / UTOOL_NUM=n (the frames a position written UF : F / UT : F moves in) and
# the motion instructions (J, L, C, A with a position or position register)
_SELECT_RE = re.compile(r"^\s*\d+\s*:\s*(UFRAME_NUM|UTOOL_NUM)\s*=\s*([^;]*?)\s*;", re.M | re.IGNORECASE)
_MOTION_RE = re.compile(r"^\s*\d+\s*:\s*[JLCA]\s+(?:P|PR)\[", re.M)
_SELECT_KEYS = {"UFRAME_NUM": "UF", "UTOOL_NUM": "UT"}


def selected_frames(head: str) -> dict[str, tuple[int | None, str]]:
    """For ``UF`` and ``UT``: the frame number ``F`` stands for, read from the program's
    ``UFRAME_NUM=n`` / ``UTOOL_NUM=n`` (``head``: the text before ``/POS``), and how it was found;
    ``None`` with the reason where the program does not fix it statically. It is fixed when every
    assignment gives the same constant and the first comes before the first motion (before it
    the frame is whatever the controller had)."""
    first_motion = _MOTION_RE.search(head)
    out: dict[str, tuple[int | None, str]] = {}
    for name, key in _SELECT_KEYS.items():
        sets = [m for m in _SELECT_RE.finditer(head) if m.group(1).upper() == name]
        values = {m.group(2) for m in sets}
        if not sets:
            out[key] = (None, f"the program sets no {name}")
        elif len(values) > 1 or not next(iter(values)).isdigit():
            out[key] = (None, f"{name} is set to {', '.join(sorted(values))} in the program")
        elif first_motion is not None and sets[0].start() > first_motion.start():
            out[key] = (None, f"a motion comes before {name}={sets[0].group(2)}")
        else:
            out[key] = (int(sets[0].group(2)), f"{name}={sets[0].group(2)}")
    return out


def _resolve(fail, label, key, value, offset, given: dict, flag: str, active: dict | None = None):
    if value.upper() == "F":
        n_active, how = (active or {}).get(key, (None, "no /MN section"))
        if n_active is None:
            fail(
                offset,
                f"{label}: {key} : F (the frame active at run time) cannot be compensated statically: {how}",
            )
        T, name = _resolve(fail, label, key, str(n_active), offset, given, flag)
        return T, f"{name} (F: {how})"
    try:
        n = int(value)
    except ValueError:
        fail(offset, f"{label}: {key}: expected a frame number, got {value!r}")
    if n in given:
        return _frame(given[n]), str(n)
    if None in given:
        return _frame(given[None]), f"{n} ({flag})"
    if n == 0:
        return np.eye(4), "0"
    fail(offset, f"{label}: {key} {n} is not given: pass {flag} {n}=X,Y,Z,W,P,R")
