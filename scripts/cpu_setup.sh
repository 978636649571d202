# Sourced by the CPU-profile scripts (cpu.sh, cpu_claims.sh, cpu_transfer.sh, cpu_adamli_sweep.sh): where a study lives, from
#   OBS=rgb (two cameras + proprioception: Table 1; default) | rgbd (+ agentview depth: Table 2, profile cpu_rgbd)
#   CAPACITY=configured (default) | matched (BC-LSTM's and BC-RSSM's widths give NOSTRA's parameter count,
#            nostra.workflows.capacity; NOSTRA, the reference, is the configured run, linked, not retrained)
# Sets PROFILE, RUNS (data/runs/cpu[-rgbd][-matched]) and REPORTS (reports/cpu[-rgbd][-matched]);
# defines collection and same_as_best.
OBS=${OBS:-rgb}
CAPACITY=${CAPACITY:-configured}
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
RUNS=data/runs/cpu$SUFFIX
REPORTS=reports/cpu$SUFFIX

# 0 when a model's last checkpoint is its best (the final in-training check was the best): the same
# weights under both names, so a last cell can be a copy of the best cell, not a second run
same_as_best() {  # $1 = model, $2 = training seed; needs NAME (the task's name)
  python - "$RUNS/train/pretrain-$1-$NAME-s$2/run.json" <<'PY'
import json, sys
run = json.load(open(sys.argv[1]))
sys.exit(0 if ((run.get("rollouts") or {}).get("best") or {}).get("step") == run["steps"] else 1)
PY
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
