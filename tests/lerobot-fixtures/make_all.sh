#!/bin/sh
# Regenerates the multi-camera / non-square fixtures (and re-checks the public one) with LeRobot 0.6.1.
# usage (as root): tests/lerobot-fixtures/make_all.sh [OUTDIR=/work/fixtures] [LEROBOT_ENV=/tmp/lerobot-env]
set -eu
HERE=$(cd "$(dirname "$0")" && pwd -P)
ROOT=$(cd "$HERE/../.." && pwd)
OUT=${1:-/work/fixtures}
ENV=${LEROBOT_ENV:-/tmp/lerobot-env}
T=${LEROBOT_CHECK:-$ROOT/../shared/tools/lerobot-check}
PUB=${PUBLIC_FIXTURE:-$ROOT/../shared/fixtures/smolvla-tiny-a}
T=$(cd "$T" && pwd -P); PUB=$(cd "$PUB" && pwd -P)
mkdir -p "$OUT"; OUT=$(cd "$OUT" && pwd -P)
export HOSTDIR="$HERE:$OUT:$PUB"
mk() { name=$1; shift; "$T/run.sh" "$ENV" python3 "$HERE/make_fixture.py" "$OUT/$name" --force --vlm-src "$PUB/vlm" "$@"; }
# 0. the public recipe again (must be bitwise equal to smolvla-tiny-a)
mk repro_tiny_a --set-name a --camera top=32x32 --camera wrist=32x32 --check-against "$PUB"
# 1. one portrait camera
mk cams1 --camera wrist=48x32
# 2. two cameras of different non-square sizes, config order NOT alphabetical (wrist before front)
mk cams2 --camera wrist=24x40 --camera front=40x24
# 3. landscape / square / portrait, config order NOT alphabetical (top, wrist, side)
mk cams3 --camera top=30x44 --camera wrist=32x32 --camera side=44x30
# 3s. the same sizes with names whose alphabetical order equals the config order (isolates resize/pad)
mk cams3_sorted --camera camera1=30x44 --camera camera2=32x32 --camera camera3=44x30
# 4. larger model input 64x64 (vision image_size 64): 4:3 landscape downscale, square identity, portrait upscale
mk cams3_in64 --resize 64x64 --vision-image-size 64 --camera camera1=96x128 --camera camera2=64x64 --camera camera3=50x30
# 5. model input 64x64 on a vision tower with image_size 32 (SmolVLM buckets patch coordinates onto 4x4)
mk cams2_in64_vis32 --resize 64x64 --camera camera1=48x64 --camera camera2=64x40
