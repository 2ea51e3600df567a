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


# --- golden-model checks (``rotate``, ``rotate_ideal``: a block's model functions) -----------

def model_error_one_million_vectors(rotate, rotate_ideal, corner_cases):
    """The model against float on a million random vectors and the named corners: the shared
    targets (max ≤ 2 LSB, rms ≤ 0.7 LSB, no bias); returns the errors for tighter bounds."""
    x, y, theta = random_vectors(1_000_000, seed=11)
    cx, cy, ct = corner_cases()
    x, y, theta = (np.concatenate(a) for a in ((x, cx), (y, cy), (theta, ct)))
    gx, gy = rotate(x, y, theta)
    ix, iy = rotate_ideal(x, y, theta)
    err = np.concatenate([gx - ix, gy - iy])
    assert np.max(np.abs(err)) <= 2.0            # target
    assert math.sqrt(np.mean(err ** 2)) <= 0.7   # target
    assert abs(np.mean(err)) < 0.01              # no bias from the rounding
    return err


def check_corners_saturate_never_wrap(rotate):
    """Full-scale corners saturate instead of wrapping (16-bit data and angles)."""
    turn = 1 << 16
    # (32767, 32767) by +45° → (0, 46341): y saturates to +32767.
    ox, oy = rotate([FS - 1, -FS, -FS], [FS - 1, -FS, FS - 1], [turn // 8, turn // 8, 0])
    assert abs(ox[0]) <= 1 and oy[0] == FS - 1
    # (−32768, −32768) by +45° → (0, −46341): saturates to −32768.
    assert abs(ox[1]) <= 1 and oy[1] == -FS
    # θ = 0 of (−32768, 32767) passes through.
    assert (ox[2], oy[2]) == (-FS, FS - 1)
    # θ = −π (raw 0x8000) negates; −(−32768) saturates to +32767.
    ox, oy = rotate([-FS, 12345], [FS - 1, -FS], [turn // 2, turn // 2])
    assert (ox[0], oy[0]) == (FS - 1, -(FS - 1))
    assert (ox[1], oy[1]) == (-12345, FS - 1)


def check_quarter_turns_and_small_angles(rotate, rotate_ideal, raws=(1, (1 << 16) - 1,
                                                                      (1 << 15) - 1)):
    """±π/2 and 0 exact on one vector; the angles ``raws`` within one LSB of the ideal."""
    turn = 1 << 16
    x, y = 20000, -7000
    assert tuple(int(v[0]) for v in rotate([x], [y], [turn // 4])) == (-y, x)        # +π/2
    assert tuple(int(v[0]) for v in rotate([x], [y], [3 * turn // 4])) == (y, -x)    # −π/2
    assert tuple(int(v[0]) for v in rotate([x], [y], [0])) == (x, y)
    for raw in raws:
        gx, gy = rotate([x], [y], [raw])
        ix, iy = rotate_ideal([x], [y], [raw])
        assert abs(gx[0] - ix[0]) <= 1 and abs(gy[0] - iy[0]) <= 1


def check_zero_vector_stays_zero(rotate):
    theta = np.arange(0, 1 << 16, 7)
    ox, oy = rotate(np.zeros_like(theta), np.zeros_like(theta), theta)
    assert not ox.any() and not oy.any()


def check_park_inverse_park_round_trip_model(rotate):
    """Park (rotation by −θ) then inverse Park (by +θ) of 200 000 vectors: back within 2 LSB."""
    rng = np.random.default_rng(13)
    n = 200_000
    r = rng.uniform(0, FS - 1, n)
    phi = rng.uniform(-math.pi, math.pi, n)
    x, y = np.round(r * np.cos(phi)).astype(np.int64), np.round(r * np.sin(phi)).astype(np.int64)
    theta = rng.integers(0, 1 << 16, n)
    dx, dy = rotate(x, y, (-theta) % (1 << 16))        # Park: rotate by −θ
    ax, ay = rotate(dx, dy, theta)                      # inverse Park: by +θ
    err = np.maximum(np.abs(ax - x), np.abs(ay - y))
    assert err.max() <= 2


# --- gateware checks -------------------------------------------------------------------------

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
