#!/usr/bin/env bash
# Imagination over longer windows (issue 11: why BC-RSSM + LI loses nothing to BC-NOSTRA + MLI on
# LiftD1): the oracle variants of one training seed's best checkpoints under NOISE, with the task's
# windows replaced by each of WINDOWS (";"-separated settings of "start-end" windows, "+" between
# windows of one setting), EPISODES paired episodes each (the initial states of make cpu-claims).
# Then nostra.workflows.horizon_report: success, the paired difference and each variant's
# end-effector drift from its own clean run, beside the claims cells of the same checkpoint (the
# task's windows; make cpu-claims must have run that seed's none and NOISE cells). Resumable: a
# setting with records is kept.
#   TASK=liftd1 SEED=2 WINDOWS="15-65;15-200;5-200" bash scripts/cpu_horizon.sh   # ~4 min a setting here
#   NOISE=wrist_mask WINDOWS="15-35+45-60;5-200" ...   # one camera lost: what per-modality imagination keeps
#   VARIANTS=nostra_adamli NOISE=agentview_mask WINDOWS=5-200 ...   # AdaMLI too (paired with MLI in the report);
#     variants other than the default go into <setting>/<variants>, so a setting run before is not taken for them
#   ADAMLI="{warmup: 0}" VARIANTS="nostra_mli nostra_adamli" ...   # AdaMLI's settings changed (AdaMLIConfig's keys):
#     its runs under <noise>-adamli-<settings> and its report apart (e.g. horizon-wrist_mask-s4-adamli-warmup0)
#   CAPACITY=matched WINDOWS=5-200 ...   # BC-RSSM at NOSTRA's parameter count (make cpu-claims with CAPACITY=matched
#     first; NOSTRA's configured run is linked): runs and report under data/runs/cpu-matched, reports/cpu-matched
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$PWD/.venv/bin:$PATH"
TASK=${TASK:-liftd1}
SEED=${SEED:-2}
WINDOWS=${WINDOWS:-15-65;15-200;5-200}
NOISE=${NOISE:-mask}
EPISODES=${EPISODES:-50}
VARIANTS=${VARIANTS:-nostra_mli rssm_li}
ADAMLI=${ADAMLI:-}
TAG=$(echo "$ADAMLI" | tr -d ' {}:' | tr ',' '-')   # {warmup: 0, f_c: 12} -> warmup0-f_c12 (no comma: Hydra's list)
ADA=(${ADAMLI:+"evaluate.variants.nostra_adamli.adamli=$ADAMLI"})
source scripts/cpu_setup.sh   # OBS, CAPACITY -> PROFILE, RUNS, REPORTS
start=$(date +%s)
NAME=$(python -c "from nostra.sim.tasks import get_task; print(get_task('$TASK').name)")
ROOT=$RUNS/evaluate/$TASK-horizon/s$SEED/$NOISE${TAG:+-adamli-$TAG}
case "$CAPACITY $VARIANTS" in matched*nostra*) link_configured nostra $SEED ;; esac   # as make cpu-claims links it
drop=$(for v in lstm diffusion rssm rssm_li nostra nostra_mli nostra_adamli; do
  case " $VARIANTS " in *" $v "*) ;; *) printf 'evaluate.variants.%s=null ' $v ;; esac; done)
IFS=';' read -ra SETTINGS <<< "$WINDOWS"
for setting in "${SETTINGS[@]}"; do
  out=$ROOT/$setting
  [ "$VARIANTS" = "nostra_mli rssm_li" ] || out=$out/$(echo $VARIANTS | tr ' ' '+')
  if [ -f "$out/success.csv" ]; then echo "windows $setting: done before, kept"; continue; fi
  windows="[$(echo "$setting" | sed -E 's/([0-9]+)-([0-9]+)/[\1,\2]/g; s/\+/,/g')]"   # 15-35+45-60 -> [[15,35],[45,60]]
  echo "[$(date +%H:%M:%S)] seed $SEED $NOISE windows $windows ($EPISODES episodes, $VARIANTS)"
  nostra evaluate profile=$PROFILE task=$TASK paths.runs=$RUNS seed=$SEED evaluate.checkpoint=best \
    "evaluate.noises=[$NOISE]" evaluate.episodes=$EPISODES $drop "evaluate.windows={$NAME: $windows}" "${ADA[@]}" \
    evaluate.offline.enabled=false evaluate.out_dir=$out
done
OUT=${OUT:-$REPORTS/$TASK/horizon-$NOISE-s$SEED${TAG:+-adamli-$TAG}}
TASK_WINDOWS=$(python -c "import yaml; w = yaml.safe_load(open('conf/task/$TASK.yaml'))['noise_windows']; print('+'.join(f'{a}-{b}' for a, b in w))")
HORIZON=$(python - <<PY
from hydra import compose, initialize_config_dir
from pipeline._hydra import CONF_DIR
with initialize_config_dir(CONF_DIR, version_base="1.3"):
    print(compose("config", overrides=["profile=$PROFILE", "task=$TASK"]).evaluate.horizon)
PY
)
# AdaMLI's settings changed: the claims cells' AdaMLI (the paper's) is not this study's, so it is not read
EXCLUDE=(${ADAMLI:+--reference-excludes nostra_adamli})
CAP=$([ "$CAPACITY" = configured ] || echo " CAPACITY=$CAPACITY")   # the command as run
python -m nostra.workflows.horizon_report --evaluations "$ROOT" --reference "$RUNS/evaluate/$TASK/s$SEED/best" \
  --reference-windows "$TASK_WINDOWS" "${EXCLUDE[@]}" --horizon "$HORIZON" --noise "$NOISE" --out "$OUT" --wall-seconds $(( $(date +%s) - start )) \
  --command "OBS=$OBS$CAP TASK=$TASK SEED=$SEED WINDOWS=\"$WINDOWS\" NOISE=$NOISE EPISODES=$EPISODES VARIANTS=\"$VARIANTS\"${ADAMLI:+ ADAMLI=\"$ADAMLI\"} OUT=$OUT bash scripts/cpu_horizon.sh"
