"""Summarise a frames CSV written by run_sim.py: what the host sent and what it got back.

usage: summarise.py OUT   (the prefix given to run_sim.py: reads OUT-frames.csv, OUT-status.json)
"""

import csv
import json
import math
import struct
import sys
from collections import Counter

STATES = {0x10: "OFF", 0x12: "READY", 0x14: "ON", 0x18: "ERROR", 0x11: "KEEP", 0x1F: "CLEAR"}


def summarise(out):
    out = str(out)
    with open(out + "-frames.csv") as f:
        rows = [
            (float(t), int(i), int(d), bytes.fromhex(x)) for t, i, d, x in list(csv.reader(f))[1:]
        ]
    with open(out + "-status.json") as f:
        status = json.load(f)
    lines = []
    ids = Counter(f"0x{i:03X}(dlc{d})" for _, i, d, _ in rows)
    lines.append(f"frames by id: {dict(sorted(ids.items()))}")
    t201 = [t for t, i, _, _ in rows if i == 0x201]
    if len(t201) > 1:
        dts = sorted(b - a for a, b in zip(t201, t201[1:], strict=False))
        span = t201[-1] - t201[0]
        lines.append(
            f"0x201: {len(t201)} over {span:.2f} s = {len(t201) / span:.0f} Hz; "
            f"interval median {dts[len(dts) // 2] * 1e3:.2f} ms, min {dts[0] * 1e3:.3f}, "
            f"max {dts[-1] * 1e3:.1f}"
        )
    # state command / reply sequence, collapsed runs
    seq = []
    pending = []
    for _t, i, _d, x in rows:
        if i == 0x200:
            endstop = struct.unpack_from("<h", x, 2)[0]
            pending.append(
                f"{STATES.get(x[0], hex(x[0]))} (endstop {endstop} deg, limits {x[6]}/{x[7]} %)"
            )
        elif i == 0x210:
            e = f"cmd {pending.pop(0) if pending else '?'} -> {STATES.get(x[0], hex(x[0]))}"
            if seq and seq[-1][0] == e:
                seq[-1][1] += 1
            else:
                seq.append([e, 1])
    for p in pending:
        seq.append([f"cmd {p} -> (no reply)", 1])
    lines.append("0x200/0x210 sequence (runs collapsed, xN = repeated):")
    for e, n in seq:
        lines.append(f"   {e}{f'  x{n}' if n > 1 else ''}")
    cmds = Counter()
    for _t, i, d, x in rows:
        if i == 0x201 and d == 8:
            tq, fr, b, k = struct.unpack("<hhhh", x)
            cmds[(tq, fr, b, k)] += 1
    lines.append(
        "0x201 fields (raw mN·m, mN·m, mN·m/rpm, mN·m/deg -> SI torque, friction, "
        "damping N·m·s/rad, stiffness N·m/rad): count"
    )
    for (tq, fr, b, k), n in cmds.most_common(8):
        lines.append(
            f"   {tq},{fr},{b},{k} -> {tq / 1000:.3f} N·m, {fr / 1000:.3f} N·m, "
            f"{b * 60 / (2 * math.pi) / 1000:.3f}, {k * 180 / math.pi / 1000:.3f}: {n}"
        )
    rep = [struct.unpack("<ihh", x) for _, i, d, x in rows if i == 0x211]
    if rep:
        angs = [r[0] * 0.009 for r in rep]
        tqs = [r[2] / 1000 for r in rep]
        lines.append(
            f"0x211 replies: {len(rep)}; angle (drive dir) deg first {angs[0]:.3f}, "
            f"min {min(angs):.3f}, max {max(angs):.3f}, last {angs[-1]:.3f}; "
            f"torque N·m min {min(tqs):.3f} max {max(tqs):.3f} last {tqs[-1]:.3f}"
        )
    lines.append(
        f"sim status: state {status['state']}, enabled_cycles {status['enabled_cycles']}, "
        f"requests {status['requests']}, end_stop {status['end_stop_deg']}, "
        f"limits {status['torque_limits_percent']}, errors {status['errors'][:5]}"
    )
    return "\n".join(lines)


if __name__ == "__main__":
    print(summarise(sys.argv[1]))
