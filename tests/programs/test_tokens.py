"""The tokenizer the program languages share (service.programs.tokens, issue 23): comments and
strings blanked at the file's offsets, tokens, statements, lines, and errors naming file and line;
and every language's parser reading through it."""

from __future__ import annotations

import ast
import inspect

import pytest

from service.files import InputError
from service.programs import fanuc_tp, krl, rapid, tokens, urscript
from service.programs.tokens import FANUC_TP, KRL, RAPID, URSCRIPT, Source


@pytest.mark.parametrize(
    ("lang", "text", "code"),
    [
        (KRL, 'PTP XP1 ; go "home"\nLIN XP2\n', "PTP XP1            \nLIN XP2\n"),
        (RAPID, 'TPWrite "a;b!c"; ! note\r\nMoveL p1;', 'TPWrite "     ";       \r\nMoveL p1;'),
        (URSCRIPT, 'popup("x # y") # a comment\rmovej(q)', 'popup("     ")            \rmovej(q)'),
        # TP: what is read holds no comment or string to blank (a label's "comment" read by its pattern)
        (FANUC_TP, '  1:  !UFRAME_NUM=2 ;\n  2:  J P[1:"a!"] ;', '  1:  !UFRAME_NUM=2 ;\n  2:  J P[1:"a!"] ;'),
        # a string that does not close ends with its line; the next line is read
        (KRL, 'X = "open\nPTP XP1 ; c', 'X = "    \nPTP XP1    '),
    ],
)
def test_comments_and_string_contents_are_blanked_at_the_files_offsets(lang, text, code):
    src = Source(lang, "f", text)
    assert src.code == code
    assert len(src.code) == len(text)


def test_tokens_are_names_numbers_strings_and_punctuation_with_their_offsets():
    text = 'VAR robtarget p1 := [[1.5e3,-2,.25],"a;b"]; x1e5 ! p1 in a comment'
    src = Source(RAPID, "m.mod", text)
    got = [(t.kind, t.text) for t in src.tokens()]
    assert got == [
        ("ident", "VAR"),
        ("ident", "robtarget"),
        ("ident", "p1"),
        ("punct", ":"),
        ("punct", "="),
        ("punct", "["),
        ("punct", "["),
        ("number", "1.5e3"),
        ("punct", ","),
        ("punct", "-"),
        ("number", "2"),
        ("punct", ","),
        ("number", ".25"),
        ("punct", "]"),
        ("punct", ","),
        ("string", '"a;b"'),
        ("punct", "]"),
        ("punct", ";"),
        ("ident", "x1e5"),
    ]
    assert all(text[t.start : t.end] == t.text for t in src.tokens())
    assert [t.text for t in src.identifiers(0, 20)] == ["VAR", "robtarget", "p1"]


def test_statements_end_at_the_terminator_or_the_line():
    rapid_src = Source(RAPID, "m.mod", "MoveL p1,\n  v100, fine, tool0; ! a; b\nENDPROC")
    assert [rapid_src.code[s:e].strip() for s, e in rapid_src.statements()] == [
        "MoveL p1,\n  v100, fine, tool0",
        "ENDPROC",
    ]
    krl_src = Source(KRL, "t.src", "PTP XP1 ; a\r\nLIN XP2\n")
    assert [krl_src.code[s:e] for s, e in krl_src.statements()] == ["PTP XP1    ", "LIN XP2"]
    assert [(ln, s) for ln, s, _ in krl_src.lines()] == [(1, 0), (2, 13)]


def test_an_error_names_the_file_and_the_line_of_its_offset():
    src = Source(KRL, "dir/t.src", "DEF t( )\r\nPTP {X 1}\rEND\n")
    assert src.line(src.text.index("{")) == 2
    assert src.line_text(3) == "END"
    with pytest.raises(InputError, match=r"^dir/t\.src, line 2: expected Y$"):
        src.fail(src.text.index("X"), "expected Y")


def test_case_follows_the_language():
    assert KRL.pattern(r"ptp").match("PTP")
    assert RAPID.pattern(r"movel").match("MoveL")
    assert not URSCRIPT.pattern(r"movel").match("MOVEL")


def test_top_level_split_keeps_nested_commas():
    code = "p1, Offs(p1, 1, 2), [1, [2, 3]]\\WObj:=w"
    pieces = [code[a:b] for a, b in tokens.split_top_level(code, 0, len(code))]
    assert pieces == ["p1", " Offs(p1, 1, 2)", " [1, [2, 3]]\\WObj:=w"]
    assert tokens.trim(code, 3, 19) == (4, 19)


@pytest.mark.parametrize("module", [krl, rapid, fanuc_tp, urscript])
def test_every_language_reads_through_the_tokenizer_with_short_functions(module):
    """Each parser uses the shared Source, and no function of it is over 80 lines."""
    source = inspect.getsource(module)
    assert "Source(" in source or "(Source)" in source
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.FunctionDef):
            assert node.end_lineno - node.lineno + 1 <= 80, f"{module.__name__}.{node.name}"
