"""Fault to gates-off latency through the real chain: :class:`Protection` → :class:`Gates`.

Issue target: any fault takes every gate low within ≤ 3 clocks of the (synchronised) fault signal.
Each fault input is driven on its own, with gates switching on both sides beforehand, and the clocks
from the fault appearing at the protection block's input to all six gate outputs low are counted
(the latency as every block here states it: a signal set for cycle ``t`` that shows on the
output in cycle ``t + L`` has latency ``L``). The latch must hold the gates off after the fault
goes away, and a clear with the cause gone must release it.
"""

from amaranth.hdl import Module
from amaranth.lib import wiring

from ...hdl.gates import Gates
from ...hdl.protect import FAULTS, Protection
from ..harness import simulate

__all__ = ["FaultChain", "run"]


class FaultChain(wiring.Component):
    """Protection and Gates wired as in the top: ``gates.trip`` ← ``protect.trip``
    (``trip_register``: :class:`Protection`'s, the ECP5's form or ``False`` the iCE40's)."""

    def __init__(self, *, trip_register=True):
        self.protect = Protection(trip_register=trip_register)
        self.gates = Gates()
        super().__init__({})

    def elaborate(self, platform):
        m = Module()
        m.submodules.protect = self.protect
        m.submodules.gates = self.gates
        m.d.comb += self.gates.trip.eq(self.protect.trip)
        return m


# How each fault is provoked: (signal path, value while present, value when gone).
# Sampled causes (current, bus voltage, speed) are presented as a one-clock valid sample.
OC, OV, UV, OS = 20000, 30000, 5000, 25000


def _stimuli(p):
    return {
        "external": [(p.fault_n, 0, 1)],
        "overcurrent_a": [(p.i.payload.a, -OC - 1, 0), (p.i.valid, 1, 1)],
        "overcurrent_b": [(p.i.payload.b, OC + 1, 0), (p.i.valid, 1, 1)],
        "overcurrent_c": [(p.i.payload.c, OC + 1, 0), (p.i.valid, 1, 1)],
        "overcurrent_comparator": [(p.oc_comp, 1, 0)],
        "overvoltage": [(p.udc.payload, OV + 1, 20000), (p.udc.valid, 1, 1)],
        "undervoltage": [(p.udc.payload, UV - 1, 20000), (p.udc.valid, 1, 1)],
        "overspeed": [(p.speed.payload, -OS - 1, 0), (p.speed.valid, 1, 1)],
        "encoder": [(p.encoder_illegal, 1, 0)],
        "hall": [(p.hall_invalid, 1, 0)],
        "encoder_hall": [(p.encoder_hall, 1, 0)],
    }


def run(*, dead_time=3, progress=False, trip_register=True):
    """Returns ``{"latency_clk": {cause: clocks}, "fault_latency_clk_max": int,
    "latched": bool, "released": bool}`` (``trip_register``: :class:`FaultChain`'s)."""
    dut = FaultChain(trip_register=trip_register)
    p, g = dut.protect, dut.gates
    stimuli = _stimuli(p)
    missing = set(FAULTS) - set(stimuli)
    if missing:
        raise RuntimeError(f"fault chain check does not provoke {sorted(missing)}")
    result = {"latency_clk": {}, "latched": True, "released": True}

    strobes = (p.i.valid, p.udc.valid, p.speed.valid)

    def is_strobe(sig):
        return any(sig is s for s in strobes)

    def gates_on(ctx):
        return any(ctx.get(getattr(g.high, ph)) or ctx.get(getattr(g.low, ph)) for ph in "abc")

    async def testbench(ctx):
        ctx.set(p.oc_limit, OC)
        ctx.set(p.ov_limit, OV)
        ctx.set(p.uv_limit, UV)
        ctx.set(p.os_limit, OS)
        ctx.set(p.uv_enable, 1)
        ctx.set(g.dead_time, dead_time)
        ctx.set(g.enable, 1)
        ctx.set(g.pwm, {"a": 1, "b": 0, "c": 1})
        ctx.set(p.udc.payload, 20000)   # arms the under-voltage detector
        ctx.set(p.udc.valid, 1)
        await ctx.tick()
        ctx.set(p.udc.valid, 0)
        for cause, stim in stimuli.items():
            await ctx.tick().repeat(dead_time + 3)
            if not gates_on(ctx) or ctx.get(p.trip):
                raise RuntimeError(f"gates did not come on before provoking {cause}")
            for sig, on, _ in stim:
                ctx.set(sig, on)
            clocks = 0
            while gates_on(ctx):
                await ctx.tick()
                clocks += 1
                for sig in strobes:             # sampled causes: one valid sample only
                    ctx.set(sig, 0)
                if clocks > 100:
                    raise RuntimeError(f"{cause}: gates still on after 100 clocks")
            result["latency_clk"][cause] = clocks
            for sig, _, off in stim:            # the cause goes away, with a fresh in-limit
                ctx.set(sig, 1 if is_strobe(sig) else off)  # sample where it is sampled
            await ctx.tick()
            for sig in strobes:
                ctx.set(sig, 0)
            await ctx.tick().repeat(dead_time + 3)
            result["latched"] &= not gates_on(ctx) and bool(ctx.get(p.trip))
            ctx.set(p.clear, 1)
            await ctx.tick()
            ctx.set(p.clear, 0)
            await ctx.tick().repeat(dead_time + 3)
            result["released"] &= gates_on(ctx) and not ctx.get(p.trip)

    simulate(dut, [testbench], name="fault_chain")
    result["fault_latency_clk_max"] = max(result["latency_clk"].values())
    return result
