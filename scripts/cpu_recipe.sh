#!/usr/bin/env bash
# `make cpu-recipe`: which switches of the CPU recipe move BC-LSTM's success on a task (default
# LiftD1), each with the rest of the recipe kept, at the same number of training steps (STEPS,
# default 1000) as the `make cpu` run's step checkpoint it is compared with:
#   image augmentation off, noise-free demos, a 3x learning rate (the paper's 1e-4 is for 300k
#   steps), and the LSTM state carried all episode instead of reset every rnn_horizon steps (the
#   last also for NOSTRA: decides reset vs carry).
# Needs the `make cpu` runs of seed 0. 50 episodes per cell on the evaluation seeds; writes
# reports/cpu/<task>/recipe.md. Resumable like `make cpu`.
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$PWD/.venv/bin:$PATH"
TASK=${TASK:-liftd1}
STEPS=${STEPS:-1000}
RUNS=data/runs/cpu
COMMON="profile=cpu task=$TASK paths.runs=$RUNS"
NAME=$(python -c "from nostra.sim.tasks import get_task; print(get_task('$TASK').name)")
BASE=$RUNS/train/pretrain-lstm-$NAME-s0
EV=$RUNS/evaluate/$TASK/recipe
start=$(date +%s)
log() { echo "[$(date +%H:%M:%S)] $*"; }
only() {  # evaluate.variants overrides keeping only $1
  local v
  for v in lstm diffusion rssm rssm_li nostra nostra_mli nostra_adamli; do
    [ "$v" = "$1" ] || echo "evaluate.variants.$v=null"
  done
}
evaluate() {  # $1 = out name, $2 = variant, $3 = checkpoint path, $4 = which, rest: extra overrides
  local name=$1 variant=$2 ckpt=$3 which=$4
  shift 4
  [ -f "$EV/$name/success.csv" ] && { log "evaluate $name: done before"; return; }
  log "evaluate $name"
  nostra evaluate $COMMON $(only "$variant") "evaluate.variants.$variant.checkpoint=$ckpt" \
    "evaluate.checkpoint='$which'" "evaluate.noises=[none]" evaluate.offline.enabled=false \
    evaluate.videos_per_cell=0 evaluate.out_dir=$EV/$name "$@"
}
train() {  # $1 = run name, $2 = collection, rest: extra overrides
  local name=$1 collection=$2
  shift 2
  [ -f "$RUNS/train/$name/run.json" ] && { log "train $name: done before"; return; }
  log "train $name ($STEPS steps)"
  nostra train $COMMON model=lstm "data.collections=[$collection]" train.run_name=$name train.max_steps=$STEPS \
    train.max_minutes=null train.rollout.every=0 train.rollout.final_episodes=0 "$@"
}

reuse() {  # $1 = out name, $2 = variant: its clean rollouts from `make cpu`'s best-checkpoint evaluation (not re-run)
  local from=$RUNS/evaluate/$TASK/s0/best/none  # where scripts/cpu.sh writes its clean cell
  [ -f "$from/success.csv" ] || { echo "run make cpu first: $from/success.csv is missing" >&2; exit 1; }
  mkdir -p "$EV/$1/records/$NAME/none"
  cp "$from"/records/"$NAME"/none/"$2"_seed*.npz "$EV/$1/records/$NAME/none/"
}

# the baseline: the `make cpu` run at the same step; its best checkpoint with the state reset (the
# recipe, as `make cpu` evaluated it) and carried
evaluate base lstm "$BASE/policy.ckpt" "step=$STEPS"
reuse reset10 lstm
evaluate carry lstm "$BASE/policy.ckpt" best +evaluate.variants.lstm.rnn_horizon=0
NOSTRA=$RUNS/train/pretrain-nostra-$NAME-s0
if [ -f "$NOSTRA/policy.ckpt" ]; then
  reuse nostra_carry nostra
  evaluate nostra_reset10 nostra "$NOSTRA/policy.ckpt" best +evaluate.variants.nostra.rnn_horizon=10
fi

# augmentation off
train recipe-noaug-lstm ${TASK}_cpu model.net.image_aug=none
evaluate noaug lstm "$RUNS/train/recipe-noaug-lstm/policy.ckpt" last

# a 3x learning rate
train recipe-lr3e-4-lstm ${TASK}_cpu model.optim.lr=3e-4
evaluate lr3e-4 lstm "$RUNS/train/recipe-lr3e-4-lstm/policy.ckpt" last

# noise-free demos (the same expert seeds, no action noise)
raw=data/raw/${TASK}_clean.hdf5
[ -f "$raw" ] || nostra generate $COMMON generate.collection=${TASK}_clean generate.action_noise=0
nostra ingest $COMMON "ingest.sources=[$raw]" ingest.progress=false
train recipe-nonoise-lstm ${TASK}_clean
evaluate nonoise lstm "$RUNS/train/recipe-nonoise-lstm/policy.ckpt" last

python -m nostra.workflows.cpu_report recipe --evaluations "$EV" --task "$TASK" --steps "$STEPS" \
  --out reports/cpu/$TASK/recipe.md --command "TASK=$TASK STEPS=$STEPS make cpu-recipe" \
  --wall-seconds $(( $(date +%s) - start ))
log "done in $(( ($(date +%s) - start) / 60 )) min: reports/cpu/$TASK/recipe.md"
