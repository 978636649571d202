#!/usr/bin/env bash
# Table 3 / AdaMLI detection at the CPU profile (issue 11): offline analyses of BC-NOSTRA's best
# checkpoint of each training seed on its 20 held-out demos, under the noises that act on recorded
# observations (the task's noise windows), then reports/cpu/<task>/offline/ (offline.md, kl.csv,
# detection.csv). Needs `make cpu` (or cpu-claims) first; an analysis already written is kept.
#   TASK=liftd1 SEEDS="0 1" NOISES="mask proprio_zero proprio_stuck" bash scripts/cpu_offline.sh
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$PWD/.venv/bin:$PATH"
TASK=${TASK:-liftd1}
SEEDS=${SEEDS:-0 1}
NOISES=${NOISES:-mask proprio_zero proprio_stuck}
RUNS=data/runs/cpu
ROOT=$RUNS/offline/$TASK
NAME=$(python -c "from nostra.sim.tasks import get_task; print(get_task('$TASK').name)")
# the task config's windows, as the rollouts use them (nostra evaluate: task.noise_windows)
WINDOWS=$(python -c "import yaml; print(yaml.safe_load(open('conf/task/$TASK.yaml'))['noise_windows'])" | tr -d ' ')
for seed in $SEEDS; do
  for noise in $NOISES; do
    out=$ROOT/s$seed/$noise
    [ -f "$out/offline/offline.json" ] && { echo "offline seed $seed $noise: done before, kept"; continue; }
    echo "[$(date +%H:%M:%S)] offline seed $seed $noise"
    nostra evaluate profile=cpu task=$TASK paths.runs=$RUNS seed=$seed evaluate.rollouts=false \
      evaluate.offline.checkpoint=$RUNS/train/pretrain-nostra-$NAME-s$seed/checkpoints/best.ckpt \
      "evaluate.offline.collections=[${TASK}_cpu]" evaluate.offline.noise=$noise evaluate.offline.episodes=20 \
      "evaluate.offline.windows=$WINDOWS" evaluate.offline.setting=good_view evaluate.out_dir=$out
  done
done
python -m nostra.workflows.offline_report --analyses "$ROOT" --out "reports/cpu/$TASK/offline" \
  --command "TASK=$TASK SEEDS=\"$SEEDS\" NOISES=\"$NOISES\" bash scripts/cpu_offline.sh"
