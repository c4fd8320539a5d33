#!/usr/bin/env bash
# Eight MPC processes on two cores (issue 51): what eight replicas cost beside eight static shards at the
# same small fleet, and how much of it is the replicas' heartbeats (five per lease, each replica's heard
# by the seven others): the lease doubled halves the beats. Three rounds, each mode in turn.
set -u
cd "$(dirname "$0")"
PY=${PY:-../../../.venv/bin/python}
for round in 1 2 3; do
  for mode in replicas-lease0.05 replicas-lease0.1 sharding; do
    case $mode in
      replicas-lease0.05) args=(--modes replicas) ;;
      replicas-lease0.1) args=(--modes replicas --mpc-set mpc.takeover_after_s=0.1) ;;
      sharding) args=(--modes sharding) ;;
    esac
    timeout 300 $PY -m dynqos.bench.edge_scale --processes 8 "${args[@]}" --loaders 2 --counts 40 \
      --seconds 10 --out "r$round-$mode.json" 2>&1 | grep -E 'edge_scale:'
  done
done
