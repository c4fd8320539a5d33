#!/bin/bash
# usage: cpu.sh scenario.toml outdir  -> per-process CPU share over 15 s of steady flight
cd /work/main
rm -rf $2; .venv/bin/dynqos run $1 --out $2 > $2.log 2>&1 &
RP=$!
for i in $(seq 120); do grep -q "10\.[0-9]/" $2.log 2>/dev/null && break; sleep 1; done
snap() { for p in $(pgrep -P $RP); do echo "$p $(awk '{print $14+$15}' /proc/$p/stat 2>/dev/null) $(tr '\0' ' ' < /proc/$p/cmdline | grep -oE '(onboard|edge [a-z]+|sim [a-z]+).*(replica_id="[a-z0-9-]+"|instance [0-9]|uav[0-9].toml)?' | head -c 60)"; done; }
snap > /tmp/prof/s1; head -1 /proc/stat > /tmp/prof/st1; sleep 15; snap > /tmp/prof/s2; head -1 /proc/stat > /tmp/prof/st2
python3 - <<'PY'
a={l.split()[0]:l.split(None,2) for l in open('/tmp/prof/s1') if len(l.split())>=2}
tot=0
rows=[]
for l in open('/tmp/prof/s2'):
    p=l.split(None,2)
    if p[0] in a and len(p)>=2:
        d=(int(p[1])-int(a[p[0]][1]))/100/15
        tot+=d; rows.append((d,p[2].strip() if len(p)>2 else ''))
for d,n in sorted(rows,reverse=True): print(f"{d*100:5.1f}% {n}")
s1=list(map(int,open('/tmp/prof/st1').read().split()[1:])); s2=list(map(int,open('/tmp/prof/st2').read().split()[1:]))
dt=[y-x for x,y in zip(s1,s2)]; busy=1-(dt[3]+dt[4])/sum(dt)
print(f"processes total {tot*100:.0f}% of a core; machine busy {busy*100:.0f}% of 2 cores")
PY
wait $RP
