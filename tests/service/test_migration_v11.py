"""Schema version 11 on a store made by version 10: a calibration's parameter covariance is
stored once, in the model's ``identification.covariance``; the copy in ``calibration.covariance``
(another shape) goes, what only it had (the held parameters' relations) joining the block, so
that an old calibration still serves as the next session's prior and is read as before."""

from __future__ import annotations

import json

import numpy as np
from sqlalchemy import inspect, text
from sqlmodel import Session

from service.kinds.pose import stored_covariance
from service.models import Calibration
from service.store import SCHEMA_VERSION, make_engine, migrate

NAMES = ["base.tx", "j2.theta"]
MATRIX = [[4e-10, 1e-12], [1e-12, 9e-10]]
BLOCK_COV = {"units": "SI (m, rad; gains 1)", "names": NAMES, "kinds": ["length", "angle"], "matrix": MATRIX}
HELD = {"tool.rz": [["j6.theta", 1.0]]}


def test_version_10_store_is_upgraded(database_url):
    engine = make_engine(database_url)
    migrate(engine)
    copy = {"names": NAMES, "kinds": ["length", "angle"], "matrix": MATRIX}
    calibrations = [  # (its model document, its calibration.covariance of version 10)
        (
            {"name": "a", "identification": {"rows": 40, "covariance": {**BLOCK_COV, "model_error_scale": 1.2}}},
            {**copy, "held": HELD},
        ),
        ({"name": "b", "identification": {"rows": 40, "covariance": BLOCK_COV}}, {**copy, "held": {}}),
        ({"name": "c"}, {**copy, "held": {}}),  # a model without the block's covariance: given the copy's
        ({"name": "d"}, None),  # a circle or joint calibration: none
    ]
    with engine.begin() as conn:  # back to what version 10 made
        conn.execute(text("ALTER TABLE calibration ADD COLUMN covariance JSON"))
        conn.execute(text("UPDATE schema_version SET version = 10"))
        conn.execute(
            text(
                "INSERT INTO cell (name, site, model, devices, created_at, model_version) "
                "VALUES ('c', 'default', '{}', '{}', CURRENT_TIMESTAMP, 1)"
            )
        )
        for model, cov in calibrations:
            conn.execute(
                text(
                    "INSERT INTO calibration (cell_id, kind, model, report, covariance, created_at, nominal_version) "
                    "VALUES (1, 'pose', :model, '{}', :cov, CURRENT_TIMESTAMP, 1)"
                ),
                {"model": json.dumps(model), "cov": None if cov is None else json.dumps(cov)},
            )
    assert migrate(engine) == SCHEMA_VERSION >= 11
    assert "covariance" not in {c["name"] for c in inspect(engine).get_columns("calibration")}
    with Session(engine) as db:
        a, b, c, d = (db.get(Calibration, i) for i in (1, 2, 3, 4))
        assert a.model["identification"]["covariance"] == {
            **BLOCK_COV,
            "model_error_scale": 1.2,
            "held_relations": HELD,
        }
        assert a.model["identification"]["rows"] == 40 and a.model["name"] == "a"
        assert b.model == calibrations[1][0]  # nothing to add: unchanged
        assert c.model["identification"]["covariance"] == BLOCK_COV
        assert d.model == {"name": "d"}
        names, kinds, matrix, held = stored_covariance(a)
        assert names == tuple(NAMES) and kinds == ["length", "angle"] and np.array_equal(matrix, MATRIX)
        assert held == {"tool.rz": (("j6.theta", 1.0),)}
        assert stored_covariance(b)[3] == {} and stored_covariance(c)[0] == tuple(NAMES)
        assert stored_covariance(d) is None
    assert migrate(engine) == SCHEMA_VERSION  # idempotent
    engine.dispose()
