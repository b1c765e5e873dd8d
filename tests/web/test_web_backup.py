"""The result page takes a zipped controller backup and gives one back (issue 24), in a real
(headless) browser against the real service: an ABB backup (RAPID/TASK1/PROGMOD with the
program, SYSMOD with its tooldata, another file) uploaded, the zip of the same layout downloaded,
its program compensated, the other files as they were, the report beside them."""

from __future__ import annotations

import dataclasses
import io
import json
import re
import zipfile

import numpy as np
import pytest

pytestmark = pytest.mark.slow

NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
MOD = (
    "MODULE job\r\n  PROC main()\r\n"
    "    MoveAbsJ [[10,-80,90,-100,70,20],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]], v1000, fine, tGripper;\r\n"
    "  ENDPROC\r\nENDMODULE\r\n"
)
SYS = "MODULE user(SYSMODULE)\n  PERS tooldata tGripper:=[TRUE,[[0,0,200],[1,0,0,0]],[1,[0,0,50],[1,0,0,0],0,0,0]];\nENDMODULE\n"
INFO = b"[BACKUP]\r\nSYSTEM=recal-test\r\n"


@pytest.fixture
def calibrated(tmp_path, browser, web):
    from calibration.model import model_to_dict
    from calibration.robots import nominal
    from calibration.simulate import perturbed, random_configurations, simulate_measurements
    from service.client import Api

    with web.service_with_technician(tmp_path) as (url, token, engine, settings):
        nom = dataclasses.replace(nominal("ur10e"), targets={"smr": np.array([0.0, 0.0, 0.05])})
        cell_id = Api(url, token).call(
            "POST", "/cells", {"name": "abb-like", "model": model_to_dict(nom), "devices": {}}
        )["id"]
        rng = np.random.default_rng(5)
        truth = dataclasses.replace(perturbed(nom, rng), base=np.array([1.5, -0.4, 0.2, 0, 0, 1.0]))
        data = simulate_measurements(truth, random_configurations(nom, 40, rng), rng, targets=("smr",))
        yield url, token, web.store_finished_pose_session(engine, settings, cell_id, data, {"method": "random"})


def test_a_zipped_backup_goes_in_and_comes_back_from_the_page(page, calibrated, tmp_path, web):
    url, token, calibration_id = calibrated
    src = tmp_path / "cell7.zip"
    with zipfile.ZipFile(src, "w") as zf:
        zf.writestr("RAPID/TASK1/PROGMOD/job.mod", MOD)
        zf.writestr("RAPID/TASK1/SYSMOD/user.sys", SYS)
        zf.writestr("BACKINFO/backinfo.txt", INFO)
    web.sign_in_at(page, url, token)
    page.goto(f"{url}/#/calibrations/{calibration_id}")
    page.wait_for_selector("#backup-file")
    page.set_input_files("#backup-file", str(src))
    page.click("#compensate-backup")
    banner = page.wait_for_selector("#backup-compensated", timeout=60_000).inner_text()
    assert "Every target was compensated" in banner, banner
    with page.expect_download() as dl:
        page.click("#download-backup")
    assert dl.value.suggested_filename == "cell7-compensated.zip"
    out = tmp_path / "out.zip"
    dl.value.save_as(out)
    z = zipfile.ZipFile(io.BytesIO(out.read_bytes()))
    assert z.namelist() == [
        "RAPID/TASK1/PROGMOD/job.mod",
        "RAPID/TASK1/SYSMOD/user.sys",
        "BACKINFO/backinfo.txt",
        "recal-compensation-report.json",
    ]
    assert z.read("BACKINFO/backinfo.txt") == INFO and z.read("RAPID/TASK1/SYSMOD/user.sys").decode() == SYS
    job = z.read("RAPID/TASK1/PROGMOD/job.mod").decode()
    assert job != MOD and NUMBER.sub("#", job) == NUMBER.sub("#", MOD)
    assert json.loads(z.read("recal-compensation-report.json"))["layout"] == "abb"
    page.evaluate("document.querySelector('#backup-compensated').closest('.card').scrollIntoView()")
    web.shot(page, "63-backup-compensated", full_page=False)
