"""SEMCAL_PERTURB (semcal_ros/engine/numerics.py): the map handed to the engine in another order
or moved by a micrometre, the data otherwise unchanged; unset, nothing is touched."""

from __future__ import annotations

import numpy as np
import pytest

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.numerics import ENV, Perturbation, perturb_points
from semcal_ros.engine.render import prepare_map


def test_parse_names_every_bad_item():
    assert Perturbation.parse("") == Perturbation()
    assert Perturbation.parse("order, jitter=1e-6") == Perturbation(True, 1e-6)
    for bad in ("shuffle", "jitter", "jitter=1", "order=2", "jitter=nan"):
        with pytest.raises(ValueError, match=ENV):
            Perturbation.parse(bad)


def test_unset_passes_the_same_arrays(monkeypatch):
    monkeypatch.delenv(ENV, raising=False)
    xyz, label = np.random.default_rng(0).normal(size=(50, 3)), np.arange(50)
    out, (lab,) = perturb_points(xyz, label)
    assert out is xyz and lab is label


def test_order_and_jitter_keep_each_point_with_its_label(monkeypatch):
    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(500, 3)) * 20.0
    label = rng.integers(0, 30, 500)
    monkeypatch.setenv(ENV, "order,jitter=1e-6")
    out, (lab, none) = perturb_points(xyz, label, None)
    assert none is None and not np.array_equal(lab, label)  # another order
    back = np.lexsort((lab, out[:, 0].round(4)))
    ref = np.lexsort((label, xyz[:, 0].round(4)))
    assert np.array_equal(lab[back], label[ref])  # the same points with the same labels
    moved = np.abs(out[back] - xyz[ref])
    assert 0.0 < moved.max() <= 1e-6 + 1e-12


def test_the_prepared_map_holds_the_same_points(monkeypatch):
    rng = np.random.default_rng(2)
    cloud = LabelledCloud(rng.uniform(-30, 30, (3000, 3)), np.full(3000, 40, np.uint16))
    plain = prepare_map(cloud)
    monkeypatch.setenv(ENV, "order")
    shuffled = prepare_map(cloud)
    assert len(plain) == len(shuffled)
    key = lambda p: np.sort(np.round(p.xyz.astype(np.float64) + p.origin, 3), axis=0)  # noqa: E731
    assert np.allclose(key(plain), key(shuffled), atol=1e-3)
