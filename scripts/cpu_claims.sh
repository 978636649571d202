#!/usr/bin/env bash
# `make cpu-claims`: the paper's claims at the CPU profile on one task (issue 11). Trains and runs
# the make-cpu cells through scripts/cpu.sh (every training seed), then every Table 1 cell
# {none, mask, cam_jitter, table_tex} and the controls {clean_windows, blind} for the best and the
# last checkpoint, 50 episodes each on the same initial states, and writes reports/cpu/<task>/claims/
# (python -m nostra.workflows.claims: tables per seed and pooled, paired tests, verdicts).
#
# Resumable: a cell whose records exist is kept, training continues from last.ckpt.
#   TASK=liftd1 SEEDS="0 1" MODELS="lstm nostra" make cpu-claims    # MODELS may add rssm diffusion
#   SEEDS=2 MODELS="lstm nostra diffusion" DP_MINUTES=90 DP_STEPS=14000 DP_CHECK_EVERY=2000 make cpu-claims  # DP its own budget (scripts/cpu.sh)
# NOISES and CHECKPOINTS pick a subset of the cells to run first (the report covers whatever has run):
#   SEEDS="0 1" NOISES="none mask blind" CHECKPOINTS=best make cpu-claims
# Table 2 (multimodal noise, AdaMLI): the policies see agentview depth too (OBS=rgbd, scripts/cpu.sh), and
# the noises are rgb (both cameras masked), rgbd (+ depth) and all (+ proprioception zeroed):
#   OBS=rgbd SEEDS=0 MODELS="lstm nostra" make cpu-claims     # reports/cpu-rgbd/<task>/claims/
# Capacity-matched (BC-LSTM and BC-RSSM at NOSTRA's parameter count; reports/cpu-matched/<task>/claims/):
#   CAPACITY=matched SEEDS=0 MODELS="lstm rssm nostra" NOISES="none mask blind" make cpu-claims
# OUT=<folder> writes the report there instead, of SEEDS only (a seed whose sibling seeds' records are not on
# this disk, so that it does not replace their report, or one reported apart from the others here):
#   OBS=rgbd SEEDS=1 MODELS=nostra CHECKPOINTS=best OUT=reports/cpu-rgbd/liftd1/claims-s1 make cpu-claims
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$PWD/.venv/bin:$PATH"
TASK=${TASK:-liftd1}
SEEDS=${SEEDS:-0 1}
MODELS=${MODELS:-lstm nostra}
MINUTES=${MINUTES:-30}
STEPS=${STEPS:-}   # a step budget under MINUTES (scripts/cpu.sh)
HORIZON=${HORIZON:-}
source scripts/cpu_setup.sh   # OBS, CAPACITY -> PROFILE, RUNS, REPORTS
CPU_OUT=${OUT:+$OUT/cpu}   # with OUT, make cpu's report goes beside it, not over the task's index.md
APART=(${OUT:+--seeds $SEEDS})   # with OUT, the report covers SEEDS only, not the other seeds on this disk
OUT=${OUT:-$REPORTS/$EVAL_NAME/claims}
case $OBS in
  rgb) NOISES=${NOISES:-none mask cam_jitter table_tex clean_windows blind} ;;
  rgbd) NOISES=${NOISES:-none rgb rgbd all blind} ;;
esac
CHECKPOINTS=${CHECKPOINTS:-best last}
EVAL=$RUNS/evaluate/$EVAL_NAME   # <task>, or <task>-h<n> at a HORIZON of its own (scripts/cpu_setup.sh)
start=$(date +%s)
log() { echo "[$(date +%H:%M:%S)] $*"; }

TASK=$TASK SEEDS="$SEEDS" MODELS="$MODELS" MINUTES=$MINUTES STEPS=$STEPS HORIZON=$HORIZON OBS=$OBS CAPACITY=$CAPACITY DEMOS=$DEMOS DEMO_NOISE=$DEMO_NOISE DEMO_NOISE_PHASES=$DEMO_NOISE_PHASES LR=$LR HEAD=$HEAD CPU_OUT=$CPU_OUT bash scripts/cpu.sh

# the variants each noise needs: under none an imagining variant is its closed-loop policy (nothing to
# imagine), under clean_windows the closed-loop ones see clean frames (= none); blind keeps the
# imagining ones and the policies with no latent to imagine (black frames)
needed() {  # $1 = noise
  local out=""
  for m in $MODELS; do
    case "$m:$1" in
      lstm:clean_windows) ;;
      lstm:*) out="$out lstm" ;;
      diffusion:clean_windows) ;;
      diffusion:*) out="$out diffusion" ;;
      rssm:none) out="$out rssm" ;;
      rssm:clean_windows|rssm:blind) out="$out rssm_li" ;;
      rssm:*) out="$out rssm rssm_li" ;;
      nostra:none) out="$out nostra nostra_adamli" ;;
      nostra:clean_windows|nostra:blind) out="$out nostra_mli" ;;
      nostra:*) out="$out nostra nostra_mli nostra_adamli" ;;
    esac
  done
  echo $out
}
ALL="lstm diffusion rssm rssm_li nostra nostra_mli nostra_adamli"
NAME=$(python -c "from nostra.sim.tasks import get_task; print(get_task('$TASK').name)")
COMMON="profile=$PROFILE task=$TASK paths.runs=$RUNS${HORIZON:+ profile.eval_horizon=$HORIZON}"
# a model whose last checkpoint is its best (same_as_best, scripts/cpu_setup.sh) has the same weights under
# both names: its last cells are copies of its best cells (folder `same-as-best`), not a second run
model_of() { case $1 in nostra*) echo nostra ;; rssm*) echo rssm ;; *) echo "$1" ;; esac; }
reuse_best() {  # $1 = seed, $2 = noise, $3... = variants: copy each variant's best records into last
  local seed=$1 noise=$2 v src dst; shift 2
  for v in "$@"; do
    same_as_best "$(model_of "$v")" "$seed" || continue
    records "$EVAL/s$seed/last/$noise" $noise $v > /dev/null && continue  # evaluated there already: no copy
    src=$(records "$EVAL/s$seed/best/$noise" $noise $v) || continue
    dst=$EVAL/s$seed/last/$noise/same-as-best/records/$NAME/$noise
    mkdir -p "$dst" && cp $src "$dst/" && log "seed $seed last $noise $v: same checkpoint as best, records copied"
  done
}
for seed in $SEEDS; do
  for ck in $CHECKPOINTS; do
    for noise in $NOISES; do
      [ $ck = last ] && reuse_best "$seed" "$noise" $(needed $noise)
      todo=""
      for v in $(needed $noise); do  # kept: a variant with records of this cell (make cpu's folder or ours)
        records "$EVAL/s$seed/$ck/$noise" $noise $v > /dev/null || todo="$todo $v"
      done
      [ -z "$todo" ] && continue
      drop=""
      for v in $ALL; do case " $todo " in *" $v "*) ;; *) drop="$drop evaluate.variants.$v=null" ;; esac; done
      out=$EVAL/s$seed/$ck/$noise/$(echo $todo | tr ' ' '+')
      log "evaluate seed $seed checkpoint=$ck noise=$noise:$todo"
      nostra evaluate $COMMON seed=$seed evaluate.checkpoint=$ck "evaluate.noises=[$noise]" $drop \
        evaluate.offline.enabled=false evaluate.out_dir=$out
    done
  done
done

note=()
if [ "$CAPACITY" = matched ]; then  # the widths the runs were trained with, in the report's header
  widths=$(for m in $MODELS; do case $m in lstm|rssm)
    python -m nostra.workflows.capacity --profile $PROFILE --task $TASK --override $m ;; esac; done | tr '\n' ' ')
  note=(--note "Capacity-matched: BC-LSTM and BC-RSSM at BC-NOSTRA's parameter count (${widths% }); BC-NOSTRA as configured")
fi
# the report's own earlier episodes stay in it (records win): cells run on another machine, whose records are
# not on this disk, are not lost when this run adds a model or a noise (delete episodes.csv to drop them)
EARLIER=()
[ -f "$OUT/episodes.csv" ] && EARLIER=(--episodes "$OUT/episodes.csv")
python -m nostra.workflows.claims --evaluations "$EVAL" --out "$OUT" "${note[@]}" "${APART[@]}" "${EARLIER[@]}" \
  --command "$(study_settings) NOISES=\"$NOISES\" CHECKPOINTS=\"$CHECKPOINTS\" OUT=$OUT make cpu-claims" \
  --wall-seconds $(( $(date +%s) - start ))
log "done in $(( ($(date +%s) - start) / 60 )) min: $OUT/claims.md"
