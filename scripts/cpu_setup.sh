# Sourced by scripts/cpu.sh and scripts/cpu_claims.sh: where a CPU-profile study lives, from
#   OBS=rgb (two cameras + proprioception: Table 1; default) | rgbd (+ agentview depth: Table 2, profile cpu_rgbd)
#   CAPACITY=configured (default) | matched (BC-LSTM's and BC-RSSM's widths give NOSTRA's parameter count,
#            nostra.workflows.capacity; NOSTRA, the reference, is the configured run, linked, not retrained)
# Sets PROFILE, RUNS (data/runs/cpu[-rgbd][-matched]) and REPORTS (reports/cpu[-rgbd][-matched]).
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
