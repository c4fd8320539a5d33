#!/bin/bash
# alternate standby_reads copies/states, N rounds
cd /work/main
for r in 1 2 3; do
for mode in states copies; do
  sed -i "s/standby_reads: Literal\[\"copies\", \"states\"\] = \"[a-z]*\"/standby_reads: Literal[\"copies\", \"states\"] = \"$mode\"/" common/config/control.py
  grep -c "= \"$mode\"" common/config/control.py
  .venv/bin/python -m dynqos.bench.edge_scale --processes 1,2 --modes replicas --loaders 2 --counts 40 --seconds 10 --out /tmp/cmp-$mode-$r.json > /tmp/cmp-$mode-$r.log 2>&1
done
done
sed -i "s/standby_reads: Literal\[\"copies\", \"states\"\] = \"[a-z]*\"/standby_reads: Literal[\"copies\", \"states\"] = \"copies\"/" common/config/control.py
echo done
