"""Benchmark of joint compliance under gravity (issue 17).

Two simulated arms that sag (``calibration.simulate.SAGGING_ARMS``: a UR10e-class cobot with a
10 kg payload, tracker noise 0.02 mm per axis; a 165 kg-payload arm, 0.03 mm), each with a
random 6-DOF error in every link and an unknown base, measured at the reflector on N random
configurations, half of them with the rated payload and half without (a session with two
payloads). For each arm, side by side in the same run:

- the hold-out RMS of the rigid model (every geometric parameter) and of the compliant model
  (``--compliance gravity``: joints 2 and 3, lumps on links 2, 3 and 6), on 2,000 fresh measured
  configurations, against the noise floor (√3 σ: the RMS length of the noise alone);
- the fraction of hold-out errors inside each model's predicted 95 % region (model covariance
  plus the instrument's noise);
- the time of ``identify()`` rigid and compliant (best of ``--repeat``), and of the 5-fold
  cross-validation of ``--compliance auto`` (``choose_compliance``);
- the same with one payload throughout (the compliance itself then cannot be separated from the
  wrist's weight: the rigid-versus-compliant figures are those of a session that never changes
  the payload).

Then residual maps (``--residual-map auto``, book §5.4) on the cobot measured in one region
(every joint within ±40° of one configuration, the rated payload on): the cross-validated RMS
without and with the map, on the rigid and on the compliant model, the hold-out RMS on 1,000
fresh configurations of that region, and the time of the nested cross-validation.

Run: ``python bench/compliance.py`` (well under a minute); ``--rows 100 400`` for other sizes.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # many small BLAS calls: threads only slow them down

import numpy as np

from calibration import compliance as C
from calibration import compliance_fit
from calibration.identify import identify
from calibration.robots import nominal
from calibration.simulate import (
    SAGGING_ARMS,
    heavy_arm_nominal,
    perturbed,
    random_configurations,
    sagging,
    simulate_measurements,
)
from calibration.uncertainty import validate

SIGMA = {"cobot": 20e-6, "arm165": 30e-6}


def cell(arm: str, seed: int):
    rng = np.random.default_rng(seed)
    nom = nominal("ur10e") if arm == "cobot" else heavy_arm_nominal()
    nom = dataclasses.replace(nom, targets={"smr": np.array([0.0, 0.0, 0.05])})
    truth = sagging(perturbed(nom, rng, base_length_m=0.5, base_angle_rad=0.3), arm, frames_of=nom)
    return nom, truth, rng


def measure(nom, truth, rng, n, payloads, sigma):
    q = random_configurations(nom, n, rng)
    pay = np.array([payloads[i % len(payloads)] for i in range(n)], dtype=float)
    return simulate_measurements(truth, q, rng, sigma_m=sigma, targets=("smr",), payload=pay)


def timed(fn, repeat):
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return out, best


def run(arm: str, rows: int, payloads, repeat: int, seed: int) -> dict:
    nom, truth, rng = cell(arm, seed)
    sigma = SIGMA[arm]
    train = measure(nom, truth, rng, rows, payloads, sigma)
    holdout = measure(nom, truth, rng, 2000, payloads, sigma)
    start = C.with_section(nom, C.default_section(nom))
    rigid, t_rigid = timed(lambda: identify(nom, train, sigma_m=sigma), repeat)
    comp, t_comp = timed(lambda: identify(start, train, sigma_m=sigma), repeat)
    cv, t_cv = timed(lambda: compliance_fit.choose_compliance(nom, train, identify_kw={"sigma_m": sigma}), 1)
    vr, vc = validate(rigid, holdout), validate(comp, holdout)
    return dict(
        arm=arm,
        rows=rows,
        payloads=len(payloads),
        floor_mm=np.sqrt(3) * sigma * 1e3,
        rigid_mm=vr.rms_m * 1e3,
        compliant_mm=vc.rms_m * 1e3,
        cov_rigid=vr.coverage_95,
        cov_compliant=vc.coverage_95,
        p_rigid=len(rigid.params),
        p_comp=len(comp.params),
        t_rigid_ms=t_rigid * 1e3,
        t_comp_ms=t_comp * 1e3,
        t_cv_s=t_cv,
        cv_joints=",".join(cv.joints) or "-",
        cv_rigid_mm=cv.rms_rigid_m * 1e3,
        cv_comp_mm=cv.rms_compliant_m * 1e3,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, nargs="+", default=[100, 200])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    print(
        f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, numpy {np.__version__}, "
        f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}"
    )
    print(
        "| arm | rows | payloads | noise floor | rigid hold-out | compliant hold-out | 95 % coverage rigid / "
        "compliant | params rigid / compliant | identify rigid / compliant | auto: 5-fold CV rigid / compliant, "
        "chosen, time |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for arm in ("cobot", "arm165"):
        rated = SAGGING_ARMS[arm]["payload"]
        for payloads in ([(0.0, 0, 0, 0), rated], [rated]):
            for rows in args.rows:
                r = run(arm, rows, payloads, args.repeat, args.seed)
                print(
                    f"| {r['arm']} | {r['rows']} | {r['payloads']} | {r['floor_mm']:.4f} mm | {r['rigid_mm']:.4f} mm "
                    f"| {r['compliant_mm']:.4f} mm | {100 * r['cov_rigid']:.1f} % / {100 * r['cov_compliant']:.1f} % "
                    f"| {r['p_rigid']} / {r['p_comp']} | {r['t_rigid_ms']:.0f} / {r['t_comp_ms']:.0f} ms "
                    f"| {r['cv_rigid_mm']:.4f} / {r['cv_comp_mm']:.4f} mm, {r['cv_joints']}, {r['t_cv_s']:.2f} s |",
                    flush=True,
                )
    print("\n| model | rows | CV RMS without / with map | kept | hold-out without / with map | inside | time |")
    print("|---|---|---|---|---|---|---|")
    for rows in args.rows:
        residual_maps(rows, args.seed)


def residual_maps(rows: int, seed: int) -> None:
    from calibration import residual_choice as RC
    from calibration import residual_map as RM

    nom, truth, rng = cell("cobot", seed)
    centre = np.deg2rad([0.0, -60.0, 90.0, -120.0, -90.0, 0.0])
    region = np.stack([centre - np.deg2rad(40), centre + np.deg2rad(40)], axis=1)
    rated = np.array(SAGGING_ARMS["cobot"]["payload"])

    def measure(n):
        return simulate_measurements(
            truth,
            random_configurations(nom, n, rng, limits=region),
            rng,
            sigma_m=SIGMA["cobot"],
            targets=("smr",),
            payload=rated,
        )

    train, holdout = measure(rows), measure(1000)
    for label, start in (("rigid", nom), ("compliant", C.with_section(nom, C.default_section(nom)))):
        t = time.perf_counter()
        rmap, fig = RC.choose_residual_map(start, train, identify_kw={"sigma_m": SIGMA["cobot"]})
        elapsed = time.perf_counter() - t
        model = identify(start, train, sigma_m=SIGMA["cobot"]).model
        r = RM.residuals(model, holdout)
        corr, inside = rmap.evaluate(holdout.q) if rmap is not None else (np.zeros_like(r), np.zeros(len(r), bool))
        rms = lambda e: float(np.sqrt(np.mean(np.sum(e**2, axis=1)))) * 1e3  # noqa: E731
        print(
            f"| {label} | {rows} | {fig['rms_without_m'] * 1e3:.4f} / {fig['rms_with_m'] * 1e3:.4f} mm | "
            f"{'yes' if rmap is not None else 'no'} | {rms(r):.4f} / {rms(r - corr):.4f} mm | "
            f"{100 * inside.mean():.0f} % | {elapsed:.2f} s |",
            flush=True,
        )


if __name__ == "__main__":
    main()
