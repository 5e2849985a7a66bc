"""A random forest's inference from plain arrays (an ``.npz``, no pickle), compiled with numba.

The point labeller's model is a forest of decision trees trained offline
(``semcal_tools/train_point_labeller.py``, scikit-learn at training time only). All trees' nodes
are stored in flat arrays: ``feature`` (-1 at a leaf), ``threshold`` (go left when the value
is <= it), ``left`` / ``right`` child indices (at a leaf ``left`` is the row of
``leaf_values``), ``roots`` the first node of each tree, ``leaf_values`` the class shares of each
leaf (uint8, 255 = all). A forest's class probability is the mean of its trees' leaf shares.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numba as nb
import numpy as np

# As in engine.render.fast: OpenMP (in the numba wheel) without a probe of an old TBB that
# warns, and idle pool threads that sleep instead of spinning on 2 shared cores.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
if not os.environ.get("NUMBA_THREADING_LAYER"):
    nb.config.THREADING_LAYER = "omp"  # type: ignore[attr-defined]

_ARRAYS = ("feature", "threshold", "left", "right", "roots", "leaf_values", "classes",
           "feature_names")


@nb.njit(parallel=True, cache=True, nogil=True)
def _predict(x, roots, feature, threshold, left, right, leaf_values):  # pragma: no cover - numba
    n, c = x.shape[0], leaf_values.shape[1]
    out = np.zeros((n, c), np.float32)
    for i in nb.prange(n):
        for t in range(roots.shape[0]):
            node = roots[t]
            while feature[node] >= 0:
                if x[i, feature[node]] <= threshold[node]:
                    node = left[node]
                else:
                    node = right[node]
            row = left[node]
            for k in range(c):
                out[i, k] += leaf_values[row, k]
    scale = np.float32(1.0 / (255.0 * roots.shape[0]))
    for i in nb.prange(n):
        for k in range(c):
            out[i, k] *= scale
    return out


@dataclass(frozen=True)
class Forest:
    """A trained forest: ``predict_proba(x)`` gives (V, len(classes)) class shares."""

    feature: np.ndarray
    threshold: np.ndarray
    left: np.ndarray
    right: np.ndarray
    roots: np.ndarray
    leaf_values: np.ndarray
    classes: np.ndarray  # output id of each class column (SemanticKITTI ids, 0 = unlabeled)
    feature_names: tuple[str, ...]

    @classmethod
    def load(cls, path: str | Path, feature_names: tuple[str, ...]) -> "Forest":
        """Read a forest file and check it was trained on ``feature_names`` in that order."""
        path = Path(path)
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in _ARRAYS if k not in data]
            if missing:
                raise ValueError(f"{path}: not a forest file (missing {', '.join(missing)})")
            arrays = {k: data[k] for k in _ARRAYS}
        names = tuple(str(s) for s in arrays.pop("feature_names"))
        if names != tuple(feature_names):
            raise ValueError(f"{path}: trained on features {names}, the labeller computes "
                             f"{tuple(feature_names)}; retrain the model")
        forest = cls(np.ascontiguousarray(arrays["feature"], np.int32),
                     np.ascontiguousarray(arrays["threshold"], np.float32),
                     np.ascontiguousarray(arrays["left"], np.int32),
                     np.ascontiguousarray(arrays["right"], np.int32),
                     np.ascontiguousarray(arrays["roots"], np.int32),
                     np.ascontiguousarray(arrays["leaf_values"], np.uint8),
                     np.asarray(arrays["classes"], np.uint16), names)
        forest.check()
        return forest

    def check(self) -> None:
        """Refuse arrays that would index out of bounds inside the compiled loop."""
        n = len(self.feature)
        ok = (len(self.threshold) == n and len(self.left) == n and len(self.right) == n
              and len(self.roots) > 0 and self.leaf_values.shape[1] == len(self.classes)
              and self.roots.min() >= 0 and self.roots.max() < n
              and self.feature.max() < len(self.feature_names))
        inner = self.feature >= 0
        ok = ok and bool(np.all((self.left[inner] >= 0) & (self.left[inner] < n)
                                & (self.right[inner] >= 0) & (self.right[inner] < n)))
        ok = ok and bool(np.all((self.left[~inner] >= 0)
                                & (self.left[~inner] < len(self.leaf_values))))
        if not ok:
            raise ValueError("forest arrays are inconsistent (child, leaf or feature index out "
                             "of range)")

    def predict_proba(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, np.float32)
        if x.ndim != 2 or x.shape[1] != len(self.feature_names):
            raise ValueError(f"forest input must be (n, {len(self.feature_names)}), got {x.shape}")
        return _predict(x, self.roots, self.feature, self.threshold, self.left, self.right,
                        self.leaf_values)

    def save(self, path: str | Path) -> None:
        np.savez_compressed(path, feature=self.feature, threshold=self.threshold,
                            left=self.left, right=self.right, roots=self.roots,
                            leaf_values=self.leaf_values, classes=self.classes,
                            feature_names=np.array(self.feature_names))


def from_sklearn(model, classes: np.ndarray, feature_names: tuple[str, ...]) -> Forest:
    """A fitted scikit-learn forest (RandomForest / ExtraTrees classifier) as flat arrays.
    Thresholds are rounded down to float32 so that float32 features split as in scikit-learn
    (which compares float32 inputs with float64 thresholds)."""
    feats, thrs, lefts, rights, roots, leaves = [], [], [], [], [], []
    offset = leaf_offset = 0
    for est in model.estimators_:
        tree = est.tree_
        n = tree.node_count
        is_leaf = tree.children_left < 0
        feature = np.where(is_leaf, -1, tree.feature).astype(np.int32)
        thr64 = tree.threshold
        thr = thr64.astype(np.float32)
        # float32(x) <= t64  <=>  x <= largest float32 not above t64
        above = thr.astype(np.float64) > thr64
        thr[above] = np.nextafter(thr[above], np.float32(-np.inf))
        leaf_rows = np.cumsum(is_leaf) - 1 + leaf_offset
        left = np.where(is_leaf, leaf_rows, tree.children_left + offset).astype(np.int32)
        right = np.where(is_leaf, -1, tree.children_right + offset).astype(np.int32)
        value = tree.value[is_leaf, 0, :]
        value = value / np.maximum(value.sum(axis=1, keepdims=True), 1e-12)
        feats.append(feature)
        thrs.append(thr)
        lefts.append(left)
        rights.append(right)
        roots.append(offset)
        leaves.append(np.round(value * 255).astype(np.uint8))
        offset += n
        leaf_offset += int(is_leaf.sum())
    return Forest(np.concatenate(feats), np.concatenate(thrs), np.concatenate(lefts),
                  np.concatenate(rights), np.array(roots, np.int32), np.concatenate(leaves),
                  np.asarray(classes, np.uint16), tuple(feature_names))
