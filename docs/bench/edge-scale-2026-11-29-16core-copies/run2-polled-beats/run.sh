#!/usr/bin/env bash
# The edge_scale benchmark on a larger host (issue 51), with the standby reading the holder's copies:
# the wheels in .whl (dynqos and what the host's image lacks), then one process against 8 replicas,
# then 2 and 4 replicas (heartbeats polled from zenoh slots on the loop).
set -u
export PYTHONUNBUFFERED=1 PIP_DISABLE_PIP_VERSION_CHECK=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
export PYTHONPATH=/tmp/site PATH=/tmp/site/bin:$PATH
cd /tmp || exit 3
{ date -u; nproc; python3 -c 'import os; print("os.cpu_count", os.cpu_count(), "affinity", len(os.sched_getaffinity(0)))';
  lscpu 2>/dev/null | grep -E "Model name|^CPU\(s\)|Thread|Socket|MHz|NUMA node\(s\)"; free -g | head -2; python3 -V;
  python3 -c 'import numpy, scipy, osqp, zenoh, dynqos.edge.mpc; print("numpy", numpy.__version__, "scipy", scipy.__version__, "osqp", osqp.__version__, "zenoh", __import__("importlib.metadata").metadata.version("eclipse-zenoh"))';
  which dynqos; dynqos --version; } 2>&1 | tee $OUT/host.txt
python3 -c 'import dynqos.edge.mpc.service as s; assert s.WATCH_COPY_NS and "_beat_slots" in open(s.__file__).read()' || exit 4
COUNTS=50,75,88,100,125
timeout 200 python3 -m dynqos.bench.edge_scale --processes 1,8 --modes replicas --loaders 8 \
  --per-process --counts $COUNTS --seconds 3 --out $OUT/edge-scale-16core-1-8.json 2>&1 | tee $OUT/run-1-8.log | grep -vE '^ |^\{|^\}|^\[|^\]'
echo "first part rc=${PIPESTATUS[0]} at $(date -u)"
timeout 150 python3 -m dynqos.bench.edge_scale --processes 2,4 --modes replicas --loaders 8 \
  --per-process --counts $COUNTS --seconds 3 --out $OUT/edge-scale-16core-2-4.json 2>&1 | tee $OUT/run-2-4.log | grep -vE "^ |^\{|^\}|^\[|^\]"
echo "second part rc=${PIPESTATUS[0]} at $(date -u)"
