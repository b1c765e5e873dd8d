"""The identification's report is made once per calibration (issue 23): the model file's
``identification`` block is cut from the report the CLI and the service make anyway, and it is
the same block as one made from the result alone."""

from __future__ import annotations

import json

import numpy as np

from calibration.identify import identify
from calibration.model import Units
from calibration.report import identification_block, identification_report
from calibration.robots import nominal
from calibration.simulate import perturbed, random_configurations, simulate_measurements


def test_the_block_cut_from_a_given_report_is_the_block_made_from_the_result():
    rng = np.random.default_rng(11)
    nom = nominal("ur5e")
    truth = perturbed(nom, rng)
    data = simulate_measurements(truth, random_configurations(nom, 60, rng), rng)
    result = identify(nom, data)
    units = Units("mm", "deg")
    report = identification_report(result, units, data_rows=np.arange(len(data)) + 7)
    given = identification_block(result, units, nominal=nom, q=data.q, report=report)
    made = identification_block(result, units, nominal=nom, q=data.q)
    assert json.dumps(given, sort_keys=True) == json.dumps(made, sort_keys=True)
    assert given["parameters"] is report["parameters"]  # cut from it, not made again
