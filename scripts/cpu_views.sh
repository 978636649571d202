#!/usr/bin/env bash
# Table 3's second arm at the CPU profile (issue 11): BC-NOSTRA trained with an occluded agent view
# (the robot blocks the camera in every demo), analysed offline like the good-view run, so the
# report shows each modality's share of the KL under both views (paper: the occluded view's share
# falls). The occluded demos use the good-view collection's seeds (the same initial states), and the
# occluded run trains as many steps as the good-view checkpoint that scripts/cpu_offline.sh analyses,
# with no in-training rollouts (the KL is the measure, not success), so the two differ only in the view.
# Needs scripts/cpu_offline.sh's good-view analyses for the comparison; every step is resumable.
#   TASK=liftd1 SEED=0 bash scripts/cpu_views.sh
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$PWD/.venv/bin:$PATH"
TASK=${TASK:-liftd1}
SEED=${SEED:-0}
NOISES=${NOISES:-mask}
OBS=rgb CAPACITY=configured source scripts/cpu_setup.sh   # PROFILE=cpu, RUNS=data/runs/cpu, collection
ROOT=$RUNS/offline/$TASK
COLL=${TASK}_occluded_cpu
COMMON="profile=cpu task=$TASK paths.runs=$RUNS"
NAME=$(python -c "from nostra.sim.tasks import get_task; print(get_task('$TASK').name)")
RUN=pretrain-nostra-${NAME}-occluded-s$SEED
log() { echo "[$(date +%H:%M:%S)] $*"; }

# the step of the good-view checkpoint that the offline analysis reads (best.ckpt)
STEPS=$(python - "$RUNS/train/pretrain-nostra-$NAME-s$SEED/run.json" <<'PY'
import json, sys
run = json.load(open(sys.argv[1]))
print(((run.get("rollouts") or {}).get("best") or {}).get("step") or run["steps"])
PY
)
collection $COLL $TASK generate.variation.occluded=1.0   # the good view's seeds: the same initial states
if [ -f "$RUNS/train/$RUN/run.json" ]; then log "train $RUN: finished before, kept"; else
  log "train $RUN: $STEPS steps (the good-view checkpoint's)"
  nostra train $COMMON model=nostra seed=$SEED "data.collections=[$COLL]" train.run_name=$RUN \
    train.max_steps=$STEPS train.max_minutes=null train.rollout.every=0
fi
WINDOWS=$(python -c "import yaml; print(yaml.safe_load(open('conf/task/$TASK.yaml'))['noise_windows'])" | tr -d ' ')
for noise in $NOISES; do
  out=$ROOT/s$SEED-occluded/$noise
  [ -f "$out/offline/offline.json" ] && { log "offline occluded seed $SEED $noise: done before, kept"; continue; }
  log "offline occluded seed $SEED $noise"
  nostra evaluate $COMMON seed=$SEED evaluate.rollouts=false \
    evaluate.offline.checkpoint=$RUNS/train/$RUN/policy.ckpt "evaluate.offline.collections=[$COLL]" \
    evaluate.offline.noise=$noise evaluate.offline.episodes=20 "evaluate.offline.windows=$WINDOWS" \
    evaluate.offline.setting=occluded_view evaluate.out_dir=$out
done
python -m nostra.workflows.offline_report --analyses "$ROOT" --out "reports/cpu/$TASK/offline" \
  --command "TASK=$TASK SEEDS=\"0\" bash scripts/cpu_offline.sh; TASK=$TASK SEED=$SEED bash scripts/cpu_views.sh"
log "done: reports/cpu/$TASK/offline/offline.md"
