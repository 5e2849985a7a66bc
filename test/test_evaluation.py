"""The evaluation protocol: statistics by hand, initial guesses, one tiny real run, the CLI."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from semcal_tools.protocol import (
    ProtocolParams, evaluate_scene, format_table, initial_guesses, summarize,
)
from semcal_ros.io.files import pose_from_dict, read_pose
from semcal_ros.engine.evidence import STRIPS
from semcal_ros.engine.quality import VERDICTS
from semcal_ros.engine.params import CalibrationParams, ScheduleParams, VerificationParams
from semcal_ros.engine.pose import Pose, rotation_error_deg, translation_error

#: A short coarse stage and a few full-resolution steps, one start: enough to move a start,
#: cheap enough for a unit test.
CHEAP = replace(CalibrationParams(), schedule=ScheduleParams(
    scales=(4, 1), simplex=(1.0, 0.03), fatol=(1e-4, 1e-6), max_evaluations=(60, 5),
    restarts=(0, 0)), verification=VerificationParams(starts=0))


def test_summary_statistics_match_a_hand_computation():
    losses = [0.30, 0.10, 0.20, 0.10, 0.50]
    t = [0.02, 0.04, 0.10, 0.01, 1.00]  # m
    r = [0.05, 0.20, 0.03, 0.02, 2.00]  # deg
    s = [1.0, 2.0, 3.0, 4.0, 5.0]
    out = summarize(losses, t, r, s, keep=3)
    # lowest losses: run 1 (0.10), run 3 (0.10, later tie), run 2 (0.20)
    assert out.kept_translation_cm == pytest.approx((4 + 1 + 10) / 3)
    assert out.kept_rotation_deg == pytest.approx((0.20 + 0.02 + 0.03) / 3)
    assert out.all_translation_cm == pytest.approx((2 + 4 + 10 + 1 + 100) / 5)
    assert out.all_rotation_deg == pytest.approx((0.05 + 0.2 + 0.03 + 0.02 + 2.0) / 5)
    assert out.median_translation_cm == pytest.approx(4.0)
    # success (< 5 cm and < 0.1 deg): runs 0 and 3 of all; run 3 of the kept three
    assert out.success_rate == pytest.approx(2 / 5)
    assert out.kept_success_rate == pytest.approx(1 / 3)
    assert out.seconds_per_run == pytest.approx(3.0)
    assert (out.runs, out.keep) == (5, 3)
    with pytest.raises(ValueError, match="keep"):
        summarize(losses, t, r, s, keep=6)
    with pytest.raises(ValueError, match="equal length"):
        summarize(losses, t[:4], r, s, keep=2)


def test_initial_guesses_are_uniform_within_the_papers_ranges_and_seeded():
    truth = Pose.from_body_rpy_deg([10.0, -4.0, 6.0], [0.0, 18.0, 120.0])
    starts = initial_guesses(truth, ProtocolParams(runs=400, keep=10, seed=3))
    dt = np.array([s.translation - truth.translation for s in starts])
    drpy = np.array([s.body_rpy_deg() - truth.body_rpy_deg() for s in starts])
    assert np.abs(dt).max() <= 2.5 and np.abs(dt).max() > 2.3
    assert np.abs(drpy[:, 0]).max() < 1e-9  # roll untouched
    assert np.abs(drpy[:, 1:]).max() <= 5.0 + 1e-9 and np.abs(drpy[:, 1:]).max() > 4.7
    assert abs(dt.mean()) < 0.2  # centred: uniform noise around the truth
    again = initial_guesses(truth, ProtocolParams(runs=400, keep=10, seed=3))
    np.testing.assert_array_equal(starts[7].translation, again[7].translation)
    with pytest.raises(ValueError, match="--keep"):
        ProtocolParams(runs=5, keep=6)


def test_a_tiny_real_evaluation_reports_its_own_runs(demo_scene: Path):
    protocol = ProtocolParams(runs=2, keep=1, seed=1)
    seen = []
    res = evaluate_scene(demo_scene, "huber", protocol, CHEAP, on_run=lambda i, r: seen.append(i))
    assert seen == [0, 1] and res.scene == "junction/ideal seed 0" and res.loss == "huber"
    truth = read_pose(demo_scene / "ground_truth.yaml")
    for run, start in zip(res.runs, initial_guesses(truth, protocol)):
        np.testing.assert_allclose(run.start.translation, start.translation)
        assert run.translation_m == pytest.approx(translation_error(run.pose, truth))
        assert run.rotation_deg == pytest.approx(rotation_error_deg(run.pose, truth))
        # the schedule's renders plus the uncertainty's refinements on the four image strips
        # (engine/evidence.py) and the report's render
        evidence = STRIPS * (CHEAP.quality.evidence_evaluations + 1)
        assert 0 < run.evaluations <= 60 + 5 + 2 + evidence and run.loss >= 0
        assert run.quality["verdict"] in VERDICTS and len(run.quality["uncertainty_rpy_deg"]) == 3
    # the optimiser moved every start closer to the truth
    assert np.mean([r.translation_m for r in res.runs]) < np.mean(
        [translation_error(r.start, truth) for r in res.runs])
    expected = summarize([r.loss for r in res.runs], [r.translation_m for r in res.runs],
                         [r.rotation_deg for r in res.runs], [r.seconds for r in res.runs], 1)
    assert res.summary == expected
    assert res.best is min(res.runs, key=lambda r: r.loss).pose
    table = format_table([res])
    assert "| junction/ideal seed 0 | 1 of 2 |" in table and "Huber (kept)" in table


def test_cli_writes_json_table_and_overlay(demo_scene: Path, tmp_path: Path, capsys):
    from semcal_ros.cli import main

    config = tmp_path / "cheap.yaml"
    config.write_text("calibrator:\n  ros__parameters:\n    engine:\n      schedule:\n"
                      "        scales: [4, 1]\n        simplex: [1.0, 0.03]\n"
                      "        fatol: [0.0001, 0.000001]\n        max_evaluations: [12, 3]\n"
                      "        restarts: [0, 0]\n      verification: {starts: 0}\n")
    out = tmp_path / "ev.json"
    code = main(["evaluate", str(demo_scene), "--runs", "2", "--keep", "1", "--quiet",
                 "--config", str(config), "--json", str(out), "--overlay",
                 str(tmp_path / "ov_{scene}_{loss}.png")])
    assert code == 0
    printed = capsys.readouterr().out
    assert "| junction/ideal seed 0 | 1 of 2 |" in printed and "L2 (kept)" in printed
    data = json.loads(out.read_text())
    assert data["protocol"]["runs"] == 2
    runs = data["results"][0]["runs"]
    best = min(runs, key=lambda r: r["loss"])
    truth = read_pose(demo_scene / "ground_truth.yaml")
    assert data["results"][0]["summary"]["kept_translation_cm"] == pytest.approx(
        translation_error(pose_from_dict(best["pose"]), truth) * 100)
    assert (tmp_path / f"ov_{demo_scene.name}_l2.png").is_file()
    assert main(["evaluate", "--from-json", str(out)]) == 0  # the table again, from the JSON
    assert capsys.readouterr().out.strip() == printed.split("\nall numbers")[0].strip()

    assert main(["evaluate", str(tmp_path), "--runs", "2", "--keep", "1"]) == 1
    assert "not a scene folder" in capsys.readouterr().err
    assert main(["evaluate", str(demo_scene), "--runs", "2", "--keep", "3"]) == 1
    assert "--keep must be between" in capsys.readouterr().err


def test_a_refused_start_counts_as_a_failed_run(demo_scene: Path):
    from semcal_ros.engine.loss import LossParams

    blind = replace(CHEAP, loss=LossParams(min_coverage=1.0))  # no view covers everything
    res = evaluate_scene(demo_scene, "l2", ProtocolParams(runs=2, keep=1, seed=1), blind)
    assert len(res.runs) == 2 and res.summary.success_rate == 0.0
    for run in res.runs:
        assert "no map point in view" in run.error and run.evaluations == 0
        assert run.pose is run.start and run.loss == blind.loss.degenerate_loss


def test_cli_start_ranges_and_yaw_search_reach_the_protocol(demo_scene: Path, monkeypatch):
    """`--start-xyz/--start-pitch/--start-yaw` set the starts' ranges, `--yaw-search` the engine's
    full-circle heading search (the basin study in docs/engine.md runs through these)."""
    import semcal_tools.protocol as evaluation
    from semcal_ros.cli import main

    seen = []

    def record(folder, loss, protocol, params, *a, **kw):
        seen.append((protocol, params))
        raise ValueError("recorded")

    monkeypatch.setattr(evaluation, "evaluate_scene", record)
    assert main(["evaluate", str(demo_scene), "--runs", "2", "--keep", "1", "--quiet",
                 "--start-xyz", "0.5", "--start-pitch", "2", "--start-yaw", "180",
                 "--yaw-search"]) == 1
    assert main(["evaluate", str(demo_scene), "--runs", "2", "--keep", "1", "--quiet"]) == 1
    (p1, e1), (p2, e2) = seen
    assert (p1.noise_xyz_m, p1.noise_pitch_deg, p1.noise_yaw_deg) == (0.5, 2.0, 180.0)
    assert (p2.noise_xyz_m, p2.noise_pitch_deg, p2.noise_yaw_deg) == (2.5, 5.0, 5.0)
    assert e1.search.yaw_search and not e2.search.yaw_search


def test_the_parser_imports_no_numba_and_evaluate_checks_its_loss(capsys):
    """Every ``semcal`` command builds the whole parser: one subcommand importing the engine's
    loss package for its ``--loss`` choices cost every ``--help`` numba's 0.3-0.5 s."""
    import subprocess
    import sys

    from semcal_ros.cli import main

    probe = subprocess.run([sys.executable, "-c", "import sys; from semcal_ros.cli import "
                            "build_parser; build_parser(); print('numba' in sys.modules)"],
                           capture_output=True, text=True, check=True)
    assert probe.stdout.strip() == "False", probe.stdout + probe.stderr
    with pytest.raises(SystemExit):
        main(["evaluate", "somewhere", "--loss", "l3"])
    assert "argument --loss: invalid choice: 'l3' (choose from l2, huber, mi, likelihood, " \
           "balanced, both, all)" in capsys.readouterr().err
