"""The moves of a URScript program, as the simulated UR controller runs them.

A real controller runs any program sent to its script port. The fake runs the part that
moves the robot, which is what a compensated task program is: ``movej``, ``movel`` and
``movep`` to literal targets (``p[x, y, z, rx, ry, rz]`` poses in the base frame, metres and a
rotation vector; ``[q1, ..., q6]`` joints in radians), to variables assigned such a literal
(``global Waypoint_1_p = p[...]``), and to ``get_inverse_kin(pose, qnear=q)``; ``a=``/``v=``
(or the second and third positional arguments) set the motion's acceleration and speed, and
``set_tcp(p[...])`` the TCP that pose targets are for. Everything else is skipped (logic,
I/O, ``sleep``, ``textmsg`` ...), as the fake has nothing to do for it; a move whose target it
cannot evaluate (an expression) makes the program fail to start, with the line, as a real
controller's compile error would.

Pure parsing: :func:`parse_program` returns the steps; ``fakes.ur_controller`` executes them
through the cell (pose targets through the controller's factory calibration).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from calibration.errors import RecalError

_COMMENT = re.compile(r"#.*$")
_ASSIGN = re.compile(r"^(?:global\s+|local\s+)?([A-Za-z_]\w*)\s*=\s*(.+)$")
_CALL = re.compile(r"^(movej|movel|movep|set_tcp)\s*\((.*)\)$")
_LITERAL = re.compile(r"^(p?)\[([^\[\]]*)\]$")
_IK = re.compile(r"^get_inverse_kin\s*\((.*)\)$")
# URScript's defaults: movej a=1.4 rad/s^2, v=1.05 rad/s; movel/movep a=1.2 m/s^2, v=0.25 m/s.
_DEFAULTS = {"movej": (1.4, 1.05), "movel": (1.2, 0.25), "movep": (1.2, 0.25)}


class ProgramError(RecalError, ValueError):
    """The program cannot be run by the fake; the message names the line."""


@dataclass(frozen=True)
class Step:
    """One thing the program does to the robot, with its 1-based ``line``.

    ``kind``: ``movej``/``movel``/``movep`` (``pose`` (6,) or ``joints`` (6,) set; ``qnear`` the
    ``get_inverse_kin`` branch hint, if any) or ``set_tcp`` (``pose`` the TCP offset)."""

    kind: str
    line: int
    pose: tuple[float, ...] | None = None
    joints: tuple[float, ...] | None = None
    qnear: tuple[float, ...] | None = None
    accel: float = 0.0
    speed: float = 0.0


def is_control_script(text: str) -> bool:
    """``ur_rtde``'s control script (it reads its commands from the RTDE input registers)."""
    return "read_input_integer_reg" in text


def _split_args(text: str) -> list[str]:
    """Top-level comma-separated arguments (brackets and parentheses kept together)."""
    out, depth, start = [], 0, 0
    for i, ch in enumerate(text):
        if ch in "([":
            depth += 1
        elif ch in ")]":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append(text[start:i].strip())
            start = i + 1
    tail = text[start:].strip()
    if tail:
        out.append(tail)
    return out


def _literal(text: str, variables: dict, line: int) -> tuple[str, tuple[float, ...]]:
    """``("pose" | "joints", values)`` of a literal or a variable holding one."""
    text = text.strip()
    if text in variables:
        return variables[text]
    m = _LITERAL.match(text)
    if m is None:
        raise ProgramError(
            f"line {line}: cannot evaluate the target {text!r} (the simulator runs literal targets "
            f"and variables assigned one)"
        )
    try:
        values = tuple(float(v) for v in m.group(2).split(","))
    except ValueError:
        raise ProgramError(f"line {line}: expected numbers in {text!r}") from None
    if len(values) != 6:
        raise ProgramError(f"line {line}: expected 6 values in {text!r}, got {len(values)}")
    return ("pose" if m.group(1) else "joints"), values


def parse_program(text: str) -> list[Step]:
    """The steps of a URScript program (see the module docstring)."""
    variables: dict[str, tuple[str, tuple[float, ...]]] = {}
    steps: list[Step] = []
    for n, raw in enumerate(text.splitlines(), start=1):
        code = _COMMENT.sub("", raw).strip()
        if not code:
            continue
        call = _CALL.match(code)
        if call is None:
            assign = _ASSIGN.match(code)
            if assign and _LITERAL.match(assign.group(2).strip()):
                variables[assign.group(1)] = _literal(assign.group(2), {}, n)
            continue
        kind, args = call.group(1), _split_args(call.group(2))
        if not args:
            raise ProgramError(f"line {n}: {kind} without a target")
        if kind == "set_tcp":
            what, values = _literal(args[0], variables, n)
            if what != "pose":
                raise ProgramError(f"line {n}: set_tcp expects a pose p[...]")
            steps.append(Step("set_tcp", n, pose=values))
            continue
        accel, speed = _DEFAULTS[kind]
        positional = [a for a in args[1:] if "=" not in a]
        keywords = dict(a.split("=", 1) for a in args[1:] if "=" in a)
        try:
            if positional:
                accel = float(positional[0])
            if len(positional) > 1:
                speed = float(positional[1])
            accel = float(keywords.get("a", accel))
            speed = float(keywords.get("v", speed))
        except ValueError:
            raise ProgramError(f"line {n}: expected numbers for a= and v=") from None
        target, qnear = args[0], None
        ik = _IK.match(target)
        if ik is not None:
            ik_args = _split_args(ik.group(1))
            target = ik_args[0]
            for a in ik_args[1:]:
                name, _, value = a.partition("=")
                if name.strip() == "qnear" or not value:
                    qnear = _literal(value or name, variables, n)[1]
        what, values = _literal(target, variables, n)
        if what == "pose":
            steps.append(Step(kind, n, pose=values, qnear=qnear, accel=accel, speed=speed))
        else:
            steps.append(Step(kind, n, joints=values, accel=accel, speed=speed))
    return steps
