"""The API reads CSV with the CLI's reader (issue 22, case 3): a lone carriage return between LF
lines was a 500 on /compensate and on the measurement import; it is a 422 naming the line, and
nothing is stored."""

from __future__ import annotations

from .conftest import auth

BAD = b"q1,q2,q3,q4,q5,q6\n0,-80,90,0,90,0\r10,-80,90,0,90,0\n"


def test_compensate_answers_a_bare_cr_with_422_naming_the_line(calibrated, tokens):
    client, _cell, cal = calibrated
    r = client.post(
        f"/api/v1/calibrations/{cal}/compensate?name=t.csv", content=BAD, headers=auth(tokens["technician"])
    )
    assert r.status_code == 422, r.text
    assert "line 2" in r.text and "carriage return (CR) alone" in r.text, r.text


def test_a_measurement_import_with_a_bare_cr_is_refused_and_stores_nothing(calibrated, tokens):
    client, cell, _ = calibrated
    before = client.get(f"/api/v1/cells/{cell}/sessions", headers=auth(tokens["viewer"])).json()
    body = b"q1,q2,q3,q4,q5,q6,x,y,z\n0,-80,90,0,90,0,1,2,3\r10,-80,90,0,90,0,1,2,3\n"
    r = client.post(f"/api/v1/cells/{cell}/measurements?kind=pose", content=body, headers=auth(tokens["technician"]))
    assert r.status_code == 422, r.text
    assert "line 2" in r.text and "carriage return (CR) alone" in r.text, r.text
    assert client.get(f"/api/v1/cells/{cell}/sessions", headers=auth(tokens["viewer"])).json() == before


def test_a_task_file_with_a_bare_cr_is_refused_at_registration(calibrated, tokens):
    client, cell, _ = calibrated
    r = client.post(
        f"/api/v1/cells/{cell}/tasks",
        json={"name": "t.csv", "content": BAD.decode()},
        headers=auth(tokens["technician"]),
    )
    assert r.status_code == 422, r.text
    assert "carriage return (CR) alone" in r.text, r.text
