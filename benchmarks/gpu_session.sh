#!/usr/bin/env bash
# One short GPU session of speed measurements (benchmarks/gpu_session.py), from the repository
# root, on a machine with a CUDA GPU and python3 with torch: figures and log under $OUT
# (default out/gpu-session). Extra arguments go to gpu_session.py (e.g. --deadline-s 300).
set -u
OUT="${OUT:-out/gpu-session}"
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
python3 benchmarks/gpu_session.py --out "$OUT" "$@" 2>&1 | tee "$OUT/gpu_session.log"
exit "${PIPESTATUS[0]}"
