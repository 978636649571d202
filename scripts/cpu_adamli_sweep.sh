#!/usr/bin/env bash
# AdaMLI's threshold sensitivity at the CPU profile (issue 11, what the paper's reviewers asked):
# offline analyses of BC-NOSTRA's best checkpoint on its 20 held-out demos under one noise, for a
# grid of (f_o, f_c) with k_o, k_c at the paper's values, then one table and one figure of
# precision, recall and false imagination (reports/cpu/<task>/adamli_sweep/). Offline: AdaMLI
# replays the recorded demos, so each setting costs about a minute here, not a training run.
# Closed loop: each setting also drives BC-NOSTRA + AdaMLI (best checkpoint) for EPISODES rollouts
# per noise of ROLLOUT_NOISES (the same initial states as make cpu-claims; ~3-4 min a cell on Lift
# here); ROLLOUT_NOISES="" skips them. Resumable: an analysis or a rollout cell already written is kept.
#   TASK=liftd1 SEED=0 F_O="5 10 20 40" F_C="1.5 3 6" NOISE=mask bash scripts/cpu_adamli_sweep.sh
#   ROLLOUT_NOISES="none mask" EPISODES=50 F_O="5 20 80" F_C=3 bash scripts/cpu_adamli_sweep.sh
# OBS=rgbd sweeps the Table 2 policy (make cpu-claims OBS=rgbd), e.g. f_c under zeroed proprioception:
#   OBS=rgbd NOISE=proprio_zero ROLLOUT_NOISES="none proprio_zero" F_O=20 F_C="3 6 12" bash scripts/cpu_adamli_sweep.sh
# WARMUP=0 runs the settings with AdaMLI's warm-up changed (its own settings, -w0, beside the others).
# OUT=<folder> writes the report there instead of $REPORTS/<task>/adamli_sweep (e.g. one per training seed).
# CHECKPOINT=last sweeps the last checkpoint instead of the best (its analyses and rollouts apart: <task>-adamli-last);
# the study's knobs (DEMOS, DEMO_NOISE[_PHASES], LR, HEAD, HORIZON: scripts/cpu_setup.sh) pick its runs, demos and horizon:
#   TASK=stack DEMOS=1000 DEMO_NOISE=0.2 DEMO_NOISE_PHASES=approach LR=cosine STEPS=18000 HORIZON=600 CHECKPOINT=last \
#     F_O=20 F_C=12 ROLLOUT_NOISES="none mask" OUT=<folder> bash scripts/cpu_adamli_sweep.sh
# Where make cpu-claims has evaluated the same checkpoint, each setting's rollouts are also paired with
# its cells (the paper's AdaMLI, the oracle MLI and BC-LSTM under the same noise, the clean closed loop).
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$PWD/.venv/bin:$PATH"
TASK=${TASK:-liftd1}
SEED=${SEED:-0}
F_O=${F_O:-5 10 20 40}
F_C=${F_C:-1.5 3 6}
NOISE=${NOISE:-mask}
ROLLOUT_NOISES=${ROLLOUT_NOISES-none mask}
EPISODES=${EPISODES:-50}
WARMUP=${WARMUP:-}   # AdaMLI's warm-up in steps (empty: AdaMLIConfig's 10); a setting's name then ends -w<steps>
CHECKPOINT=${CHECKPOINT:-best}
case $CHECKPOINT in best) CK="" ;; last) CK=-last ;;
  *) echo "$0: unknown CHECKPOINT=$CHECKPOINT; valid: best, last" >&2; exit 2 ;; esac
HORIZON=${HORIZON:-}
source scripts/cpu_setup.sh   # OBS and the study's knobs -> PROFILE, RUNS, REPORTS, EVAL_NAME, NOISE_TAG
ROOT=$RUNS/offline/$TASK-adamli$CK
ROLLOUTS=$RUNS/evaluate/$EVAL_NAME-adamli$CK
NAME=$(python -c "from nostra.sim.tasks import get_task; print(get_task('$TASK').name)")
# the rollouts' windows (pipeline.evaluate.noise_windows): the task config's, else the registry's (the paper's)
WINDOWS=$(python -c "import yaml; from nostra.sim.tasks import get_task
w = yaml.safe_load(open('conf/task/$TASK.yaml')).get('noise_windows') or [list(w) for w in get_task('$TASK').noise_windows]
print(w)" | tr -d ' ')
drop=$(for v in lstm diffusion rssm rssm_li nostra nostra_mli; do printf 'evaluate.variants.%s=null ' $v; done)
for fo in $F_O; do
  for fc in $F_C; do
    setting=s$SEED-fo$fo-fc$fc${WARMUP:+-w$WARMUP} ada="{f_o: $fo, f_c: $fc${WARMUP:+, warmup: $WARMUP}}"
    out=$ROOT/$setting/$NOISE
    if [ -f "$out/offline/offline.json" ]; then echo "f_o=$fo f_c=$fc: done before, kept"; else
      echo "[$(date +%H:%M:%S)] offline seed $SEED $NOISE f_o=$fo f_c=$fc"
      nostra evaluate profile=$PROFILE task=$TASK paths.runs=$RUNS seed=$SEED evaluate.rollouts=false \
        evaluate.offline.checkpoint=$RUNS/train/pretrain-nostra-$NAME-s$SEED/checkpoints/$CHECKPOINT.ckpt \
        "evaluate.offline.collections=[${TASK}_cpu$NOISE_TAG]" evaluate.offline.noise=$NOISE evaluate.offline.episodes=20 \
        "evaluate.offline.windows=$WINDOWS" "evaluate.offline.adamli=$ada" \
        evaluate.offline.setting=good_view evaluate.out_dir=$out
    fi
    for noise in $ROLLOUT_NOISES; do
      out=$ROLLOUTS/$setting/$noise
      [ -f "$out/success.csv" ] && { echo "rollouts f_o=$fo f_c=$fc $noise: done before, kept"; continue; }
      echo "[$(date +%H:%M:%S)] rollouts seed $SEED $noise f_o=$fo f_c=$fc ($EPISODES episodes)"
      nostra evaluate profile=$PROFILE task=$TASK paths.runs=$RUNS seed=$SEED evaluate.checkpoint=$CHECKPOINT \
        ${HORIZON:+profile.eval_horizon=$HORIZON} \
        "evaluate.noises=[$noise]" evaluate.episodes=$EPISODES $drop \
        "evaluate.variants.nostra_adamli.adamli=$ada" evaluate.offline.enabled=false evaluate.out_dir=$out
    done
  done
done
OUT=${OUT:-$REPORTS/$TASK/adamli_sweep}
CLAIMS=$RUNS/evaluate/$EVAL_NAME/s$SEED/$CHECKPOINT
reference=(); [ -d "$CLAIMS" ] && reference=(--reference "$CLAIMS")
python -m nostra.workflows.offline_report --analyses "$ROOT" --out "$OUT" --no-figures \
  --rollouts "$ROLLOUTS" "${reference[@]}" \
  --command "OBS=$OBS TASK=$TASK SEED=$SEED${DEMOS:+ DEMOS=$DEMOS}$KNOBS${STEPS:+ STEPS=$STEPS}${HORIZON:+ HORIZON=$HORIZON} CHECKPOINT=$CHECKPOINT F_O=\"$F_O\" F_C=\"$F_C\" NOISE=$NOISE ROLLOUT_NOISES=\"$ROLLOUT_NOISES\" EPISODES=$EPISODES${WARMUP:+ WARMUP=$WARMUP} OUT=$OUT bash scripts/cpu_adamli_sweep.sh"
