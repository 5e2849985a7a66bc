"""Perturbations of the arithmetic that leave the data unchanged: a test of machine independence.

Two machines run the same calibration on the same files and still round differently: another CPU
takes other SIMD paths (numpy's dispatch, Embree's ray casts in the scene generator), another
thread count splits the renders' z-buffers otherwise, another reader hands the map's points over
in another order. None of that changes what the data say, so no decision of the product (a
verdict, a drift alarm, a test's pass) may change with it. ``SEMCAL_PERTURB`` makes such a
difference on one machine, so that a decision balanced on the rounding shows here and not first
on somebody else's CPU (``make test-perturbed`` runs the engine and node tests under each):

* ``order``: the map's points shuffled (a fixed seed) before the engine prepares them;
* ``jitter=E``: every map coordinate moved by a uniform offset in [-E, E] metres (1e-6: a
  micrometre, far below any lidar's noise, well above float64 rounding).

Several are joined with commas (``order,jitter=1e-6``). The render's thread count is numba's
(``NUMBA_NUM_THREADS``) and numpy's SIMD is numpy's (``NPY_DISABLE_CPU_FEATURES``): neither
needs a hook here. Unset (the default) nothing is touched and nothing is computed.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

ENV = "SEMCAL_PERTURB"
SEED = 20261128


@dataclass(frozen=True)
class Perturbation:
    """What ``SEMCAL_PERTURB`` asks for (see the module docstring)."""

    order: bool = False
    jitter_m: float = 0.0

    @property
    def active(self) -> bool:
        return self.order or self.jitter_m > 0.0

    @classmethod
    def parse(cls, text: str) -> "Perturbation":
        order, jitter = False, 0.0
        for item in filter(None, (part.strip() for part in text.split(","))):
            name, _, value = item.partition("=")
            if name == "order" and not value:
                order = True
            elif name == "jitter" and value:
                jitter = float(value)
                if not (np.isfinite(jitter) and 0.0 <= jitter <= 1e-3):
                    raise ValueError(f"{ENV}: jitter must be in [0, 1e-3] m, got {value}")
            else:
                raise ValueError(f"{ENV}: unknown item {item!r} (known: order, jitter=E)")
        return cls(order, jitter)

    @classmethod
    def from_env(cls) -> "Perturbation":
        return cls.parse(os.environ.get(ENV, ""))


def perturb_points(xyz: np.ndarray, *columns: np.ndarray | None
                   ) -> tuple[np.ndarray, tuple[np.ndarray | None, ...]]:
    """The map's points (and the per-point ``columns`` that go with them, None passed through)
    as ``SEMCAL_PERTURB`` asks; unchanged (the same arrays) when it is unset."""
    how = Perturbation.from_env()
    if not how.active or len(xyz) == 0:
        return xyz, columns
    rng = np.random.default_rng(SEED)
    if how.order:
        order = rng.permutation(len(xyz))
        xyz = xyz[order]
        columns = tuple(None if c is None else c[order] for c in columns)
    if how.jitter_m > 0.0:
        xyz = xyz + rng.uniform(-how.jitter_m, how.jitter_m, xyz.shape)
    return xyz, columns


__all__ = ["ENV", "Perturbation", "perturb_points"]
