#!/usr/bin/env bash
# `make demo`: the main job end to end on the tiny profile.
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/python -m pipeline.demo_synthetic "$@"
