"""Text that can be stored can be read (issue 22, case 1): a lone surrogate (JSON's "\\ud800",
valid JSON, not text), a NUL, or a name longer than a file name may be, anywhere in a request
(a model's name, a key of its targets, a cell's name, an import's ``name=``), is a 422 naming the
field, and nothing is stored: a PATCH that answered 500 kept the model, after which GET /cells,
/cells/{id} and /overview answered 500 for every role. The bodies are sent as raw JSON text,
the escape as a client would write it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from calibration.robots import nominal_document
from service.api.app import create_app

from .conftest import auth


@pytest.fixture
def client(settings, tokens):
    with TestClient(create_app(settings)) as c:
        yield c


def _model_text(name: str = "ur5e-cell", target_key: str = "smr") -> str:
    """A recal.model/1 document as JSON text, with ``name`` and one target key written verbatim
    (an escape such as \\ud800 stays an escape)."""
    doc = nominal_document("ur5e")
    doc["name"] = "@NAME@"
    doc["targets"] = {"@KEY@": [0, 0, 50]}
    return json.dumps(doc).replace('"@NAME@"', f'"{name}"').replace('"@KEY@"', f'"{target_key}"')


def _post_json(client, method, url, text, token):
    return client.request(
        method, url, content=text.encode(), headers={**auth(token), "content-type": "application/json"}
    )


def _ok_cell(client, tokens) -> int:
    r = _post_json(client, "POST", "/api/v1/cells", f'{{"name": "c1", "model": {_model_text()}}}', tokens["technician"])
    assert r.status_code == 201, r.text
    return r.json()["id"]


@pytest.mark.parametrize(
    "name,key,field",
    [
        ("ur\\ud800x", "smr", "body.model.name"),
        ("ur5e", "s\\udc00mr", "body.model.targets"),
        ("ur\\u0000x", "smr", "body.model.name"),
    ],
    ids=["surrogate-name", "surrogate-key", "nul"],
)
def test_a_patch_that_cannot_be_stored_is_refused_and_stores_nothing(client, tokens, name, key, field):
    cell = _ok_cell(client, tokens)
    before = client.get(f"/api/v1/cells/{cell}", headers=auth(tokens["viewer"])).json()
    r = _post_json(
        client, "PATCH", f"/api/v1/cells/{cell}", f'{{"model": {_model_text(name, key)}}}', tokens["technician"]
    )
    assert r.status_code == 422, r.text
    assert r.json()["errors"][0]["field"].startswith(field), r.text
    # nothing changed, and every read still answers, for every role
    for role in ("viewer", "technician", "admin"):
        assert client.get(f"/api/v1/cells/{cell}", headers=auth(tokens[role])).json() == before
        assert client.get("/api/v1/cells", headers=auth(tokens[role])).status_code == 200
        assert client.get("/api/v1/overview", headers=auth(tokens[role])).status_code == 200


def test_a_new_cell_with_a_surrogate_in_a_target_key_or_its_name_is_refused(client, tokens):
    r = _post_json(
        client,
        "POST",
        "/api/v1/cells",
        '{"name": "c2", "model": ' + _model_text("ur5e", "a\\ud800") + "}",
        tokens["admin"],
    )
    assert r.status_code == 422 and "unpaired surrogate" in r.text, r.text
    r = _post_json(
        client, "POST", "/api/v1/cells", f'{{"name": "c\\ud83d", "model": {_model_text()}}}', tokens["admin"]
    )
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "body.name", r.text
    assert client.get("/api/v1/cells", headers=auth(tokens["viewer"])).json() == []
    # a paired surrogate is a character like any other (JSON's way of writing U+1F600)
    r = _post_json(
        client, "POST", "/api/v1/cells", f'{{"name": "c\\ud83d\\ude00", "model": {_model_text()}}}', tokens["admin"]
    )
    assert r.status_code == 201, r.text


def test_an_overlong_import_name_is_a_422_naming_it(client, tokens):
    cell = _ok_cell(client, tokens)
    r = client.post(
        f"/api/v1/cells/{cell}/measurements?kind=pose&name={'n' * 10_000}.csv",
        content=b"q1,q2,q3,q4,q5,q6,x,y,z\n",
        headers=auth(tokens["technician"]),
    )
    assert r.status_code == 422, r.text
    assert r.json()["errors"][0]["field"] == "query.name" and "at most 255 characters" in r.text, r.text


def test_recal_export_on_a_model_file_with_a_surrogate_is_one_line(tmp_path):
    (tmp_path / "m.json").write_text(_model_text("ur\\ud800x"))
    recal = Path(sys.executable).with_name("recal")
    p = subprocess.run(
        [str(recal), "export", "--model", "m.json", "--format", "dh-csv", "--out", "m.csv"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert "m.json: field 'name': expected text (UTF-8)" in p.stderr and "U+D800" in p.stderr, p.stderr
    assert not (tmp_path / "m.csv").exists()
