# Ref: paper eq. (1); SPEC.md §1 (Clarke transform) and §2 (current scaling)
"""Gateware :class:`~foc_servo.hdl.clarke.Clarke` against its golden model, vector by vector.

For speed the stimulus (with random ``i.valid`` gaps) and the golden model's expected outputs sit in
ROMs of a simulation-only wrapper that feeds the block and counts mismatches in gateware; the
testbench only ticks the clock.
"""

import numpy as np
from amaranth.hdl import Module, Shape, Signal, signed, unsigned
from amaranth.lib import data, wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import Out

from ...hdl.clarke import Clarke
from ...hdl.fixed import Q, shape_range
from ..harness import Progress, pack_words, simulate
from ..models.clarke import clarke as clarke_model

__all__ = ["run", "stimulus"]

_OUTPUTS = ("a", "b", "c", "alpha", "beta")


def stimulus(count, *, seed=0, width=16, adc_shape=signed(16), gain_format=Q(18, 15),
             three_phase=False):
    """Seeded test vectors: ``count`` random ones, then the corner cases.

    Random vectors come in segments of 100 … 500 that share gains and offsets; a segment's gains
    are drawn uniformly over the whole format, or near the gain that maps the ADC range onto the
    output range (either polarity), or from the corner values; offsets over their whole range or
    near the ADC's zero-current code; codes uniformly over the ADC range or near the offset. Corner
    vectors: codes at both extremes, mid-scale and the offset; offsets at both extremes, zero and
    mid-scale; gains at both extremes (incl. the most negative), ±1 LSB, zero and unity.

    Returns
    -------
    dict of int64 arrays
        ``code_x``, ``gain_x``, ``offset_x`` for each measured phase ``x``.
    """
    rng = np.random.default_rng(seed)
    phases = "abc" if three_phase else "ab"
    adc = Shape.cast(adc_shape)
    c_lo, c_hi = shape_range(adc)
    o_lo, o_hi = shape_range(signed(adc.width + 1))
    g_lo, g_hi = gain_format.min_raw, gain_format.max_raw
    c_mid = (c_lo + c_hi + 1) // 2
    # The gain mapping half the ADC span onto the output full scale: 2**(w-1) / 2**(n-1).
    unity = 1 << gain_format.frac
    g_fit = int(np.clip(round(unity * 2.0 ** (width - adc.width)), 1, g_hi))
    g_corner = np.array(sorted({g_lo, g_lo + 1, -1, 0, 1, min(unity, g_hi), g_hi}), dtype=np.int64)

    vec = {f"{k}_{p}": [] for k in ("code", "gain", "offset") for p in phases}
    done = 0
    while done < count:
        n = min(int(rng.integers(100, 501)), count - done)
        for p in phases:
            kind = rng.integers(3)
            if kind == 0:
                g = rng.integers(g_lo, g_hi + 1)
            elif kind == 1:
                g = int(np.clip(rng.choice([-1, 1]) * g_fit * rng.uniform(0.5, 1.5), g_lo, g_hi))
            else:
                g = rng.choice(g_corner)
            if rng.integers(4) == 0:
                off = rng.integers(o_lo, o_hi + 1)
            else:
                off = c_mid + rng.integers(-(1 << max(adc.width - 4, 0)),
                                           (1 << max(adc.width - 4, 0)) + 1)
            if rng.integers(2):
                code = rng.integers(c_lo, c_hi + 1, size=n)
            else:
                span = 1 << int(rng.integers(1, adc.width))
                code = np.clip(off + rng.integers(-span, span + 1, size=n), c_lo, c_hi)
            vec[f"code_{p}"].append(np.asarray(code, dtype=np.int64))
            vec[f"gain_{p}"].append(np.full(n, g, dtype=np.int64))
            vec[f"offset_{p}"].append(np.full(n, off, dtype=np.int64))
        done += n

    # Corners: every gain corner and offset corner (cycled across the phases so they differ), each
    # with every combination of code corners.
    code_c = np.array(sorted({c_lo, c_hi, c_mid, 0}), dtype=np.int64)
    off_c = np.array([o_lo, o_hi, 0, c_mid], dtype=np.int64)
    grids = np.meshgrid(*([code_c] * len(phases)), indexing="ij")
    combos = [g.ravel() for g in grids]
    for gi in range(len(g_corner)):
        for oi in range(len(off_c)):
            for k, p in enumerate(phases):
                n = combos[k].size
                vec[f"code_{p}"].append(combos[k])
                vec[f"gain_{p}"].append(np.full(n, g_corner[(gi + k) % len(g_corner)]))
                vec[f"offset_{p}"].append(np.full(n, off_c[(oi + k) % len(off_c)]))
                # The same codes with the offset at the code itself: exactly zero current.
                vec[f"code_{p}"].append(combos[k])
                vec[f"gain_{p}"].append(np.full(n, g_corner[(gi + k) % len(g_corner)]))
                vec[f"offset_{p}"].append(combos[k])
    return {k: np.concatenate(v).astype(np.int64) for k, v in vec.items()}




class _ClarkeBench(wiring.Component):
    """Simulation-only wrapper: stimulus ROM → Clarke → compare with expected-output ROM.

    ``mismatches`` counts outputs that differ from the expected word, plus any surplus output;
    ``received`` counts outputs; ``first_mismatch`` is the index of the first bad one.
    """

    received: Out(32)
    mismatches: Out(32)
    first_mismatch: Out(32, init=0xFFFF_FFFF)

    def __init__(self, dut, stim_words, stim_layout, exp_words):
        self._dut = dut
        self._stim = stim_words
        self._stim_layout = stim_layout
        self._exp = exp_words
        super().__init__()

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = dut = self._dut
        layout = self._stim_layout
        out_layout = dut.o.payload.shape()

        m.submodules.stim = stim = Memory(shape=unsigned(layout.size), depth=len(self._stim),
                                          init=self._stim)
        m.submodules.exp = exp = Memory(shape=unsigned(out_layout.size),
                                        depth=max(len(self._exp), 1), init=self._exp)
        srd = stim.read_port(domain="comb")
        erd = exp.read_port(domain="comb")

        n_in = Signal(range(len(self._stim) + 1))
        word = data.View(layout, srd.data)
        running = n_in < len(self._stim)
        m.d.comb += [
            srd.addr.eq(n_in),
            dut.i.valid.eq(running & word.valid),
            erd.addr.eq(self.received),
        ]
        for p in dut.phases:
            m.d.comb += [
                dut.i.payload[p].eq(word[f"code_{p}"]),
                getattr(dut, f"gain_{p}").eq(word[f"gain_{p}"]),
                getattr(dut, f"offset_{p}").eq(word[f"offset_{p}"]),
            ]
        with m.If(running):
            m.d.sync += n_in.eq(n_in + 1)

        with m.If(dut.o.valid):
            m.d.sync += self.received.eq(self.received + 1)
            bad = (self.received >= len(self._exp)) | (dut.o.payload.as_value() != erd.data)
            with m.If(bad):
                m.d.sync += self.mismatches.eq(self.mismatches + 1)
                with m.If(self.mismatches == 0):
                    m.d.sync += self.first_mismatch.eq(self.received)
        return m


def _run_mode(count, *, seed, progress, width, adc_shape, gain_format, three_phase,
              mul_width=18):
    phases = "abc" if three_phase else "ab"
    adc = Shape.cast(adc_shape)
    vec = stimulus(count, seed=seed, width=width, adc_shape=adc, gain_format=gain_format,
                   three_phase=three_phase)
    n = vec["code_a"].size
    exp = clarke_model(*(vec[f"code_{p}"] for p in phases),
                       **{f"{k}_{p}": vec[f"{k}_{p}"] for k in ("gain", "offset") for p in phases},
                       width=width, gain_frac=gain_format.frac, three_phase=three_phase)

    # Random i.valid gaps (about 1 clock in 8), carrying random junk that must not be sampled.
    rng = np.random.default_rng([seed, 1])
    gaps = rng.random(n) < 0.125
    slots = n + int(gaps.sum())
    is_valid = np.ones(slots, dtype=bool)
    is_valid[np.flatnonzero(gaps) + np.arange(int(gaps.sum()))] = False
    c_lo, c_hi = shape_range(adc)
    o_lo, o_hi = shape_range(signed(adc.width + 1))
    cols = {"valid": is_valid.astype(np.int64)}
    for key, (lo, hi) in (("code", (c_lo, c_hi)), ("offset", (o_lo, o_hi)),
                          ("gain", (gain_format.min_raw, gain_format.max_raw))):
        for p in phases:
            col = rng.integers(lo, hi + 1, size=slots)
            col[is_valid] = vec[f"{key}_{p}"]
            cols[f"{key}_{p}"] = col

    stim_layout = data.StructLayout({
        "valid": 1,
        **{f"code_{p}": adc for p in phases},
        **{f"gain_{p}": gain_format.shape for p in phases},
        **{f"offset_{p}": signed(adc.width + 1) for p in phases},
    })
    dut = Clarke(width=width, adc_shape=adc, gain_format=gain_format, three_phase=three_phase,
                 mul_width=mul_width)
    out_layout = dut.o.payload.shape()
    bench = _ClarkeBench(dut, pack_words(stim_layout, cols, slots), stim_layout,
                         pack_words(out_layout, exp, n))
    clocks = slots + dut.latency + 1
    result = {}
    label = f"clarke {'three' if three_phase else 'two'}-phase"
    prog = Progress(label, clocks, enabled=progress)

    async def testbench(ctx):
        await prog.ticks(ctx, clocks, step=2000)
        result["received"] = ctx.get(bench.received)
        result["mismatches"] = ctx.get(bench.mismatches)
        result["first_mismatch"] = ctx.get(bench.first_mismatch)

    sim_s = simulate(bench, [testbench], name=f"clarke_{'3' if three_phase else '2'}ph")
    prog.close()
    missing = n - min(result["received"], n)
    first = result["first_mismatch"]
    if first == 0xFFFF_FFFF and missing:
        first = result["received"]
    return {
        "mismatches": result["mismatches"] + missing,
        "vectors": n,
        "clocks": clocks,
        "sim_s": sim_s,
        "clocks_per_s": clocks / sim_s if sim_s > 0 else float("inf"),
        "saturated_vectors": int(exp["saturated"].sum()),
        "first_mismatch": None if first == 0xFFFF_FFFF else int(first),
        "latency": dut.latency,
    }


def run(count=100_000, *, seed=0, progress=False, width=16, adc_shape=signed(16),
        gain_format=Q(18, 15), three_phase=None, mul_width=18):
    """Simulate :class:`Clarke` on ``count`` seeded random vectors plus the corner cases, in each
    mode, and compare all five outputs with the golden model.

    Parameters
    ----------
    count : int
        Random vectors per mode (the corner cases come on top).
    three_phase : bool or None
        One mode, or both (``None``, the default: ``count`` vectors each).
    mul_width : int or None
        The gateware's multiplier width (:mod:`foc_servo.hdl.dsp`; the model has none: the
        results must not depend on it).

    Returns
    -------
    dict
        ``mismatches``, ``vectors``, ``clocks``, ``sim_s``, ``saturated_vectors`` (summed over the
        modes run), ``clocks_per_s``, ``latency``, and per mode (``"two_phase"``,
        ``"three_phase"``) the same figures plus ``first_mismatch`` (index or ``None``).
    """
    modes = (False, True) if three_phase is None else (bool(three_phase),)
    per_mode = {}
    for tp in modes:
        per_mode["three_phase" if tp else "two_phase"] = _run_mode(
            count, seed=seed, progress=progress, width=width, adc_shape=adc_shape,
            gain_format=gain_format, three_phase=tp, mul_width=mul_width)
    total = {k: sum(r[k] for r in per_mode.values())
             for k in ("mismatches", "vectors", "clocks", "sim_s", "saturated_vectors")}
    total["clocks_per_s"] = total["clocks"] / total["sim_s"] if total["sim_s"] > 0 else 0.0
    total["latency"] = next(iter(per_mode.values()))["latency"]
    total.update(per_mode)
    return total
