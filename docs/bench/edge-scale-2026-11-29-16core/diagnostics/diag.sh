#!/usr/bin/env bash
# Issue 51 diagnostics on a larger host: when the misses fall (per tick) at 4 and 8 replicas, and
# where two replicas' time goes (py-spy) while 8 replicas fly a fleet.
set -u
export PYTHONUNBUFFERED=1 PIP_DISABLE_PIP_VERSION_CHECK=1
PY=${PY:-python3}; N4=${N4:-50}; N8=${N8:-400}
if [ -z "${LOCAL:-}" ]; then
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
  export PYTHONPATH=/tmp/site PATH=/tmp/site/bin:$PATH
fi
cd /tmp || exit 3
[ -n "${SKIPTICKS:-}" ] || timeout 100 $PY -m dynqos.bench.edge_scale --processes 4,8 --modes replicas --loaders 8 --per-process \
  --counts $N4 --seconds 5 --out $OUT/diag-ticks.json 2>&1 | grep -E 'edge_scale:'
echo "ticks part done $(date -u)"
( timeout 100 $PY -m dynqos.bench.edge_scale --processes 8 --modes replicas --loaders 8 --counts $N8 \
  --seconds 12 --out $OUT/diag-spy.json 2>&1 | grep -E 'edge_scale:' ) &
BG=$!
for i in $(seq 60); do [ "$(pgrep -f 'edge_scale --load' | wc -l)" -ge 8 ] && break; sleep 0.5; done
sleep 5  # the loaders declare, get ready and warm up; then the fleet flies for 12 s
P0=$(pgrep -f 'mpc.replica_id=mpc0 --config' | head -1); P1=$(pgrep -f 'mpc.replica_id=mpc1 --config' | head -1)
echo "mpc0=$P0 mpc1=$P1"
py-spy record --nonblocking --threads -d 4 -r 200 -f raw -o $OUT/spy-mpc0-threads.txt -p $P0 > /dev/null 2>&1 &
py-spy record --nonblocking --gil -d 4 -r 200 -f raw -o $OUT/spy-mpc1-gil.txt -p $P1 > /dev/null 2>&1 &
wait
echo "spy part done $(date -u)"
ls -la $OUT
