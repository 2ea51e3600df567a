"""Shared by the engine tests: follow the gateware Engine's trace port through one program run
and compare it, entry by entry, with the trace of :class:`~foc_servo.sim.models.engine.EngineModel`."""


async def follow_trace(ctx, dut, trace, *, limit=400):
    """Clock ``dut`` (its ``start`` already pulsed) until its trace port has given
    ``len(trace)`` entries. Returns ``(error, clocks)``: ``error`` is ``None`` when every entry
    matched (pc, P, write enable, and destination and value on writes), else ``("no END",)``
    after ``limit`` clocks or ``(index, want, got)`` for the first entry that differs. From the
    first entry on, one entry per clock: a bubble (a folded NOP, ``trace[i]["bubble"]``) must
    find ``trace_valid`` low in its clock, every other entry high."""
    i = cyc = 0
    while i < len(trace):
        await ctx.tick()
        cyc += 1
        if cyc > limit:
            return ("no END",), cyc
        e = trace[i]
        valid = ctx.get(dut.trace_valid)
        if i and bool(e.get("bubble")) == bool(valid):
            return (i, {"bubble": e.get("bubble")}, {"trace_valid": valid}), cyc
        if not valid:
            i += bool(i)                # a bubble, or the clocks before the first entry
            continue
        got = {"pc": ctx.get(dut.trace_pc), "p": ctx.get(dut.trace_p),
               "wen": ctx.get(dut.trace_wen)}
        if e["wen"]:
            got.update(dst=ctx.get(dut.trace_dst), y=ctx.get(dut.trace_y))
        want = {key: e[key] for key in got}
        if got != want:
            return (i, want, got), cyc
        i += 1
    return None, cyc


async def start_and_follow(ctx, dut, trace, *, limit=400):
    """Pulse ``dut.start`` for one clock, then :func:`follow_trace`: one engine run checked
    against the interpreter's ``trace``; returns what :func:`follow_trace` returns."""
    ctx.set(dut.start, 1)
    await ctx.tick()
    ctx.set(dut.start, 0)
    return await follow_trace(ctx, dut, trace, limit=limit)


def random_speed_args(rng):
    """Random inputs of one speed-loop run (:class:`~foc_servo.sim.models.engine.EngineSpeedModel`
    ``run``'s keywords): full-range speeds, slews at their corners, random gains and hold."""
    return dict(speed=int(rng.integers(-(1 << 31), 1 << 31)),
                speed_ref=int(rng.integers(-(1 << 31), 1 << 31)),
                speed_slew=int(rng.choice([0, 1, 1 << 20, (1 << 32) - 1])),
                iq_ff=int(rng.integers(-(1 << 15), 1 << 15)), lim_lo=-20000, lim_hi=20000,
                ref_delay=int(rng.integers(0, 32)), int_hold=int(rng.random() < 0.3),
                kp=int(rng.integers(1 << 24)), kx=int(rng.integers(1 << 24)))
