# Ref: SPEC.md §2.3 (paper Fig. 6), M/T speed D_n = k·ΔM/ΔT: the divider.
"""Gateware :class:`~foc_servo.hdl.divider.Divider` against its golden model.

Fast by construction: the simulated design is :class:`DividerBench`, ``lanes`` dividers side by
side, each fed from a ROM holding its operands and the golden model's expected result, with a
mismatch counter and an accept-to-done latency meter in gateware. The testbench only ticks.
"""

import time

import numpy as np
from amaranth.hdl import Cat, Module, Signal, signed, unsigned
from amaranth.lib import data, wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import Out

from ...hdl.divider import Divider, divider_params
from ...hdl.fixed import shape_range
from ..harness import Progress, simulate
from ..models import divider as model

__all__ = ["run", "vectors", "corner_cases", "DividerBench"]


def _ranges(p):
    shape = signed if p["signed"] else unsigned
    return shape_range(shape(p["width"])), shape_range(shape(p["divisor_width"]))


def corner_cases(**params):
    """Named corner cases: every pair of special dividends and divisors (zero, ±1, ±2, small odd,
    powers of two and their neighbours, the extremes of each range).

    Returns
    -------
    dividend, divisor : lists of int
    """
    p = divider_params(**params)
    (nlo, nhi), (dlo, dhi) = _ranges(p)

    def specials(lo, hi, w):
        s = {0, 1, 2, 3, 7, lo, lo + 1, hi, hi - 1, 1 << (w - 2), (1 << (w - 2)) - 1}
        if p["signed"]:
            s |= {-1, -2, -3, -7, -(1 << (w - 2)), 1 - (1 << (w - 2))}
        return sorted(v for v in s if lo <= v <= hi)

    ns, ds = specials(nlo, nhi, p["width"]), specials(dlo, dhi, p["divisor_width"])
    n, d = [n for n in ns for _ in ds], [d for _ in ns for d in ds]
    qw = p["quotient_width"]
    if qw < p["width"]:
        # The saturation boundary of a narrow quotient: quotients 2**qw − 1 and 2**qw.
        for dv in ds:
            for nv in (dv << qw) - 1, dv << qw, (dv << qw) + dv - 1, ((dv + 1) << qw) - 1:
                if dv and nlo <= nv <= nhi:
                    n.append(nv)
                    d.append(dv)
    return n, d


def _randbits(rng, bits, size, dtype):
    """Uniform integers in [0, 2**bits)."""
    if dtype is not object:
        return rng.integers(0, 1 << bits, size=size, dtype=np.int64)
    out = np.zeros(size, dtype=object)
    for shift in range(0, bits, 32):
        chunk = rng.integers(0, 1 << min(32, bits - shift), size=size, dtype=np.int64)
        out = out + (chunk.astype(object) << shift)
    return out


def _uniform(rng, lo, hi, size, dtype):
    """Uniform integers in [lo, hi] (negligible modulo bias beyond 62 bits)."""
    if dtype is not object:
        return rng.integers(lo, hi, size=size, dtype=np.int64, endpoint=True)
    return _randbits(rng, (hi - lo).bit_length() + 16, size, dtype) % (hi - lo + 1) + lo


def vectors(count, *, seed=0, **params):
    """``count`` seeded random operand pairs from a mix of distributions.

    Mix: uniform over the full ranges (30 %), log-uniform magnitudes (20 %), small magnitudes
    (10 %), powers of two ± 1 (10 %), ``|dividend| < |divisor|`` (10 %), small divisor and full
    dividend (12 %), divisor ±1 (6 %), divisor 0 (1 %), ``min / -1`` (1 %; unsigned: ``max / 1``).
    With a narrow quotient (``quotient_width < width``) a third of the pairs are then redrawn
    with quotients around the saturation boundary ``2**quotient_width`` (the draws before are
    unchanged: the same seed gives the same other pairs).

    Returns
    -------
    dividend, divisor : arrays (int64, or object beyond 62 bits)
    """
    p = divider_params(**params)
    (nlo, nhi), (dlo, dhi) = _ranges(p)
    dtype = model._dtype(p["width"], p["divisor_width"])
    rng = np.random.default_rng(seed)
    nb = p["width"] - p["signed"]               # magnitude bits
    db = p["divisor_width"] - p["signed"]

    def signs(x):
        if not p["signed"]:
            return x
        return np.where(rng.integers(0, 2, size=len(x)) == 1, -x, x).astype(dtype)

    def loguniform(bits, size):
        return _randbits(rng, bits, size, dtype) >> rng.integers(0, bits + 1, size=size)

    def pow2(bits, size):
        k = rng.integers(0, bits, size=size)
        e = rng.integers(-1, 2, size=size)
        return np.array([(1 << int(a)) + int(b) for a, b in zip(k, e)], dtype=dtype)

    kind = rng.choice(9, size=count, p=[.30, .20, .10, .10, .10, .12, .06, .01, .01])
    n = _uniform(rng, nlo, nhi, count, dtype)
    d = _uniform(rng, dlo, dhi, count, dtype)
    # 1: log-uniform magnitudes
    n = np.where(kind == 1, signs(loguniform(nb, count)), n)
    d = np.where(kind == 1, signs(loguniform(db, count)), d)
    # 2: small magnitudes (< 2**8)
    n = np.where(kind == 2, signs(loguniform(min(nb, 8), count)), n)
    d = np.where(kind == 2, signs(loguniform(min(db, 8), count)), d)
    # 3: powers of two ± 1
    n = np.where(kind == 3, signs(pow2(nb, count)), n)
    d = np.where(kind == 3, signs(pow2(db, count)), d)
    # 4: |dividend| < |divisor|
    dm = np.abs(signs(loguniform(db, count)))
    dm = np.where(dm == 0, 1, dm)
    small = _randbits(rng, min(nb + 2, 62), count, dtype) % dm
    n = np.where(kind == 4, signs(small), n)
    d = np.where(kind == 4, signs(dm), d)
    # 5: full dividend, small divisor
    d = np.where(kind == 5, signs(loguniform(min(db, 8), count)), d)
    # 6: divisor ±1
    d = np.where(kind == 6, signs(np.ones(count, dtype=dtype)), d)
    # 7: division by zero
    d = np.where(kind == 7, 0, d)
    # 8: the overflow case
    n = np.where(kind == 8, nlo if p["signed"] else nhi, n)
    d = np.where(kind == 8, -1 if p["signed"] else 1, d)
    # Divisor 0 only where asked for (log-uniform and small magnitudes would give it often).
    d = np.where((d == 0) & (kind != 7), signs(np.ones(count, dtype=dtype)), d)
    n = np.clip(n, nlo, nhi).astype(dtype)
    d = np.clip(d, dlo, dhi).astype(dtype)
    qw = p["quotient_width"]
    if qw < p["width"]:
        # Quotient in [2**qw − 4, 2**qw + 4) (where the dividend range allows it), any remainder.
        near = rng.random(count) < 1 / 3
        dd = np.maximum(d, 1)
        q = (1 << qw) - 4 + rng.integers(0, 8, size=count)
        rem = _randbits(rng, min(p["divisor_width"], 62), count, dtype) % dd
        nn = dd.astype(object) * q.astype(object) + rem.astype(object)
        ok = near & (nn <= nhi)
        n = np.where(ok, nn, n).astype(dtype)
    return n, d


class DividerBench(wiring.Component):
    """Simulation-only wrapper: ``len(lanes)`` dividers fed from ROMs, checked in gateware.

    Each lane's ROM row packs ``dividend | divisor << w | expected o.payload << (w + dw)``. A lane
    offers its next row while it has rows left, holds ``o.ready`` high, compares every result
    with the expected payload and checks that it arrives exactly ``latency`` clocks after the
    transfer on ``i``. All the bookkeeping is one array-of-structs signal, :attr:`state`, driven
    by one process: the Python simulator's cost grows with the number of processes and of
    signals driven per clock, hardly with their width.

    Members
    -------
    done : Out(1)
        Every lane has checked all of its rows.

    Attributes
    ----------
    clocks : Signal
        Clocks simulated until :attr:`done`.
    state : Signal(data.ArrayLayout(lane, len(lanes)))
        Per lane: ``idx`` (rows done), ``t_accept`` (clock of the last transfer on ``i``),
        ``lat_sum`` (sum of the measured latencies), ``mismatches`` (payload differs from the
        model), ``late`` (latency differs from ``Divider.latency``), ``first_bad`` (first
        mismatching row) and ``got`` (its payload).
    """

    done: Out(1)

    def __init__(self, lanes, **params):
        self._p = divider_params(**params)
        self._rows = [list(r) for r in lanes]
        if not self._rows or not all(self._rows):
            raise ValueError("DividerBench lanes must be a non-empty list of non-empty row lists")
        super().__init__()
        depth = max(len(r) for r in self._rows) + 1
        lane = data.StructLayout({
            "idx": range(depth),
            "t_accept": 40,
            "lat_sum": 48,
            "mismatches": range(depth),
            "late": range(depth),
            "first_bad": range(depth),
            "got": self._p["quotient_width"] + self._p["divisor_width"] + 2,
        })
        self.clocks = Signal(40)
        self.state = Signal(data.ArrayLayout(lane, len(self._rows)))

    def elaborate(self, platform):
        m = Module()
        in_bits = self._p["width"] + self._p["divisor_width"]
        all_done = []
        for k, rows in enumerate(self._rows):
            m.submodules[f"dut{k}"] = dut = Divider(**self._p)
            m.submodules[f"rom{k}"] = rom = Memory(
                shape=unsigned(in_bits + dut.o_layout.size), depth=len(rows), init=rows)
            port = rom.read_port(domain="comb")
            st = self.state[k]
            lane_done = st.idx == len(rows)
            all_done.append(lane_done)
            got = dut.o.payload.as_value()
            m.d.comb += [
                port.addr.eq(st.idx),
                dut.i.payload.eq(port.data[:in_bits]),
                dut.i.valid.eq(~lane_done),
                dut.o.ready.eq(1),
            ]
            with m.If(dut.i.valid & dut.i.ready):
                m.d.sync += st.t_accept.eq(self.clocks)
            with m.If(dut.o.valid):
                m.d.sync += [
                    st.idx.eq(st.idx + 1),
                    st.lat_sum.eq(st.lat_sum + (self.clocks - st.t_accept)),
                ]
                with m.If(self.clocks - st.t_accept != dut.latency):
                    m.d.sync += st.late.eq(st.late + 1)
                with m.If(got != port.data[in_bits:]):
                    m.d.sync += st.mismatches.eq(st.mismatches + 1)
                    with m.If(st.mismatches == 0):
                        m.d.sync += [st.first_bad.eq(st.idx), st.got.eq(got)]
        m.d.comb += self.done.eq(Cat(all_done).all())
        with m.If(~self.done):
            m.d.sync += self.clocks.eq(self.clocks + 1)
        return m


def _pack(n, d, q, r, z, v, p):
    w, dw, qw = p["width"], p["divisor_width"], p["quotient_width"]
    mw, md, mq = (1 << w) - 1, (1 << dw) - 1, (1 << qw) - 1
    o = w + dw                          # the expected payload: quotient, remainder, div0, ovf
    return [(int(a) & mw) | (int(b) & md) << w | (int(c) & mq) << o
            | (int(e) & md) << (o + qw) | int(f) << (o + qw + dw)
            | int(g) << (o + qw + dw + 1)
            for a, b, c, e, f, g in zip(n, d, q, r, z, v)]


def _unpack_payload(bits, p):
    qw, dw = p["quotient_width"], p["divisor_width"]

    def field(x, width):
        x &= (1 << width) - 1
        return x - (1 << width) if p["signed"] and x >> (width - 1) else x

    return {"quotient": field(bits, qw), "remainder": field(bits >> qw, dw),
            "div0": bits >> (qw + dw) & 1, "ovf": bits >> (qw + dw + 1) & 1}


def run(count=100_000, *, seed=0, progress=False, lanes=16, **params):
    """Simulate the divider on ``count`` seeded random divisions plus :func:`corner_cases` and
    compare every result with :func:`foc_servo.sim.models.divider.divide`.

    Parameters
    ----------
    count : int
        Number of random divisions (:func:`vectors`), on top of the corner cases.
    seed : int
        Seed of the random stimulus.
    progress : bool
        Show a progress line on stderr.
    lanes : int
        Dividers simulated side by side (a speed knob; the results do not depend on it).
    **params :
        ``width``, ``divisor_width``, ``signed``, ``quotient_width`` of
        :class:`~foc_servo.hdl.divider.Divider`.

    Returns
    -------
    dict
        ``mismatches``, ``vectors``, ``clocks`` (simulated), ``sim_s`` (wall seconds of
        simulation), ``clocks_per_s`` (simulated clocks per wall second),
        ``divider_clocks_per_s`` (the same times ``lanes``: divider-clocks per second),
        ``wall_s`` (wall seconds of the whole run: stimulus, model, elaboration, simulation),
        ``clocks_per_division`` (measured clocks from the transfer on ``i`` to ``o.valid``, mean
        over all divisions), ``latency_deviations`` (divisions
        whose latency differed from :attr:`Divider.latency`),
        ``div0_cases``, ``ovf_cases``, ``lanes``, the parameters, and ``first_mismatch`` (None, or
        the operands, expected and gateware payloads of the first mismatching division).
    """
    if not isinstance(lanes, int) or isinstance(lanes, bool) or lanes < 1:
        raise TypeError(f"lanes must be an integer of at least 1, not {lanes!r}")
    if not isinstance(count, int) or isinstance(count, bool) or count < 0:
        raise TypeError(f"count must be a non-negative integer, not {count!r}")
    start = time.perf_counter()
    p = divider_params(**params)
    cn, cd = corner_cases(**p)
    rn, rd = vectors(count, seed=seed, **p)
    dtype = model._dtype(p["width"], p["divisor_width"])
    n = np.concatenate([np.array(cn, dtype=dtype), rn])
    d = np.concatenate([np.array(cd, dtype=dtype), rd])
    q, r, z, v = model.divide(n, d, **p)
    rows = _pack(n, d, q, r, z, v, p)
    total = len(rows)
    lanes = min(lanes, total)
    bench = DividerBench([rows[k::lanes] for k in range(lanes)], **p)
    bar = Progress(f"divider {p['width']}/{p['divisor_width']}"
                   f"{'' if p['signed'] else 'u'}", total, enabled=progress)
    res = {}

    async def testbench(ctx):
        chunk = 64 * (p["width"] + 3)
        while not ctx.get(bench.done):
            await ctx.tick().repeat(chunk)
            bar.update(sum(lane.idx for lane in ctx.get(bench.state)))
        res["clocks"] = ctx.get(bench.clocks)
        stats = list(ctx.get(bench.state))
        res["mismatches"] = sum(st.mismatches for st in stats)
        res["late"] = sum(st.late for st in stats)
        res["lat_sum"] = sum(st.lat_sum for st in stats)
        bad = [(st.first_bad * lanes + k, k) for k, st in enumerate(stats) if st.mismatches]
        if bad:
            row, k = min(bad)
            res["first_mismatch"] = {
                "dividend": int(n[row]), "divisor": int(d[row]),
                "expected": {"quotient": int(q[row]), "remainder": int(r[row]),
                             "div0": int(z[row]), "ovf": int(v[row])},
                "got": _unpack_payload(stats[k].got, p),
            }

    sim_s = simulate(bench, [testbench], name=f"divider_verify_{p['width']}_{p['divisor_width']}")
    bar.close()
    return {
        "mismatches": res["mismatches"],
        "vectors": total,
        "clocks": res["clocks"],
        "sim_s": round(sim_s, 3),
        "clocks_per_s": round(res["clocks"] / sim_s),
        "divider_clocks_per_s": round(res["clocks"] * lanes / sim_s),
        "wall_s": round(time.perf_counter() - start, 3),
        "clocks_per_division": res["lat_sum"] / total,
        "latency_deviations": res["late"],
        "div0_cases": int(np.count_nonzero(z)),
        "ovf_cases": int(np.count_nonzero(v)),
        "lanes": lanes,
        **p,
        "first_mismatch": res.get("first_mismatch"),
    }
