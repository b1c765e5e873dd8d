"""Whether joint compliance earns its place on a data set (``recal identify --compliance auto``):
k-fold cross-validation of the hold-out error, rigid against compliant (issue 17).

Apart from :mod:`calibration.compliance` (the model) because it runs the identification:
``identify`` uses the model, this uses ``identify``.
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass

import numpy as np

from .compliance import default_section, with_section
from .identify import identify
from .jacobian import predict
from .model import GravityCompliance, KinematicModel

# ``--compliance auto`` adds a joint's compliance only when it lowers the cross-validated RMS by
# at least this fraction: extra parameters always fit the training data a little better, and a
# gain this small would not be worth the terms (a rigid arm's data give a few tenths of a percent).
MIN_CV_GAIN = 0.05


@dataclass(frozen=True, eq=False)
class CrossValidation:
    """What k-fold cross-validation said about compliance (m). ``tried`` lists every set of
    deflecting joints evaluated, as ``(joints, cv_rms_m)`` (``()``: rigid), in the order tried;
    ``joints`` the set chosen (``()``: the model stays rigid); ``rms_rigid_m`` and
    ``rms_compliant_m`` the cross-validated RMS of the rigid model and of the model with every
    candidate joint's compliance; ``folds`` the number of folds; ``section`` the compliance
    section chosen (every term 0, for identification to start from), or None."""

    folds: int
    tried: tuple[tuple[tuple[str, ...], float], ...]
    joints: tuple[str, ...]
    rms_rigid_m: float
    rms_compliant_m: float
    section: GravityCompliance | None

    @property
    def rms_chosen_m(self) -> float:
        return dict(self.tried)[self.joints]

    @property
    def gain(self) -> float:
        """Relative reduction of the cross-validated RMS, compliant (every candidate joint)
        against rigid."""
        return 1.0 - self.rms_compliant_m / self.rms_rigid_m if self.rms_rigid_m > 0 else 0.0


def fold_indices(data, folds: int, seed: int = 0) -> list[np.ndarray]:
    """Row indices of each held-out fold: rows of one configuration (``pose_id``) stay together,
    so a fold never tests a configuration the training saw."""
    N = len(data)
    groups = np.asarray(data.pose_id, dtype=object) if data.pose_id is not None else np.arange(N)
    keys = list(dict.fromkeys(groups.tolist()))
    order = np.random.default_rng(seed).permutation(len(keys))
    fold_of = {keys[k]: i % folds for i, k in enumerate(order)}
    labels = np.array([fold_of[g] for g in groups.tolist()])
    return [np.nonzero(labels == f)[0] for f in range(folds)]


def cv_rms(model: KinematicModel, data, folds: list[np.ndarray], identify_kw: dict) -> float:
    """Cross-validated RMS (m) of the position error of ``model`` identified on all folds but one
    and tested on that one, over every row."""
    sq = 0.0
    n = 0
    for test in folds:
        train = np.setdiff1d(np.arange(len(data)), test)
        result = identify(model, data.subset(train), **identify_kw)
        held = data.subset(test)
        p_tool = np.array([result.model.target(t) for t in held.target])
        p = predict(result.model, held.q, p_tool, payload=held.payload).p_world
        sq += float(np.sum((held.p_world - p) ** 2))
        n += len(test)
    return float(np.sqrt(sq / max(n, 1)))


def choose_compliance(
    model: KinematicModel,
    data,
    *,
    candidates: GravityCompliance | None = None,
    folds: int = 5,
    min_gain: float = MIN_CV_GAIN,
    seed: int = 0,
    identify_kw: dict | None = None,
) -> CrossValidation:
    """Which joints' compliance the data support (``recal identify --compliance auto``): forward
    selection by k-fold cross-validation over :func:`calibration.identify.identify`
    (:func:`select_terms`): starting rigid, add the candidate joint (or, when no single one
    passes, the pair, then all the remaining joints) whose compliance lowers the cross-validated
    RMS most, while it lowers it by at least ``min_gain`` (relative). ``candidates``: the section whose joints are
    tried (default :func:`default_section`); the chosen section keeps its gravity and lumps."""
    kw = dict(identify_kw or {})
    cand = candidates if candidates is not None else default_section(model)
    rigid = dataclasses.replace(model, compliance=None)
    fidx = fold_indices(data, folds, seed)
    last = model.joints[-1].name

    def section(joints):
        if not joints:
            return None
        lumps = tuple(lump for lump in cand.lumps if lump in joints or lump == last or lump not in cand.joints)
        return GravityCompliance(tuple(j for j in cand.joints if j in joints), lumps, cand.gravity, {}, cand.payload)

    tried: dict[tuple[str, ...], float] = {}

    def score(joints):
        key = tuple(j for j in cand.joints if j in joints)
        if key not in tried:
            tried[key] = cv_rms(with_section(rigid, section(key)), data, fidx, kw)
        return tried[key]

    chosen = select_terms(cand.joints, score, min_gain)
    full = score(cand.joints)
    return CrossValidation(folds, tuple(tried.items()), chosen, tried[()], full, section(chosen))


def select_terms(candidates: tuple[str, ...], score, min_gain: float) -> tuple[str, ...]:
    """Forward selection of model terms by a cross-validated error ``score(terms)`` (lower is
    better), from none: each step adds the term that lowers it most, while it lowers it by at
    least ``min_gain`` (relative). When no single term passes, the pairs are tried, then every
    remaining term at once: two joints' compliance can each gain a little and together pass
    (the WAM: j2 alone 1.1 %, j3 alone 2.3 %, both 5.6 %), which one-at-a-time selection never
    finds. Cost: a step tries at most k + k(k-1)/2 + 1 sets of the k remaining terms (each one
    ``score``, i.e. one identification per fold). Returns the chosen terms in ``candidates``'
    order."""
    chosen: tuple[str, ...] = ()
    best = score(chosen)

    def ordered(terms):
        return tuple(x for x in candidates if x in terms)

    while True:
        options = [j for j in candidates if j not in chosen]
        step = None
        for size in (1, 2):
            if len(options) < size:
                break
            sets = [ordered(chosen + c) for c in itertools.combinations(options, size)]
            rms, terms = min((score(t), t) for t in sets)
            if rms <= (1.0 - min_gain) * best:
                step = (rms, terms)
                break
        if step is None and len(options) > 2:
            rms = score(ordered(candidates))
            if rms <= (1.0 - min_gain) * best:
                step = (rms, ordered(candidates))
        if step is None:
            return chosen
        best, chosen = step


def compare(model: KinematicModel, data, *, folds: int = 5, seed: int = 0, identify_kw: dict | None = None) -> dict:
    """Rigid against compliant for a model with a compliance section: the k-fold
    cross-validated RMS (m) of the model identified without its section and with it (every term
    from 0), with the section's joints; what a result page shows side by side."""
    if model.compliance is None:
        raise ValueError("the model has no compliance section to compare with")
    kw = dict(identify_kw or {})
    fidx = fold_indices(data, folds, seed)
    fresh = dataclasses.replace(model.compliance, values={})
    rigid = cv_rms(with_section(model, None), data, fidx, kw)
    compliant = cv_rms(with_section(model, fresh), data, fidx, kw)
    return {
        "folds": folds,
        "joints": list(fresh.joints),
        "lumps": list(fresh.lumps),
        "cv_rms_rigid_m": rigid,
        "cv_rms_compliant_m": compliant,
        "gain": 1.0 - compliant / rigid if rigid > 0 else 0.0,
    }
