"""The moves the simulated UR controller finds in a user's URScript program
(``fakes.urscript_program``): what it runs and what it refuses, by line."""

from __future__ import annotations

import pytest

from fakes.urscript_program import ProgramError, is_control_script, parse_program

PROGRAM = """def task():
  global Waypoint_1_p=p[0.4, -0.2, 0.35, 0.0, 3.1416, 0.0]  # a PolyScope waypoint
  Home_q = [0.3, -1.2, 1.4, -1.6, -1.5, 0.2]
  set_tcp(p[0, 0, 0.05, 0, 0, 0])
  movej(Home_q, a=1.4, v=1.05)
  movel(Waypoint_1_p, a=1.2, v=0.25)
  textmsg("moved")
  movej(get_inverse_kin(p[0.45, -0.15, 0.3, 0.0, 3.1416, 0.0], qnear=Home_q), 2.0, 0.5)
  movep(p[0.5, -0.1, 0.3, 0, 3.1416, 0], v=0.1)  # movel(p[9, 9, 9, 9, 9, 9]) in a comment
end
"""


def test_moves_targets_and_parameters_are_read_in_program_order():
    steps = parse_program(PROGRAM)
    assert [(s.kind, s.line) for s in steps] == [("set_tcp", 4), ("movej", 5), ("movel", 6), ("movej", 8), ("movep", 9)]
    assert steps[0].pose == (0, 0, 0.05, 0, 0, 0)
    assert steps[1].joints == (0.3, -1.2, 1.4, -1.6, -1.5, 0.2) and (steps[1].accel, steps[1].speed) == (1.4, 1.05)
    assert steps[2].pose == (0.4, -0.2, 0.35, 0.0, 3.1416, 0.0) and steps[2].qnear is None
    assert steps[3].pose[:3] == (0.45, -0.15, 0.3) and steps[3].qnear == steps[1].joints
    assert (steps[3].accel, steps[3].speed) == (2.0, 0.5)
    assert (steps[4].accel, steps[4].speed) == (1.2, 0.1)  # URScript's default a= for movep
    assert not is_control_script(PROGRAM)
    assert is_control_script("def rtde_control():\n  cmd = read_input_integer_reg(0)\nend\n")


@pytest.mark.parametrize(
    "line, message",
    [
        ("  movel(pose_trans(Waypoint_1_p, p[0, 0, 0.01, 0, 0, 0]))", "line 2: cannot evaluate the target"),
        ("  movel(p[0.4, -0.2, 0.35])", "line 2: expected 6 values"),
        ("  movej([0.1, x, 0, 0, 0, 0])", "line 2: expected numbers"),
    ],
)
def test_a_target_it_cannot_evaluate_is_refused_with_its_line(line, message):
    with pytest.raises(ProgramError, match=message):
        parse_program(f"def task():\n{line}\nend\n")
