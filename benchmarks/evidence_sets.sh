#!/usr/bin/env bash
# The evidence study (issue 40) over every source: every real single frame, frame 0 with six
# scans, KITTI 00 frames in groups of 3, 5 and 8 (one rig, one extrinsic), three paper starts
# each; the catalogue with ideal and network-like labels, two starts each.
#   bash benchmarks/evidence_sets.sh SCENES OUT.jsonl
# SCENES: benchmarks/make_real_scenes.sh's folder, plus cat_<layout>_<ideal|noisy_labels> from
# `semcal scene <layout> --seed 0 --variant ...` (small).
set -euo pipefail
cd "$(dirname "$0")/.."
SCENES=${1:?usage: evidence_sets.sh SCENES OUT.jsonl}; OUT=${2:?}
k() { local IFS=,; echo "${*/#/kitti00_}" | sed 's/,/_esp,/g; s/$/_esp/'; }
S="kitti00_000000_esp kitti00_000556_esp kitti00_001112_esp kitti00_001668_esp kitti00_002224_esp
   kitti00_002780_esp kitti00_003336_esp kitti00_003892_esp kitti00_004448_esp
   object_tr_000000_esp object_tr_000001_esp object_tr_000002_esp object_te_000007_esp
   pjlab_auto_esp pjlab_manual_esp pjlab_ours1_esp pjlab_ours2_esp kitti00_000000x6_esp"
G="$(k 000556 002224 003892) $(k 001112 002780 004448) $(k 000000 001668 003336)
   $(k 000556 001668 002780 003892 004448) $(k 000000 001112 002224 003336 004448)
   $(k 000556 001112 001668 002224 002780 003336 003892 004448)"
C="cat_junction_ideal cat_roundabout_ideal cat_arterial_ideal cat_highway_ideal
   cat_junction_noisy_labels cat_roundabout_noisy_labels cat_arterial_noisy_labels
   cat_highway_noisy_labels"
# shellcheck disable=SC2086
.venv/bin/python benchmarks/evidence_study.py run --scenes "$SCENES" --sets $S $G --starts 0 1 2 \
  --out "$OUT"
# shellcheck disable=SC2086
.venv/bin/python benchmarks/evidence_study.py run --scenes "$SCENES" --sets $C --starts 0 1 \
  --out "$OUT"
.venv/bin/python benchmarks/evidence_study.py table "$OUT"
