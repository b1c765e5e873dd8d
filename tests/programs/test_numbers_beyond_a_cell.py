"""A number no robot cell can have is refused alike in every program language (issue 22): a KRL
``PTP {X 1e200, ...}`` was left alone (and answered 200 by the service) while URScript with the
same value was refused. Each program is written here; the refusal names the file, line and target."""

from __future__ import annotations

import pytest

from service import programs
from service.files import InputError

KRL = "DEF t( )\nPTP {X %s, Y 0, Z 500, A 0, B 90, C 0}\nEND\n"
KRL_DAT = ("DEF t( )\nLIN XP1\nEND\n", "DEFDAT t\nDECL E6POS XP1={X 1,Y %s,Z 3,A 0,B 0,C 0}\nENDDAT\n")
KRL_AXIS = "DEF t( )\nPTP {A1 0, A2 -90, A3 %s, A4 0, A5 0, A6 0}\nEND\n"
RAPID = (
    "MODULE m\n  CONST robtarget p1:=[[%s,2,3],[1,0,0,0],[0,0,0,0],[9E9,9E9,9E9,9E9,9E9,9E9]];\n"
    "  PROC main()\n    MoveL p1, v100, fine, tool0;\n  ENDPROC\nENDMODULE\n"
)
TP = (
    "/PROG X\r\n/POS\r\nP[1]{\r\n   GP1:\r\n\tUF : 0, UT : 0,\t\tCONFIG : 'N U T, 0, 0, 0',\r\n"
    "\tX = 1.0 mm, Y = 2.0 mm, Z = %s mm,\r\n\tW = 0.0 deg, P = 0.0 deg, R = 0.0 deg\r\n};\r\n/END\r\n"
)
URSCRIPT = "def prog():\n  movel(p[%s, 0.1, 0.4, 0, 3.14, 0], a=1.2, v=0.25)\nend\n"


def _write(tmp_path, name: str, text: str):
    (tmp_path / name).write_bytes(text.encode())
    return tmp_path / name


@pytest.mark.parametrize("value", ["1e200", "-2e9", "1.5e8"])  # 1.5e8 mm is 150 km: beyond any cell
@pytest.mark.parametrize(
    "fmt, name, text, where",
    [
        ("krl", "t.src", KRL, r"t\.src, line 2: PTP: "),
        ("krl", "t.src", KRL_AXIS, r"t\.src, line 2: PTP: "),
        ("rapid", "prog.mod", RAPID, r"prog\.mod, line 2: p1: "),
        ("fanuc-tp", "prog.ls", TP, r"prog\.ls, line 3: P\[1\]: "),
        ("urscript", "prog.script", URSCRIPT, r"prog\.script, line 2: "),
    ],
)
def test_a_number_beyond_any_cell_is_refused_in_every_language(tmp_path, fmt, name, text, where, value):
    if fmt == "urscript":
        value = str(float(value) / 1000)  # URScript is in metres: the same length
    path = _write(tmp_path, name, text % value)
    with pytest.raises(InputError, match=where):
        programs.parse(fmt, path)


def test_a_krl_dat_target_beyond_any_cell_is_refused(tmp_path):
    _write(tmp_path, "t.src", KRL_DAT[0])
    _write(tmp_path, "t.dat", KRL_DAT[1] % "1e200")
    with pytest.raises(InputError, match=r"t\.dat, line 2: XP1: expected a number from -1e\+09 to 1e\+09, got 1e\+200"):
        programs.parse("krl", tmp_path / "t.src")


@pytest.mark.parametrize(
    "fmt, name, text", [("krl", "t.src", KRL), ("rapid", "prog.mod", RAPID), ("fanuc-tp", "prog.ls", TP)]
)
def test_ordinary_numbers_are_taken(tmp_path, fmt, name, text):
    prog = programs.parse(fmt, _write(tmp_path, name, text % "900.5"))
    assert len(prog.targets) == 1
