"""SYNC lockstep: once SYNCs run, every timer of the drive (SYNC timeout 0x1006, heartbeat producer 0x1017, ...)
runs on the drive's own cycle clock, so a master slower than real time (one that waits for each answer) is seen
as a master that keeps time. `virtualaxis serve --lockstep` in a child process, `LockstepMaster` here."""

from __future__ import annotations

import time

from served_drive import served

from virtualaxis.master import LockstepMaster, connect


def test_slow_lockstep_master_sees_no_sync_timeout_and_heartbeats_per_drive_time():
    with served("--lockstep") as s:
        net = connect(s.spec)
        emcy: list[bytes] = []
        beats: list[int] = []
        try:
            net.subscribe(0x81, lambda _c, d, _t: emcy.append(bytes(d)))
            with LockstepMaster(net, 1, mode="csp", period_s=0.001) as m:  # 0x1006 = 1 ms: SYNC timeout 1.5 ms
                node = m.nodes[1]
                node.sdo[0x1017].raw = 10  # heartbeat every 10 ms of drive time = every 10 SYNCs
                net.subscribe(0x701, lambda _c, _d, _t: beats.append(m.syncs))
                x0 = m.position_m(1)
                syncs0 = m.syncs

                def slow(n: int):
                    for _ in range(n):
                        time.sleep(0.004)  # the master takes 4 ms of wall time per 1 ms communication cycle
                        yield x0

                m.run(slow(200))
                syncs = m.syncs - syncs0
        finally:
            net.disconnect()
    codes = [int.from_bytes(d[0:2], "little") for d in emcy if len(d) >= 2]
    assert 0x8100 not in codes, f"{codes.count(0x8100)} EMCY 0x8100 (SYNC timeout) from a master that sent every SYNC"
    # heartbeat period in SYNCs (attributed to the SYNC count at receipt: +-1)
    gaps = [b - a for a, b in zip(beats, beats[1:], strict=False) if a > syncs0]
    assert len(gaps) >= syncs // 10 - 3, (beats, syncs)
    assert all(9 <= g <= 11 for g in gaps), gaps
    assert abs(sum(gaps) / len(gaps) - 10.0) < 0.5, gaps
