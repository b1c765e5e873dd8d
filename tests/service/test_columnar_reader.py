"""The columnar CSV reader (pyarrow) and the Python reader give the same measurements, and every
fault the same words (issue 25, case 7). The files are written here, one construct each; the
Python reader (``RECAL_CSV_READER=python``) is the reference, as it was the only reader before."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calibration.robots import nominal
from service.files import ColumnTable, InputError, read_measurements, read_table

MODEL = dataclasses.replace(nominal("ur5e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
HEADER = "q1,q2,q3,q4,q5,q6,x,y,z"
ROWS = [
    "10,-20,30,-40,50,-60,100.5,-200.25,300",
    "1e1,-2.0E1,3.5,0,0,7,1,2,3",
    "-179.5,89,-1,2,3,4,0.001,-0.002,1e3",
]


def _both(path, monkeypatch):
    monkeypatch.delenv("RECAL_CSV_READER", raising=False)
    fast = read_measurements(path, MODEL)
    monkeypatch.setenv("RECAL_CSV_READER", "python")
    slow = read_measurements(path, MODEL)
    monkeypatch.delenv("RECAL_CSV_READER")
    return fast, slow


def _same(a, b) -> None:
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if x is None or y is None:
            assert x is None and y is None, f.name
        elif x.dtype == object:
            assert x.tolist() == y.tolist(), f.name
        else:
            np.testing.assert_array_equal(x, y, err_msg=f.name)


VARIANTS = {
    "plain": HEADER + "\n" + "\n".join(ROWS) + "\n",
    "crlf": (HEADER + "\n" + "\n".join(ROWS) + "\n").replace("\n", "\r\n"),
    "bom, no last newline": "\ufeff" + HEADER + "\n" + "\n".join(ROWS),
    "comment and blank lines before the header": "# units mm, deg\n\n" + HEADER + "\n" + "\n".join(ROWS) + "\n",
    "blank line between rows": HEADER + "\n" + ROWS[0] + "\n\n" + "\n".join(ROWS[1:]) + "\n",
    "spaces around header names": " q1, q2,q3 ,q4,q5,q6,x,y,z\n" + "\n".join(ROWS) + "\n",
    "target, sigma and a label": HEADER
    + ",target,sigma,label\n"
    + "\n".join(f"{r},smr,{0.01 * (i + 1)},  station {i % 2} " for i, r in enumerate(ROWS))
    + "\n",
    "orientation on some rows": HEADER
    + ",qw,qx,qy,qz\n"
    + ROWS[0]
    + ",1,0,0,0\n"
    + ROWS[1]
    + ",,,,\n"
    + ROWS[2]
    + ",0.7071067811865476,0.7071067811865476,0,0\n",
}
FAST = {
    "plain",
    "comment and blank lines before the header",
    "crlf",
    "bom, no last newline",
    "blank line between rows",
    "spaces around header names",
    "target, sigma and a label",
    "orientation on some rows",
}


@pytest.mark.parametrize("name", VARIANTS)
def test_both_readers_give_the_same_measurements(tmp_path, monkeypatch, name):
    path = tmp_path / "m.csv"
    path.write_bytes(VARIANTS[name].encode())
    fast, slow = _both(path, monkeypatch)
    _same(fast, slow)
    assert len(fast) == 3
    # the files the columnar reader is for are read by it (not handed over whole)
    assert isinstance(read_table(path), ColumnTable) == (name in FAST)


FAULTS = {
    "a word in a number column": ROWS[0] + "\n10,-20,abc,0,0,0,1,2,3\n",
    "an empty joint cell": ROWS[0] + "\n10,,30,0,0,0,1,2,3\n",
    "a written nan": ROWS[0] + "\n10,20,nan,0,0,0,1,2,3\n",
    "an infinity": ROWS[0] + "\n10,20,30,0,0,0,inf,2,3\n",
    "beyond any cell": ROWS[0] + "\n10,20,30,0,0,0,1e308,2,3\n",
    "a reading beyond the joint limits": ROWS[0] + "\n10,20,30,0,0,720,1,2,3\n",
    "one value too many": ROWS[0] + "\n10,20,30,0,0,0,1,2,3,4\n",
    "one value too few": ROWS[0] + "\n10,20,30,0,0,0,1,2\n",
    "a quoted field": ROWS[0] + '\n10,20,30,0,0,0,1,2,"3"\n',
    "a lone carriage return": ROWS[0] + "\r" + ROWS[1] + "\n",
    "a comment between rows": ROWS[0] + "\n# a note\n10,20,30,0,0,0,1,2,3,x\n",
    "a blank-only row of commas": ROWS[0] + "\n , , , , , , , , \n" + ROWS[1] + "\n",
}


@pytest.mark.parametrize("name", FAULTS)
def test_a_fault_is_named_by_the_same_words_row_and_column(tmp_path, monkeypatch, name):
    path = tmp_path / "bad.csv"
    path.write_bytes((HEADER + "\n" + FAULTS[name]).encode())
    messages = []
    for reader in ("", "python"):
        monkeypatch.setenv("RECAL_CSV_READER", reader)
        try:
            data = read_measurements(path, MODEL)
        except InputError as exc:
            messages.append(str(exc))
        else:
            messages.append(f"read {len(data)} rows")
    assert messages[0] == messages[1]
    assert "row" in messages[0] or "line" in messages[0] or messages[0].startswith("read "), messages[0]


def test_a_missing_or_duplicate_column_is_named_by_the_same_words(tmp_path, monkeypatch):
    for header in ("q1,q2,q3,q4,q5,q6,x,y", "q1,q2,q3,q4,q5,q6,x,y,z,z"):
        path = tmp_path / "h.csv"
        path.write_text(header + "\n" + "1,2,3,4,5,6,7,8,9,9\n")
        got = []
        for reader in ("", "python"):
            monkeypatch.setenv("RECAL_CSV_READER", reader)
            with pytest.raises(InputError) as exc:
                read_measurements(path, MODEL)
            got.append(str(exc.value))
        assert got[0] == got[1] and "column" in got[0], got
