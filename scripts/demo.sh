#!/usr/bin/env bash
# `make demo`: the whole pipeline on the tiny profile (params.yaml) through `dvc repro`:
# generate -> ingest -> index -> retrieve -> train -> evaluate -> report.
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$PWD/.venv/bin:$PATH"
start=$(date +%s)
dvc repro "$@"
profile=$(python -c "import yaml; print(yaml.safe_load(open('params.yaml'))['profile'])")
echo
echo "pipeline done in $(( ($(date +%s) - start) / 60 )) min; report: $PWD/reports/$profile/index.md"
