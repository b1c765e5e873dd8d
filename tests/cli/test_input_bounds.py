"""One CSV reader that cannot crash, and inputs read in bounded memory (issue 22, cases 3 and 7).
A lone carriage return between LF lines, a field longer than csv's limit and a file without end
(``/dev/zero``) each end in one line naming the file and the line, exit 2, in the CLI; the same
reader answers the API with 422 naming the line. A byte-order mark is read as the UTF-8 text it
is. The files are written here; memory is measured on the child process (its peak RSS)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

RECAL = str(Path(sys.executable).with_name("recal"))
HEADER = "q1,q2,q3,q4,q5,q6\n"


@pytest.fixture(scope="module")
def d(tmp_path_factory):
    d = tmp_path_factory.mktemp("bounds")
    subprocess.run([RECAL, "model", "ur10e", "--out", str(d / "nom.json")], check=True, capture_output=True)
    return d


def _run(d, *args, env=None):
    """Exit status, stderr and the child's peak RSS (MB), measured by a wrapper process of its own."""
    probe = (
        "import resource, subprocess, sys\n"
        "r = subprocess.run(sys.argv[1:], capture_output=True, text=True)\n"
        "sys.stdout.write(str(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss) + '\\n' + str(r.returncode))\n"
        "sys.stderr.write(r.stderr)\n"
    )
    p = subprocess.run(
        [sys.executable, "-c", probe, RECAL, *map(str, args)],
        cwd=d,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, **(env or {})},
    )
    rss_kb, status = p.stdout.split()
    return int(status), p.stderr, int(rss_kb) / 1024


@pytest.mark.parametrize(
    "verb",
    [
        ["predict", "--model", "nom.json", "--joints", "bad.csv", "--out", "p.csv"],
        ["compensate", "--model", "nom.json", "--task", "bad.csv", "--out", "c.csv"],
        ["accuracy", "--model", "nom.json", "--data", "bad.csv"],
    ],
)
@pytest.mark.parametrize(
    "content,where,what",
    [
        (HEADER + "0,0,0,0,0,0\r10,-80,90,0,90,0\n20,-80,90,0,90,0\n", "line 2", "carriage return (CR) alone"),
        (HEADER + "0,0,0,0,0," + "9" * 200_000 + "\n", "line 2", "a field longer than 131,072 characters"),
    ],
    ids=["bare-cr", "long-field"],
)
def test_a_csv_the_reader_cannot_take_is_one_line_and_exit_2(d, verb, content, where, what):
    (d / "bad.csv").write_bytes(content.encode())
    status, err, _ = _run(d, *verb)
    lines = err.strip().splitlines()
    assert status == 2 and len(lines) == 1, err
    assert lines[0].startswith(f"recal {verb[0]}: bad.csv, {where}") and what in lines[0], lines[0]
    assert not (d / verb[-1]).exists() or verb[0] == "accuracy"


def test_a_byte_order_mark_is_read_as_utf8_text(d):
    rows = "10,-80,90,0,90,0\n20,-70,80,0,90,10\n"
    (d / "plain.csv").write_text(HEADER + rows)
    (d / "bom.csv").write_bytes(b"\xef\xbb\xbf" + (HEADER + rows).encode())
    for name in ("plain", "bom"):
        assert _run(d, "predict", "--model", "nom.json", "--joints", f"{name}.csv", "--out", f"{name}-p.csv")[0] == 0
    assert (d / "bom-p.csv").read_text() == (d / "plain-p.csv").read_text()


def test_an_endless_input_is_refused_in_bounded_memory(d):
    """``/dev/zero`` grew the process to 21.8 GB before: now it is read to the bound and refused."""
    status, err, rss_mb = _run(
        d,
        "predict",
        "--model",
        "nom.json",
        "--joints",
        "/dev/zero",
        "--out",
        "p.csv",
        env={"RECAL_MAX_INPUT_BYTES": "64M"},
    )
    assert status == 2 and "/dev/zero: goes on past 67,108,864 bytes" in err and "RECAL_MAX_INPUT_BYTES" in err, err
    assert rss_mb < 64 + 250, rss_mb  # the bound, plus the interpreter and numpy


def test_a_file_over_the_bound_is_refused_before_it_is_read(d):
    """A 1 GB sparse file (no disk used) cost 1.08 GB before it was refused: now its size refuses it."""
    big = d / "big.csv"
    with big.open("wb") as f:
        f.write(HEADER.encode())
        f.truncate(1 << 30)
    status, err, rss_mb = _run(d, "predict", "--model", "nom.json", "--joints", "big.csv", "--out", "p.csv")
    assert status == 2 and "big.csv: is 1,073,741,824 bytes; expected at most 536,870,912" in err, err
    assert rss_mb < 250, rss_mb


def test_a_bad_bound_is_named(d):
    (d / "ok.csv").write_text(HEADER + "0,0,0,0,0,0\n")
    status, err, _ = _run(
        d,
        "predict",
        "--model",
        "nom.json",
        "--joints",
        "ok.csv",
        "--out",
        "p.csv",
        env={"RECAL_MAX_INPUT_BYTES": "lots"},
    )
    assert status == 2 and "RECAL_MAX_INPUT_BYTES" in err and "'lots'" in err, err
