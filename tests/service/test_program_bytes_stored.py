"""Robot programs that are not UTF-8, stored and served again byte for byte (issue 18): a KRL
program in Windows-1252 (its .src and .dat) and a RAPID module with Latin-1 comments registered
with a cell, compensated by ``/cells/{id}/tasks/compensate`` (the nightly job's route) and fetched
back from ``/compensations/{id}`` are the bytes ``recal compensate`` writes for the same model;
a program compensated through ``/calibrations/{id}/compensate`` is served again as the route
answered it. UTF-8 programs and task CSVs stay UTF-8. Runs on SQLite, and on PostgreSQL with
RECAL_TEST_POSTGRES_URL (the ``database_url`` fixture)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import auth

_EXE = Path(sys.executable).with_name("recal")
RECAL = [str(_EXE)] if _EXE.exists() else [sys.executable, "-m", "service.cli"]

# KUKA's editor writes Windows-1252: an en dash (0x96) and a plus-minus (0xB1) beside umlauts
SRC = (
    "DEF job( )\r\n; Greifer geöffnet, 90° gedreht – Übergabe\r\n"
    "PTP {A1 5.0, A2 -85.0, A3 95.0, A4 -95.0, A5 65.0, A6 25.0} ; Zwischenstellung ±0,5°\r\n"
    "PTP XHOME\r\nPTP XP1\r\nEND\r\n"
).encode("cp1252")
DAT = (
    "DEFDAT job\r\n; Positionen – Schweißnaht\r\n"
    "DECL E6AXIS XHOME={A1 10.0,A2 -80.0,A3 90.0,A4 -100.0,A5 70.0,A6 20.0,E1 0.0}\r\n"
    "DECL E6AXIS XP1={A1 -30.0,A2 -100.0,A3 60.0,A4 -50.0,A5 -80.0,A6 0.0,E1 12.5} ; Düse ±0,5 mm\r\n"
    "ENDDAT\r\n"
).encode("cp1252")
MOD = (
    "MODULE m\n  ! Schweißnaht, Düse: Lage ±0,5 mm\n  PROC main()\n"
    "    MoveAbsJ [[10,-80,90,-100,70,20],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]], v1000, fine, tool0; ! Übergabe\n"
    "  ENDPROC\nENDMODULE\n"
)


def cli_output(client, token: str, cell: int, cal: int, d: Path, files: dict[str, bytes], task: str) -> dict:
    """What ``recal compensate`` writes for ``files`` (``task`` the one given to it) with the
    calibration's model and the cell's nominal model: file name -> bytes."""
    (d / "in").mkdir()
    (d / "out").mkdir()
    model = client.get(f"/api/v1/calibrations/{cal}", headers=auth(token)).json()["model"]
    nominal = client.get(f"/api/v1/cells/{cell}", headers=auth(token)).json()["model"]
    (d / "model.json").write_text(json.dumps(model))
    (d / "nominal.json").write_text(json.dumps(nominal))
    for name, data in files.items():
        (d / "in" / name).write_bytes(data)
    args = ["compensate", "--model", "model.json", "--nominal", "nominal.json"]
    args += ["--task", f"in/{task}", "--out", f"out/{task}"]
    r = subprocess.run([*RECAL, *args], cwd=d, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return {p.name: p.read_bytes() for p in (d / "out").iterdir()}


def test_a_windows_1252_krl_program_registered_is_compensated_byte_for_byte(calibrated, tokens, tmp_path):
    client, cell, cal = calibrated
    t = auth(tokens["technician"])
    task = {
        "name": "job.src",
        "content": SRC.decode("iso-8859-1"),
        "encoding": "iso-8859-1",
        "files": [{"name": "job.dat", "content": DAT.decode("iso-8859-1"), "encoding": "iso-8859-1"}],
    }
    r = client.post(f"/api/v1/cells/{cell}/tasks", json=task, headers=t)
    assert r.status_code == 201, r.text
    stored = client.get(f"/api/v1/cells/{cell}/tasks/{r.json()['id']}", headers=t).json()
    assert stored["content"].encode(stored["encoding"]) == SRC
    assert [(f["name"], f["content"].encode(f["encoding"])) for f in stored["files"]] == [("job.dat", DAT)]

    r = client.post(f"/api/v1/cells/{cell}/tasks/compensate", headers=auth(tokens["job"]))
    assert r.status_code == 200, r.text
    (done,) = r.json()["tasks"]
    assert "error" not in done and done["summary"]["converged"] == 3, done
    want = cli_output(client, tokens["viewer"], cell, cal, tmp_path, {"job.src": SRC, "job.dat": DAT}, "job.src")
    assert want["job.src"] != SRC and want["job.dat"] != DAT  # targets in both files were corrected

    got = client.get(f"/api/v1/compensations/{done['compensation_id']}", headers=t)
    assert got.headers["content-type"] == "text/plain; charset=iso-8859-1"
    assert got.content == want["job.src"]
    assert b"; Greifer ge\xf6ffnet, 90\xb0 gedreht \x96 \xdcbergabe\r\n" in got.content
    (dat,) = client.get(f"/api/v1/compensations/{done['compensation_id']}/report", headers=t).json()["report"]["files"]
    assert dat["name"] == "job.dat" and dat["text"].encode(dat["encoding"]) == want["job.dat"]


def test_a_krl_src_registered_alone_is_compensated_as_recal_compensate_does(calibrated, tokens, tmp_path):
    """A .src without its .dat: its inline target is corrected, the ones declared in the missing
    .dat are reported as not compensated (the CLI's warning), and the bytes are the CLI's."""
    client, cell, cal = calibrated
    t = auth(tokens["technician"])
    task = {"name": "job.src", "content": SRC.decode("iso-8859-1"), "encoding": "iso-8859-1"}
    assert client.post(f"/api/v1/cells/{cell}/tasks", json=task, headers=t).status_code == 201
    r = client.post(f"/api/v1/cells/{cell}/tasks/compensate", headers=auth(tokens["job"]))
    assert r.status_code == 200, r.text
    (done,) = r.json()["tasks"]
    assert "error" not in done and done["summary"]["converged"] == 1, done
    want = cli_output(client, tokens["viewer"], cell, cal, tmp_path, {"job.src": SRC}, "job.src")
    got = client.get(f"/api/v1/compensations/{done['compensation_id']}", headers=t)
    assert got.content == want["job.src"] != SRC
    report = client.get(f"/api/v1/compensations/{done['compensation_id']}/report", headers=t).json()["report"]
    missing = " ".join(str(u) for u in report["uninterpreted"])
    assert "XHOME" in missing and "XP1" in missing, report["uninterpreted"]


def test_a_latin_1_rapid_module_registered_and_a_utf8_one(calibrated, tokens, tmp_path):
    """The Latin-1 module comes back in Latin-1, the same module in UTF-8 in UTF-8, each the
    bytes of ``recal compensate``; a task CSV registered beside them is still answered as UTF-8."""
    client, cell, cal = calibrated
    t = auth(tokens["technician"])
    latin1, utf8 = MOD.encode("latin-1"), MOD.encode("utf-8")
    for task in (
        {"name": "m.mod", "content": latin1.decode("iso-8859-1"), "encoding": "iso-8859-1"},
        {"name": "u.mod", "content": MOD},  # UTF-8: the default, as before
        {"name": "t.csv", "content": "name,q1,q2,q3,q4,q5,q6\nP1,10,-80,90,-100,70,20\n"},
    ):
        assert client.post(f"/api/v1/cells/{cell}/tasks", json=task, headers=t).status_code == 201
    r = client.post(f"/api/v1/cells/{cell}/tasks/compensate", headers=auth(tokens["job"]))
    assert r.status_code == 200, r.text
    ids = {d["name"]: d["compensation_id"] for d in r.json()["tasks"]}
    want = cli_output(client, tokens["viewer"], cell, cal, tmp_path, {"m.mod": latin1, "u.mod": utf8}, "m.mod")
    assert want["m.mod"] != latin1 and b"! Schwei\xdfnaht, D\xfcse: Lage \xb10,5 mm\n" in want["m.mod"]

    got = client.get(f"/api/v1/compensations/{ids['m.mod']}", headers=t)
    assert got.headers["content-type"] == "text/plain; charset=iso-8859-1"
    assert got.content == want["m.mod"]
    got = client.get(f"/api/v1/compensations/{ids['u.mod']}", headers=t)
    assert got.headers["content-type"] == "text/plain; charset=utf-8"
    assert got.content == want["m.mod"].decode("latin-1").encode("utf-8")  # same numbers, UTF-8 bytes
    got = client.get(f"/api/v1/compensations/{ids['t.csv']}", headers=t)
    assert got.headers["content-type"] == "text/plain; charset=utf-8" and got.text.startswith("name,q1,")


def test_a_program_compensated_by_the_route_is_served_again_as_answered(calibrated, tokens):
    """``/calibrations/{id}/compensate`` answered a Latin-1 module in Latin-1; the stored
    compensation is served with the same bytes and charset (it was UTF-8 before)."""
    client, _, cal = calibrated
    latin1 = MOD.encode("latin-1")
    r = client.post(f"/api/v1/calibrations/{cal}/compensate?name=m.mod", content=latin1, headers=auth(tokens["job"]))
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "text/plain; charset=iso-8859-1"
    got = client.get(f"/api/v1/compensations/{r.headers['x-recal-compensation']}", headers=auth(tokens["viewer"]))
    assert got.headers["content-type"] == r.headers["content-type"]
    assert got.content == r.content and b"! Schwei\xdfnaht, D\xfcse" in got.content


@pytest.mark.parametrize(
    ("task", "field", "message"),
    [
        ({"name": "m.mod", "content": "! Ωmega\n", "encoding": "iso-8859-1"}, "body.content", "'Ω'"),
        ({"name": "m.mod", "content": "MODULE m\n", "encoding": "cp1252"}, "body.encoding", "'utf-8' or 'iso-8859-1'"),
        ({"name": "t.csv", "content": "q1\n1\n", "encoding": "iso-8859-1"}, "body.encoding", "task CSV is UTF-8"),
        (
            {
                "name": "job.src",
                "content": "DEF job( )\nEND\n",
                "files": [
                    {"name": "job.dat", "content": "DEFDAT job\n"},
                    {"name": "old.dat", "content": "DEFDAT old\n"},
                ],
            },
            "body.files",
            "job.src has one .dat",
        ),
        (
            {"name": "job.src", "content": "DEF job( )\nEND\n", "files": [{"name": "job.dat", "content": "\ud800"}]},
            "body.files[0].content",
            "unpaired surrogate U+D800",  # every request's text is checked first (service/textcheck.py)
        ),
    ],
)
def test_a_task_file_that_cannot_be_stored_as_its_bytes_is_refused(calibrated, tokens, task, field, message):
    client, cell, _ = calibrated
    body = json.dumps(task)  # "\ud800" escaped, as a JSON client may send a lone surrogate
    headers = {**auth(tokens["technician"]), "Content-Type": "application/json"}
    r = client.post(f"/api/v1/cells/{cell}/tasks", content=body, headers=headers)
    assert r.status_code == 422, r.text
    answer = r.json()  # a use case's refusal, or the request's validation (its "errors")
    detail = answer["errors"][0] if "errors" in answer else answer["detail"]
    assert detail["field"] == field and message in detail["message"], detail
    assert client.get(f"/api/v1/cells/{cell}/tasks", headers=auth(tokens["technician"])).json() == []
