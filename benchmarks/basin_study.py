"""How good must the start be? The basin of the default procedure on every catalogue layout.

For each layout scene and each start condition (translation / yaw / pitch error bounds, with or
without the full-circle yaw search) runs ``semcal evaluate --runs N --keep N`` (every start
counted) under the shared heavy-job lock, one condition at a time, and collects per condition:
the share of starts within 5 cm & 0.1 deg, the mean error and the seconds per run. Results are
appended to a JSON-lines file so that an interrupted study resumes.

Usage:
  python benchmarks/basin_study.py --scenes DIR [DIR ...] --runs 4 --out basin.jsonl
  python benchmarks/basin_study.py --out basin.jsonl --table --plot docs/img/basin.png

The plot is drawn with OpenCV (matplotlib is not in the environment): one group of bars per
condition, one bar per layout, the share of starts within 5 cm & 0.1 deg.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

LOCK = "/tmp/semcal-heavy.lock"
#: (label, start metres, start yaw deg, start pitch deg, yaw search)
CONDITIONS = [
    ("0.5 m / 5 / 2 deg", 0.5, 5.0, 2.0, False),
    ("2.5 m / 5 / 5 deg (paper)", 2.5, 5.0, 5.0, False),
    ("5 m / 5 / 10 deg", 5.0, 5.0, 10.0, False),
    ("2.5 m / 30 / 5 deg", 2.5, 30.0, 5.0, False),
    ("2.5 m / 30 / 5 deg, yaw search", 2.5, 30.0, 5.0, True),
    ("2.5 m / 180 / 5 deg, yaw search", 2.5, 180.0, 5.0, True),
    ("2.5 m / 5 / 5 deg, yaw search", 2.5, 5.0, 5.0, True),
    ("2.5 m / 180 / 5 deg", 2.5, 180.0, 5.0, False),
]


def _ok(r: dict) -> bool:
    return r["t_m"] <= 0.05 and r["r_deg"] <= 0.1


def run_condition(scene: Path, cond: tuple, runs: int, seed: int) -> list[dict]:
    label, xyz, yaw, pitch, yaw_search = cond
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "r.json"
        cmd = ["flock", LOCK, sys.executable, "-m", "semcal_ros.cli", "evaluate", str(scene),
               "--runs", str(runs), "--keep", str(runs), "--seed", str(seed), "--quiet",
               "--start-xyz", str(xyz), "--start-yaw", str(yaw), "--start-pitch", str(pitch),
               "--json", str(out)] + (["--yaw-search"] if yaw_search else [])
        if (scene / "calibrator.yaml").is_file():
            cmd += ["--config", str(scene / "calibrator.yaml")]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"{scene}: {label}: {proc.stderr.strip()[-300:]}")
        data = json.loads(out.read_text())
    load = float(Path("/proc/loadavg").read_text().split()[0])
    return [{"scene": scene.name, "condition": label, "yaw_search": yaw_search,
             "t_m": r["translation_error_m"], "r_deg": r["rotation_error_deg"],
             "seconds": r["seconds"], "verdict": (r.get("quality") or {}).get("verdict", ""),
             "error": r.get("error", ""), "load": load}
            for res in data["results"] for r in res["runs"]]


def table(rows: list[dict]) -> str:
    scenes = sorted({r["scene"] for r in rows})
    lines = ["| start (xyz / yaw / pitch) | " + " | ".join(scenes) + " | all: within 5 cm & 0.1 deg "
             "| mean error | s/run | others called good |", "|---" * (len(scenes) + 5) + "|"]
    for label, *_ in CONDITIONS:
        sel = [r for r in rows if r["condition"] == label]
        if not sel:
            continue
        cells = []
        for s in scenes:
            c = [r for r in sel if r["scene"] == s]
            ok = sum(r["t_m"] <= 0.05 and r["r_deg"] <= 0.1 for r in c)
            cells.append(f"{ok}/{len(c)}" if c else "-")
        ok = sum(r["t_m"] <= 0.05 and r["r_deg"] <= 0.1 for r in sel)
        t = np.mean([r["t_m"] for r in sel]) * 100
        rd = np.mean([r["r_deg"] for r in sel])
        sec = np.median([r["seconds"] for r in sel])
        bad = [r for r in sel if not _ok(r)]
        good_bad = sum(r["verdict"] == "good" for r in bad)
        lines.append(f"| {label} | " + " | ".join(cells) +
                     f" | {ok}/{len(sel)} ({100 * ok / len(sel):.0f} %) | {t:.1f} cm / {rd:.3f} deg"
                     f" | {sec:.1f} | {good_bad}/{len(bad)} |")
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> None:
    """Grouped bars: per condition, per layout, the share of starts within 5 cm & 0.1 deg."""
    import cv2

    scenes = sorted({r["scene"] for r in rows})
    conds = [c[0] for c in CONDITIONS if any(r["condition"] == c[0] for r in rows)]
    colours = [(180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148)]
    w, h, left, top, bottom = 1400, 620, 70, 60, 170
    img = np.full((h, w, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    plot_h = h - top - bottom
    cv2.putText(img, "share of starts within 5 cm & 0.1 deg (every start counted)", (left, 30),
                font, 0.7, (0, 0, 0), 2, cv2.LINE_AA)
    for k in range(0, 101, 20):
        y = top + plot_h - int(plot_h * k / 100)
        cv2.line(img, (left, y), (w - 20, y), (220, 220, 220), 1)
        cv2.putText(img, f"{k} %", (8, y + 5), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    group = (w - 20 - left) / max(len(conds), 1)
    bar = group * 0.8 / max(len(scenes), 1)
    for i, cond in enumerate(conds):
        x0 = left + i * group + group * 0.1
        for j, scene in enumerate(scenes):
            sel = [r for r in rows if r["condition"] == cond and r["scene"] == scene]
            if not sel:
                continue
            share = sum(map(_ok, sel)) / len(sel)
            xa, xb = int(x0 + j * bar), int(x0 + (j + 1) * bar) - 2
            cv2.rectangle(img, (xa, top + plot_h - int(plot_h * share)), (xb, top + plot_h),
                          colours[j % len(colours)], -1)
            cv2.putText(img, f"{sum(map(_ok, sel))}/{len(sel)}", (xa, top + plot_h - int(plot_h * share) - 4),
                        font, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
        for n, part in enumerate(cond.replace(", ", ",|").split("|")):
            cv2.putText(img, part, (int(x0), top + plot_h + 20 + 18 * n), font, 0.42, (0, 0, 0), 1,
                        cv2.LINE_AA)
    for j, scene in enumerate(scenes):
        x = left + j * 220
        cv2.rectangle(img, (x, h - 40), (x + 18, h - 22), colours[j % len(colours)], -1)
        cv2.putText(img, scene, (x + 24, h - 25), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"could not write {path}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="*", default=[], help="scene folders (one per layout)")
    ap.add_argument("--runs", type=int, default=4, help="starts per scene and condition")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--conditions", default="", help="comma list of condition indices (default all)")
    ap.add_argument("--out", required=True, help="JSON lines, appended (resumes)")
    ap.add_argument("--table", action="store_true")
    ap.add_argument("--plot", help="PNG: share within 5 cm & 0.1 deg per condition and layout")
    a = ap.parse_args()
    out = Path(a.out)
    rows = [json.loads(x) for x in out.read_text().splitlines()] if out.is_file() else []
    chosen = [CONDITIONS[int(i)] for i in a.conditions.split(",")] if a.conditions else CONDITIONS
    for scene in map(Path, a.scenes):
        for cond in chosen:
            if any(r["scene"] == scene.name and r["condition"] == cond[0] for r in rows):
                continue
            new = run_condition(scene, cond, a.runs, a.seed)
            with out.open("a") as f:
                for r in new:
                    f.write(json.dumps(r) + "\n")
            rows += new
            ok = sum(map(_ok, new))
            print(f"{scene.name}: {cond[0]}: {ok}/{len(new)} within 5 cm & 0.1 deg, "
                  f"median {np.median([r['seconds'] for r in new]):.1f} s/run, load {new[0]['load']:.1f}",
                  flush=True)
    if a.table or not a.scenes:
        print(table(rows))
    if a.plot:
        plot(rows, Path(a.plot))
    return 0


if __name__ == "__main__":
    sys.exit(main())
