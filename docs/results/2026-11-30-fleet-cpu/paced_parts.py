"""Send 4 drones x 15 fps x 8 parts of camera to the detector for N s over a real router; print CPU of the detector."""
import os, sys, time, subprocess, signal
from dynqos.common.config import load_config
from dynqos.common.transport import Role, open_bus
from dynqos.common import keys
from dynqos.common.keys import Flow, Stream
from dynqos.common.bus import Priority
from dynqos.common.messages import CameraFrame
cfg = load_config(sys.argv[1] if len(sys.argv) > 1 else None)
DUR = 12
PACED = os.environ.get("PACED") == "1"
env = dict(os.environ)
router = subprocess.Popen([".venv/bin/dynqos", "edge", "router", "--config", sys.argv[1]], stderr=subprocess.DEVNULL)
time.sleep(1.5)
det = subprocess.Popen([".venv/bin/dynqos", "edge", "detector", "--config", sys.argv[1]], stderr=open("/tmp/det/det.log","w"))
time.sleep(3)
bus = open_bus(cfg.zenoh, Role.DRONE)
pubs = {}
for u in range(4):
    uav = f"uav{u+1}"
    bus.declare_token(keys.drone_presence(uav))
    pubs[uav] = {k: bus.publisher(keys.uplink(uav, Flow.DEFAULT, s), Priority.DATA) for k, s in (("rgb", Stream.CAMERA_RGB), ("depth", Stream.CAMERA_DEPTH))}
def cpu(pid):
    f = open(f"/proc/{pid}/stat").read().split()
    return (int(f[13]) + int(f[14])) / 100
c0 = cpu(det.pid); t0 = time.monotonic(); seq = 0
period = 1 / 15
nxt = t0
while time.monotonic() - t0 < DUR:
    seq += 1
    for uav, p in pubs.items():
        stamp = time.monotonic_ns()
        for kind, parts in (("rgb", 4), ("depth", 4)):
            for i in range(parts):
                p[kind].put(CameraFrame(uav=uav, seq=seq, stamp_ns=stamp, kind=kind,
                    encoding="jpeg" if kind == "rgb" else "zstd16", width=104, height=78,
                    intrinsics=(85.3, 85.3, 51.5, 38.5), payload=b"\0" * 1000, part=i, parts=parts,
                    depth_unit_m=0.001))
                if PACED:
                    nxt_part = time.monotonic() + period / 32
                    while time.monotonic() < nxt_part: time.sleep(max(0, nxt_part - time.monotonic()))
    nxt += period
    time.sleep(max(0, nxt - time.monotonic()))
c1 = cpu(det.pid); el = time.monotonic() - t0
print(f"detector CPU {100 * (c1 - c0) / el:.1f}% of a core over {el:.1f} s, {seq} frames per drone")
for p in (det, router):
    p.send_signal(signal.SIGTERM)
for p in (det, router):
    p.wait(10)
