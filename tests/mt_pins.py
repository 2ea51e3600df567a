"""Shared by the M/T tests on the whole top: turn the encoder pins through a position schedule
and record M/T's strobes and outputs every clock."""

import numpy as np

from foc_servo.sim.harness import simulate

#: Quadrature (A, B) for position mod 4.
AB = ((0, 0), (1, 0), (1, 1), (0, 1))


def record_top_mt(top, at, end, *, hall, name, extra=()):
    """Simulate ``top`` for ``end`` clocks with the encoder at position ``at[c]`` from clock
    ``c`` on (0 before the first) and the Hall pins at ``hall``; returns arrays of M/T's
    ``step``, ``neg``, ``update``, ``valid``, ``speed``, ``stopped``, ``fresh`` and of each
    ``(key, signal)`` in ``extra``, one entry per clock."""
    mt = top._mt
    sigs = (("step", mt.edge.step), ("neg", mt.edge.neg), ("update", mt.update),
            ("valid", mt.o.valid), *extra)
    rec = {key: [] for key in (*(k for k, _ in sigs), "speed", "stopped", "fresh")}

    async def testbench(ctx):
        ctx.set(top.hall, hall)
        pos = 0
        for c in range(end):
            pos = at.get(c, pos)
            a, b = AB[pos % 4]
            ctx.set(top.enc_a, a)
            ctx.set(top.enc_b, b)
            p = ctx.get(mt.o.payload)
            for key, v in sigs:
                rec[key].append(ctx.get(v))
            rec["speed"].append(p.speed)
            rec["stopped"].append(p.stopped)
            rec["fresh"].append(p.fresh)
            await ctx.tick()

    simulate(top, [testbench], name=name)
    return {key: np.array(v, dtype=np.int64) for key, v in rec.items()}
