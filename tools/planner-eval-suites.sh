#!/usr/bin/env bash
# Fly the planner's evaluation suites (tools/planner-eval.py), one after the other.
# Usage: tools/planner-eval-suites.sh OUT_DIR WORKERS SUITE...  where SUITE is NAME:CRUISE:SEEDS[:DRIFT[:REALIZATION[:KINDS]]]
# (KINDS: course kinds joined by '+', default all)
# e.g. local3:3.0:0-8  local07:0.7:1000-1008:0.14
set -euo pipefail
out=$1; workers=$2; shift 2
mkdir -p "$out"
for spec in "$@"; do
  IFS=: read -r name cruise seeds drift real kinds <<<"$spec"
  kinds=${kinds:-corridor+doorway+forest+pitch+side+deadend+office+detour}
  cfg="$out/$name.toml"
  {
    echo "[envelope]"; echo "max_horizontal_speed_m_s = 4.0"
    echo "[planner]"; echo "cruise_speed_m_s = $cruise"
    echo "[sim]"; echo "camera_rate_hz = 30.0"; echo "drift_speed_m_s = ${drift:-0.0}"; echo "realization = ${real:-0}"
  } >"$cfg"
  python3 tools/planner-eval.py --config "$cfg" --seeds "$seeds" --kinds "${kinds//+/,}" --workers "$workers" --label "$name" \
    --json "$out/$name.json" >"$out/$name.txt" 2>&1 || echo "$name failed" >>"$out/$name.txt"
  cat "$out/$name.txt"
done
