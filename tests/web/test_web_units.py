"""Plain figures on the page (issue 27): lengths far below what any instrument measures are said
as such ("below 0.0001 mm", "exactly (to within 0.1 µm)"), never as 2.69e-7 mm or 3.6e-7 µm."""

from __future__ import annotations

import dataclasses
import re

import numpy as np

URSCRIPT = """def pick():
  movel(p[0.600, -0.200, 0.400, 0.0, 3.1416, 0.0], a=1.2, v=0.25)
  movel(p[0.650, -0.150, 0.350, 0.0, 3.1416, 0.0], a=1.2, v=0.25)
end
"""
EXPONENT = re.compile(r"\de[-+]?\d")


def test_tiny_lengths_are_said_in_words_not_exponents(page, web, tmp_path):
    from calibration.controller import fit_controller_model
    from calibration.kinematics import fk
    from calibration.model import model_to_dict
    from calibration.robots import nominal
    from calibration.simulate import perturbed, random_configurations, simulate_measurements
    from fakes.world import draw_factory_calibration
    from service.client import Api

    with web.service_with_technician(tmp_path) as (url, token, engine, settings):
        api = Api(url, token)
        nom = dataclasses.replace(nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
        cell_id = api.call("POST", "/cells", {"name": "ur", "model": model_to_dict(nom), "devices": {}})["id"]
        # the controller's model, fitted exactly: it reproduces the controller to 3.6e-7 µm (rounding)
        factory = draw_factory_calibration("ur10e", 5).model()
        q = np.random.default_rng(5).uniform(-np.pi, np.pi, (24, 6))
        ctrl = model_to_dict(fit_controller_model(q, fk(factory, q), nominal("ur10e")).model)
        ctrl["controller"] = {"source": "test", "check": {"position_max_um": 3.6e-7}}
        api.call("PUT", f"/cells/{cell_id}/controller-model", ctrl)
        rng = np.random.default_rng(3)
        truth = dataclasses.replace(perturbed(nom, rng), base=np.array([1.5, -0.4, 0.2, 0, 0, 1.0]))
        data = simulate_measurements(truth, random_configurations(nom, 40, rng), rng, targets=("smr",))
        calibration_id = web.store_finished_pose_session(engine, settings, cell_id, data, {"method": "random"})

        web.sign_in_at(page, url, token)
        page.goto(f"{url}/#/cells/{cell_id}")
        said = page.locator("dt:has-text('Reproduces the controller') + dd")
        said.wait_for()
        assert said.inner_text() == "exactly (to within 0.1 µm)"

        page.goto(f"{url}/#/calibrations/{calibration_id}")
        prog = tmp_path / "pick.script"
        prog.write_text(URSCRIPT)
        page.wait_for_selector("#task-file")
        page.set_input_files("#task-file", str(prog))
        page.click("#compensate")
        page.wait_for_selector("#compensated", timeout=30_000)
        said = page.locator("p", has_text="Largest remaining error").inner_text()
        assert not EXPONENT.search(said), said
        assert "Largest remaining error below 0.0001 mm" in said, said
