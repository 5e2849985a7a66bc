#!/usr/bin/env bash
# The real scene folders the accuracy and quality studies run on, from ../shared/data: one
# `semcal real-scene` per frame, one scan each, ESPNetv2 label images with their probabilities,
# the geometric point labeller, the recording's own calibration as the truth.
#
#   bash benchmarks/make_real_scenes.sh OUT_DIR
#
# OUT_DIR/kitti00_NNNNNN_esp  the nine KITTI odometry 00 frames (000000 and the eight of
#                             kitti_odometry_00_frames): one rig, one extrinsic
# OUT_DIR/kitti00_000000x6_esp frame 0 with scans 0-5 (poses.txt); x3r, x6r: scans 0-2 / 0-5
#                             without poses (registered to each other)
# OUT_DIR/object_NAME_esp     the four KITTI object frames
# OUT_DIR/pjlab_NAME_esp      the four PJLab frames (another lidar, camera and city)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:?usage: make_real_scenes.sh OUT_DIR}
DATA=../shared/data
BIN=.venv/bin
mkdir -p "$OUT/models"
MODEL="$OUT/models/espnetv2.onnx"
[ -f "$MODEL" ] || $BIN/semcal export-model espnetv2 \
  --weights $DATA/models/espnetv2_cityscapes/espnetv2_s_2.0_city_1024x512.npz --out "$MODEL"
common=(--cloud-labels geometric --model "$MODEL" --model-config "${MODEL%.onnx}.yaml"
        --probabilities)
scene() {  # name, then real-scene arguments
  local name=$1; shift
  [ -f "$OUT/$name/scene.yaml" ] && return 0
  echo "== $name"
  $BIN/semcal real-scene "$@" "${common[@]}" --out "$OUT/$name" | tail -n 1
}
K=$DATA/kitti_odometry_00
scene kitti00_000000_esp --image $K/image_2/000000.png --scans $K/velodyne/000000.bin \
  --calib $K/calib.txt
for f in 000556 001112 001668 002224 002780 003336 003892 004448; do
  F=$DATA/kitti_odometry_00_frames
  scene "kitti00_${f}_esp" --image $F/image_2/$f.png --scans $F/velodyne/$f.bin --calib $F/calib.txt
done
scene kitti00_000000x6_esp --image $K/image_2/000000.png \
  --scans $K/velodyne/00000{0,1,2,3,4,5}.bin --poses $K/poses.txt --calib $K/calib.txt
# the same without poses: the scans registered to each other (issue 41 item 3)
scene kitti00_000000x3r_esp --image $K/image_2/000000.png \
  --scans $K/velodyne/00000{0,1,2}.bin --calib $K/calib.txt
scene kitti00_000000x6r_esp --image $K/image_2/000000.png \
  --scans $K/velodyne/00000{0,1,2,3,4,5}.bin --calib $K/calib.txt
O=$DATA/kitti_object
for f in tr_000000 tr_000001 tr_000002 te_000007; do
  scene "object_${f}_esp" --image $O/$f.png --scans $O/$f.bin --calib $O/$f.txt
done
P=$DATA/pjlab_lidar_camera
scene pjlab_auto_esp --image $P/auto_calib/calib.png --scans $P/auto_calib/calib.pcd \
  --calib $P/auto_calib/center_camera-intrinsic.json \
  $P/auto_calib/top_center_lidar-to-center_camera-extrinsic.json
# its intrinsic JSON states 1920x1080 for a 1920x1200 image (the rows below 1080 unlabelled)
scene pjlab_manual_esp --image $P/manual_calib/0.png --scans $P/manual_calib/0.pcd \
  --calib $P/manual_calib/center_camera-intrinsic.json \
  $P/manual_calib/top_center_lidar-to-center_camera-extrinsic.json --ignore-calib-size
for f in ours1 ours2; do
  scene "pjlab_${f}_esp" --image $P/$f/calib.jpg --scans $P/$f/calib.pcd --calib $P/$f/calib.txt
done
echo "scenes in $OUT"
