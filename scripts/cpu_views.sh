#!/usr/bin/env bash
# Table 3's second arm at the CPU profile (issue 11): BC-NOSTRA trained with an occluded agent view
# (the robot blocks the camera in every demo), analysed offline like the good-view run, so the
# report shows each modality's share of the KL under both views (paper: the occluded view's share
# falls). The occluded demos use the good-view collection's seeds (the same initial states), and the
# occluded run trains as many steps as the good-view checkpoint that scripts/cpu_offline.sh analyses,
# with no in-training rollouts (the KL is the measure, not success), so the two differ only in the view.
# Needs scripts/cpu_offline.sh's good-view analyses for the comparison; every step is resumable.
#   TASK=liftd1 SEED=0 bash scripts/cpu_views.sh
#
# BETA=<KL weight> trains both arms here instead, at that beta, STEPS steps each (default 2000), with
# the same schedule and no in-training rollouts, and pairs them over the held-out demos (same seeds):
# reports/cpu/<task>/views/ (offline.md, views.csv). BETAS="1e-2 1e-4" runs one pair per beta.
# VIEWS lists the arms trained beside the good view (default occluded): blind is a control beyond the
# paper, the agent view facing the floor (the same image at every step, no information at all); with BETAS.
# SPLITS lists which demos each arm is analysed on (default both): held_out (never trained on) and
# train (the demos it trained on: the training-set KL), one report each (views/, views-train/).
# OUT names the report folder (default reports/cpu/<task>/views; the training split's gets -train), and
# EPISODES lists earlier reports' views_episodes.csv, whose runs (no longer on this disk) are paired and
# pooled beside this disk's: a seed trained in another sitting joins the pooled table.
#   TASK=liftd1 SEED=0 BETAS="1e-2 1e-4" bash scripts/cpu_views.sh
#   TASK=liftd1 SEED=0 BETAS="1e-2 1e-4" VIEWS="occluded blind" bash scripts/cpu_views.sh
#   TASK=liftd1 SEED=3 BETAS=1e-4 SPLITS=held_out OUT=reports/cpu/liftd1/views-s3 bash scripts/cpu_views.sh
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$PWD/.venv/bin:$PATH"
TASK=${TASK:-liftd1}
SEED=${SEED:-0}
NOISES=${NOISES:-mask}
BETAS=${BETAS:-${BETA:-}}
STEPS=${STEPS:-2000}
VIEWS=${VIEWS:-occluded}
SPLITS=${SPLITS:-held_out train}
EPISODES=${EPISODES:-}
for f in $EPISODES; do
  [ -f "$f" ] || { echo "$0: EPISODES: no such file $f (offline_report writes <out>/views_episodes.csv)" >&2; exit 2; }
done
for split in $SPLITS; do
  case $split in held_out|train) ;; *) echo "$0: unknown split $split in SPLITS; valid: held_out, train" >&2; exit 2 ;; esac
done
OBS=rgb CAPACITY=configured source scripts/cpu_setup.sh   # PROFILE=cpu, RUNS=data/runs/cpu, collection
COLL=${TASK}_occluded_cpu
COMMON="profile=cpu task=$TASK paths.runs=$RUNS"
NAME=$(python -c "from nostra.sim.tasks import get_task; print(get_task('$TASK').name)")
WINDOWS=$(python -c "import yaml; print(yaml.safe_load(open('conf/task/$TASK.yaml'))['noise_windows'])" | tr -d ' ')
start=$(date +%s)
log() { echo "[$(date +%H:%M:%S)] $*"; }

train() {  # $1 = run, $2 = collection, $3 = steps, $4... = overrides
  local run=$1 coll=$2 steps=$3; shift 3
  if [ -f "$RUNS/train/$run/run.json" ]; then log "train $run: finished before, kept"; return; fi
  log "train $run: $steps steps on $coll $*"
  nostra train $COMMON model=nostra seed=$SEED "data.collections=[$coll]" train.run_name=$run \
    train.max_steps=$steps train.max_minutes=null train.rollout.every=0 "$@"
}

analyse() {  # $1 = checkpoint, $2 = collection, $3 = setting, $4 = output folder (one per noise below it), $5 = split
  local split=${5:-held_out}
  for noise in $NOISES; do
    local out=$4/$noise
    [ -f "$out/offline/offline.json" ] && { log "offline $4 $noise: done before, kept"; continue; }
    log "offline $4 $noise"
    nostra evaluate $COMMON seed=$SEED evaluate.rollouts=false evaluate.offline.checkpoint=$1 \
      "evaluate.offline.collections=[$2]" evaluate.offline.noise=$noise evaluate.offline.episodes=20 \
      "evaluate.offline.windows=$WINDOWS" evaluate.offline.setting=$3 evaluate.offline.split=$split \
      evaluate.out_dir=$out
  done
}

collection ${TASK}_cpu $TASK
for view in $VIEWS; do   # the good view's seeds: the same initial states
  case $view in occluded|blind) ;; *) echo "$0: unknown view $view in VIEWS; valid: occluded, blind" >&2; exit 2 ;; esac
  collection ${TASK}_${view}_cpu $TASK generate.variation.$view=1.0
done
if [ -z "$BETAS" ]; then   # the occluded arm against make cpu's good-view run (scripts/cpu_offline.sh)
  ROOT=$RUNS/offline/$TASK
  RUN=pretrain-nostra-${NAME}-occluded-s$SEED
  # the step of the good-view checkpoint that the offline analysis reads (best.ckpt)
  GOOD_STEPS=$(python - "$RUNS/train/pretrain-nostra-$NAME-s$SEED/run.json" <<'PY'
import json, sys
run = json.load(open(sys.argv[1]))
print(((run.get("rollouts") or {}).get("best") or {}).get("step") or run["steps"])
PY
)
  train $RUN $COLL $GOOD_STEPS
  analyse $RUNS/train/$RUN/policy.ckpt $COLL occluded_view $ROOT/s$SEED-occluded
  python -m nostra.workflows.offline_report --analyses "$ROOT" --out "reports/cpu/$TASK/offline" \
    --command "TASK=$TASK SEEDS=\"0\" bash scripts/cpu_offline.sh; TASK=$TASK SEED=$SEED bash scripts/cpu_views.sh"
  log "done: reports/cpu/$TASK/offline/offline.md"
  exit 0
fi
root() { [ "$1" = held_out ] && echo "$RUNS/offline/$TASK-views" || echo "$RUNS/offline/$TASK-views-$1"; }
for beta in $BETAS; do
  for view in good $VIEWS; do
    tag=b$beta-s$SEED; coll=${TASK}_cpu; setting=good_view
    [ $view = good ] || { tag=$tag-$view; coll=${TASK}_${view}_cpu; setting=${view}_view; }
    run=views-nostra-$NAME-$tag
    train $run $coll $STEPS model.loss.beta=$beta
    for split in $SPLITS; do analyse $RUNS/train/$run/policy.ckpt $coll $setting "$(root $split)/$tag" $split; done
  done
done
for split in $SPLITS; do
  out=${OUT:-reports/cpu/$TASK/views}; [ $split = held_out ] || out=$out-$split
  # the report holds every call's runs under that folder: name all their training seeds
  seeds=$(ls "$(root $split)" | sed -n 's/^.*-s\([0-9][0-9]*\)\(-[a-z]*\)\{0,1\}$/\1/p' | sort -un | tr '\n' ' ')
  python -m nostra.workflows.offline_report --analyses "$(root $split)" --out "$out" \
    ${EPISODES:+--views-episodes $EPISODES} --command "TASK=$TASK SEED=$SEED \
BETAS=\"$BETAS\" STEPS=$STEPS VIEWS=\"$VIEWS\" SPLITS=\"$SPLITS\"${OUT:+ OUT=$OUT}${EPISODES:+ EPISODES=\"$EPISODES\"} \
bash scripts/cpu_views.sh ($(( ($(date +%s) - start) / 60 )) min in this call; the report holds the runs of training \
SEEDS=\"${seeds% }\" on this disk)"
  log "done: $out/offline.md"
done
