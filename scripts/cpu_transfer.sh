#!/usr/bin/env bash
# `make cpu-transfer`: the paper's Tables 4 and 5 at the CPU profile on one task (issue 11).
# Table 4: BC-LSTM, BC-RSSM and BC-NOSTRA pretrained on demos whose agent view is occluded (the robot
#   blocks the camera: a non-informative input; other initial states than the target demos), then
#   fine-tuned on N target demos with the good view.
# Table 5: BC-NOSTRA on N_TARGET target demos alone (target only: also Table 4's from-scratch reference),
#   or co-trained with a manifest retrieved (faiss) from a varied library of Lift, Stack and Can demos
#   (moved cameras, other table textures, a fifth of them occluded): obj_skill (BUDGET_OBJ episodes by
#   object and skill) and all (BUDGET_ALL of those re-ranked by camera pose and placement).
# Fine-tuned and co-trained runs check 10 rollouts every ROLLOUT_EVERY steps; each cell is 50 clean
# episodes of the best checkpoint (the paper's peak performance), the same initial states for all,
# compared paired in reports/cpu/<task>/transfer/ (python -m nostra.workflows.transfer_report).
#
# Resumable: a finished collection, run (run.json), manifest or cell is kept; training continues
# from last.ckpt. TABLES picks the tables to run (default both, Table 4 first):
#   TASK=liftd1 SEEDS=0 make cpu-transfer
#   TABLES=5 COTRAIN_MODELS="nostra lstm" make cpu-transfer
#   TABLES=5 SEEDS=1 OUT=reports/cpu/liftd1/transfer-s1 make cpu-transfer   # a seed reported apart
#   TABLES=5 SETTINGS="target_only obj_skill" make cpu-transfer               # some of Table 5's columns
#   EPISODES=reports/cpu/liftd1/transfer/episodes.csv ...   # pair with cells whose records are not on this disk
# The report holds SEEDS' cells only (other seeds' records on this disk or in EPISODES are left out).
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$PWD/.venv/bin:$PATH"
TASK=${TASK:-liftd1}
SEEDS=${SEEDS:-0}
TABLES=${TABLES:-4 5}
MODELS=${MODELS:-lstm rssm nostra}        # Table 4's rows
COTRAIN_MODELS=${COTRAIN_MODELS:-nostra}  # Table 5's rows
SETTINGS=${SETTINGS:-target_only obj_skill all}  # Table 5's columns
FT_DEMOS=${DEMOS:-10 20}                  # Table 4's columns (DEMOS): target demos to fine-tune on
N_TARGET=${N_TARGET:-10}                  # Table 5's target demos
BUDGET_OBJ=${BUDGET_OBJ:-120}
BUDGET_ALL=${BUDGET_ALL:-40}
LIBRARY=${LIBRARY:-lift:120 stack:60 pickplacecan:40}   # task:episodes of the retrieval pool
MINUTES_PRE=${MINUTES_PRE:-30}            # pretraining on the occluded view, no rollouts
MINUTES_FT=${MINUTES_FT:-15}              # fine-tuning and co-training, rollouts included
ROLLOUT_EVERY=${ROLLOUT_EVERY:-500}
EPISODES=${EPISODES:-}                    # earlier reports' episodes.csv, read beside this disk's records
DEMOS=""   # cpu_setup.sh reads DEMOS as the training collection's size; here it named Table 4's columns
OBS=rgb CAPACITY=configured source scripts/cpu_setup.sh   # PROFILE=cpu, RUNS, collection
EVAL=$RUNS/evaluate/$TASK-transfer
OUT=${OUT:-reports/cpu/$TASK/transfer}   # another folder keeps a report whose records are not on this disk
COMMON="profile=$PROFILE task=$TASK paths.runs=$RUNS"
NAME=$(python -c "from nostra.sim.tasks import get_task; print(get_task('$TASK').name)")
start=$(date +%s)
log() { echo "[$(date +%H:%M:%S)] $*"; }
has() { case " $TABLES " in *" $1 "*) return 0 ;; *) return 1 ;; esac; }
for setting in $SETTINGS; do
  case $setting in target_only|obj_skill|all) ;;
    *) echo "SETTINGS: unknown setting '$setting'; valid: target_only obj_skill all" >&2; exit 2 ;; esac
done

train() {  # $1 = run name, $2... = overrides; kept once finished (run.json)
  local run=$1; shift
  if [ -f "$RUNS/train/$run/run.json" ]; then log "train $run: finished before, kept"; return; fi
  log "train $run"
  nostra train $COMMON train.run_name=$run "$@"
}
checked() {  # the overrides of a run that checks rollouts during training (best.ckpt = its peak)
  echo "train.max_minutes=$MINUTES_FT train.rollout.every=$ROLLOUT_EVERY train.rollout.modes=[closed]" \
    "train.rollout.final_episodes=10"
}
label() { case $1 in finetune-n*) echo "${1#finetune-n} demos" ;; *) echo "${1#cotrain-}" ;; esac; }  # MLflow's setting
evaluate() {  # $1 = seed, $2 = setting (the cell's folder), $3 = model:run ... : 50 clean episodes of each best.ckpt
  local seed=$1 setting=$2 todo="" over="" pair m run v; shift 2
  for pair in "$@"; do
    m=${pair%%:*} run=${pair#*:}
    compgen -G "$EVAL/s$seed/$setting/**/records/$NAME/none/${m}_seed*.npz" > /dev/null && continue
    todo="$todo $m" over="$over evaluate.variants.$m.checkpoint=$RUNS/train/$run/policy.ckpt"
  done
  [ -z "$todo" ] && { log "evaluate seed $seed $setting: done before, kept"; return; }
  for v in lstm diffusion rssm rssm_li nostra nostra_mli nostra_adamli; do
    case " $todo " in *" $v "*) ;; *) over="$over evaluate.variants.$v=null" ;; esac
  done
  log "evaluate seed $seed $setting:$todo"
  nostra evaluate $COMMON seed=$seed evaluate.checkpoint=best "evaluate.noises=[none]" $over \
    evaluate.offline.enabled=false evaluate.table=${setting%%-*} "evaluate.setting=$(label $setting)" \
    evaluate.out_dir=$EVAL/s$seed/$setting/$(echo $todo | tr ' ' '+')
}

collection ${TASK}_cpu $TASK   # the target demos (make cpu's)
if has 4; then
  collection ${TASK}_occluded_pre_cpu $TASK generate.seed_offset=2000 generate.variation.occluded=1.0
  for seed in $SEEDS; do
    for m in $MODELS; do
      train occluded-$m-$NAME-s$seed model=$m seed=$seed "data.collections=[${TASK}_occluded_pre_cpu]" \
        train.max_minutes=$MINUTES_PRE train.rollout.every=0
    done
    for n in $FT_DEMOS; do
      for m in $MODELS; do
        train finetune-$m-$NAME-n$n-s$seed model=$m seed=$seed "data.collections=[${TASK}_cpu]" train.stage=finetune \
          train.init_from=$RUNS/train/occluded-$m-$NAME-s$seed/policy.ckpt train.num_demos=$n $(checked)
      done
      evaluate $seed finetune-n$n $(for m in $MODELS; do echo $m:finetune-$m-$NAME-n$n-s$seed; done)
    done
  done
fi

pool=${TASK}_cpu   # the target collection and the library (Table 5)
if has 5; then
  for lib in $LIBRARY; do
    t=${lib%%:*}
    collection ${t}_library_cpu $t generate.seed_offset=5000 generate.episodes=${lib#*:} \
      generate.variation.camera_pos=0.03 generate.variation.camera_rot=5 \
      "generate.variation.table_textures=[wood-tiles,gray-felt,white-bricks,light-wood]" generate.variation.occluded=0.2
    pool=$pool,${t}_library_cpu
  done
  log "index $pool"   # incremental: unchanged collections are left alone
  nostra index profile=$PROFILE retrieval.index_dir=$RUNS/index/$TASK "retrieval.collections=[$pool]" retrieval.progress=false
  for mode in $SETTINGS; do
    [ $mode = target_only ] && continue
    manifest=$RUNS/manifests/$TASK-$mode.json
    budget=$([ $mode = all ] && echo $BUDGET_ALL || echo $BUDGET_OBJ)
    [ -f "$manifest" ] && { log "retrieve $mode: $manifest kept"; continue; }
    nostra retrieve profile=$PROFILE retrieval.index_dir=$RUNS/index/$TASK retrieval.target=${TASK}_cpu \
      retrieval.mode=$mode retrieval.budget=$budget retrieval.manifest=$manifest
  done
  for seed in $SEEDS; do
    for setting in $SETTINGS; do
      stage="train.stage=cotrain train.manifest=$RUNS/manifests/$TASK-$setting.json"
      [ $setting = target_only ] && stage=train.stage=pretrain
      for m in $COTRAIN_MODELS; do
        train cotrain-$m-$NAME-$setting-s$seed model=$m seed=$seed "data.collections=[${TASK}_cpu]" $stage \
          train.num_demos=$N_TARGET $(checked)
      done
      evaluate $seed cotrain-$setting $(for m in $COTRAIN_MODELS; do echo $m:cotrain-$m-$NAME-$setting-s$seed; done)
    done
  done
fi

python -m nostra.workflows.transfer_report --evaluations "$EVAL" --out "$OUT" --target-demos $N_TARGET \
  --seeds $SEEDS ${EPISODES:+--episodes $EPISODES} \
  --command "TASK=$TASK SEEDS=\"$SEEDS\" TABLES=\"$TABLES\" MODELS=\"$MODELS\" COTRAIN_MODELS=\"$COTRAIN_MODELS\" SETTINGS=\"$SETTINGS\" DEMOS=\"$FT_DEMOS\" N_TARGET=$N_TARGET BUDGET_OBJ=$BUDGET_OBJ BUDGET_ALL=$BUDGET_ALL LIBRARY=\"$LIBRARY\" MINUTES_PRE=$MINUTES_PRE MINUTES_FT=$MINUTES_FT OUT=$OUT${EPISODES:+ EPISODES=\"$EPISODES\"} make cpu-transfer" \
  --note "Pretraining: ${TASK}_occluded_pre_cpu (agent view occluded, seeds 2000+), $MINUTES_PRE min per model; fine-tuning and co-training: $MINUTES_FT min, a 10-episode check every $ROLLOUT_EVERY steps" \
  --note "Retrieval index (target never retrieved): $pool" \
  --wall-seconds $(( $(date +%s) - start ))
log "done in $(( ($(date +%s) - start) / 60 )) min: $OUT/transfer.md"
