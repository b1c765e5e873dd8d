"""Gradient-boosted trees on the joint angles: the learned family of the residual correction
(issue 28: on a measured UR10 they took the geometric model's 0.49 mm to 0.15 mm where smooth
maps could not, the error depending on the configuration sharply).

Fitted with scikit-learn's ``HistGradientBoostingRegressor``: a well-kept library (a stable API
since 1.0, wheels for every platform we ship), pure Python over compiled code with no native
library of its own to install (LightGBM and XGBoost bring one), and its trees are plain arrays
that export cleanly. Only the fit imports it (lazily): the model file stores the fitted trees as
plain JSON arrays (per node: feature, threshold, left, right, value; no pickle, nothing
executable), and :meth:`BoostedTrees.evaluate` walks them in numpy, so ``calibration/`` needs
numpy alone to apply a correction.

Region: a tree extrapolates flat, and what it learned holds only where it saw data (issue 28: a
correction fitted on one series made another with disjoint joint ranges worse). The correction
applies within the joint ranges of the training configurations and within a radius of the
nearest of them in joint space (:data:`RADIUS_FACTOR` times the 95th percentile of the training
configurations' own nearest-neighbour distances); elsewhere it is zero and the point flagged.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

FORMAT = "recal.residual_trees/1"
# Fixed shape of each tree (shallow, shrunk); how many trees each axis gets is chosen by an inner
# k-fold cross-validation on the fitting rows alone (:func:`choose_tree_count`): the right number
# grows with the poses and with how sharply the error varies (on a measured UR10, 2,000 poses
# wanted about 800 where a UR5's 800 poses wanted about 200), so no fixed number suits every arm.
TREE_SETTINGS = dict(learning_rate=0.1, max_leaf_nodes=15, min_samples_leaf=16, l2_regularization=1e-3)
INNER_FOLDS = 3
TREES_STEP = 100  # the inner CV's error is read every this many trees
MAX_TREES = 1000  # per axis: a file of a few MB at most (on the UR10, 800 to 1,200 differ by 0.1 %)
PATIENCE_TREES = 200  # stop adding trees when the inner CV's error has not fallen for this many
RADIUS_FACTOR = 1.5
EVALUATE_CHUNK_ROWS = 4096


@dataclass(frozen=True, eq=False)
class Tree:
    """One regression tree as arrays over its nodes: ``feature`` (−1 at a leaf), ``threshold``
    (go left when ``x[feature] <= threshold``), ``left``/``right`` child indices (−1 at a leaf),
    ``value`` (the leaf's contribution)."""

    feature: np.ndarray
    threshold: np.ndarray
    left: np.ndarray
    right: np.ndarray
    value: np.ndarray

    def predict(self, X: np.ndarray) -> np.ndarray:
        node = np.zeros(len(X), dtype=np.intp)
        rows = np.arange(len(X))
        while True:
            f = self.feature[node]
            internal = f >= 0
            if not internal.any():
                return self.value[node]
            go_left = X[rows[internal], f[internal]] <= self.threshold[node[internal]]
            node[internal] = np.where(go_left, self.left[node[internal]], self.right[node[internal]])


@dataclass(frozen=True, eq=False)
class BoostedTrees:
    """Per output axis (x, y, z), a baseline (m) plus a sum of trees over the readings (SI).
    ``q_train`` (M, n) the configurations it was fitted on (its region), ``radius`` the joint-space
    distance (rad, chordal) within which a configuration counts as near them; ``cv`` figures;
    ``settings`` how the trees were grown (what a refit with scikit-learn needs; informative)."""

    baseline: np.ndarray
    trees: tuple[tuple[Tree, ...], ...]
    q_train: np.ndarray
    radius: float
    cv: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)

    def raw(self, q: np.ndarray) -> np.ndarray:
        """The trees' sum (N, 3) m at readings ``q`` (N, n), region not checked."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        out = np.tile(self.baseline, (len(q), 1))
        for axis, trees in enumerate(self.trees):
            for t in trees:  # in sklearn's order, so the sums round the same way
                out[:, axis] += t.predict(q)
        return out

    def inside(self, q: np.ndarray) -> np.ndarray:
        """(N,) within the training ranges and within ``radius`` of a training configuration."""
        from .residual_base import features
        from .residual_base import sqdist as _sqdist

        q = np.atleast_2d(np.asarray(q, dtype=float))
        rev = np.ones(q.shape[1], dtype=bool)
        lo, hi = self.q_train.min(axis=0), self.q_train.max(axis=0)
        F_train = features(self.q_train, rev)
        out = np.zeros(len(q), dtype=bool)
        for start in range(0, len(q), EVALUATE_CHUNK_ROWS):
            part = slice(start, start + EVALUATE_CHUNK_ROWS)
            d = np.sqrt(_sqdist(features(q[part], rev), F_train).min(axis=1))
            out[part] = np.all((q[part] >= lo) & (q[part] <= hi), axis=1) & (d <= self.radius)
        return out

    def evaluate(self, q: np.ndarray, p_tool: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The correction (N, 3) m and (N,) inside, as a residual map's (zero outside)."""
        inside = self.inside(q)
        corr = self.raw(q)
        corr[~inside] = 0.0
        return corr, inside


def training_radius(q_train: np.ndarray) -> float:
    """:data:`RADIUS_FACTOR` times the 95th percentile of each training configuration's distance
    to its nearest other one (chordal, on (cos q, sin q))."""
    from .residual_base import features
    from .residual_base import sqdist as _sqdist

    F = features(q_train, np.ones(q_train.shape[1], dtype=bool))
    d = np.full(len(F), np.inf)
    for start in range(0, len(F), EVALUATE_CHUNK_ROWS):
        part = slice(start, start + EVALUATE_CHUNK_ROWS)
        D = _sqdist(F[part], F)
        D[np.arange(D.shape[0]), np.arange(start, start + D.shape[0])] = np.inf
        d[part] = np.sqrt(D.min(axis=1))
    return float(RADIUS_FACTOR * np.percentile(d[np.isfinite(d)], 95)) if len(F) > 1 else 0.0


def export_sklearn(estimator) -> tuple[float, tuple[Tree, ...]]:
    """A fitted ``HistGradientBoostingRegressor``'s baseline and trees as plain arrays (numeric
    splits only: the fit uses no categorical features, and the inputs are never missing)."""
    trees = []
    for (predictor,) in estimator._predictors:  # one tree per iteration for a single output
        nodes = predictor.nodes
        leaf = nodes["is_leaf"].astype(bool)
        trees.append(
            Tree(
                feature=np.where(leaf, -1, nodes["feature_idx"]).astype(np.intp),
                threshold=np.where(leaf, 0.0, nodes["num_threshold"]).astype(float),
                left=np.where(leaf, -1, nodes["left"].astype(np.int64)).astype(np.intp),
                right=np.where(leaf, -1, nodes["right"].astype(np.int64)).astype(np.intp),
                value=np.where(leaf, nodes["value"], 0.0).astype(float),
            )
        )
    return float(np.ravel(estimator._baseline_prediction)[0]), tuple(trees)


def fit_trees(q: np.ndarray, residuals: np.ndarray, *, seed: int = 0) -> BoostedTrees:
    """Boosted trees of ``residuals`` (M, 3) m on readings ``q`` (M, n), one ensemble per axis,
    each axis's number of trees chosen by :func:`choose_tree_count` on these rows alone."""
    from sklearn.ensemble import HistGradientBoostingRegressor  # the fit only: see the module
    from threadpoolctl import threadpool_limits  # scikit-learn's own dependency

    q = np.atleast_2d(np.asarray(q, dtype=float))
    R = np.asarray(residuals, dtype=float)
    folds = configuration_folds(q, INNER_FOLDS, seed)
    baseline, trees, counts = [], [], []
    # One OpenMP thread: a few thousand rows a tree are too few to share, and on a loaded machine
    # OpenMP's waiting threads made the same fit many times slower (a CLI test went past its
    # 5-minute limit; one thread: 3.2 s against 4.6 s on a quiet one). Same trees either way.
    with threadpool_limits(limits=1, user_api="openmp"):
        for axis in range(3):
            count = choose_tree_count(q, R[:, axis], folds, seed)
            est = HistGradientBoostingRegressor(
                early_stopping=False, random_state=seed, max_iter=count, **TREE_SETTINGS
            )
            est.fit(q, R[:, axis])
            b, t = export_sklearn(est)
            baseline.append(b)
            trees.append(t)
            counts.append(count)
    settings = {**TREE_SETTINGS, "trees_per_axis": counts, "chosen_by": f"{len(folds)}-fold inner cross-validation"}
    return BoostedTrees(np.array(baseline), tuple(trees), q.copy(), training_radius(q), settings=settings)


def configuration_folds(q: np.ndarray, k: int, seed: int) -> list[np.ndarray]:
    """Row indices of ``k`` folds, every row of one configuration in the same fold (rows of one
    pose share its error: splitting them would let a fold see its own test configuration)."""
    _, group = np.unique(np.round(q, 12), axis=0, return_inverse=True)
    group = np.ravel(group)
    n_groups = int(group.max()) + 1 if len(group) else 0
    k = min(k, n_groups)
    fold_of_group = np.random.default_rng(seed).permutation(n_groups) % max(k, 1)
    return [np.flatnonzero(fold_of_group[group] == f) for f in range(k)]


def choose_tree_count(q: np.ndarray, y: np.ndarray, folds: list[np.ndarray], seed: int) -> int:
    """The number of trees (a multiple of :data:`TREES_STEP`, at most :data:`MAX_TREES`) with the
    least k-fold cross-validated squared error of ``y`` on ``q``: the trees grown in steps on each
    fold's other rows (scikit-learn's warm start adds trees to the same ensemble), stopped when
    :data:`PATIENCE_TREES` more trees have not lowered the error. Fewer than two folds: one step."""
    from sklearn.ensemble import HistGradientBoostingRegressor

    if len(folds) < 2:
        return TREES_STEP
    ests = [
        HistGradientBoostingRegressor(early_stopping=False, random_state=seed, warm_start=True, **TREE_SETTINGS)
        for _ in folds
    ]
    best_count, best_sse, count = TREES_STEP, np.inf, 0
    while count < MAX_TREES and count - best_count < PATIENCE_TREES:
        count += TREES_STEP
        sse = 0.0
        for est, test in zip(ests, folds, strict=True):
            train = np.setdiff1d(np.arange(len(y)), test)
            est.set_params(max_iter=count)
            est.fit(q[train], y[train])
            sse += float(np.sum((y[test] - est.predict(q[test])) ** 2))
        if sse < best_sse:
            best_count, best_sse = count, sse
    return best_count


# ----------------------------------------------------------------------------- the file section


def to_dict(m: BoostedTrees, model) -> dict:
    """The model file's ``residual_map`` section for the trees: thresholds and configurations in
    the model's joint units, values and baselines in its length unit."""
    u = model.units
    scale = np.array([u.angle_rad if j.revolute else u.length_m for j in model.joints])
    L = u.length_m

    def tree(t: Tree) -> dict:
        thr = np.where(t.feature >= 0, t.threshold / scale[np.maximum(t.feature, 0)], 0.0)
        return {
            "feature": t.feature.tolist(),
            "threshold": thr.tolist(),
            "left": t.left.tolist(),
            "right": t.right.tolist(),
            "value": (t.value / L).tolist(),
        }

    return {
        "format": FORMAT,
        "family": "trees",
        "inputs": "joint readings in the model's joint units; go left when value <= threshold",
        "baseline": (m.baseline / L).tolist(),
        "trees": [[tree(t) for t in axis] for axis in m.trees],
        "configurations": (m.q_train / scale).tolist(),
        "radius": m.radius,
        "settings": m.settings,
        "cross_validation": {k: (v / L if k.endswith("_m") else v) for k, v in m.cv.items()},
    }


def from_dict(d: dict, model) -> BoostedTrees:
    """The trees a model file's ``residual_map`` section of :data:`FORMAT` stores."""
    from .residual_base import ResidualMapError

    u = model.units
    n = model.n_joints
    scale = np.array([u.angle_rad if j.revolute else u.length_m for j in model.joints])
    L = u.length_m
    try:
        baseline = np.array(d["baseline"], dtype=float) * L
        Q = np.array(d["configurations"], dtype=float)
        radius = float(d["radius"])
        axes = d["trees"]
        if baseline.shape != (3,) or Q.ndim != 2 or Q.shape[1] != n or not isinstance(axes, list) or len(axes) != 3:
            raise ValueError("shape")
    except (KeyError, TypeError, ValueError):
        raise ResidualMapError(
            "residual_map.trees",
            f"expected baseline (3 numbers), trees (3 lists), configurations (rows of {n}) and radius",
        ) from None
    out = []
    for a, axis in enumerate(axes):
        trees = []
        for k, td in enumerate(axis if isinstance(axis, list) else []):
            trees.append(_tree_from_dict(td, f"residual_map.trees[{a}][{k}]", n, scale, L))
        out.append(tuple(trees))
    cv = dict(d.get("cross_validation") or {})
    settings = d["settings"] if isinstance(d.get("settings"), dict) else {}  # informative only
    return BoostedTrees(baseline, tuple(out), Q * scale, radius, cv, settings)


def _tree_from_dict(td, where: str, n: int, scale: np.ndarray, L: float) -> Tree:
    from .residual_base import ResidualMapError

    try:
        f = np.array(td["feature"], dtype=np.intp)
        thr = np.array(td["threshold"], dtype=float)
        left = np.array(td["left"], dtype=np.intp)
        right = np.array(td["right"], dtype=np.intp)
        val = np.array(td["value"], dtype=float)
    except (KeyError, TypeError, ValueError):
        raise ResidualMapError(where, "expected feature, threshold, left, right and value: lists of numbers") from None
    m = len(f)
    internal = f >= 0
    ok = (
        m > 0
        and all(a.shape == (m,) for a in (thr, left, right, val))
        and np.all(f < n)
        and np.all(np.isfinite(thr))
        and np.all(np.isfinite(val))
        # children point forward within the tree: every walk ends at a leaf
        and np.all((left[internal] > np.flatnonzero(internal)) & (left[internal] < m))
        and np.all((right[internal] > np.flatnonzero(internal)) & (right[internal] < m))
    )
    if not ok:
        raise ResidualMapError(where, f"expected a tree of nodes over {n} joints whose children come after them")
    return Tree(f, np.where(internal, thr * scale[np.maximum(f, 0)], 0.0), left, right, val * L)
