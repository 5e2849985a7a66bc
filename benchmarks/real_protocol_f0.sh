#!/usr/bin/env bash
# Issue 18's first target: KITTI 00 frame 0, the paper's protocol (30 starts of +-2.5 m / +-5 deg,
# keep the 10 of lowest loss) per scene and setting, split by seed into pieces of RUNS starts so
# that each hold of the shared lock stays short (the machine has 2 cores shared by everyone).
# Resumable: a piece whose JSON exists is skipped. docs/real-data.md "KITTI 00 frame 0, the
# paper's protocol" has the figures and the load.
#
#   benchmarks/real_protocol_f0.sh OUT SCENE [SCENE ...]
#   SETTINGS="default mi paper" SEEDS="0 1 2" RUNS=10 benchmarks/real_protocol_f0.sh ...
#   .venv/bin/python benchmarks/real_protocol_f0.py table OUT/*.json --load-log OUT/load.tsv --runs
#
# Settings (each with the scene's own calibrator.yaml as --config):
#   default         semcal evaluate --loss l2: the engine's defaults (L2 + 4 px boundary band);
#                   the scene's probabilities.npz is used when present, as semcal evaluate and the
#                   calibrator do
#   mi              semcal evaluate --loss mi (semantic mutual information), likewise
#   default-noprob  default on a view of the scene without probabilities.npz (labels only)
#   mi-noprob       mi likewise
#   paper           the paper's plain method (semcal_tools.bench.paper_params, one schedule per
#                   start, labels only): real_protocol_f0.py paper
# Measuring a fixed commit while others edit the tree: PYTHONPATH=<git archive of it> (the venv's
# editable install comes after PYTHONPATH; `python -m` from the checkout would put the working tree
# first, so the pieces run .venv/bin/semcal and a script path instead).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:?usage: real_protocol_f0.sh OUT SCENE [SCENE ...]}
shift
[ $# -ge 1 ] || { echo "real_protocol_f0.sh: no scene folder given" >&2; exit 1; }
SETTINGS=${SETTINGS:-default mi paper}
SEEDS=${SEEDS:-0 1 2}
RUNS=${RUNS:-10}
LOCK=${LOCK:-/tmp/semcal-heavy.lock}
PY=.venv/bin/python
mkdir -p "$OUT/scenes"

labels_only() {  # a view of scene $1 without probabilities.npz (symlinks), its path on stdout
    local v="$OUT/scenes/$(basename "$1")_labelsonly" f
    mkdir -p "$v"
    for f in "$1"/*; do
        [ "$(basename "$f")" = probabilities.npz ] || ln -sfn "$(realpath "$f")" "$v/"
    done
    echo "$v"
}

for scene in "$@"; do
    [ -f "$scene/labels.png" ] || { echo "real_protocol_f0.sh: $scene is not a scene folder" >&2; exit 1; }
    name=$(basename "$scene")
    for setting in $SETTINGS; do
        case $setting in
            default|mi) dir=$scene ;;
            default-noprob|mi-noprob|paper) dir=$(labels_only "$scene") ;;
            *) echo "real_protocol_f0.sh: unknown setting '$setting'" >&2; exit 1 ;;
        esac
        loss=${setting%-noprob}; [ "$loss" = default ] && loss=l2
        for seed in $SEEDS; do
            json="$OUT/${name}__${setting}_s${seed}.json"
            [ -f "$json" ] && continue
            if [ "$setting" = paper ]; then
                cmd=($PY benchmarks/real_protocol_f0.py paper "$dir" --seed "$seed" --runs "$RUNS"
                     --json "$json.part")
            else
                cmd=(.venv/bin/semcal evaluate "$dir" --loss "$loss" --runs "$RUNS"
                     --keep "$RUNS" --seed "$seed" --config "$scene/calibrator.yaml"
                     --json "$json.part" --quiet)
            fi
            # the load is read once the lock is held (others' waiting jobs do not count), and after
            flock "$LOCK" bash -c 'cut -d" " -f1 /proc/loadavg > "$1"; shift; t0=$(date +%s); "$@" || exit
                                   echo $(( $(date +%s) - t0 )) >> "$0"' "$json.load" "$json.load" "${cmd[@]}"
            mv "$json.part" "$json"
            read -r -d '' load0 secs < "$json.load" || true
            printf '%s\t%s\t%s\t%s\t%s\n' "$(basename "$json")" "$(date -u +%H:%M)" "$load0" \
                "$(cut -d' ' -f1 /proc/loadavg)" "$secs" >> "$OUT/load.tsv"
            rm -f "$json.load"
        done
    done
done
