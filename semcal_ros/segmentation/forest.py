"""A random forest's inference from plain arrays (an ``.npz``, no pickle), compiled with numba.

The point labeller's model is a forest of decision trees trained offline
(``semcal_tools/train_point_labeller.py``, scikit-learn at training time only). All trees' nodes
are stored in flat arrays: ``feature`` (-1 at a leaf), ``threshold`` (go left when the value
is <= it), ``left`` / ``right`` child indices (at a leaf ``left`` is the row of
``leaf_values``), ``roots`` the first node of each tree, ``leaf_values`` the class shares of each
leaf (uint8, 255 = all). A forest's class probability is the mean of its trees' leaf shares.
At load the nodes are re-ordered for the walk (children adjacent, breadth first), and the
walk goes one tree at a time over blocks of voxels, which keeps a tree in the cache.
"""

from __future__ import annotations

import functools
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


@nb.njit(cache=True, nogil=True)
def _relayout(roots, feature, threshold, left, right):  # pragma: no cover - numba
    """The trees in breadth-first order with each node's two children adjacent: a node's
    ``child`` is its left child (``child + 1`` the right one) or, at a leaf, its leaf row.
    The walk then needs two arrays and no branch on the comparison (see :func:`_predict`)."""
    n = feature.shape[0]
    new_feature = np.empty(n, np.int32)
    new_threshold = np.empty(n, np.float32)
    child = np.empty(n, np.int32)
    new_roots = np.empty(roots.shape[0], np.int32)
    queue = np.empty(n, np.int64)  # old node ids in their new order
    tail = 0
    for t in range(roots.shape[0]):
        head = tail
        new_roots[t] = head
        queue[tail] = roots[t]
        tail += 1
        while head < tail:
            old = queue[head]
            new_feature[head] = feature[old]
            new_threshold[head] = threshold[old]
            if feature[old] >= 0:
                if tail + 2 > n:  # a node reached twice: not a forest of trees
                    raise ValueError("forest arrays are inconsistent (a node has two parents)")
                child[head] = tail
                queue[tail] = left[old]
                queue[tail + 1] = right[old]
                tail += 2
            else:
                child[head] = left[old]
            head += 1
    return new_roots, new_feature, new_threshold, child


#: Voxels per block of the compiled walk: one tree at a time over a block keeps that tree's
#: nodes in the core's cache (walking all trees for one voxel at a time touches the whole
#: forest, 4.7 MB, per voxel: 1.5x slower on KITTI).
_BLOCK = 512


@nb.njit(parallel=True, cache=True, nogil=True)
def _predict(x, roots, feature, threshold, child, leaf_values):  # pragma: no cover - numba
    n, c = x.shape[0], leaf_values.shape[1]
    out = np.zeros((n, c), np.float32)
    blocks = (n + _BLOCK - 1) // _BLOCK
    scale = np.float32(1.0 / (255.0 * roots.shape[0]))
    for b in nb.prange(blocks):
        lo = b * _BLOCK
        hi = min(n, lo + _BLOCK)
        acc = np.zeros((hi - lo, c), np.int32)
        for t in range(roots.shape[0]):
            root = roots[t]
            for i in range(lo, hi):
                node = root
                f = feature[node]
                while f >= 0:
                    node = child[node] + (1 if x[i, f] > threshold[node] else 0)
                    f = feature[node]
                row = child[node]
                for k in range(c):
                    acc[i - lo, k] += leaf_values[row, k]
        for i in range(lo, hi):
            for k in range(c):
                out[i, k] = acc[i - lo, k] * scale
    return out


@nb.njit(parallel=True, cache=True, nogil=True)
def smoothed_best(shares, neighbours, k):  # pragma: no cover - numba
    """(best class column, its share) of each row after averaging the class shares over the
    row's first ``k`` ``neighbours`` (itself included): one pass, no (V, k, C) temporary."""
    n, c = shares.shape
    best = np.zeros(n, np.int64)
    top = np.zeros(n, np.float32)
    for i in nb.prange(n):
        acc = np.zeros(c, np.float32)
        for j in range(k):
            row = neighbours[i, j]
            for m in range(c):
                acc[m] += shares[row, m]
        b = 0
        for m in range(1, c):
            if acc[m] > acc[b]:
                b = m
        best[i] = b
        top[i] = acc[b] / k
    return best, top


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
        roots, feature, threshold, child = self._walk_layout
        return _predict(x, roots, feature, threshold, child, self.leaf_values)

    @functools.cached_property
    def _walk_layout(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The nodes re-ordered for :func:`_predict` (once per forest, a few ms)."""
        return _relayout(self.roots, self.feature, self.threshold, self.left, self.right)

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
