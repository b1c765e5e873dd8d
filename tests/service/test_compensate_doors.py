"""One compensation, whatever the door (issue 27): ``recal compensate`` and the API's compensation
route give the same bytes for the same identified model, task and UR controller model; the CLI
takes the controller model from ``--nominal`` or from the calibration's ``identification.controller``
(what the service records for a cell that keeps one), and without either warns in one line,
naming the published table it assumes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibration.controller import fit_controller_model
from calibration.kinematics import fk
from calibration.model import model_to_dict
from calibration.robots import nominal
from fakes.world import draw_factory_calibration
from service.cli import main as recal

from .conftest import auth

SCRIPT = """def task():
  movel(p[0.600, -0.200, 0.400, 0.0, 3.1416, 0.0], a=1.2, v=0.25)
  movej(p[0.550, -0.250, 0.450, 0.0, 3.1416, 0.0], a=1.2, v=0.25)
  movel(p[0.650, -0.150, 0.350, 0.0, 3.1416, 0.0], a=1.2, v=0.25)
end
"""
TASK_CSV = "x,y,z,qw,qx,qy,qz\n600,-200,400,0,1,0,0\n650,-150,350,0,1,0,0\n"  # the cell's units: mm


def controller_doc(seed: int) -> dict:
    """What `recal controller-model` writes for a UR10e whose factory calibration is ``seed``."""
    model = draw_factory_calibration("ur10e", seed).model()
    q = np.random.default_rng(seed).uniform(-np.pi, np.pi, (24, 6))
    fit = fit_controller_model(q, fk(model, q), nominal("ur10e"))
    return {**model_to_dict(fit.model), "controller": {"source": "test", "check": {"position_max_um": 1e-7}}}


@pytest.fixture
def doors(calibrated, tokens, tmp_path):
    """The API's answers for SCRIPT (URScript) and TASK_CSV (targets mode) once the cell keeps its
    controller's model, and the files the CLI is given: the calibration's model, the controller's."""
    client, cell, cal = calibrated
    r = client.put(f"/api/v1/cells/{cell}/controller-model", json=controller_doc(5), headers=auth(tokens["technician"]))
    assert r.status_code == 200, r.text
    ctrl = client.get(f"/api/v1/cells/{cell}/controller-model", headers=auth(tokens["viewer"])).json()["model"]
    model = client.get(f"/api/v1/calibrations/{cal}", headers=auth(tokens["viewer"])).json()["model"]
    api = {}
    for name, body, mode in (("task.script", SCRIPT, "joints"), ("task.csv", TASK_CSV, "targets")):
        r = client.post(
            f"/api/v1/calibrations/{cal}/compensate?name={name}&mode={mode}", content=body, headers=auth(tokens["job"])
        )
        assert r.status_code == 200, r.text
        api[name] = r.content
        (tmp_path / name).write_text(body)
    (tmp_path / "model.json").write_text(json.dumps(model))
    (tmp_path / "controller.json").write_text(json.dumps(ctrl))
    return tmp_path, api, model, ctrl


def _cli(d, model_file, name, *extra):
    mode = ["--mode", "targets"] if name.endswith(".csv") else []
    out = d / f"out-{model_file}-{name}"
    code = recal(
        ["compensate", "--model", str(d / model_file), "--task", str(d / name), "--out", str(out), *mode, *extra]
    )
    assert code == 0
    return out.read_bytes()


@pytest.mark.parametrize("name", ["task.script", "task.csv"])
def test_the_cli_with_the_controller_model_gives_the_apis_bytes(doors, capsys, name):
    d, api, _, _ = doors
    assert _cli(d, "model.json", name, "--nominal", str(d / "controller.json")) == api[name]
    assert "warning" not in capsys.readouterr().err


@pytest.mark.parametrize("name", ["task.script", "task.csv"])
def test_a_calibration_that_records_the_controller_model_needs_no_nominal(doors, capsys, name):
    d, api, model, ctrl = doors
    (d / "with-controller.json").write_text(
        json.dumps({**model, "identification": {**model["identification"], "controller": ctrl}})
    )
    assert _cli(d, "with-controller.json", name) == api[name]
    assert "warning" not in capsys.readouterr().err


def test_without_a_controller_model_the_published_table_is_named(doors, capsys):
    d, api, model, _ = doors
    out = _cli(d, "model.json", "task.script")  # the calibration predates the controller model: none recorded
    err = capsys.readouterr().err.splitlines()
    warned = [line for line in err if line.startswith("warning:")]
    assert len(warned) == 1 and "no controller model" in warned[0], err
    table = model["identification"]["nominal"]["name"]
    assert f"against {table} (identification.nominal), UR's published DH table of the ur10e" in warned[0]
    assert "--nominal CONTROLLER.json" in warned[0]
    assert out != api["task.script"]  # the published table is not what the controller computes with
