"""Test helpers shared by the two rotation blocks, :class:`~foc_servo.hdl.cordic.Cordic` and
:class:`~foc_servo.hdl.rotator.Rotator` (same ports: ``i`` = x, y, θ [, tag], ``o`` = x, y [, tag];
the Cordic takes a vector every clock, the Rotator one every ``interval`` clocks)."""

import math

import numpy as np
from amaranth.hdl import Const, Module, Value

from foc_servo.sim.harness import simulate

FS = 1 << 15


def random_vectors(n, seed, width=16, angle_width=None):
    """``n`` random (x, y, θ) integer arrays of a ``width``-bit rotation block."""
    angle_width = width if angle_width is None else angle_width
    rng = np.random.default_rng(seed)
    fs = 1 << (width - 1)
    return (rng.integers(-fs, fs, n), rng.integers(-fs, fs, n),
            rng.integers(0, 1 << angle_width, n))


def _feed(k, count, spacing):
    """Clock ``k`` of a feed of ``count`` vectors, one every ``spacing`` clocks: (index, fed)."""
    j, phase = divmod(k, spacing)
    return j, phase == 0 and j < count


def simulate_vectors(dut, vectors, spacing=1):
    """Feed ``vectors`` (dicts of payload fields) one every ``spacing`` clocks; return the outputs
    in order, (x, y) or (x, y, tag)."""
    outputs = []

    async def testbench(ctx):
        for k in range(len(vectors) * spacing + dut.latency + 1):
            j, fed = _feed(k, len(vectors), spacing)
            if fed:
                ctx.set(dut.i.payload, vectors[j])
            ctx.set(dut.i.valid, fed)
            await ctx.tick()
            if ctx.get(dut.o.valid):
                p = ctx.get(dut.o.payload)
                outputs.append((p.x, p.y, p.tag) if dut.tag_width else (p.x, p.y))

    simulate(dut, [testbench], name=f"{type(dut).__name__.lower()}_test")
    return outputs


def check_latency_cycle_by_cycle(dut, rotate):
    """One vector in: ``o.valid`` rises exactly ``dut.latency`` clocks later, once, carrying
    ``rotate([x], [y], [θ])`` (the golden model) and the tag."""
    turn = 1 << dut.angle_width
    fs = 1 << (dut.width - 1)
    vector = {"x": fs // 2, "y": -fs // 3, "theta": turn // 6}
    if dut.tag_width:
        vector["tag"] = 2
    ex, ey = rotate([vector["x"]], [vector["y"]], [vector["theta"]])
    seen = []

    async def testbench(ctx):
        ctx.set(dut.i.payload, vector)
        ctx.set(dut.i.valid, 1)
        await ctx.tick()
        ctx.set(dut.i.valid, 0)
        ctx.set(dut.i.payload, {"x": 0, "y": 0, "theta": 0})
        for clock in range(1, dut.latency + 4):
            # Before the edge of clock `clock` + 1, o reflects `clock` clocks after i.valid.
            seen.append((clock, ctx.get(dut.o.valid)))
            if clock == dut.latency:
                p = ctx.get(dut.o.payload)
                assert (p.x, p.y) == (ex[0], ey[0])
                if dut.tag_width:
                    assert p.tag == 2
            await ctx.tick()

    simulate(dut, [testbench], name=f"{type(dut).__name__.lower()}_latency")
    assert [c for c, v in seen if v] == [dut.latency]


def check_park_inverse_park_round_trip(park, inverse, n, spacing=1):
    """Park (θ negated) feeds inverse Park, θ travelling in the first block's 16-bit tag: the
    vectors come back within 2 LSB."""
    m = Module()
    m.submodules.park, m.submodules.inverse = park, inverse
    m.d.comb += [
        inverse.i.valid.eq(park.o.valid),
        inverse.i.payload.x.eq(park.o.payload.x),
        inverse.i.payload.y.eq(park.o.payload.y),
        inverse.i.payload.theta.eq(park.o.payload.tag),
    ]
    rng = np.random.default_rng(14)
    r = rng.uniform(0, FS - 1, n)
    phi = rng.uniform(-math.pi, math.pi, n)
    x, y = np.round(r * np.cos(phi)).astype(int), np.round(r * np.sin(phi)).astype(int)
    theta = rng.integers(0, 1 << 16, n)
    got = []

    async def testbench(ctx):
        for k in range(n * spacing + park.latency + inverse.latency + 1):
            j, fed = _feed(k, n, spacing)
            if fed:
                ctx.set(park.i.payload, {"x": int(x[j]), "y": int(y[j]),
                                         "theta": int(-theta[j]) % (1 << 16),
                                         "tag": int(theta[j])})
            ctx.set(park.i.valid, fed)
            await ctx.tick()
            if ctx.get(inverse.o.valid):
                p = ctx.get(inverse.o.payload)
                got.append((p.x, p.y))

    simulate(m, [testbench], name="round_trip")
    got = np.array(got)
    assert len(got) == n
    assert np.max(np.abs(got - np.stack([x, y], axis=1))) <= 2


def signal_ports(dut):
    """The component's ports without its constant members: the always-ready streams' ``ready``
    are constants, which ``convert`` cannot take as ports (amaranth-lang/amaranth#1574)."""
    return [Value.cast(v) for _, _, v in dut.signature.flatten(dut) if not isinstance(v, Const)]
