#!/usr/bin/env bash
# AdaMLI's threshold sensitivity at the CPU profile (issue 11, what the paper's reviewers asked):
# offline analyses of BC-NOSTRA's best checkpoint on its 20 held-out demos under one noise, for a
# grid of (f_o, f_c) with k_o, k_c at the paper's values, then one table and one figure of
# precision, recall and false imagination (reports/cpu/<task>/adamli_sweep/). Offline: AdaMLI
# replays the recorded demos, so each setting costs about a minute here, not a training run.
# Resumable: an analysis already written is kept.
#   TASK=liftd1 SEED=0 F_O="5 10 20 40" F_C="1.5 3 6" NOISE=mask bash scripts/cpu_adamli_sweep.sh
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$PWD/.venv/bin:$PATH"
TASK=${TASK:-liftd1}
SEED=${SEED:-0}
F_O=${F_O:-5 10 20 40}
F_C=${F_C:-1.5 3 6}
NOISE=${NOISE:-mask}
RUNS=data/runs/cpu
ROOT=$RUNS/offline/$TASK-adamli
NAME=$(python -c "from nostra.sim.tasks import get_task; print(get_task('$TASK').name)")
WINDOWS=$(python -c "import yaml; print(yaml.safe_load(open('conf/task/$TASK.yaml'))['noise_windows'])" | tr -d ' ')
for fo in $F_O; do
  for fc in $F_C; do
    out=$ROOT/s$SEED-fo$fo-fc$fc/$NOISE
    [ -f "$out/offline/offline.json" ] && { echo "f_o=$fo f_c=$fc: done before, kept"; continue; }
    echo "[$(date +%H:%M:%S)] offline seed $SEED $NOISE f_o=$fo f_c=$fc"
    nostra evaluate profile=cpu task=$TASK paths.runs=$RUNS seed=$SEED evaluate.rollouts=false \
      evaluate.offline.checkpoint=$RUNS/train/pretrain-nostra-$NAME-s$SEED/checkpoints/best.ckpt \
      "evaluate.offline.collections=[${TASK}_cpu]" evaluate.offline.noise=$NOISE evaluate.offline.episodes=20 \
      "evaluate.offline.windows=$WINDOWS" "evaluate.offline.adamli={f_o: $fo, f_c: $fc}" \
      evaluate.offline.setting=good_view evaluate.out_dir=$out
  done
done
python -m nostra.workflows.offline_report --analyses "$ROOT" --out "reports/cpu/$TASK/adamli_sweep" --no-figures \
  --command "TASK=$TASK SEED=$SEED F_O=\"$F_O\" F_C=\"$F_C\" NOISE=$NOISE bash scripts/cpu_adamli_sweep.sh"
