# Ref: SPEC.md §2.3 (encoder A/B/Z + Hall, ×4 position counter); §4 (synchronisers, glitch filters)
"""Gateware :class:`~foc_servo.hdl.encoder.EncoderFrontEnd` against its golden model and the
issue's targets, in three simulations:

* **random** — seeded pin waveforms (a random walk of the rotor with short and long glitches,
  illegal A/B jumps, Z marks, Hall codes from the true angle with injected 000/111 faults,
  ``realign`` strobes) under segments of random configuration (filter length, lines, pole pairs,
  Z and Hall offsets, invalid ones included). Stimulus and the model's expected outputs sit in ROMs
  of a simulation-only wrapper that compares every output on every clock in gateware.
* **drift** — a gateware stimulus generator drives the :class:`QuadratureDecoder`'s A/B at one
  state change per clock (a test hook past the synchronisers and filters): after the first Z, ``count`` forward counts, ``count`` back, then ``count`` clocks of
  random walk (an LFSR). A gateware checker compares ``count`` with a reference counter on every
  clock and checks ``theta == floor(e·2**16 / cpr)`` by multiplication
  (``theta·cpr ≤ e·2**16 < (theta + 1)·cpr``); the testbench compares ``e`` with the exact
  ``(pole_pairs·net + z_offset) mod cpr`` (Python integers) every few thousand clocks and at the
  end of each phase.
* **events** — directed pulses at every filter length 0 … 12 (and a few long ones) and every
  width around it on A, B, Z and a Hall input, illegal A/B transitions from every state, and Hall
  codes 000/111: counts what was seen downstream.
"""

import numpy as np
from amaranth.hdl import Cat, Module, Mux, Signal, unsigned
from amaranth.lib import data, wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import Out

from ...hdl.encoder import ANGLE, HALL_CODES, EncoderFrontEnd, QuadratureDecoder
from ..harness import Progress, pack_words, simulate
from ..models import encoder as model

__all__ = ["run", "run_random", "run_drift", "run_events", "stimulus"]

_AB = ((0, 0), (1, 0), (1, 1), (0, 1))          # quadrature state of phase 0 … 3 (A, B)
_LINES = (5000, 1, 2, 3, 7, 13, 50, 997, 65535)
_POLE_PAIRS = (4, 1, 3, 7, 255)


def _pins(a, b, z, hall):
    return a | (b << 1) | (z << 2) | (hall << 3)


def _segment(rng, n, max_length):
    """One segment of ``n`` clocks with its own configuration: returns pins and config columns."""
    if rng.random() < 0.4:
        length = int(rng.integers(0, 4))
    else:
        length = int(rng.integers(0, min(max_length, 12) + 1))
    lines = int(rng.choice(_LINES)) if rng.random() < 0.7 else int(rng.integers(1, 1 << 16))
    pole_pairs = int(rng.choice(_POLE_PAIRS)) if rng.random() < 0.8 else int(rng.integers(0, 256))
    cpr = 4 * lines
    if rng.random() < 0.05:
        z_offset = int(rng.integers(0, 1 << 18))        # often ≥ cpr: an invalid configuration
    else:
        z_offset = int(rng.integers(0, cpr))
    hall_offset = int(rng.integers(0, ANGLE.turn))

    pins, realign = [], []
    pos = int(rng.integers(-12, 13))                    # true position, counts (Z at 0 mod cpr)
    direction = 1
    hall_fault_left = 0
    done = 0
    while done < n:
        r = rng.random()
        if r < 0.08:
            direction = -direction
        event = rng.random()
        # Dwell of the current state: mostly long enough to pass the filter.
        if event < 0.1:
            dwell = int(rng.integers(1, length + 3))
        else:
            dwell = length + int(rng.integers(0, 4)) + (int(rng.geometric(0.1)) if r < 0.02 else 0)
        dwell = max(1, min(dwell, n - done))
        phase = pos % 4
        a, b = _AB[phase]
        z = int(pos % cpr == 0)
        e_true = (pole_pairs * pos) % cpr if cpr else 0
        hall = model.hall_code(((e_true << 16) // cpr) if cpr else 0)
        if hall_fault_left > 0:
            hall = 0 if hall_fault_left % 2 else 7
            hall_fault_left -= 1
        elif rng.random() < 0.01:
            hall_fault_left = int(rng.integers(1, 4))
        word = _pins(a, b, z, hall)
        if event < 0.1:
            # A glitch on one pin for `dwell` clocks, then back.
            word ^= 1 << int(rng.integers(0, 6))
            pins.extend([word] * dwell)
            realign.extend([0] * dwell)
            done += dwell
            continue
        pins.extend([word] * dwell)
        realign.extend([int(rng.random() < 0.003)] + [0] * (dwell - 1))
        done += dwell
        pos += 2 * direction if event > 0.995 else direction    # rare illegal jump by 2
    n = len(pins)
    cols = {"length": length, "lines": lines, "pole_pairs": pole_pairs, "z_offset": z_offset,
            "hall_offset": hall_offset}
    return (np.array(pins, dtype=np.int64), np.array(realign, dtype=np.int64),
            {k: np.full(n, v, dtype=np.int64) for k, v in cols.items()})


def stimulus(count, *, seed=0, max_length=255):
    """Seeded pin waveforms and configuration, ``count`` clocks: segments of 1 000 … 8 000 clocks,
    the first with the default configuration (5000 lines, 4 pole pairs).

    Returns
    -------
    dict of int64 arrays
        ``pins`` (A, B, Z, H_a, H_b, H_c in bits 0 … 5) and the configuration columns
        ``length``, ``lines``, ``pole_pairs``, ``z_offset``, ``hall_offset``, ``realign``.
    """
    rng = np.random.default_rng(seed)
    parts = []
    done = 0
    first = True
    while done < count:
        n = min(int(rng.integers(1000, 8001)), count - done)
        pins, realign, cols = _segment(rng, n, max_length)
        if first:
            cols["lines"][:] = 5000
            cols["pole_pairs"][:] = 4
            cols["z_offset"][:] = cols["z_offset"][0] % 20000
            first = False
        parts.append({"pins": pins, "realign": realign, **cols})
        done += n
    return {k: np.concatenate([p[k] for p in parts])[:count] for k in parts[0]}




_STIM = ("pins", "length", "lines", "pole_pairs", "z_offset", "hall_offset", "realign")


class _RandomBench(wiring.Component):
    """Simulation-only: stimulus ROM → EncoderFrontEnd → compare every output with the expected-
    output ROM on every clock (entry ``t`` is the state during clock ``t``)."""

    compared: Out(32)
    mismatches: Out(32)
    first_mismatch: Out(32, init=0xFFFF_FFFF)
    illegal_seen: Out(32)
    hall_faults_seen: Out(32)

    def __init__(self, dut, stim, stim_layout, exp, exp_layout):
        self._dut, self._stim, self._stim_layout = dut, stim, stim_layout
        self._exp, self._exp_layout = exp, exp_layout
        super().__init__()

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = dut = self._dut
        n = len(self._stim)
        m.submodules.stim = stim = Memory(shape=unsigned(self._stim_layout.size), depth=n,
                                          init=self._stim)
        m.submodules.exp = exp = Memory(shape=unsigned(self._exp_layout.size),
                                        depth=len(self._exp), init=self._exp)
        srd = stim.read_port(domain="comb")
        erd = exp.read_port(domain="comb")
        t = Signal(range(n + 2))
        word = data.View(self._stim_layout, srd.data)
        m.d.comb += [srd.addr.eq(t), erd.addr.eq(t)]
        m.d.comb += [
            Cat(dut.a, dut.b, dut.z, dut.hall).eq(word.pins),
            dut.length.eq(word.length), dut.lines.eq(word.lines),
            dut.pole_pairs.eq(word.pole_pairs), dut.z_offset.eq(word.z_offset),
            dut.hall_offset.eq(word.hall_offset), dut.realign.eq(word.realign & (t < n)),
        ]
        got = Cat(*(getattr(dut, name) for name, _ in self._exp_layout))
        with m.If(t <= n):
            m.d.sync += [t.eq(t + 1), self.compared.eq(self.compared + 1)]
            with m.If(got != erd.data):
                m.d.sync += self.mismatches.eq(self.mismatches + 1)
                with m.If(self.mismatches == 0):
                    m.d.sync += self.first_mismatch.eq(t)
        fault_prev = Signal()
        m.d.sync += fault_prev.eq(dut.hall_fault)
        with m.If(dut.illegal):
            m.d.sync += self.illegal_seen.eq(self.illegal_seen + 1)
        with m.If(dut.hall_fault & ~fault_prev):
            m.d.sync += self.hall_faults_seen.eq(self.hall_faults_seen + 1)
        return m


def run_random(count=100_000, *, seed=0, progress=False, max_length=255, z_gate=None):
    """Random pin waveforms against :func:`~foc_servo.sim.models.encoder.front_end`, every
    output on every clock. Returns ``mismatches``, ``vectors`` (clocks compared), ``clocks``,
    ``sim_s``, ``clocks_per_s``, ``first_mismatch`` and event tallies."""
    vec = stimulus(count, seed=seed, max_length=max_length)
    n = vec["pins"].size
    exp = model.front_end(vec["pins"], max_length=max_length, z_gate=z_gate,
                          **{k: vec[k] for k in _STIM[1:]})
    dut = EncoderFrontEnd(max_length=max_length, z_gate=z_gate)
    stim_layout = data.StructLayout({
        "pins": 6, "length": dut.length.shape(), "lines": dut.lines.shape(),
        "pole_pairs": dut.pole_pairs.shape(), "z_offset": dut.z_offset.shape(),
        "hall_offset": dut.hall_offset.shape(), "realign": 1,
    })
    exp_layout = data.StructLayout({k: getattr(dut, k).shape() for k in model.OUTPUTS})
    bench = _RandomBench(dut, pack_words(stim_layout, vec, n), stim_layout,
                         pack_words(exp_layout, exp, n + 1), exp_layout)
    clocks = n + 2
    result = {}
    prog = Progress("encoder random", clocks, enabled=progress)

    async def testbench(ctx):
        done = 0
        while done < clocks:
            k = min(4000, clocks - done)
            await ctx.tick().repeat(k)
            done += k
            prog.update(done)
        for name in ("compared", "mismatches", "first_mismatch", "illegal_seen",
                     "hall_faults_seen"):
            result[name] = ctx.get(getattr(bench, name))

    sim_s = simulate(bench, [testbench], name="encoder_random")
    prog.close()
    first = result["first_mismatch"]
    missing = (n + 1) - result["compared"]
    return {
        "mismatches": result["mismatches"] + max(missing, 0),
        "vectors": n + 1,
        "clocks": clocks,
        "sim_s": sim_s,
        "clocks_per_s": clocks / sim_s if sim_s > 0 else float("inf"),
        "first_mismatch": None if first == 0xFFFF_FFFF else int(first),
        "illegal_strobes": result["illegal_seen"],
        "illegal_strobes_model": int(exp["illegal"].sum()),
        "hall_fault_episodes": result["hall_faults_seen"],
        "index_strobes_model": int(exp["index"].sum()),
        "align_events_model": int(np.sum(np.diff(exp["aligned"]) == 1)),
        "config_commits_model": int(np.sum(np.diff(exp["busy"]) == -1)),
    }


class _DriftBench(wiring.Component):
    """Simulation-only: a quadrature generator (one state change per clock) and an exact checker
    around a :class:`QuadratureDecoder` (the block that holds the angle arithmetic; the
    synchronisers and filters in front of it are covered by the random comparison).

    Phases: ``INIT`` (settle and configuration commit, then a Z pulse at position 0), ``FWD``
    (``counts`` forward), ``BWD`` (``counts`` back), ``WALK`` (``counts`` clocks; an LFSR moves
    forward, back or holds), ``DONE``. ``net`` is the generator's signed position (counts since
    the Z); the checker's ``ref_count`` is ``net mod cpr`` delayed by the decoder's latency.
    """

    net: Out(48)                # generator position, two's complement
    ref_net: Out(48)            # the same, delayed to line up with the DUT outputs
    phase: Out(3)
    count_errors: Out(32)
    theta_errors: Out(32)
    checked: Out(32)

    INIT_CLOCKS = 160

    def __init__(self, dut, counts, *, lines, pole_pairs, z_offset):
        self._dut, self._counts = dut, counts
        self._cpr = 4 * lines
        self._cfg = (lines, pole_pairs, z_offset)
        super().__init__()

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = dut = self._dut
        lines, pole_pairs, z_offset = self._cfg
        cpr = self._cpr
        m.d.comb += [dut.lines.eq(lines), dut.pole_pairs.eq(pole_pairs),
                     dut.z_offset.eq(z_offset)]

        INIT, FWD, BWD, WALK, DONE = range(5)
        n = Signal(range(max(self._counts, self.INIT_CLOCKS) + 1))
        pos = Signal(2)             # quadrature phase of the generator
        lfsr = Signal(32, init=0xACE1_2468)
        move = Signal()
        fwd = Signal()
        # quadrature_phase(a, b) = (a ^ b) | (b << 1) = pos: a = pos0 ^ pos1, b = pos1.
        m.d.comb += [dut.a.eq(pos[0] ^ pos[1]), dut.b.eq(pos[1])]

        with m.Switch(self.phase):
            with m.Case(INIT):
                m.d.sync += n.eq(n + 1)
                m.d.comb += dut.z.eq((n >= self.INIT_CLOCKS - 16) & (n < self.INIT_CLOCKS - 8))
                with m.If(n == self.INIT_CLOCKS):
                    m.d.sync += [n.eq(0), self.phase.eq(FWD)]
            with m.Case(FWD):
                m.d.comb += [move.eq(1), fwd.eq(1)]
            with m.Case(BWD):
                m.d.comb += [move.eq(1), fwd.eq(0)]
            with m.Case(WALK):
                m.d.comb += [move.eq(lfsr[0]), fwd.eq(lfsr[1])]
                m.d.sync += lfsr.eq(_galois2(lfsr))
        with m.If((self.phase == FWD) | (self.phase == BWD) | (self.phase == WALK)):
            m.d.sync += n.eq(n + 1)
            with m.If(n == self._counts - 1):
                m.d.sync += [n.eq(0), self.phase.eq(self.phase + 1)]
            with m.If(move):
                m.d.sync += [pos.eq(pos + (fwd * 2 - 1)),
                             self.net.eq(self.net + (fwd * 2 - 1))]

        # Reference, delayed by the DUT latency: the DUT sees `pos` on the clock after it changes
        # (as `net` does) and its outputs follow `latency` clocks later.
        delay = [self.net]
        for k in range(dut.latency):
            r = Signal(48, name=f"net_d{k}")
            m.d.sync += r.eq(delay[-1])
            delay.append(r)
        m.d.comb += self.ref_net.eq(delay[-1])
        ref_count = Signal(range(cpr))
        d = (delay[-2] - delay[-1])[:2]     # the move that reaches the DUT outputs next clock
        with m.If(d == 1):
            m.d.sync += ref_count.eq(Mux(ref_count == cpr - 1, 0, ref_count + 1))
        with m.Elif(d == 3):
            m.d.sync += ref_count.eq(Mux(ref_count == 0, cpr - 1, ref_count - 1))

        armed = Signal()
        with m.If((self.phase != INIT) & (self.phase != DONE)):
            m.d.sync += armed.eq(1)
        with m.If(armed & dut.aligned):
            m.d.sync += self.checked.eq(self.checked + 1)
            with m.If(dut.count != ref_count):
                m.d.sync += self.count_errors.eq(self.count_errors + 1)
            lhs = dut.theta * cpr
            rhs = dut.e << ANGLE.width
            with m.If((lhs > rhs) | (lhs + cpr <= rhs)):
                m.d.sync += self.theta_errors.eq(self.theta_errors + 1)
        with m.If(armed & ~dut.aligned):
            m.d.sync += self.count_errors.eq(self.count_errors + 1)
        return m


def _galois2(lfsr):
    """Two steps of the right-shifting Galois LFSR with taps 0x80200003 (x^32+x^22+x^2+x+1)."""
    v = lfsr
    for _ in range(2):
        v = Cat(v[1:], 0) ^ Mux(v[0], 0x8020_0003, 0)
    return v


def run_drift(counts=100_000, *, progress=False, lines=5000, pole_pairs=4, z_offset=12345,
              checkpoint=4096):
    """Angle drift after ``counts`` counts forward, ``counts`` back and ``counts`` clocks of
    random walk.

    Returns
    -------
    dict
        ``angle_drift_counts`` (largest ``|e − e_exact|``, cyclic, over all checkpoints, electrical
        counts), ``theta_errors`` (clocks where ``theta ≠ floor(e·2**16/cpr)``), ``count_errors``
        (clocks where ``count`` differs from the reference counter or the encoder is not
        aligned), ``checked`` (clocks checked), ``checkpoints``, ``final_net`` (net counts after
        the walk), ``clocks``, ``sim_s``, ``clocks_per_s``.
    """
    dut = QuadratureDecoder()
    bench = _DriftBench(dut, counts, lines=lines, pole_pairs=pole_pairs, z_offset=z_offset)
    cpr = 4 * lines
    clocks = bench.INIT_CLOCKS + 1 + 3 * counts + dut.latency + 2
    result = {"drift": 0, "checkpoints": 0}
    prog = Progress("encoder drift", clocks, enabled=progress)

    def check(ctx):
        net = ctx.get(bench.ref_net)
        net = net - (1 << 48) if net >> 47 else net
        want = (pole_pairs * net + z_offset) % cpr
        got = ctx.get(dut.e)
        err = abs(got - want)
        result["drift"] = max(result["drift"], min(err, cpr - err))
        result["checkpoints"] += 1
        result["final_net"] = net

    async def testbench(ctx):
        await ctx.tick().repeat(bench.INIT_CLOCKS + 1 + dut.latency + 2)
        done = bench.INIT_CLOCKS + 1 + dut.latency + 2
        boundaries = {bench.INIT_CLOCKS + 1 + k * counts for k in (1, 2, 3)}
        while done < clocks:
            k = min(checkpoint, clocks - done)
            nxt = min((b + dut.latency + 1 for b in boundaries if b + dut.latency + 1 > done),
                      default=clocks)
            k = max(1, min(k, nxt - done))
            await ctx.tick().repeat(k)
            done += k
            check(ctx)
            prog.update(done)
        for name in ("count_errors", "theta_errors", "checked"):
            result[name] = ctx.get(getattr(bench, name))

    sim_s = simulate(bench, [testbench], name="encoder_drift")
    prog.close()
    return {
        "angle_drift_counts": result["drift"],
        "theta_errors": result["theta_errors"],
        "count_errors": result["count_errors"],
        "checked": result["checked"],
        "checkpoints": result["checkpoints"],
        "final_net": result.get("final_net"),
        "counts": counts,
        "clocks": clocks,
        "sim_s": sim_s,
        "clocks_per_s": clocks / sim_s if sim_s > 0 else float("inf"),
    }


class _EventBench(wiring.Component):
    """Simulation-only: an :class:`EncoderFrontEnd` with event counters (steps, index strobes,
    illegal strobes, Hall changes = a new sector or a rising ``hall_fault``)."""

    steps: Out(32)
    indexes: Out(32)
    illegals: Out(32)
    hall_changes: Out(32)
    hall_faults: Out(32)

    def __init__(self, dut):
        self._dut = dut
        super().__init__()

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = dut = self._dut
        sector_prev = Signal.like(dut.hall_sector)
        fault_prev = Signal()
        m.d.sync += [sector_prev.eq(dut.hall_sector), fault_prev.eq(dut.hall_fault)]
        for flag, counter in ((dut.step, self.steps), (dut.index, self.indexes),
                              (dut.illegal, self.illegals)):
            with m.If(flag):
                m.d.sync += counter.eq(counter + 1)
        rise = dut.hall_fault & ~fault_prev
        with m.If(rise | (dut.hall_sector != sector_prev)):
            m.d.sync += self.hall_changes.eq(self.hall_changes + 1)
        with m.If(rise):
            m.d.sync += self.hall_faults.eq(self.hall_faults + 1)
        return m


def _widths(length):
    if length <= 12:
        return list(range(1, length + 4))
    return sorted({1, length // 2, length - 2, length - 1, length, length + 1, length + 2})


def run_events(*, seed=0, progress=False, lengths=None, max_length=255):
    """Directed pulses, illegal transitions and Hall faults through the whole front end.

    For each filter length (default 0 … 12, 20, 100) and every pulse width around it, one pulse
    (clock-aligned, starting from a random legal state) on each of A, B, Z and a Hall input.

    Returns
    -------
    dict
        ``glitch_short_counted``: pulses shorter than ``length`` that caused any event;
        ``glitch_long_missed``: pulses of ``length + 2`` or more that did not cause exactly the
        expected events (two counts for A/B, one index strobe for Z, a Hall change);
        ``glitch_threshold_errors``: pulses seen although shorter than ``max(length, 1)`` or not
        seen although at least that long (the filter's exact threshold); ``glitch_pulses``;
        ``illegal_injected``, ``illegal_detected`` (each injection flagged exactly once, with no
        count); ``hall_fault_injected``, ``hall_fault_detected`` (000/111 codes, each raising
        ``hall_fault`` once); ``hall_fault_false`` (faults raised over full valid Hall
        sequences); ``clocks``, ``sim_s``.
    """
    lengths = list(range(13)) + [20, 100] if lengths is None else list(lengths)
    rng = np.random.default_rng([seed, 7])
    dut = EncoderFrontEnd(max_length=max_length)
    bench = _EventBench(dut)
    pins = Cat(dut.a, dut.b, dut.z, dut.hall)
    res = {k: 0 for k in ("glitch_short_counted", "glitch_long_missed", "glitch_threshold_errors",
                          "glitch_pulses", "illegal_injected", "illegal_detected",
                          "hall_fault_injected", "hall_fault_detected", "hall_fault_false",
                          "clocks")}
    prog = Progress("encoder events", len(lengths), enabled=progress)

    async def testbench(ctx):
        clocks = 0

        async def wait(k):
            nonlocal clocks
            await ctx.tick().repeat(k)
            clocks += k

        def counters():
            return {k: ctx.get(getattr(bench, k))
                    for k in ("steps", "indexes", "illegals", "hall_changes", "hall_faults")}

        await wait(8)
        for li, length in enumerate(lengths):
            ctx.set(dut.length, length)
            quiet = max(length, 1) + 6
            for bit in (0, 1, 2, 3 + li % 3):
                for w in _widths(length):
                    phase = int(rng.integers(4))
                    a, b = _AB[phase]
                    base = _pins(a, b, 0, HALL_CODES[int(rng.integers(6))])
                    ctx.set(pins, base)
                    await wait(quiet)
                    c0 = counters()
                    ctx.set(pins, base ^ (1 << bit))
                    await wait(w)
                    ctx.set(pins, base)
                    await wait(quiet)
                    c1 = counters()
                    d = {k: c1[k] - c0[k] for k in c0}
                    seen = any(d.values())
                    if bit < 2:
                        right = d == {"steps": 2, "indexes": 0, "illegals": 0,
                                      "hall_changes": 0, "hall_faults": 0}
                    elif bit == 2:
                        right = d == {"steps": 0, "indexes": 1, "illegals": 0,
                                      "hall_changes": 0, "hall_faults": 0}
                    else:
                        right = (d["hall_changes"] >= 1 and d["steps"] == 0
                                 and d["indexes"] == 0 and d["illegals"] == 0)
                    res["glitch_pulses"] += 1
                    if w < length and seen:
                        res["glitch_short_counted"] += 1
                    if w >= length + 2 and not right:
                        res["glitch_long_missed"] += 1
                    if seen != (w >= max(length, 1)) or (seen and not right):
                        res["glitch_threshold_errors"] += 1
            # Illegal transitions: from every state, A and B together, and back.
            for phase in range(4):
                a, b = _AB[phase]
                base = _pins(a, b, 0, HALL_CODES[0])
                ctx.set(pins, base)
                await wait(quiet)
                c0 = counters()
                ctx.set(pins, base ^ 0b11)
                await wait(quiet)
                ctx.set(pins, base)
                await wait(quiet)
                c1 = counters()
                res["illegal_injected"] += 2
                if c1["steps"] == c0["steps"]:
                    res["illegal_detected"] += min(c1["illegals"] - c0["illegals"], 2)
            # Hall: a full valid turn each way (no fault allowed), then 000 and 111 from every
            # sector.
            c0 = counters()
            for code in list(HALL_CODES) + list(HALL_CODES[::-1]):
                ctx.set(pins, _pins(0, 0, 0, code))
                await wait(quiet)
            res["hall_fault_false"] += counters()["hall_faults"] - c0["hall_faults"]
            for k, code in enumerate(HALL_CODES):
                for bad in (0b000, 0b111):
                    ctx.set(pins, _pins(0, 0, 0, code))
                    await wait(quiet)
                    c0 = counters()
                    ctx.set(pins, _pins(0, 0, 0, bad))
                    await wait(max(length, 1) + 1)
                    ctx.set(pins, _pins(0, 0, 0, code))
                    await wait(quiet)
                    res["hall_fault_injected"] += 1
                    if counters()["hall_faults"] - c0["hall_faults"] == 1:
                        res["hall_fault_detected"] += 1
            prog.update(li + 1)
        res["clocks"] = clocks

    res["sim_s"] = simulate(bench, [testbench], name="encoder_events")
    prog.close()
    return res


def run(count=100_000, *, seed=0, progress=False, drift_counts=None, max_length=255,
        z_gate=None, events=True):
    """Everything the issue asks of the encoder front end, against the golden model.

    Parameters
    ----------
    count : int
        Clocks of random pin waveforms compared with the golden model.
    drift_counts : int or None
        Counts per phase of the drift run (forward, back, random walk); ``None``: ``count``.
    events : bool
        Run the directed glitch / illegal / Hall-fault pulses too.

    Returns
    -------
    dict
        ``mismatches`` (random-run output mismatches + drift checker errors + angle drift),
        ``vectors`` (clocks compared), ``clocks`` and ``sim_s`` (all runs), ``clocks_per_s``,
        the issue's keys ``angle_drift_counts``, ``glitch_short_counted``,
        ``glitch_long_missed``, ``illegal_detected`` (with ``illegal_injected``),
        ``hall_fault_detected`` (with ``hall_fault_injected``), and the per-run dicts
        ``random``, ``drift``, ``events``.
    """
    drift_counts = count if drift_counts is None else drift_counts
    r = run_random(count, seed=seed, progress=progress, max_length=max_length, z_gate=z_gate)
    d = run_drift(drift_counts, progress=progress)
    e = run_events(seed=seed, progress=progress, max_length=max_length) if events else None
    out = {
        "mismatches": (r["mismatches"] + d["theta_errors"] + d["count_errors"]
                       + d["angle_drift_counts"]),
        "vectors": r["vectors"] + d["checked"],
        "clocks": r["clocks"] + d["clocks"] + (e["clocks"] if e else 0),
        "sim_s": r["sim_s"] + d["sim_s"] + (e["sim_s"] if e else 0.0),
        "angle_drift_counts": d["angle_drift_counts"],
        "drift_counts_per_phase": drift_counts,
    }
    out["clocks_per_s"] = out["clocks"] / out["sim_s"] if out["sim_s"] > 0 else float("inf")
    if e:
        for k in ("glitch_short_counted", "glitch_long_missed", "glitch_threshold_errors",
                  "illegal_injected", "illegal_detected", "hall_fault_injected",
                  "hall_fault_detected", "hall_fault_false"):
            out[k] = e[k]
    out.update(random=r, drift=d, events=e)
    return out
