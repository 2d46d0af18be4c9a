#!/usr/bin/env bash
# One short GPU session of speed measurements (speed/gpu_session.py), from the repository
# root, on a machine with a CUDA GPU and python3 with torch: the figures (gpu-session.json and
# the page gpu.md) in $OUT, default docs/figures; the log in $OUT (default out/), gpu_session.log.
# Extra arguments go to gpu_session.py (e.g. --deadline-s 300).
set -u
LOG_DIR="${OUT:-out}"
mkdir -p "$LOG_DIR"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
python3 speed/gpu_session.py "$@" 2>&1 | tee "$LOG_DIR/gpu_session.log"
exit "${PIPESTATUS[0]}"
