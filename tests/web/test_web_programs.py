"""The compensate form of the result page takes ABB RAPID, Fanuc TP and KUKA KRL programs, in a
real (headless) browser against the real service, and hands them back byte for byte but the
targets' numbers, a program in Windows-1252 (as KUKA's and ABB's editors write them) included.
The calibration is a stored pose session of an ABB IRB 4600, analysed as the session loop
analyses one (no cell process needed)."""

from __future__ import annotations

import dataclasses
import re
import urllib.request

import numpy as np
import pytest

pytestmark = pytest.mark.slow

NUMBER = re.compile(rb"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")


def skeleton(data: bytes) -> bytes:
    """The file with every number replaced by ``#``: what must not change at all."""
    return NUMBER.sub(b"#", data)


@pytest.fixture
def abb_result(tmp_path, browser, web):
    from calibration.model import model_to_dict
    from calibration.robots import nominal
    from calibration.simulate import perturbed, random_configurations, simulate_measurements
    from service.client import Api

    with web.service_with_technician(tmp_path) as (url, token, engine, settings):
        nom = dataclasses.replace(nominal("irb4600"), targets={"smr": np.array([0.0, 0.0, 0.05])})
        cell_id = Api(url, token).call(
            "POST", "/cells", {"name": "welding", "model": model_to_dict(nom), "devices": {}}
        )["id"]
        rng = np.random.default_rng(5)
        truth = dataclasses.replace(perturbed(nom, rng), base=np.array([1.5, -0.4, 0.2, 0, 0, 1.0]))
        data = simulate_measurements(truth, random_configurations(nom, 60, rng), rng, targets=("smr",))
        calibration_id = web.store_finished_pose_session(engine, settings, cell_id, data, {"method": "random"})
        yield url, token, calibration_id


RAPID = (
    "MODULE Weld\r\n  ! Schweißnaht an der Düse (Latin-1, not UTF-8)\r\n"
    "  CONST jointtarget jHome:=[[0,-10,20,0,60,0],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]];\r\n"
    "  PROC main()\r\n    MoveAbsJ jHome\\NoEOffs, v1000, fine, tool0;\r\n"
    "    MoveAbsJ [[10,-20,30,40,50,60],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]], v1000, fine, tool0;\r\n"
    "  ENDPROC\r\nENDMODULE\r\n"
).encode("latin-1")
TP = (
    "/PROG  PICK\r\n/MN\r\n   1:J P[1] 100% FINE    ;\r\n   2:  ! J1= 1.000 deg ;\r\n/POS\r\nP[1]{\r\n   GP1:\r\n"
    "\tUF : 0, UT : 0,\r\n\tJ1=    10.000 deg,\tJ2=    20.000 deg,\tJ3=   -10.000 deg,\r\n"
    "\tJ4=   -40.000 deg,\tJ5=    60.000 deg,\tJ6=    70.000 deg\r\n};\r\n/END\r\n"
).encode("ascii")
SRC = "DEF job( )\n; Greifer geöffnet, 90° gedreht\nPTP XHOME\nEND\n".encode("cp1252")
DAT = (
    "DEFDAT job\r\nDECL E6AXIS XHOME={A1 10.0,A2 -20.0,A3 30.0,A4 -40.0,A5 50.0,A6 20.0,E1 0.0} ; Übergabe – Lage ±0,5\r\n"
    "ENDDAT\r\n"
).encode("cp1252")


def test_programs_of_each_brand_compensated_from_the_page(page, abb_result, tmp_path, web):
    url, token, calibration_id = abb_result
    web.sign_in_at(page, url, token)
    page.goto(f"{url}/#/calibrations/{calibration_id}")
    page.wait_for_selector("#task-file")

    def download(button: str):
        with page.expect_download() as dl:
            page.click(button)
        (tmp_path / "out").mkdir(exist_ok=True)
        path = tmp_path / "out" / dl.value.suggested_filename
        dl.value.save_as(path)
        return path

    def compensate(*names: str, banner: str):
        page.set_input_files("#task-file", [str(tmp_path / n) for n in names])
        page.click("#compensate")
        page.wait_for_selector(f"#compensated:has-text('{banner}')", timeout=30_000)

    (tmp_path / "weld.mod").write_bytes(RAPID)
    compensate("weld.mod", banner="weld-compensated.mod")
    assert "2 point(s), 2 converged" in page.inner_text("#compensated")
    out = download("#download-compensated")
    assert out.name == "weld-compensated.mod"
    data = out.read_bytes()
    assert data != RAPID and skeleton(data) == skeleton(RAPID)
    assert b"! Schwei\xdfnaht an der D\xfcse" in data  # the Latin-1 bytes as they were
    # the stored compensation (the store's first) is served again as the bytes the page saved
    req = urllib.request.Request(f"{url}/api/v1/compensations/1", headers={"Authorization": f"Bearer {token}"})
    with urllib.request.urlopen(req, timeout=30) as stored:
        assert stored.headers["Content-Type"] == "text/plain; charset=iso-8859-1" and stored.read() == data

    (tmp_path / "pick.ls").write_bytes(TP)
    compensate("pick.ls", banner="pick-compensated.ls")
    data = download("#download-compensated").read_bytes()
    assert data != TP and skeleton(data) == skeleton(TP) and data.split(b"/POS")[0] == TP.split(b"/POS")[0]

    (tmp_path / "job.src").write_bytes(SRC)
    (tmp_path / "job.dat").write_bytes(DAT)
    compensate("job.src", "job.dat", banner="job-compensated.src")
    assert download("#download-compensated").read_bytes() == SRC  # no target's number in it
    data = download("#download-compensated-1").read_bytes()
    assert data != DAT and skeleton(data) == skeleton(DAT)
    assert b"; \xdcbergabe \x96 Lage \xb10,5\r\n" in data  # Windows-1252 bytes as they were
