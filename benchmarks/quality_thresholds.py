"""Verdict thresholds and uncertainty coverage from label_noise_study.py JSON lines (docs/quality.md):
which thresholds call no bad result good, and how often the per-axis uncertainty covers the error.
Usage: python benchmarks/quality_thresholds.py RESULTS.jsonl ..."""

import itertools
import json
import sys
import numpy as np

recs = [json.loads(l) for f in sys.argv[1:] for l in open(f)]
recs = [d for d in recs if "q" in d]
print(len(recs), "results")
for tt, tr in itertools.product([0.05, 0.06, 0.08, 0.10], [0.1, 0.12, 0.15, 0.2]):
    bad_good = within = within_good = good = 0
    for d in recs:
        q = d["q"]
        failed = q["verdict"] == "failed" or q["reason"].startswith("the map covers")
        ut = max(q["uncertainty_translation_m"])
        ur = max(q["uncertainty_rpy_deg"][1:])
        g = (not failed) and ut <= tt and ur <= tr
        good += g
        w = d["t"] < 0.05 and d["r"] < 0.1
        within += w
        within_good += w and g
        bad_good += g and (d["t"] > 0.10 or d["r"] > 0.2)
    print(
        f"max {tt * 100:.0f} cm / {tr} deg: good {good}, good but worse than 10 cm/0.2 deg {bad_good}, "
        f"good among within-5cm/0.1deg {within_good}/{within} = {within_good / max(within, 1) * 100:.0f} %"
    )
recs = [json.loads(l) for f in sys.argv[1:] for l in open(f)]
recs = [d for d in recs if "q" in d]


def covered(d, ut, ur):
    return all(abs(a) <= u + 1e-9 for a, u in zip(d["dxyz"], ut)) and all(
        abs(a) <= u + 1e-9 for a, u in zip(d["drpy"][1:], ur[1:])
    )


for noise in ("legacy", "network", "none"):
    sel = [d for d in recs if d["noise"] == noise]
    c = sum(covered(d, d["q"]["uncertainty_translation_m"], d["q"]["uncertainty_rpy_deg"]) for d in sel)
    sel2 = [d for d in sel if not d["scene"].startswith("highway")]
    c2 = sum(covered(d, d["q"]["uncertainty_translation_m"], d["q"]["uncertainty_rpy_deg"]) for d in sel2)
    print(
        noise,
        f"all five axes covered: {c}/{len(sel)} = {c / len(sel) * 100:.0f} %; "
        f"without highway {c2}/{len(sel2)}",
    )
for noise in ("legacy", "network", "none"):
    sel = [d for d in recs if d["noise"] == noise]
    ratios = np.array(
        [
            [
                abs(a) / max(u, 1e-9)
                for a, u in zip(
                    d["dxyz"] + d["drpy"][1:],
                    d["q"]["uncertainty_translation_m"] + d["q"]["uncertainty_rpy_deg"][1:],
                )
            ]
            for d in sel
        ]
    )
    print(
        noise,
        "per-axis coverage x y z pitch yaw",
        (ratios <= 1).mean(axis=0).round(2),
        "median ratio",
        np.median(ratios, axis=0).round(2),
        "90th pct of max ratio",
        np.percentile(ratios.max(axis=1), 90).round(2),
    )
