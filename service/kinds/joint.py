"""``joint``: each chosen joint swept over its allowed range with a reference encoder (or
resolver) on it; per joint, the reference reading against the controller's, fitted with book
eq. 2.4 ``θ = k1·q + k2 + k3·sin(k4·q + k5)``; gains and eccentricity harmonics stored as a
calibration of kind ``joint``."""

from __future__ import annotations

import dataclasses

import numpy as np

from calibration.geometry import fit_joint_harmonic

from .. import records
from ..analysis import AnalysisError, store_calibration
from ..control import SessionStopped, retry
from ..devices import encoder_nodes, open_encoders, stored_devices
from ..models import KindRules, Measurement
from ..plans import Plan, PlanRequest, joint_sweeps
from ..problems import Invalid
from ..records import current_model
from ..results import joint_residuals
from .base import SessionKind, Step, cell_devices

# Calibration.kind of what a joint session stores (named once: its rules and its store)
CALIBRATION_KIND = "joint"


class Joint(SessionKind):
    name = "joint"
    order = 40
    title = "Joint encoders"
    summary = "sweep joints against reference encoders: gains and gear eccentricity"
    heading = "Joint encoder session"
    default_count = 12
    count_help = "points per swept joint"
    instruments = ("encoder",)
    device_choice = False
    rules = KindRules(max_count=360, calibration_kind=CALIBRATION_KIND, live_residuals=joint_residuals)

    def check(self, cell, model, *, device, joints, payloads) -> None:
        have = sorted(encoder_nodes(cell_devices(cell, field="body.kind")))
        if not have:
            raise Invalid("body.kind", "this cell has no reference encoders or resolvers (devices.can)")
        wanted = joints or list(range(1, model.n_joints + 1))
        missing = [j for j in wanted if j not in have]
        if missing:
            raise Invalid(
                "body.joints",
                f"no reference encoder or resolver on joint {', '.join(map(str, missing))}; "
                f"the cell has them on joint {', '.join(map(str, have))}",
            )

    def instrument(self, run) -> str:
        return "encoder"

    def plan(self, req: PlanRequest) -> Plan:
        return joint_sweeps(req, "joint sweeps")

    def open_instrument(self, devices, cell, run, settings) -> None:
        swept = run.session_plan().joints
        joints = None if swept is None else list(swept)
        devices.encoders = open_encoders(stored_devices(cell.devices), joints, timeout_s=settings.device_timeout_s)

    def measure_one(self, step: Step, seq, q_read, joint) -> list[Measurement]:
        enc = step.devices.encoders.get(joint)
        if enc is None:  # checked when the session started; the cell's devices may have changed since
            raise SessionStopped("failed", f"no reference encoder on joint {joint}")
        reading = retry(enc.read, f"read encoder on joint {joint}", step.settings, step.control, "encoder")
        return [
            Measurement(
                session_id=step.run.id,
                seq=seq,
                joint=joint,
                q=[float(v) for v in q_read],
                x=0.0,
                y=0.0,
                z=0.0,
                reference=float(reading.angle_rad),
            )
        ]

    def finish(self, db, run, cell, settings) -> None:
        run.calibration_id = joint_session(db, run, cell).id


def joint_session(db, run, cell):
    rows = records.stored_rows(db, run)
    if not rows:
        raise AnalysisError("the session has no measurements")
    model, _ = current_model(db, cell)
    results = {}
    joints = list(model.joints)
    for j in sorted({r.joint for r in rows if r.joint}):
        sel = [r for r in rows if r.joint == j]
        q = np.array([r.q[j - 1] for r in sel])
        ref = np.array([r.reference for r in sel])
        freq = joints[j - 1].harmonic[1] if joints[j - 1].harmonic else None
        fit = dataclasses.asdict(fit_joint_harmonic(q, ref, freq))
        results[str(j)] = fit
        if model.coupling is None:
            joints[j - 1] = dataclasses.replace(
                joints[j - 1],
                gain=fit["gain"],
                harmonic=(fit["amplitude"], fit["frequency"], fit["phase"]) if fit["amplitude"] > 0 else None,
            )
    new = dataclasses.replace(model, joints=tuple(joints))
    report = {
        "joints": results,
        "note": "reference encoder offsets are the encoders' own zeros; joint offsets come from pose calibration",
    }
    return store_calibration(db, cell, run, CALIBRATION_KIND, new, report, None)


KIND = Joint()
