"""The point labeller's parts: the forest's compiled inference against a plain reference walk,
the shipped model file, the closed-form eigen features against numpy, and refusals in one line."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from semcal_ros.segmentation.forest import Forest
from semcal_ros.segmentation.geometric import MODEL_FILE, load_model
from semcal_ros.segmentation.point_features import FEATURE_NAMES, FeatureParams, _neighbourhoods


def two_trees() -> Forest:
    """Tree 0: x0 <= 0.5 -> leaf A (class 0) else (x1 <= 2 -> leaf B (class 1), leaf C (50/50));
    tree 1: a single leaf D (class 1)."""
    feature = np.array([0, -1, 1, -1, -1, -1], np.int32)
    threshold = np.array([0.5, 0, 2.0, 0, 0, 0], np.float32)
    left = np.array([1, 0, 3, 1, 2, 3], np.int32)
    right = np.array([2, -1, 4, -1, -1, -1], np.int32)
    roots = np.array([0, 5], np.int32)
    leaves = np.array([[255, 0], [0, 255], [128, 127], [0, 255]], np.uint8)
    return Forest(feature, threshold, left, right, roots, leaves, np.array([0, 40], np.uint16),
                  ("a", "b"))


def reference_walk(forest: Forest, x: np.ndarray) -> np.ndarray:
    out = np.zeros((len(x), forest.leaf_values.shape[1]))
    for i, row in enumerate(x):
        for root in forest.roots:
            node = root
            while forest.feature[node] >= 0:
                node = (forest.left[node] if row[forest.feature[node]] <= forest.threshold[node]
                        else forest.right[node])
            out[i] += forest.leaf_values[forest.left[node]] / 255.0
    return out / len(forest.roots)


def test_forest_inference_matches_a_plain_walk_of_the_trees():
    forest = two_trees()
    forest.check()
    x = np.array([[0.5, 9.0], [0.51, 2.0], [3.0, 2.01], [-1.0, -1.0]], np.float32)
    got = forest.predict_proba(x)
    np.testing.assert_allclose(got, reference_walk(forest, x), atol=1e-6)
    # the threshold is inclusive on the left: x0 = 0.5 goes to leaf A
    np.testing.assert_allclose(got[0], [0.5, 0.5], atol=1e-6)
    np.testing.assert_allclose(got[2], [64 / 255, 191 / 255], atol=1e-3)


def test_shipped_model_is_small_and_consistent():
    assert MODEL_FILE.is_file()
    assert MODEL_FILE.stat().st_size < 4_000_000
    forest = load_model()
    assert forest.feature_names == FEATURE_NAMES
    assert len(forest.roots) >= 8
    assert set(forest.classes.tolist()) >= {40, 48, 50, 70, 80, 10}
    rng = np.random.default_rng(0)
    x = rng.normal(size=(300, len(FEATURE_NAMES))).astype(np.float32)
    shares = forest.predict_proba(x)
    np.testing.assert_allclose(shares.sum(axis=1), 1.0, atol=0.03)
    sample = rng.choice(len(x), 20, replace=False)
    np.testing.assert_allclose(shares[sample], reference_walk(forest, x[sample]), atol=1e-5)


def test_bad_model_files_are_refused_in_one_line(tmp_path):
    not_forest = tmp_path / "x.npz"
    np.savez(not_forest, a=np.zeros(3))
    with pytest.raises(ValueError, match="not a forest file") as err:
        Forest.load(not_forest, FEATURE_NAMES)
    assert "\n" not in str(err.value)
    other = tmp_path / "other.npz"
    two_trees().save(other)
    with pytest.raises(ValueError, match="retrain the model"):
        Forest.load(other, FEATURE_NAMES)
    broken = two_trees()
    bad = Forest(broken.feature, broken.threshold, broken.left + 7, broken.right, broken.roots,
                 broken.leaf_values, broken.classes, broken.feature_names)
    with pytest.raises(ValueError, match="out of range"):
        bad.check()
    with pytest.raises(ValueError, match=r"forest input must be \(n, 2\)"):
        two_trees().predict_proba(np.zeros((3, 5), np.float32))


def test_closed_form_eigen_features_match_numpy():
    rng = np.random.default_rng(1)
    centroid = rng.normal(size=(400, 3)) * [4.0, 1.0, 0.2]
    params = FeatureParams(knn_small=8, knn_large=20)
    feats, idx = _neighbourhoods(centroid, params)
    for k, offset in ((8, 0), (20, 7)):
        _, nn = cKDTree(centroid).query(centroid, k=k)
        nb = centroid[nn]
        centred = nb - nb.mean(axis=1, keepdims=True)
        values, vectors = np.linalg.eigh(np.einsum("vki,vkj->vij", centred, centred) / k)
        l3, l2, l1 = values[:, 0], values[:, 1], values[:, 2]
        np.testing.assert_allclose(feats[:, offset], (l1 - l2) / l1, atol=1e-4)
        np.testing.assert_allclose(feats[:, offset + 1], (l2 - l3) / l1, atol=1e-4)
        np.testing.assert_allclose(feats[:, offset + 2], l3 / l1, atol=1e-4)
        np.testing.assert_allclose(feats[:, offset + 3], np.abs(vectors[:, 2, 0]), atol=1e-3)
        np.testing.assert_allclose(feats[:, offset + 4], np.abs(vectors[:, 2, 2]), atol=1e-3)
        np.testing.assert_allclose(feats[:, offset + 5], np.sqrt(l1), rtol=1e-4)
    assert idx.shape == (400, 8)


def test_a_node_with_two_parents_is_refused_in_one_line():
    forest = two_trees()
    # node 2's right child is the root: a cycle, which the walk would never leave
    right = forest.right.copy()
    right[2] = 0
    bad = Forest(forest.feature, forest.threshold, forest.left, right, forest.roots,
                 forest.leaf_values, forest.classes, forest.feature_names)
    with pytest.raises(ValueError, match="two parents"):
        bad.predict_proba(np.zeros((2, 2), np.float32))


_FIRST_RUN = """
import sys
from semcal_ros.segmentation import forest, geometric, point_features
from semcal_ros.segmentation.geometric import SPARSE_LIDAR, GeometricParams, label_scan
from semcal_tools.precompile import labeller_scan
labels = label_scan(labeller_scan())
label_scan(labeller_scan(), None, GeometricParams(**SPARSE_LIDAR))
kernels = {"_predict": forest._predict, "_relayout": forest._relayout,
           "smoothed_best": forest.smoothed_best, "_kerb_steps": geometric._kerb_steps,
           "_radial_bridges": geometric._radial_bridges,
           "_eigen_features": point_features._eigen_features}
for name, kernel in kernels.items():
    stats = kernel.stats
    print(name, "hits", sum(stats.cache_hits.values()), "misses", sum(stats.cache_misses.values()))
print("labelled", int((labels > 0).sum()))
"""


def test_precompile_leaves_the_labeller_nothing_to_compile(tmp_path):
    """After ``semcal_tools.precompile``'s labeller step, a user's first label_scan loads every
    kernel from numba's cache (a fresh cache directory, two processes)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"),
           "PYTHONPATH": f"{repo}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    subprocess.run([sys.executable, "-c",
                    "from semcal_tools.precompile import compile_labeller; compile_labeller()"],
                   env=env, check=True, timeout=600)
    out = subprocess.run([sys.executable, "-c", _FIRST_RUN], env=env, check=True,
                         capture_output=True, text=True, timeout=600).stdout
    lines = dict(line.split(" ", 1) for line in out.strip().splitlines())
    for name in ("_predict", "_relayout", "smoothed_best", "_kerb_steps", "_radial_bridges",
                 "_eigen_features"):
        assert lines[name].endswith("misses 0"), out
        assert not lines[name].startswith("hits 0"), out
    assert int(lines["labelled"]) > 1000, out


def test_smoothed_best_is_the_argmax_of_the_neighbours_mean():
    from semcal_ros.segmentation.forest import smoothed_best

    rng = np.random.default_rng(3)
    shares = rng.random((200, 11)).astype(np.float32)
    neighbours = rng.integers(0, 200, (200, 10)).astype(np.int64)
    for k in (1, 4, 10):
        best, top = smoothed_best(shares, neighbours, k)
        mean = shares[neighbours[:, :k]].mean(axis=1)
        np.testing.assert_array_equal(best, mean.argmax(axis=1))
        np.testing.assert_allclose(top, mean.max(axis=1), rtol=1e-5)
