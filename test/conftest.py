"""Shared fixtures: synthetic scenes generated once per test session.

``scene_factory(kind, seed, variant, **options)`` returns the folder of a generated scene
(docs/CONTRACTS.md format), cached by its arguments; options are :class:`SceneOptions` fields
applied on top of the ``small`` size (50 scans). ``demo_scene`` is the small junction scene used by
the end-to-end and calibration tests (about 10-20 s to generate on 2 cores, a 5 s bag).
"""

from __future__ import annotations

import os

# OpenBLAS spins up threads even for (N, 3) x (3, 3) products; with 2 cores shared by parallel
# jobs that makes such a product ~100x slower (measured 110 ms vs 0.6 ms). Must precede numpy.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import fcntl  # noqa: E402
import hashlib  # noqa: E402
import shutil  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Callable  # noqa: E402

import pytest  # noqa: E402


def _file_rank(items: list[pytest.Item]) -> dict[Path, int]:
    """Per test file: 0 if it holds a test marked ``slow``, 1 if one marked ``ros`` (processes
    that wait on each other), else 2."""
    rank: dict[Path, int] = {}
    for item in items:
        mark = 0 if item.get_closest_marker("slow") else 1 if item.get_closest_marker("ros") else 2
        rank[item.path] = min(rank.get(item.path, 2), mark)
    return rank


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The files holding slow tests first, then those starting ROS processes, then the rest (each
    group in collection order): the suite's workers take whole files (``--dist loadfile``, with
    ``--no-loadscope-reorder`` so this order is the one they follow), and a long file taken last
    leaves one worker busy while the others idle. ``SEMCAL_TEST_ORDER=reverse`` runs the tests in
    reverse order: every test must build the state it checks, whatever ran before it in its file
    (module fixtures included)."""
    rank = _file_rank(items)
    items.sort(key=lambda item: rank[item.path])  # stable: files stay whole
    if os.environ.get("SEMCAL_TEST_ORDER", "") == "reverse":
        items.reverse()


@pytest.fixture(scope="session")
def scene_factory(tmp_path_factory: pytest.TempPathFactory) -> Callable[..., Path]:
    """Scenes are generated once per run, not once per worker: under pytest-xdist the workers
    share a folder beside their own temporary folders, and the first worker to ask for a scene
    generates it while the others wait on its lock (the demo scene alone is about 10 s of CPU,
    which three workers paid three times). Tests read scenes and never write into them."""
    from semcal_tools.scenes import SIZES, generate_scene

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent / "shared-scenes"
        root.mkdir(exist_ok=True)
    cache: dict[tuple, Path] = {}

    def make(kind: str = "junction", seed: int = 0, variant: str = "ideal", **options) -> Path:
        key = (kind, seed, variant, tuple(sorted(options.items())))
        if key not in cache:
            digest = hashlib.sha1(repr(key).encode()).hexdigest()[:10]
            out = root / f"scene-{kind}-{variant}-{seed}-{digest}"
            with open(root / f"{out.name}.lock", "w") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
                done = root / f"{out.name}.done"
                if not done.is_file():
                    shutil.rmtree(out, ignore_errors=True)  # a worker that died half-way
                    out.mkdir()
                    generate_scene(out, kind, seed, variant, replace(SIZES["small"], **options),
                                   progress=False)
                    done.touch()
            cache[key] = out
        return cache[key]

    return make


@pytest.fixture(scope="session")
def world():
    """The small synthetic street (12 cm sampling) the engine tests calibrate against."""
    from semcal_tools.synthetic import street_world

    return street_world(step=0.12)


@pytest.fixture(scope="session")
def target(world):
    """The street rendered as the calibrator renders it at the ground truth (loss 0 there)."""
    from semcal_tools.synthetic import camera, target_image

    return target_image(camera(), world=world)


@pytest.fixture(scope="session")
def demo_scene(scene_factory: Callable[..., Path]) -> Path:
    """A small but realistic junction scene with everything: map, scans, images, bag."""
    return scene_factory("junction", 0, "ideal")


#: Real data shared beside the checkout (../shared/data); tests that need it skip without it.
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
REAL_WEIGHTS = {
    "espnetv2": SHARED_DATA / "models" / "espnetv2_cityscapes" / "espnetv2_s_2.0_city_1024x512.npz",
    "espnet": SHARED_DATA / "models" / "espnet_cityscapes" / "espnet_p_2_q_8.npz",
}


@pytest.fixture(scope="session")
def exported(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, Path]]:
    """Both real networks exported once per session: arch -> (model.onnx, config beside it)."""
    from semcal_ros.segmentation.export.exporter import export_model

    if not all(p.is_file() for p in REAL_WEIGHTS.values()):
        pytest.skip(f"real segmentation weights not found under {SHARED_DATA}")
    root = tmp_path_factory.mktemp("real-models")
    out = {}
    for arch, weights in REAL_WEIGHTS.items():
        result = export_model(arch, weights, root / f"{arch}.onnx")
        out[arch] = (result.model_path, result.config_path)
    return out


@pytest.fixture
def graph(tmp_path: Path):
    """The ROS processes of one test in a domain of their own (test/ros_helpers.py); their logs
    are printed, and shown by pytest only when the test failed."""
    from ros_helpers import RosGraph

    g = RosGraph(tmp_path / "logs")
    yield g
    g.close()
    print(g.logs())
