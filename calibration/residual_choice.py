"""Which correction of what the geometric model leaves, by nested cross-validation (issue 28):
none, the smooth map (:mod:`calibration.residual_map`), the joint transmission
(:mod:`calibration.transmission`) or boosted trees (:mod:`calibration.trees`).

Outer k-fold cross-validation of the whole procedure, a configuration's rows in one fold: identify
the geometric model on the training folds, fit each family to its residuals there (each family
chooses its own settings inside, on the training folds only: the map its smoothness by an inner
cross-validation, the transmission its gear ratios, the trees their number by an inner
cross-validation), and measure every
family's error on the held-out fold. The family with the least cross-validated RMS is kept when it
lowers the RMS of none by at least :data:`MIN_CV_GAIN`; it is then fitted to all the data. A
learning curve (the held-out RMS of the best family fitted to a share of each training fold's
configurations, against that number of poses) tells whether more poses would help.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from . import residual_map as rm
from . import transmission as tr
from . import trees as tt
from .identification import INSTRUMENT_SIGMA_M
from .model import KinematicModel
from .residual_base import corrected_model_sigma, quantile_model_sigma

FAMILIES = ("none", "map", "transmission", "trees")
MIN_CV_GAIN = rm.MIN_CV_GAIN
LEARNING_SHARES = (0.25, 0.5, 1.0)


@dataclass(frozen=True, eq=False)
class Choice:
    """``family`` chosen (``"none"``: no correction), ``correction`` (an object with
    ``evaluate(q, p_tool=None) -> (corr, inside)``, None for none) and ``figures`` (m)."""

    family: str
    correction: object | None
    figures: dict

    def section(self, model: KinematicModel) -> dict | None:
        """The model file's ``residual_map`` section (None for none)."""
        if self.correction is None:
            return None
        c = self.correction
        if isinstance(c, rm.ResidualMap):
            return rm.to_dict(c, model)
        if isinstance(c, tr.TransmissionCorrection):
            return tr.to_dict(c, model)
        assert isinstance(c, tt.BoostedTrees), type(c)
        return tt.to_dict(c, model)

    def report(self, model: KinematicModel) -> dict:
        """The figures in ``model``'s length unit, each ``…_m`` key without its suffix: the
        report's ``residual_map`` (``recal identify --residual-map auto`` and the service's pose
        sessions write this one shape: ``families`` with each one's cross-validated ``rms``,
        ``chosen``, ``gain``, ``learning_curve``, ``noise_sigma``, ...)."""
        return in_length_unit(self.figures, model.units.length_m)


def in_length_unit(value, length_m: float, key: str = ""):
    """``value`` with every number under a key ending in ``_m`` divided by ``length_m`` (the key
    without the suffix), recursively through dicts and lists."""
    if isinstance(value, dict):
        return {k.removesuffix("_m"): in_length_unit(v, length_m, k) for k, v in value.items()}
    if isinstance(value, list):
        return [in_length_unit(v, length_m, key) for v in value]
    return value / length_m if key.endswith("_m") and isinstance(value, float) else value


def _p_tool(model: KinematicModel, data) -> np.ndarray:
    return np.array([model.target(t) for t in data.target])


def fit_family(family: str, start: KinematicModel, model: KinematicModel, data, identify_kw: dict, seed: int = 0):
    """``family`` fitted to the residuals of ``model`` (identified from ``start``) on ``data``."""
    from .identify import identify

    r = rm.residuals(model, data)
    revolute = np.array([j.revolute for j in model.joints])
    if family == "map":
        return _fitted_map(data, r, revolute, 5, seed)
    if family == "transmission":
        t = tr.fit_transmission(model, data.q, r, _p_tool(model, data), target_names=data.target, payload=data.payload)
        # identified again on the corrected readings from ``model`` with its tool and targets held:
        # a point of ``model``'s tool frame is then the same point of the corrected model's
        kw = {**identify_kw, "fixed": (*identify_kw.get("fixed", ()), "tool.*", "target.*")}
        corrected = identify(model, tr.corrected_readings(data, t), **kw).model
        return tr.TransmissionCorrection(model, corrected, t)
    if family == "trees":
        rows = rm.map_rows(data, MAX_TREE_CONFIGURATIONS, seed + 5)
        sub = data.subset(rows)
        return tt.fit_trees(sub.q, r[rows], seed=seed)
    raise ValueError(f"unknown family {family!r}; expected one of {', '.join(FAMILIES)}")


# the trees are fitted on at most this many configurations (a seeded draw): their cost grows
# linearly, and a few thousand poses are what the measured arms of issue 28 had
MAX_TREE_CONFIGURATIONS = 3000


def _held_out_sq(correction, model: KinematicModel, te) -> tuple[float, float]:
    """Sum of squared held-out errors with ``correction`` (None: without), and the share inside."""
    s, share, _ = _held_out(correction, model, te, 0.0)
    return s, share


def _held_out(correction, model: KinematicModel, te, sigma_m: float) -> tuple[float, float, tuple[float, float, int]]:
    """:func:`_held_out_sq`, and over the held-out rows inside the correction's region: the sum
    of squared errors, the sum of the stated noise's 3 σ² (rows without their own σ: ``sigma_m``)
    and their number (what :func:`calibration.residual_base.corrected_model_sigma` needs)."""
    s, share, within, _ = _held_out_errors(correction, model, te, sigma_m)
    return s, share, within


def _held_out_errors(correction, model: KinematicModel, te, sigma_m: float):
    """:func:`_held_out`, and the (K,) error norms (m) of the held-out rows inside the region."""
    r = rm.residuals(model, te)
    inside = np.ones(len(te), dtype=bool)
    if correction is not None:
        corr, inside = correction.evaluate(te.q, _p_tool(model, te))
        r = r - corr
    sigma = np.where(np.isfinite(te.sigma) & (te.sigma > 0), te.sigma, sigma_m)
    sq = np.sum(r**2, axis=1)
    within = (float(np.sum(sq[inside])), float(np.sum(3.0 * sigma[inside] ** 2)), int(inside.sum()))
    return float(np.sum(sq)), float(np.mean(inside)) if len(te) else 1.0, within, np.sqrt(sq[inside])


class _OuterFolds:
    """What the outer folds of :func:`choose_correction` gather, per family: the held-out Σ|e|²
    (``sq``; per fold in ``held_sq``: the learning curve's last point), the share inside the
    region, inside it Σ|e|², Σ 3σ² and rows (``within``) and each row's |e| (``norms``), and each
    fold's (training, held-out, model) (``fitted``)."""

    def __init__(self, families: tuple[str, ...]):
        self.families = families
        self.sq = {f: 0.0 for f in families}
        self.inside: dict[str, list[float]] = {f: [] for f in families}
        self.within = {f: np.zeros(3) for f in families}
        self.norms: dict[str, list[np.ndarray]] = {f: [] for f in families}
        self.held_sq: list[dict[str, float]] = []
        self.fitted: list = []

    def run(self, start: KinematicModel, data, test: np.ndarray, kw: dict, seed: int, sigma_m: float) -> None:
        """One outer fold: identify on the others, fit every family there, test on ``test``."""
        from .identify import identify

        train = np.setdiff1d(np.arange(len(data)), test)
        tr_data, te = data.subset(train), data.subset(test)
        model = identify(start, tr_data, **kw).model
        self.fitted.append((tr_data, te, model))
        self.held_sq.append({})
        for f in self.families:
            c = None if f == "none" else fit_family(f, start, model, tr_data, kw, seed)
            s, share, w, e = _held_out_errors(c, model, te, sigma_m)
            self.norms[f].append(e)
            self.held_sq[-1][f] = s
            self.sq[f] += s
            self.inside[f].append(share)
            self.within[f] += w


def choose_correction(
    start: KinematicModel,
    data,
    *,
    folds: int = 5,
    families: tuple[str, ...] = FAMILIES,
    min_gain: float = MIN_CV_GAIN,
    seed: int = 0,
    identify_kw: dict | None = None,
    final: KinematicModel | None = None,
) -> Choice:
    """``recal identify --residual-map auto``: see the module. ``final``: the geometric model
    identified on all ``data`` (default: identified here); the chosen correction corrects it."""
    from .compliance_fit import fold_indices
    from .identify import identify

    kw = dict(identify_kw or {})
    all_data = data
    data = data.subset(rm.map_rows(data, rm.MAX_CV_CONFIGURATIONS, seed + 3))
    families, not_tried = families_tried(families, _poses(data))
    sigma_m = float(kw.get("sigma_m", INSTRUMENT_SIGMA_M))
    outer = _OuterFolds(families)
    for test in fold_indices(data, folds, seed):
        outer.run(start, data, test, kw, seed, sigma_m)
    sq, inside, within, norms, fitted_per_fold = outer.sq, outer.inside, outer.within, outer.norms, outer.fitted
    n = len(data)
    rms = {f: math.sqrt(sq[f] / n) for f in families}
    best = min((f for f in families if f != "none"), key=lambda f: rms[f], default=None)
    base = rms.get("none", math.inf)
    gain = 1.0 - rms[best] / base if best is not None and base > 0 else 0.0
    kept = best is not None and gain >= min_gain
    sigma = {f: corrected_model_sigma(within[f][0], within[f][1], int(within[f][2])) for f in families}
    sigma_95 = {f: _bound_sigma(norms[f], within[f], sigma[f]) for f in families}
    figures = {
        "folds": folds,
        "cv_rows": n,
        "cv_poses": _poses(data),
        "families": {
            f: {
                "rms_m": rms[f],
                "held_out_inside_share": float(np.mean(inside[f])),
                "model_sigma_m": sigma[f],
                "model_sigma_95_m": sigma_95[f],
            }
            for f in families
        },
        "not_tried": not_tried,
        "best": best,
        "gain": gain,
        "min_gain": min_gain,
        "chosen": best if kept else "none",
        "learning_curve": (
            learning_curve(best, start, fitted_per_fold, kw, seed, [h[best] for h in outer.held_sq]) if best else []
        ),
        # the instrument's per-axis noise the rows state (what extrapolate_learning_curve needs)
        "noise_sigma_m": noise_sigma(data, sigma_m),
    }
    if not kept or best is None:
        return Choice("none", None, figures)
    final = final if final is not None else identify(start, all_data, **kw).model
    c = fit_family(best, start, final, all_data, kw, seed)
    cv_figures = {
        "family": best,
        "rms_without_m": base,
        "rms_with_m": rms[best],
        "gain": gain,
        "folds": folds,
        # the corrected model's per-axis uncertainty inside its region: what u95 uses there
        # (calibration.uncertainty.stored_position_covariance)
        "model_sigma_m": sigma[best],
        # the σ whose Gaussian 95 % radius is the held-out errors' own 95 % quantile: what the
        # bound uses (calibration.uncertainty.correction_sigma_from_model)
        "model_sigma_95_m": sigma_95[best],
    }
    if best == "transmission":
        c = dataclasses.replace(c, transmission=dataclasses.replace(c.transmission, cv=cv_figures))
    else:
        c = dataclasses.replace(c, cv=cv_figures)
    return Choice(best, c, figures)


def _bound_sigma(norms: list[np.ndarray], within: np.ndarray, sigma_rms_m: float) -> float:
    """:func:`calibration.residual_base.quantile_model_sigma` of a family's held-out error norms
    inside its region, the instrument's noise their stated one (``within``: Σ|e|², Σ 3σ², rows)."""
    from .uncertainty import chi2_quantile

    rows = int(within[2])
    noise_m = math.sqrt(within[1] / (3.0 * rows)) if rows else 0.0
    e = np.concatenate(norms) if norms else np.zeros(0)
    return quantile_model_sigma(e, noise_m, chi2_quantile(0.95, 3), sigma_rms_m)


def noise_sigma(data, sigma_m: float) -> float:
    """The per-axis noise (m) the rows of ``data`` state, as one figure (root mean square; rows
    without their own σ: ``sigma_m``)."""
    sigma = np.where(np.isfinite(data.sigma) & (data.sigma > 0), data.sigma, sigma_m)
    return float(np.sqrt(np.mean(sigma**2))) if len(sigma) else float(sigma_m)


# Boosted trees learn the error configuration by configuration: with fewer configurations than
# this, their leaves (at least min_samples_leaf poses each, calibration.trees.TREE_SETTINGS) can
# barely split on an inner fold's share of an outer fold's training poses, and choosing their
# number by an inner cross-validation costs seconds for nothing; the family is not tried there and
# the report says so. Dense pose sessions (issue 28) start at this size too.
MIN_TREE_POSES = 200


def families_tried(families: tuple[str, ...], poses: int) -> tuple[tuple[str, ...], dict[str, str]]:
    """The families worth trying on ``poses`` configurations, and why each other one is not."""
    if "trees" in families and poses < MIN_TREE_POSES:
        why = f"{poses} configurations: boosted trees are tried from {MIN_TREE_POSES} (too few to split leaves)"
        return tuple(f for f in families if f != "trees"), {"trees": why}
    return families, {}


def _poses(data) -> int:
    return len(np.unique(np.asarray(data.pose_id).astype(str))) if data.pose_id is not None else len(data)


def learning_curve(
    family: str, start, fitted_per_fold, kw: dict, seed: int, whole_fold_sq: list[float] | None = None
) -> list[dict]:
    """The held-out RMS (m) of ``family`` (``"none"``: the geometric model alone) fitted to a
    share of each training fold's poses, the geometric model identified on that share too,
    against the number of those poses: the whole procedure's error at that many poses. A share
    too small to identify from gives no point (the whole fold's model in its place made a
    30-pose session's curve flat: three points of one model). ``whole_fold_sq``: each fold's
    held-out Σ|e|² of ``family`` fitted to the whole fold, when the caller has it (the last
    point is then not fitted again: the same rows, the same fit)."""
    from .identify import identify

    out = []
    for share in LEARNING_SHARES:
        sq, n, poses = 0.0, 0, []
        try:
            for i, (tr_data, te, model) in enumerate(fitted_per_fold):
                k = max(int(share * _poses(tr_data)), 10)
                rows = rm.map_rows(tr_data, k, seed + 7)
                sub = tr_data.subset(rows)
                if share == 1.0 and whole_fold_sq is not None:
                    sq += whole_fold_sq[i]
                else:
                    sub_model = model if share == 1.0 else identify(start, sub, **kw).model
                    c = None if family == "none" else fit_family(family, start, sub_model, sub, kw, seed)
                    sq += _held_out_sq(c, sub_model, te)[0]
                n += len(te)
                poses.append(_poses(sub))
        except ValueError:  # too few poses at this share to identify (NotEnoughData): no point
            continue
        out.append({"poses": int(np.mean(poses)), "rms_m": math.sqrt(sq / max(n, 1))})
    return out


def extrapolate_learning_curve(curve: list[dict], poses: int, sigma_m: float) -> dict | None:
    """The held-out RMS (m) a learning curve (``[{"poses", "rms_m"}]``, :func:`learning_curve`)
    predicts at ``poses`` poses, by a power law of what exceeds the instrument's noise:

        rms(n)² = 3 σ² + a · n^(−b),   b in [0, 2]

    fitted in log-log to the points whose RMS exceeds the noise's ``√3 σ`` (per-axis ``sigma_m``).
    Why this form: a held-out error is the model's plus the instrument's, and only the model's
    part falls with more poses (as ``n^(−1)`` in variance for a fixed set of parameters; slower
    for a learned correction that refines with the data, faster never). ``b`` is bounded so that
    three points cannot promise more. Returns ``{"poses", "rms_m", "law", "a_m2", "b",
    "extrapolated", "points"}`` or None when the curve has no point."""
    pts = [(int(p["poses"]), float(p["rms_m"])) for p in curve if p.get("poses") and p.get("rms_m") is not None]
    if not pts:
        return None
    noise2 = 3.0 * float(sigma_m) ** 2
    n = np.array([p[0] for p in pts], dtype=float)
    excess = np.array([p[1] ** 2 for p in pts]) - noise2
    keep = excess > 0
    out = {"poses": int(poses), "extrapolated": bool(poses > n.max()), "points": len(pts)}
    law = "rms(n)^2 = 3 sigma^2 + a n^-b (power law of the excess over the instrument's noise)"
    if keep.sum() >= 2 and len(np.unique(n[keep])) >= 2:
        slope, _intercept = np.polyfit(np.log(n[keep]), np.log(excess[keep]), 1)
        b = float(np.clip(-slope, 0.0, 2.0))
        # the intercept at the mean of the points, so that a clipped slope still passes through them
        a = float(np.exp(np.mean(np.log(excess[keep]) + b * np.log(n[keep]))))
        rms = math.sqrt(noise2 + a * float(poses) ** (-b))
        return {**out, "rms_m": rms, "law": law, "a_m2": a, "b": b}
    if keep.sum() == 0:  # already at the instrument's noise: more poses cannot show better
        return {**out, "rms_m": math.sqrt(noise2), "law": "at the instrument's noise already", "a_m2": 0.0, "b": 0.0}
    # one point above the noise: no slope to fit; the model's part taken to fall as 1/n (fixed parameters)
    k = int(np.flatnonzero(keep)[0])
    a = float(excess[k] * n[k])
    return {**out, "rms_m": math.sqrt(noise2 + a / float(poses)), "law": law + ", b = 1 assumed", "a_m2": a, "b": 1.0}


# ----------------------------------------------------------------------------- the smooth map alone


def choose_residual_map(
    start: KinematicModel,
    data,
    *,
    folds: int = 5,
    min_gain: float = MIN_CV_GAIN,
    seed: int = 0,
    identify_kw: dict | None = None,
    final: KinematicModel | None = None,
) -> tuple[rm.ResidualMap | None, dict]:
    """``recal identify --residual-map auto``: k-fold cross-validation of the whole procedure
    (identify ``start`` on the training folds, fit a map to its residuals with the smoothness
    chosen by an inner cross-validation, test on the held-out fold, with and without the map).
    Returns the map fitted to ``final``'s residuals on all ``data`` (``final``: the model
    identified from all of them; default: identified here) when it lowers the cross-validated RMS
    by at least ``min_gain``, else None; and the figures either way (m)."""
    from .compliance_fit import fold_indices
    from .identify import identify

    kw = dict(identify_kw or {})
    revolute = np.array([j.revolute for j in start.joints])
    all_data = data
    data = data.subset(rm.map_rows(data, rm.MAX_CV_CONFIGURATIONS, seed + 3))
    outer = fold_indices(data, folds, seed)
    sq_without = sq_with = 0.0
    inside_share = []
    fitted_per_fold = []  # (training, held-out, model) of each fold: the learning curve refits on shares
    within = np.zeros(3)  # inside the map's region: Σ|e|² with it, Σ 3σ² stated, rows
    sigma_m = float(kw.get("sigma_m", INSTRUMENT_SIGMA_M))
    for test in outer:
        train = np.setdiff1d(np.arange(len(data)), test)
        tr, te = data.subset(train), data.subset(test)
        model = identify(start, tr, **kw).model
        fitted_per_fold.append((tr, te, model))
        m = _fitted_map(tr, rm.residuals(model, tr), revolute, folds, seed)
        r_te = rm.residuals(model, te)
        corr, inside = m.evaluate(te.q)
        sq_without += float(np.sum(r_te**2))
        sq_with += float(np.sum((r_te - corr) ** 2))
        inside_share.append(float(np.mean(inside)))
        sigma = np.where(np.isfinite(te.sigma) & (te.sigma > 0), te.sigma, sigma_m)[inside]
        within += (float(np.sum((r_te - corr)[inside] ** 2)), float(np.sum(3.0 * sigma**2)), int(inside.sum()))
    n = len(data)
    rms_without, rms_with = math.sqrt(sq_without / n), math.sqrt(sq_with / n)
    gain = 1.0 - rms_with / rms_without if rms_without > 0 else 0.0
    figures: dict = {
        "folds": folds,
        "rms_without_m": rms_without,
        "rms_with_m": rms_with,
        "gain": gain,
        "min_gain": min_gain,
        "held_out_inside_share": float(np.mean(inside_share)),
        "kept": gain >= min_gain,
        "max_configurations": rm.MAX_MAP_CONFIGURATIONS,
        "cv_rows": n,
        # the corrected model's per-axis uncertainty inside the region (what u95 uses there)
        "model_sigma_m": corrected_model_sigma(within[0], within[1], int(within[2])),
    }
    # the held-out RMS against the number of poses, of the procedure kept (map or none): what a
    # planned session's accuracy is predicted from (residual_choice.extrapolate_learning_curve)
    figures["learning_curve"] = learning_curve("map" if gain >= min_gain else "none", start, fitted_per_fold, kw, seed)
    figures["noise_sigma_m"] = noise_sigma(data, sigma_m)
    if gain < min_gain:
        return None, figures
    final = final if final is not None else identify(start, all_data, **kw).model
    m = _fitted_map(all_data, rm.residuals(final, all_data), revolute, folds, seed)
    figures.update(length_scale=m.length_scale, ridge=m.ridge, rows=len(m.q_train))
    # the file's section keeps the figures that judge the map, not the curve (in the report)
    return dataclasses.replace(m, cv={k: v for k, v in figures.items() if k != "learning_curve"}), figures


def _fitted_map(data, r: np.ndarray, revolute: np.ndarray, folds: int, seed: int) -> rm.ResidualMap:
    """The map of residuals ``r`` (N, 3) m on ``data``'s rows (at most :data:`rm.MAX_MAP_CONFIGURATIONS`
    configurations of them, :func:`map_rows`), its smoothness chosen by k-fold cross-validation."""
    from .compliance_fit import fold_indices

    rows = rm.map_rows(data, seed=seed + 2)
    sub = data.subset(rows)
    ell, lam, _ = rm.select_smoothness(sub.q, r[rows], revolute, fold_indices(sub, folds, seed + 1))
    return rm.fit(sub.q, r[rows], revolute, ell, lam)
