#!/usr/bin/env bash
# Issue 51 diagnostics: per-thread CPU of two MPC processes, 8 replicas vs 8 static shards at 400 drones
# (16 cores), and py-spy of one replica's threads, in the steady state.
set -u
export PYTHONUNBUFFERED=1 PIP_DISABLE_PIP_VERSION_CHECK=1
PY=${PY:-python3}; N=${N:-400}
if [ -z "${LOCAL:-}" ]; then
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
  export PYTHONPATH=/tmp/site PATH=/tmp/site/bin:$PATH
fi
cd /tmp || exit 3
snap() { for t in /proc/$1/task/*; do echo "$(basename $t) $(tr ' ' _ < $t/comm) $(awk '{print $14+$15}' $t/stat)"; done; }
threads() {  # pid label: per-thread CPU over 4 s, % of a core
  snap $1 > /tmp/a.$1; sleep 4; snap $1 > /tmp/b.$1
  join <(sort /tmp/a.$1) <(sort /tmp/b.$1) | awk -v L=$2 '{d=$5-$3; s+=d; n[$2]+=d} END {for (k in n) if (n[k]>0) printf "%s %-16s %6.1f%%\n", L, k, n[k]/4; printf "%s total %6.1f%%\n", L, s/4}'
}
for MODE in replicas sharding; do
  ( timeout 60 $PY -m dynqos.bench.edge_scale --processes 8 --modes $MODE --loaders 8 --counts $N \
    --seconds 14 --out $OUT/diag-$MODE.json 2>&1 | grep -E 'edge_scale:' ) &
  BG=$!
  for i in $(seq 80); do [ "$(pgrep -f 'edge_scale --load' | wc -l)" -ge 8 ] && break; sleep 0.5; done
  sleep 6
  P0=$(pgrep -f 'mpc.replica_id=mpc0 --config|mpc.shard_index=0 ' | head -1); P1=$(pgrep -f 'mpc.replica_id=mpc1 --config|mpc.shard_index=1 ' | head -1)
  R=$(pgrep -f 'edge router' | head -1)
  echo "$MODE mpc0=$P0 mpc1=$P1 router=$R"
  [ $MODE = replicas ] && py-spy record --nonblocking --threads -d 4 -r 100 -f raw -o $OUT/spy-$MODE-mpc1.txt -p $P1 > /dev/null 2>&1 &
  threads $P0 $MODE-mpc0 > $OUT/threads-$MODE-mpc0.txt &
  threads $P1 $MODE-mpc1 > $OUT/threads-$MODE-mpc1.txt &
  [ -n "$R" ] && threads $R $MODE-router > $OUT/threads-$MODE-router.txt &
  wait $BG; wait
  cat $OUT/threads-$MODE-*.txt | sort -k1,1 -k3,3nr | awk '$3+0 >= 1.0 || $2 == "total"'
done
ls $OUT
