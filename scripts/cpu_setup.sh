# Sourced by the CPU-profile scripts (cpu.sh, cpu_claims.sh, cpu_transfer.sh, cpu_adamli_sweep.sh, cpu_horizon.sh): where a study lives, from
#   OBS=rgb (two cameras + proprioception: Table 1; default) | rgbd (+ agentview depth: Table 2, profile cpu_rgbd)
#   CAPACITY=configured (default) | matched (BC-LSTM's and BC-RSSM's widths give NOSTRA's parameter count,
#            nostra.workflows.capacity; NOSTRA, the reference, is the configured run, linked, not retrained)
#   DEMOS=<n> demos to train on (default: the profile's demos_per_task, 200); more adds a second collection
#            of the other n - 200 (episode seeds from 10000: apart from the first demos' and the evaluation's,
#            1000...) and gives the study its own runs and reports (data/runs/cpu-d<n>, reports/cpu-d<n>)
#   DEMO_NOISE=<std> (optional) the demos' action noise (generate.action_noise; the profile's: 0.05) for demos of
#            its own (collections <task>_cpu_n<std>[_plus<n>], '.' written 'p'; the same expert seeds) and a study
#            of its own (data/runs/cpu[...]-n<std>, reports/cpu[...]-n<std>); the labels stay the expert's (DART)
#   DEMO_NOISE_PHASES=<phase>[,<phase>...] (optional, with DEMO_NOISE) that noise only while the expert is in these
#            phases of its script (generate.action_noise_phases; e.g. approach): collections <task>_cpu_n<std>_<phases>,
#            study cpu[...]-n<std>-<phases> ('-' between phases)
#   STEPS=<n> (optional) a whole number of training steps, checked here for the scripts that take one
#   LR=constant (the paper's Adam at 1e-4; default) | cosine: BC-LSTM's, BC-RSSM's and BC-NOSTRA's rate decays to
#            0 over STEPS (needed) by a half cosine, not the paper's recipe; the study gets its own runs and reports
#            (data/runs/cpu[...]-cosine, reports/cpu[...]-cosine; Diffusion Policy keeps its own schedule)
#   HEAD=gaussian (the paper's decoder: learned mean, fixed variance; default) | gmm: BC-LSTM's, BC-RSSM's and
#            BC-NOSTRA's actions from a 5-mode Gaussian mixture (robomimic BC-RNN's head), not the paper's
#            recipe; the study gets its own runs and reports (data/runs/cpu[...]-gmm, reports/cpu[...]-gmm)
#   HORIZON=<n> (optional) rollout steps instead of the profile's eval_horizon: the cells (and the reports)
#            are named <task>-h<n>, so that they never mix with, or are kept as, the profile horizon's
# Sets PROFILE, RUNS (data/runs/cpu[-rgbd][-matched][-d<n>][-n<std>[-<phases>]][-cosine][-gmm]), REPORTS (reports/cpu[...]),
# EVAL_NAME, RECIPE (the overrides LR and HEAD give the recurrent policies) and KNOBS (DEMO_NOISE[_PHASES], LR and HEAD as
# the command line sets them);
# defines collection, demo_collections, same_as_best, records, link_configured and study_settings.
OBS=${OBS:-rgb}
CAPACITY=${CAPACITY:-configured}
DEMOS=${DEMOS:-}
[ -z "${STEPS:-}" ] || [[ $STEPS =~ ^[1-9][0-9]*$ ]] ||
  { echo "$0: STEPS=$STEPS must be a whole number of training steps above 0" >&2; exit 2; }
[ -z "${HORIZON:-}" ] || [[ $HORIZON =~ ^[1-9][0-9]*$ ]] ||
  { echo "$0: HORIZON=$HORIZON must be a whole number of rollout steps above 0" >&2; exit 2; }
EVAL_NAME=${TASK:-}${HORIZON:+-h$HORIZON}   # evaluate/<EVAL_NAME>: the task's cells at this horizon
case $OBS in
  rgb) PROFILE=cpu SUFFIX="" ;;
  rgbd) PROFILE=cpu_rgbd SUFFIX=-rgbd ;;
  *) echo "$0: unknown OBS=$OBS; valid: rgb, rgbd" >&2; exit 2 ;;
esac
case $CAPACITY in
  configured) ;;
  matched) SUFFIX=$SUFFIX-matched ;;
  *) echo "$0: unknown CAPACITY=$CAPACITY; valid: configured, matched" >&2; exit 2 ;;
esac
if [ -n "$DEMOS" ]; then
  BASE_DEMOS=$(python -c "
from hydra import compose, initialize_config_dir
from pipeline._hydra import CONF_DIR
with initialize_config_dir(CONF_DIR, version_base='1.3'):
    print(compose('config', overrides=['profile=$PROFILE']).profile.demos_per_task)")
  [[ $DEMOS =~ ^[0-9]+$ ]] && [ "$DEMOS" -gt "$BASE_DEMOS" ] ||
    { echo "$0: DEMOS=$DEMOS must be a whole number above the profile's demos_per_task ($BASE_DEMOS)" >&2; exit 2; }
  SUFFIX=$SUFFIX-d$DEMOS
fi
DEMO_NOISE=${DEMO_NOISE:-} NOISE_TAG=""
if [ -n "$DEMO_NOISE" ]; then
  [[ $DEMO_NOISE =~ ^(0|[1-9][0-9]*)?(\.[0-9]+)?$ ]] && awk "BEGIN { exit !($DEMO_NOISE > 0) }" ||
    { echo "$0: DEMO_NOISE=$DEMO_NOISE must be a number above 0 (the std of the demos' action noise)" >&2; exit 2; }
  NOISE_TAG=_n${DEMO_NOISE/./p} SUFFIX=$SUFFIX-n$DEMO_NOISE
fi
DEMO_NOISE_PHASES=${DEMO_NOISE_PHASES:-}
if [ -n "$DEMO_NOISE_PHASES" ]; then
  [ -n "$DEMO_NOISE" ] || { echo "$0: DEMO_NOISE_PHASES=$DEMO_NOISE_PHASES needs DEMO_NOISE=<std> too" >&2; exit 2; }
  VALID_PHASES=$(python -c "from nostra.sim.experts import PHASES; print(' '.join(PHASES))")
  for phase in ${DEMO_NOISE_PHASES//,/ }; do
    [[ " $VALID_PHASES " == *" $phase "* ]] || { echo "$0: DEMO_NOISE_PHASES: unknown phase '$phase'; the \
experts' phases: $VALID_PHASES" >&2; exit 2; }
  done
  NOISE_TAG=${NOISE_TAG}_${DEMO_NOISE_PHASES//,/_} SUFFIX=$SUFFIX-${DEMO_NOISE_PHASES//,/-}
fi
LR=${LR:-constant}
case $LR in
  constant) ;;
  cosine) [ -n "${STEPS:-}" ] || { echo "$0: LR=cosine decays over STEPS: give STEPS=<n> too" >&2; exit 2; }
          SUFFIX=$SUFFIX-cosine ;;
  *) echo "$0: unknown LR=$LR; valid: constant, cosine" >&2; exit 2 ;;
esac
HEAD=${HEAD:-gaussian}
case $HEAD in
  gaussian) ;;
  gmm) SUFFIX=$SUFFIX-gmm ;;
  *) echo "$0: unknown HEAD=$HEAD; valid: gaussian, gmm" >&2; exit 2 ;;
esac
# where the study departs from the paper (Diffusion Policy keeps its own recipe; the demos are everyone's)
RECIPE="" KNOBS="${DEMO_NOISE:+ DEMO_NOISE=$DEMO_NOISE}${DEMO_NOISE_PHASES:+ DEMO_NOISE_PHASES=$DEMO_NOISE_PHASES}"
[ $LR = constant ] || { RECIPE="$RECIPE model.optim.lr_scheduler=$LR"; KNOBS="$KNOBS LR=$LR"; }
[ $HEAD = gaussian ] || { RECIPE="$RECIPE model.net.head=$HEAD"; KNOBS="$KNOBS HEAD=$HEAD"; }
RECIPE=${RECIPE# }

# the study's settings as `make cpu` / `make cpu-claims` takes them, for a report's command line
study_settings() {
  echo "TASK=$TASK SEEDS=\"$SEEDS\" MODELS=\"$MODELS\" MINUTES=$MINUTES${STEPS:+ STEPS=$STEPS}${DP_MINUTES:+ DP_MINUTES=$DP_MINUTES}${DP_STEPS:+ DP_STEPS=$DP_STEPS}${DP_CHECK_EVERY:+ DP_CHECK_EVERY=$DP_CHECK_EVERY}${HORIZON:+ HORIZON=$HORIZON} OBS=$OBS CAPACITY=$CAPACITY${DEMOS:+ DEMOS=$DEMOS}$KNOBS"
}
RUNS=data/runs/cpu$SUFFIX
REPORTS=reports/cpu$SUFFIX

# prints a variant's episode records in a cell, in the cell itself or in one run's subfolder; fails when none
records() {  # $1 = the cell's folder, $2 = the noise, $3 = the variant; needs NAME (the task's name)
  compgen -G "$1/records/$NAME/$2/${3}_seed*.npz" || compgen -G "$1/*/records/$NAME/$2/${3}_seed*.npz"
}

# 0 when a model's last checkpoint is its best (the final in-training check was the best): the same
# weights under both names, so a last cell can be a copy of the best cell, not a second run
same_as_best() {  # $1 = model, $2 = training seed; needs NAME (the task's name)
  python - "$RUNS/train/pretrain-$1-$NAME-s$2/run.json" <<'PY'
import json, sys
run = json.load(open(sys.argv[1]))
sys.exit(0 if ((run.get("rollouts") or {}).get("best") or {}).get("step") == run["steps"] else 1)
PY
}

# CAPACITY=matched: NOSTRA, the reference, is the configured run (same OBS), linked into RUNS, not retrained
link_configured() {  # $1 = model, $2 = training seed; needs NAME (the task's name)
  local ref=cpu${SUFFIX/-matched/}/train/pretrain-$1-$NAME-s$2
  [ -f "data/runs/$ref/run.json" ] ||
    { echo "$0: CAPACITY=matched needs data/runs/$ref: run it first with CAPACITY=configured" >&2; exit 2; }
  mkdir -p "$RUNS/train" && ln -sfn "../../$ref" "$RUNS/train/pretrain-$1-$NAME-s$2"
  echo "[$(date +%H:%M:%S)] $1 seed $2: the configured run, linked"
}

# a demo collection in the store: generated (unless its file exists; generation also skips finished
# demos) and ingested (unless the store has it)
collection() {  # $1 = collection, $2 = task, $3... = generate overrides
  local name=$1 task=$2 raw=data/raw/$1.hdf5; shift 2
  [ -f "$raw" ] || { echo "[$(date +%H:%M:%S)] generate $raw"
    nostra generate profile=$PROFILE task=$task generate.collection=$name "$@"; }
  if [ -d "data/store.zarr/$name" ]; then echo "[$(date +%H:%M:%S)] ingest $raw: the store has $name"
  else echo "[$(date +%H:%M:%S)] ingest $raw"; nostra ingest profile=$PROFILE "ingest.sources=[$raw]" ingest.progress=false; fi
}

# the task's training collections in the store, made if missing; sets COLLECTIONS (comma-separated) and
# DEMO_SEEDS (where they came from, for the report)
demo_collections() {  # $1 = task
  local base=${1}_cpu$NOISE_TAG noise=(${DEMO_NOISE:+generate.action_noise=$DEMO_NOISE}
                                      ${DEMO_NOISE_PHASES:+"generate.action_noise_phases=[$DEMO_NOISE_PHASES]"})
  collection $base $1 "${noise[@]}"
  COLLECTIONS=$base DEMO_SEEDS="expert seeds from 0"
  if [ -n "$DEMOS" ]; then
    local more=$(( DEMOS - BASE_DEMOS ))
    collection ${base}_plus$more $1 generate.episodes=$more generate.seed_offset=10000 "${noise[@]}"
    COLLECTIONS=$COLLECTIONS,${base}_plus$more
    DEMO_SEEDS="$DEMOS in all, expert seeds from 0 ($base) and from 10000 (${base}_plus$more)"
  fi
  DEMO_SEEDS="$DEMO_SEEDS${DEMO_NOISE:+, action noise $DEMO_NOISE}${DEMO_NOISE_PHASES:+ (only in $DEMO_NOISE_PHASES)}"
}
