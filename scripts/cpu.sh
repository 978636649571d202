#!/usr/bin/env bash
# `make cpu`: the CPU profile end to end on one task (default LiftD1): 200 noise-injected expert
# demos -> store -> BC-LSTM and BC-NOSTRA, 30 minutes each with rollouts during training ->
# 50 rollouts per cell on seeds no demo used, with the best and the last checkpoint, clean and
# blind (no camera all episode) -> reports/cpu/<task>/index.md.
#
# Every step is resumable: generation skips a finished file, ingest is idempotent, training
# continues from last.ckpt (a finished run ends at once), so a killed run continues where it stopped;
# a run with nothing left to train or evaluate keeps the report (command, wall time) of the run that made it.
#   TASK=stackd1 MINUTES=60 HORIZON=300 SEEDS="0 1" MODELS="lstm nostra" make cpu
#   OBS=rgbd make cpu    # the policies see agentview depth too (profile cpu_rgbd, Table 2), in data/runs/cpu-rgbd
#   CAPACITY=matched MODELS="lstm rssm nostra" make cpu   # BC-LSTM and BC-RSSM at NOSTRA's parameter count
#   SEEDS=2 CPU_OUT=reports/cpu/liftd1/claims-s2/cpu make cpu   # the report elsewhere, not over seeds 0-1's
#   TASK=stack DEMOS=1000 MODELS=nostra MINUTES=60 make cpu   # 1000 demos (the paper's for MimicGen's tasks)
#   TASK=stack DEMOS=1000 SEEDS="0 1" MODELS=nostra HORIZON=400 make cpu   # finished runs rolled out 400 steps:
#     cells in evaluate/stack-h400, report in reports/cpu-d1000/stack-h400 (apart from the profile horizon's)
#   TASK=liftd1 SEEDS=4 MODELS=rssm STEPS=3268 make cpu   # a step budget too (train.max_steps): match a run
#     trained on another machine, whose minutes bought a different number of steps
#   LR=cosine TASK=stack DEMOS=1000 MODELS=nostra STEPS=18000 MINUTES=200 make cpu   # the rate decayed to 0 over
#     STEPS (not the paper's constant rate): runs and reports of its own (data/runs/cpu-d1000-cosine)
#   HEAD=gmm LR=cosine TASK=stack DEMOS=1000 MODELS=nostra STEPS=18000 MINUTES=200 make cpu   # a 5-mode GMM action
#     head (robomimic BC-RNN's, not the paper's fixed-variance Gaussian): data/runs/cpu-d1000-cosine-gmm
#   DEMO_NOISE=0.2 LR=cosine TASK=stack DEMOS=1000 MODELS=nostra STEPS=18000 MINUTES=200 HORIZON=600 make cpu
#     # demos with action noise 0.2 (the profile's: 0.05), collections and runs of their own (cpu-d1000-n0.2-cosine)
#   MODELS=diffusion DP_MINUTES=90 DP_STEPS=14000 DP_CHECK_EVERY=2000 make cpu   # Diffusion Policy's own budget:
#     its cosine spans DP_STEPS (what DP_MINUTES buys here), an in-training check every DP_CHECK_EVERY steps
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$PWD/.venv/bin:$PATH"
TASK=${TASK:-liftd1}
SEEDS=${SEEDS:-0}
MODELS=${MODELS:-lstm nostra}
MINUTES=${MINUTES:-30}
STEPS=${STEPS:-}   # empty: the minutes alone end training
HORIZON=${HORIZON:-}   # rollout horizon in steps; empty: the profile's (200, enough for Lift; MimicGen rolls Stack out 400)
DP_MINUTES=${DP_MINUTES:-} DP_STEPS=${DP_STEPS:-} DP_CHECK_EVERY=${DP_CHECK_EVERY:-}
source scripts/cpu_setup.sh   # OBS, CAPACITY -> PROFILE, RUNS, REPORTS
OUT=${CPU_OUT:-$REPORTS/$EVAL_NAME}   # CPU_OUT: elsewhere (a seed run alone, its siblings' runs not on this disk)
COMMON="profile=$PROFILE task=$TASK paths.runs=$RUNS${HORIZON:+ profile.eval_horizon=$HORIZON}"
start=$(date +%s)
ran=0   # set when this run trained or evaluated something: otherwise the report of the run that did is kept
log() { echo "[$(date +%H:%M:%S)] $*"; }

demo_collections $TASK   # -> COLLECTIONS, DEMO_SEEDS

NAME=$(python -c "from nostra.sim.tasks import get_task; print(get_task('$TASK').name)")
for seed in $SEEDS; do
  for model in $MODELS; do
    if [ -f "$RUNS/train/pretrain-$model-$NAME-s$seed/run.json" ]; then  # written when a run has finished
      log "train $model seed $seed: finished before, kept"
      continue
    fi
    width=""
    if [ "$CAPACITY" = matched ]; then
      case $model in
        lstm|rssm) width=$(python -m nostra.workflows.capacity --profile $PROFILE --task $TASK --override $model) ;;
        *) link_configured $model $seed; continue ;;  # the reference: the configured run
      esac
    fi
    minutes=$MINUTES extra=""
    [ $model = diffusion ] || extra=$RECIPE
    if [ $model = diffusion ]; then
      minutes=${DP_MINUTES:-$MINUTES}
      extra="${DP_STEPS:+profile.dp_total_steps=$DP_STEPS}${DP_CHECK_EVERY:+ train.rollout.every=$DP_CHECK_EVERY}"
    fi
    log "train $model seed $seed ($minutes min budget${STEPS:+, at most $STEPS steps}${width:+, $width}${extra:+, $extra})"; ran=1
    nostra train $COMMON model=$model seed=$seed "data.collections=[$COLLECTIONS]" train.max_minutes=$minutes \
      "train.rollout.modes=[closed]" ${STEPS:+train.max_steps=$STEPS} $width $extra
  done
done

# The cells: clean with the best and the last checkpoint, the blind control with the best. The
# imagining variants (NOSTRA + MLI, BC-RSSM + LI) run only blind (with no noise they imagine nothing:
# they are the closed-loop policy) and the closed-loop NOSTRA and BC-RSSM only clean.
kept() {  # $1 = the noise; prints the variants this cell needs
  local m
  for m in $MODELS; do
    case "$m:$1" in
      nostra:none) echo nostra ;;
      nostra:*) echo nostra_mli ;;
      rssm:none) echo rssm ;;
      rssm:*) echo rssm_li ;;
      *) echo $m ;;  # lstm, diffusion: black frames when blind
    esac
  done
}
drop() {  # $@ = the variants to run; prints the overrides that drop every other one
  local v
  for v in lstm diffusion rssm rssm_li nostra nostra_mli nostra_adamli; do
    case " $* " in *" $v "*) ;; *) printf 'evaluate.variants.%s=null ' "$v" ;; esac
  done
}
all_same_as_best() { local m; for m in $MODELS; do same_as_best $m $1 || return 1; done; }
for seed in $SEEDS; do
  for c in best:none best:blind last:none; do
    ck=${c%%:*} noise=${c##*:}
    cell=$RUNS/evaluate/$EVAL_NAME/s$seed/$ck/$noise
    todo=""   # the variants without records in this cell (another model's run may have filled it first)
    for v in $(kept $noise); do
      records "$cell" $noise $v > /dev/null || todo="$todo $v"
    done
    if [ -z "$todo" ]; then log "evaluate seed $seed $ck $noise: done before, kept"; continue; fi
    out=$cell
    [ -e "$cell/success.csv" ] && out=$cell/$(echo $todo | tr ' ' '+')   # beside the other models' records
    best=$RUNS/evaluate/$EVAL_NAME/s$seed/best/$noise
    if [ $ck = last ] && [ ! -e "$cell" ] && [ -f "$best/success.csv" ] && all_same_as_best $seed; then
      mkdir -p "$(dirname "$cell")" && cp -r "$best" "$cell"
      echo "The last checkpoint of every model trained here ($MODELS) is its best (the final check was the best): a copy of best/$noise." \
        > "$cell/SAME_AS_BEST.txt"
      log "evaluate seed $seed last $noise: the same checkpoints as best, its records copied"; ran=1; continue
    fi
    log "evaluate seed $seed checkpoint=$ck noise=$noise:$todo"; ran=1
    nostra evaluate $COMMON seed=$seed evaluate.checkpoint=$ck "evaluate.noises=[$noise]" $(drop $todo) \
      evaluate.offline.enabled=false evaluate.out_dir=$out
  done
done

if [ $ran = 0 ] && [ -f "$OUT/index.md" ]; then
  log "nothing new to train or evaluate: $OUT/index.md kept (its command and wall time are the run's that made it)"; exit 0
fi
python -m nostra.workflows.cpu_report --task "$TASK" --runs "$RUNS" --seeds $SEEDS --models $MODELS --out "$OUT" \
  --demos "$DEMO_SEEDS" ${HORIZON:+--horizon $HORIZON} \
  --command "$(study_settings) make cpu" \
  --wall-seconds $(( $(date +%s) - start ))
log "done in $(( ($(date +%s) - start) / 60 )) min: $OUT/index.md"
