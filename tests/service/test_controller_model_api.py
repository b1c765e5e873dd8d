"""The cell's copy of its UR controller's own kinematics (issue 16): uploaded and read through
the API, used by compensation; over Modbus, a session's start checks it against UR's TCP-pose
registers (our driver and pymodbus' server, the simulated controller's Modbus side, on
NET.70 with a free port)."""

from __future__ import annotations

import os

import numpy as np
import pytest
from sqlmodel import Session, select

from calibration.controller import fit_controller_model
from calibration.kinematics import fk
from calibration.model import model_from_dict, model_to_dict
from calibration.robots import nominal
from drivers.modbus_robot import UR_REGISTER_MAP_HIRES, ModbusRobot, ModbusRobotConfig
from fakes.modbus_server import ModbusRobotFake
from fakes.world import SimCell, draw_factory_calibration
from service.controller import refresh_on_session_start
from service.models import Cell, RunSession
from service.store import add_controller_model, current_controller_model, make_engine
from service.stored_compensation import compensate_text

from .conftest import auth, register_cell

NET = os.environ.get("RECAL_TEST_NET", "127.0.0")
SCRIPT = """def task():
  movel(p[0.600, -0.200, 0.400, 0.0, 3.1416, 0.0], a=1.2, v=0.25)
  movel(p[0.650, -0.150, 0.350, 0.0, 3.1416, 0.0], a=1.2, v=0.25)
end
"""


def controller_doc(robot: str, seed: int) -> dict:
    """What `recal controller-model` writes for a controller with factory calibration ``seed``."""
    model = draw_factory_calibration(robot, seed).model()
    q = np.random.default_rng(seed).uniform(-np.pi, np.pi, (24, 6))
    fit = fit_controller_model(q, fk(model, q), nominal(robot))
    return {**model_to_dict(fit.model), "controller": {"source": "test", "check": {"position_max_um": 1e-7}}}


@pytest.fixture
def calibrated(idle_app, tokens, stored_session):
    with idle_app() as client:
        cell = register_cell(client, tokens["technician"], "ur-cell")
        yield client, cell, stored_session(cell["id"], seed=2)[1]


def test_uploaded_controller_model_is_versioned_and_used_by_compensation(calibrated, tokens):
    client, cell, cal = calibrated
    url = f"/api/v1/cells/{cell['id']}/controller-model"
    r = client.get(url, headers=auth(tokens["viewer"]))
    assert r.status_code == 404 and "no controller model" in r.text
    compensate = f"/api/v1/calibrations/{cal}/compensate?name=task.script"
    before = client.post(compensate, content=SCRIPT, headers=auth(tokens["job"]))
    assert before.status_code == 200, before.text

    doc = controller_doc("ur10e", 3)
    r = client.put(url, json=doc, headers=auth(tokens["technician"]))
    assert r.status_code == 200, r.text
    assert r.json()["version"] == 1 and r.json()["moved_mm"] is None
    r = client.put(url, json=controller_doc("ur10e", 4), headers=auth(tokens["technician"]))
    assert r.json()["version"] == 2 and r.json()["moved_mm"] > 0.1
    got = client.get(url, headers=auth(tokens["viewer"])).json()
    assert got["version"] == 2 and [h["version"] for h in got["history"]] == [2, 1]
    summary = client.get(f"/api/v1/cells/{cell['id']}/summary", headers=auth(tokens["viewer"])).json()
    assert summary["controller_model"]["version"] == 2

    # compensation now goes through the controller's model (version 2), not the cell's nominal
    after = client.post(compensate, content=SCRIPT, headers=auth(tokens["job"]))
    assert after.status_code == 200, after.text
    cal_doc = client.get(f"/api/v1/calibrations/{cal}", headers=auth(tokens["viewer"])).json()["model"]
    expected, _ = compensate_text(SCRIPT, name="task.script", model_doc=cal_doc, nominal_doc=got["model"])
    assert after.text == expected and after.text != before.text


@pytest.mark.parametrize(
    "body, field",
    [
        ({"format": "recal.model/1"}, "body.units"),
        ("nominal", "body.controller"),
    ],
)
def test_a_bad_upload_names_the_field(calibrated, tokens, body, field):
    client, cell, _ = calibrated
    if body == "nominal":
        from calibration.robots import nominal_document

        body = nominal_document("ur10e")
    r = client.put(f"/api/v1/cells/{cell['id']}/controller-model", json=body, headers=auth(tokens["technician"]))
    assert r.status_code == 422 and r.json()["detail"]["field"] == field, r.text
    assert (
        client.put(
            f"/api/v1/cells/{cell['id']}/controller-model",
            json=controller_doc("ur10e", 1),
            headers=auth(tokens["viewer"]),
        ).status_code
        == 403
    )


@pytest.fixture
def modbus_controller():
    """The simulated controller's Modbus server (factory calibration seed 4: 2 mm from the
    published table at its joints), in this process."""
    import dataclasses

    truth = dataclasses.replace(nominal("ur10e"), base=np.array([1.5, -0.3, 0.2, 0.0, 0.0, 0.5]))
    cell = SimCell(
        truth, factory=draw_factory_calibration("ur10e", 4), q_home=np.array([0.3, -1.2, 1.4, -1.6, -1.5, 0.2])
    )
    fake = ModbusRobotFake(cell, host=f"{NET}.70", port=0)
    fake.start()
    host, port = fake.endpoint()["modbus"].rsplit(":", 1)
    # the motion program's microradian joints (160-171): the check is then as tight as the TCP registers
    robot = ModbusRobot(ModbusRobotConfig(host=host, port=int(port), register_map=UR_REGISTER_MAP_HIRES))
    yield robot
    robot.close()
    fake.stop()


@pytest.mark.parametrize("stored, warns", [("factory", False), ("published", True)])
def test_over_modbus_a_session_checks_the_stored_model_against_the_tcp_registers(
    settings, tokens, modbus_controller, stored, warns
):
    from calibration.robots import nominal_document

    engine = make_engine(settings.effective_database_url)
    with Session(engine) as db:
        cell = Cell(name="m", model=nominal_document("ur10e"), devices={})
        db.add(cell)
        db.commit()
        run = RunSession(cell_id=cell.id, kind="verify")
        db.add(run)
        db.commit()
        doc = controller_doc("ur10e", 4) if stored == "factory" else {**nominal_document("ur10e"), "controller": {}}
        add_controller_model(db, cell_id=cell.id, model=doc)
        info = refresh_on_session_start(db, run, cell, modbus_controller)
        assert info["version"] == 1 and db.get(RunSession, run.id).controller().to_json() == info
        if warns:  # the published table is 2 mm from what this controller computes there
            assert info["changed"] is True and "TCP-pose registers disagree" in info["warning"]
            assert info["tcp_registers_mm"] > 1.5
        else:  # within the registers' resolution (0.1 mm, 1 mrad)
            assert info["warning"] is None and info["tcp_registers_mm"] < 0.1 and info["tolerance_mm"] < 0.25
    engine.dispose()


def test_over_modbus_a_changed_controller_is_fitted_again_from_the_tcp_registers(settings, tokens, modbus_controller):
    """The stored model (the published table) disagrees with the TCP-pose registers at the
    session's start; the registers read at the session's configurations (microradian joints) give
    a new version, within tens of micrometres of what the controller computes there, and the audit
    log says the model changed."""
    from calibration.robots import nominal_document
    from service.controller import learn_from_registers
    from service.models import AuditEntry

    engine = make_engine(settings.effective_database_url)
    robot = modbus_controller
    with Session(engine) as db:
        cell = Cell(name="m", model=nominal_document("ur10e"), devices={})
        db.add(cell)
        db.commit()
        run = RunSession(cell_id=cell.id, kind="pose")
        db.add(run)
        db.commit()
        add_controller_model(db, cell_id=cell.id, model={**nominal_document("ur10e"), "controller": {}})
        assert refresh_on_session_start(db, run, cell, robot)["changed"] is True
        q_plan = np.array([0.3, -1.2, 1.4, -1.6, -1.5, 0.2]) + np.random.default_rng(6).uniform(-0.8, 0.8, (20, 6))
        samples = []
        for q in q_plan:  # what the session loop reads where the robot stands
            robot.move_joints(q, speed_rad_s=1.0, accel_rad_s2=2.0)
            samples.append((robot.read_joints(), robot.read_tcp_pose()))
        info = learn_from_registers(db, run, cell, robot, samples)
        assert info["version"] == 2 and info["changed"] is True and info["from_registers"] is True, info
        assert "TCP-pose registers disagree" in info["warning"] and info["moved_mm"] > 1.0
        stored = current_controller_model(db, cell.id)
        assert stored.version == 2 and stored.session_id == run.id
        assert db.exec(select(AuditEntry).where(AuditEntry.action == "controller model changed")).first() is not None
        # what the controller computes near the session's configurations
        q = q_plan[:, None, :] + np.random.default_rng(7).uniform(-0.05, 0.05, (20, 5, 6))
        q = q.reshape(-1, 6)
        truth = fk(draw_factory_calibration("ur10e", 4).model(), q)[:, :3, 3]
        fitted = fk(model_from_dict(stored.model), q)[:, :3, 3]
        published = fk(nominal("ur10e"), q)[:, :3, 3]
        err = np.linalg.norm(fitted - truth, axis=1)
        assert np.sqrt(np.mean(err**2)) < 60e-6 and err.max() < 0.15e-3, (np.sqrt(np.mean(err**2)), err.max())
        assert np.linalg.norm(published - truth, axis=1).max() > 1e-3
    engine.dispose()


def test_registers_with_a_tcp_offset_are_refused():
    """A TCP offset would hide in the fitted flange: registers 10 cm from the published table are
    refused with one line, nothing fitted."""
    import dataclasses

    from service.controller import ControllerModelError, model_from_registers

    controller = draw_factory_calibration("ur5e", 2).model()
    tool = dataclasses.replace(controller, tool=np.array([0.0, 0.0, 0.1, 0.0, 0.0, 0.0]))
    q = np.random.default_rng(1).uniform(-np.pi, np.pi, (20, 6))
    kw = {"source": "test", "joint_step_rad": 1e-6}
    assert model_from_registers(q, fk(controller, q), nominal("ur5e"), **kw)["controller"]["poses_fit"] == 20
    with pytest.raises(ControllerModelError, match=r"TCP offset is not zero .*nothing stored") as exc:
        model_from_registers(q, fk(tool, q), nominal("ur5e"), **kw)
    assert "\n" not in str(exc.value) and "100 mm" in str(exc.value)
    with pytest.raises(ControllerModelError, match="at least 12"):
        model_from_registers(q[:8], fk(controller, q[:8]), nominal("ur5e"), **kw)
