#!/usr/bin/env bash
# NOSTRA's sensitivity to its KL weight beta and KL balance gamma at the CPU profile (issue 11, what
# the paper's reviewers asked): one setting varied at a time around the paper's (beta 1e-4, gamma
# 0.1, which is make cpu's BC-NOSTRA run of that seed, reused). The new settings train BC-NOSTRA
# for MINUTES each (make cpu's budget) as one `nostra sweep`, then each best checkpoint runs 50 clean episodes (closed loop) and
# 50 under mask (closed loop, + MLI, + AdaMLI) on the evaluation seeds, and an offline analysis of
# its held-out demos under mask (per-modality KL, AdaMLI's detection). Report:
# OUT (default reports/cpu/<task>/sweep/: sweep.md, sweep.csv, sweep.png). ~40 min a setting here.
# Each training seed has its own cells (evaluate/<task>-sweep-s<seed>), so a second seed reuses none of
# the first's; give it its own OUT and pool the two with `python -m nostra.workflows.sweep_pool`.
#
# Resumable: a finished training (run.json) or a cell already written is kept.
#   TASK=liftd1 SEED=0 BETAS="1e-5 1e-3 1e-2" GAMMAS="0.5 0.9" bash scripts/cpu_sweep.sh
#   TASK=liftd1 SEED=2 BETAS=1e-2 GAMMAS=" " OUT=reports/cpu/liftd1/sweep-s2 bash scripts/cpu_sweep.sh
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$PWD/.venv/bin:$PATH"
TASK=${TASK:-liftd1}
SEED=${SEED:-0}
MINUTES=${MINUTES:-30}
BETAS=${BETAS:-1e-5 1e-3 1e-2}
GAMMAS=${GAMMAS:-0.5 0.9}
OUT=${OUT:-reports/cpu/$TASK/sweep}
BETA0=1e-4 GAMMA0=0.1   # the paper's (conf/model/nostra.yaml's defaults)
source scripts/cpu_setup.sh   # PROFILE=cpu, RUNS=data/runs/cpu, demo_collections
COMMON="profile=$PROFILE task=$TASK paths.runs=$RUNS"
NAME=$(python -c "from nostra.sim.tasks import get_task; print(get_task('$TASK').name)")
EVAL=$RUNS/evaluate/$TASK-sweep-s$SEED
OFFLINE=$RUNS/offline/$TASK-sweep-s$SEED
WINDOWS=$(python -c "import yaml; print(yaml.safe_load(open('conf/task/$TASK.yaml'))['noise_windows'])" | tr -d ' ')
start=$(date +%s)
log() { echo "[$(date +%H:%M:%S)] $*"; }

settings="b${BETA0}_g${GAMMA0}"
for b in $BETAS; do settings="$settings b${b}_g${GAMMA0}"; done
for g in $GAMMAS; do settings="$settings b${BETA0}_g${g}"; done

# the paper's setting is make cpu's BC-NOSTRA run, trained here with make cpu's command when missing (its
# cells are not needed); the others train as one `nostra sweep`, each setting merged into model.loss, one
# job after the other (LAUNCHER=serial: a time budget must not share the cores; slurm: a job array). The
# same folder again keeps the finished jobs and resumes the others.
demo_collections $TASK   # -> COLLECTIONS
if [ ! -f "$RUNS/train/pretrain-nostra-$NAME-s$SEED/run.json" ]; then
  log "train nostra seed $SEED, the paper's setting ($MINUTES min budget)"
  nostra train $COMMON model=nostra seed=$SEED "data.collections=[$COLLECTIONS]" train.max_minutes=$MINUTES \
    "train.rollout.modes=[closed]"
fi
values=""
for b in $BETAS; do values="$values{beta:$b},"; done
for g in $GAMMAS; do values="$values{gamma:$g},"; done
if [ -n "$values" ]; then
  log "nostra sweep: model.loss=${values%,} ($MINUTES min budget each)"
  nostra sweep launcher=${LAUNCHER:-serial} hydra.sweep.dir=$RUNS/sweeps/$TASK-sensitivity-s$SEED $COMMON \
    model=nostra seed=$SEED "data.collections=[$COLLECTIONS]" train.max_minutes=$MINUTES "train.rollout.modes=[closed]" \
    "model.loss=${values%,}" 'train.run_name=sweep-nostra-${task.name}-b${model.loss.beta}_g${model.loss.gamma}-s${seed}' \
    'train.out_dir=${paths.runs}/train/${train.run_name}'
fi

for s in $settings; do
  beta=${s%_g*}; beta=${beta#b}; gamma=${s#*_g}
  run=pretrain-nostra-$NAME-s$SEED   # the paper's setting: make cpu's run
  # the sweep's run name: the job's config renders the floats as Python does (1e-5 -> 1e-05)
  [ "$s" = "b${BETA0}_g${GAMMA0}" ] || run=sweep-nostra-$NAME-$(python -c "print(f'b{float(\"$beta\")}_g{float(\"$gamma\")}')")-s$SEED
  ckpt=$RUNS/train/$run/policy.ckpt   # evaluate.checkpoint=best: its checkpoints/best.ckpt
  for noise in none mask; do
    out=$EVAL/$s/$noise
    [ -f "$out/success.csv" ] && { log "evaluate $s $noise: done before, kept"; continue; }
    keep="nostra"; [ $noise = mask ] && keep="nostra nostra_mli nostra_adamli"
    args=""
    for v in lstm diffusion rssm rssm_li nostra nostra_mli nostra_adamli; do
      case " $keep " in *" $v "*) args="$args evaluate.variants.$v.checkpoint=$ckpt" ;;
                        *) args="$args evaluate.variants.$v=null" ;; esac
    done
    log "evaluate $s $noise:$keep"
    nostra evaluate $COMMON seed=$SEED evaluate.checkpoint=best "evaluate.noises=[$noise]" $args \
      evaluate.offline.enabled=false evaluate.out_dir=$out
  done
  out=$OFFLINE/$s/mask
  if [ -f "$out/offline/offline.json" ]; then log "offline $s: done before, kept"; else
    log "offline $s mask"
    nostra evaluate $COMMON seed=$SEED evaluate.rollouts=false \
      evaluate.offline.checkpoint=$RUNS/train/$run/checkpoints/best.ckpt \
      "evaluate.offline.collections=[${TASK}_cpu]" evaluate.offline.noise=mask evaluate.offline.episodes=20 \
      "evaluate.offline.windows=$WINDOWS" evaluate.offline.setting=good_view evaluate.out_dir=$out
  fi
done

python -m nostra.workflows.sweep_report --evaluations "$EVAL" --offline "$OFFLINE" --out "$OUT" \
  --command "TASK=$TASK SEED=$SEED MINUTES=$MINUTES BETAS=\"$BETAS\" GAMMAS=\"$GAMMAS\" OUT=$OUT bash scripts/cpu_sweep.sh" \
  --wall-seconds $(( $(date +%s) - start ))
