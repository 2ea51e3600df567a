# Ref: paper eq. (4)–(6) (CORDIC vector rotation), SPEC.md §2.1
"""Gateware :class:`~foc_servo.hdl.cordic.Cordic` against its golden model and the float ideal.

The stimulus lives in a ROM inside a simulation-only wrapper that feeds the CORDIC one vector per
clock and writes every output into a RAM, so the testbench only waits; the outputs are read back
once at the end and compared, bit for bit, with :func:`foc_servo.sim.models.cordic.rotate`, and
against :func:`~foc_servo.sim.models.cordic.rotate_ideal` for the error figures.
"""

import math

import numpy as np
from amaranth.hdl import Module, Mux, Signal, unsigned
from amaranth.lib import wiring
from amaranth.lib.memory import Memory

from ...hdl.cordic import Cordic
from ..harness import Progress, simulate
from ..models.cordic import rotate, rotate_ideal

__all__ = ["run", "corner_cases"]


def corner_cases(width=16, angle_width=None):
    """Named corner vectors: every combination of x, y ∈ {−2**(W−1), −(2**(W−1)−1), 0,
    2**(W−1)−1} with θ ∈ {0, ±1 LSB, ±π/2, π (raw 2**(AW−1)), just below π, ±45°, ±135°}.

    Returns
    -------
    x, y, theta : ndarray of int64
    """
    angle_width = width if angle_width is None else angle_width
    half, quarter, eighth = 1 << (angle_width - 1), 1 << (angle_width - 2), 1 << (angle_width - 3)
    turn = 1 << angle_width
    thetas = [0, 1, turn - 1, quarter, turn - quarter, half, half - 1,
              eighth, turn - eighth, quarter + eighth, turn - quarter - eighth]
    fs = 1 << (width - 1)
    values = [-fs, -(fs - 1), 0, fs - 1]
    x, y, theta = np.meshgrid(values, values, thetas, indexing="ij")
    return x.ravel().astype(np.int64), y.ravel().astype(np.int64), theta.ravel().astype(np.int64)


class RotationBench(wiring.Component):
    """Simulation-only wrapper: a stimulus ROM feeding a rotator (CORDIC or sine table) one vector
    every ``spacing`` clocks, a RAM capturing its outputs, and counters for latency and
    throughput."""

    def __init__(self, dut, words, spacing=1):
        self.dut = dut
        self.words = words
        self.count = len(words)
        self.spacing = spacing
        super().__init__({})

    def elaborate(self, platform):
        m = Module()
        dut, n = self.dut, self.count
        m.submodules.dut = dut
        in_bits = dut.i.payload.shape().size
        out_bits = dut.o.payload.shape().size
        m.submodules.stim = stim = Memory(shape=unsigned(in_bits), depth=n, init=self.words)
        m.submodules.capture = self.capture = capture = Memory(shape=unsigned(out_bits), depth=n,
                                                               init=[])
        rd = stim.read_port(domain="comb")
        wr = capture.write_port()

        self.in_addr = in_addr = Signal(range(n + 1))
        self.out_addr = out_addr = Signal(range(n + 1))
        self.cycle = cycle = Signal(32)
        self.first_out = first_out = Signal(32)
        self.last_out = last_out = Signal(32)
        phase = Signal(range(self.spacing))
        feeding = (in_addr < n) & (phase == 0)
        m.d.comb += [
            rd.addr.eq(in_addr),
            dut.i.valid.eq(feeding),
            dut.i.payload.eq(rd.data),
            wr.addr.eq(out_addr),
            wr.data.eq(dut.o.payload.as_value()),
            wr.en.eq(dut.o.valid),
        ]
        m.d.sync += [cycle.eq(cycle + 1),
                     phase.eq(Mux(phase == self.spacing - 1, 0, phase + 1))]
        with m.If(feeding):
            m.d.sync += in_addr.eq(in_addr + 1)
        with m.If(dut.o.valid):
            m.d.sync += [out_addr.eq(out_addr + 1), last_out.eq(cycle)]
            with m.If(out_addr == 0):
                m.d.sync += first_out.eq(cycle)
        return m


def _field(words, offset, width, signed):
    v = (words >> offset) & ((1 << width) - 1)
    if signed:
        v = np.where(v >= 1 << (width - 1), v - (1 << width), v)
    return v.astype(np.int64)


def run_rotation(dut, rotate, rotate_ideal, model, *, count, seed, spacing, name, progress):
    """Feed a rotation block (the CORDIC or the sine-table rotator: same ports, ``params``,
    ``latency``) the corner cases plus ``count`` seeded random vectors (x, y, θ and tag uniform
    over their full ranges), one every ``spacing`` clocks, from a :class:`RotationBench`;
    compare the captured outputs with ``rotate(x, y, θ, **model)`` bit for bit and with
    ``rotate_ideal`` for the error figures. Returns the dict of :func:`run`."""
    p = dut.params
    w, aw, tw = p.width, p.angle_width, p.tag_width
    rng = np.random.default_rng(seed)
    cx, cy, ct = corner_cases(w, aw)
    fs = 1 << (w - 1)
    x = np.concatenate([cx, rng.integers(-fs, fs, count)])
    y = np.concatenate([cy, rng.integers(-fs, fs, count)])
    theta = np.concatenate([ct, rng.integers(0, 1 << aw, count)])
    vectors = len(x)
    tag = rng.integers(0, 1 << tw, vectors) if tw else np.zeros(vectors, dtype=np.int64)

    mask = (1 << w) - 1
    words = [(int(a) & mask) | (int(b) & mask) << w | int(t) << 2 * w | int(g) << (2 * w + aw)
             for a, b, t, g in zip(x, y, theta, tag)]
    bench = RotationBench(dut, words, spacing)
    clocks = (vectors - 1) * spacing + p.latency + 2

    result = {}
    bar = Progress(f"{name} {vectors} vectors", clocks, enabled=progress)

    async def testbench(ctx):
        await bar.ticks(ctx, clocks, step=max(1000, clocks // 100))
        result["outputs"] = ctx.get(bench.out_addr)
        result["first_out"] = ctx.get(bench.first_out)
        result["last_out"] = ctx.get(bench.last_out)
        result["words"] = [ctx.get(bench.capture.data[j]) for j in range(vectors)]

    sim_s = simulate(bench, [testbench], name=f"{name}_verify")
    bar.close()
    out = np.array(result["words"], dtype=object)
    gx = _field(out, 0, w, True)
    gy = _field(out, w, w, True)
    gt = _field(out, 2 * w, tw, False) if tw else np.zeros(vectors, dtype=np.int64)

    ex, ey = rotate(x, y, theta, **model)
    produced = result["outputs"]
    mismatches = int(np.count_nonzero((gx != ex) | (gy != ey) | (gt != tag)))
    ix, iy = rotate_ideal(x, y, theta, width=w, angle_width=aw)
    err = np.concatenate([gx - ix, gy - iy])
    span = result["last_out"] - result["first_out"] + spacing
    return {
        "mismatches": mismatches,
        "outputs_missing": vectors - produced,
        "vectors": vectors,
        "clocks": clocks,
        "sim_s": sim_s,
        "clk_per_s": clocks / sim_s,
        "latency_clk": result["first_out"],
        "throughput_per_clk": produced / span if produced else 0.0,
        "max_err_lsb": float(np.max(np.abs(err))),
        "rms_err_lsb": float(math.sqrt(np.mean(err ** 2))),
    }


def run(count=100_000, *, seed=0, progress=False, **params):
    """Simulate :class:`Cordic` on the corner cases plus ``count`` seeded random vectors (x, y, θ
    uniform over their full ranges) fed one per clock; compare with the golden model.

    Parameters
    ----------
    count : int
        Number of random vectors (the corner cases come on top).
    seed : int
        Seed of the random stimulus.
    progress : bool
        Progress line on stderr.
    **params
        Passed to :class:`Cordic` (``width``, ``stages``, ``angle_width``, ``guard_bits``,
        ``iterations_per_stage``, ``tag_width``).

    Returns
    -------
    dict
        ``mismatches`` (gateware outputs, tag included, differing from the golden model),
        ``vectors``, ``clocks``, ``sim_s`` (wall seconds of simulation), ``clk_per_s``,
        ``latency_clk`` (measured: clocks from the first ``i.valid`` to the first ``o.valid``),
        ``throughput_per_clk`` (outputs per clock between the first and the last output),
        ``max_err_lsb`` and ``rms_err_lsb`` (gateware outputs against the float rotation by the
        quantized angle, clipped to the output range; x and y pooled), ``outputs_missing``.
    """
    dut = Cordic(**params)
    model = {k: v for k, v in params.items() if k not in ("iterations_per_stage", "tag_width")}
    return run_rotation(dut, rotate, rotate_ideal, model, count=count, seed=seed, spacing=1,
                        name="cordic", progress=progress)
