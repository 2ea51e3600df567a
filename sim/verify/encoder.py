# Ref: SPEC.md §2.3 (encoder A/B/Z + Hall, ×4 position counter); §4 (synchronisers, glitch filters)
"""Gateware :class:`~foc_servo.hdl.encoder.EncoderFrontEnd` against its golden model and the
issue's targets, in three simulations:

* **random** — seeded pin waveforms (a random walk of the rotor with short and long glitches,
  illegal A/B jumps, Z marks, Hall codes from the true angle with injected 000/111 faults,
  ``realign`` strobes) under segments of random configuration (filter length, lines, pole pairs,
  Z and Hall offsets, invalid ones included). Stimulus and the model's expected outputs sit in ROMs
  of a simulation-only wrapper that compares every output on every clock in gateware.
* **drift** — a gateware stimulus generator drives the :class:`QuadratureDecoder`'s A/B at one
  state change per clock (a test hook past the synchronisers and filters): after the first Z,
  ``count`` forward counts, ``count`` back, then ``count`` clocks of random walk (an LFSR). A
  gateware checker compares ``count`` with a reference counter on every clock and checks
  ``theta == floor(e·2**16 / cpr)`` by multiplication
  (``theta·cpr ≤ e·2**16 < (theta + 1)·cpr``); the testbench compares ``e`` with the exact
  ``(pole_pairs·net + z_offset) mod cpr`` (Python integers) every few thousand clocks and at the
  end of each phase.
* **events** — directed pulses at every filter length 0 … 12 (and a few long ones) and every
  width around it on A, B, Z and a Hall input, illegal A/B transitions from every state, and Hall
  codes 000/111: counts what was seen downstream.

And with the motor model (:func:`run_plant`, issue 6 item 7): the encoder and Hall pins from
:meth:`foc_servo.sim.pmsm.Plant.sensor_events` (rotor held at a speed, or swinging back and forth
under a load torque), optionally with the encoder's A line broken
(:meth:`~foc_servo.sim.pmsm.Plant.sensor_fault`) and Hall bounce, through the golden model
(event-driven, full scale) or the gateware (compared with the model on every clock): the
plausibility check's detection latency and its false trips.
"""

import numpy as np
from amaranth.hdl import Cat, Module, Mux, Signal, unsigned
from amaranth.lib import data, wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import Out

import math
import time

from ...hdl.encoder import ANGLE, HALL_CODES, EncoderFrontEnd, QuadratureDecoder
from ..harness import Progress, pack_words, simulate
from ..models import encoder as model

__all__ = ["run", "run_random", "run_drift", "run_events", "run_plant", "plant_schedule",
           "stimulus", "changes"]

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
    if rng.random() < 0.5 and cpr:
        # Hall offset matching the Z offset (the plausibility check passes, up to quantisation).
        hall_offset = (model.theta_exact(z_offset % cpr, cpr)
                       + int(rng.integers(-600, 601))) % ANGLE.turn
    else:
        hall_offset = int(rng.integers(0, ANGLE.turn))
    pick = rng.random()
    hall_tolerance = (8192 if pick < 0.4 else int(rng.integers(0, 2000)) if pick < 0.6 else
                      int(rng.integers(8192, ANGLE.turn)) if pick < 0.8 else
                      int(rng.integers(0, ANGLE.turn)))
    hall_misses = int(rng.integers(1, 3)) if rng.random() < 0.5 else int(rng.integers(0, 16))

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
            "hall_offset": hall_offset, "hall_tolerance": hall_tolerance,
            "hall_misses": hall_misses}
    return (np.array(pins, dtype=np.int64), np.array(realign, dtype=np.int64),
            {k: np.full(n, v, dtype=np.int64) for k, v in cols.items()})


def stimulus(count, *, seed=0, max_length=255, segment_clocks=(1000, 8000)):
    """Seeded pin waveforms and configuration, ``count`` clocks: segments of
    ``segment_clocks`` = (shortest, longest) clocks (1 000 … 8 000), the first with the default
    configuration (5000 lines, 4 pole pairs). Shorter segments make a short run see many
    configurations (invalid ones included: 5 % of the segments have a random 18-bit Z offset,
    mostly ≥ cpr).

    Returns
    -------
    dict of int64 arrays
        ``pins`` (A, B, Z, H_a, H_b, H_c in bits 0 … 5) and the configuration columns
        ``length``, ``lines``, ``pole_pairs``, ``z_offset``, ``hall_offset``, ``realign``,
        ``hall_tolerance``, ``hall_misses`` (half of the segments with a Hall offset that
        matches the Z offset, so the plausibility check sees passes as well as misses).
    """
    rng = np.random.default_rng(seed)
    parts = []
    done = 0
    first = True
    while done < count:
        n = min(int(rng.integers(segment_clocks[0], segment_clocks[1] + 1)), count - done)
        pins, realign, cols = _segment(rng, n, max_length)
        if first:
            cols["lines"][:] = 5000
            cols["pole_pairs"][:] = 4
            cols["z_offset"][:] = cols["z_offset"][0] % 20000
            first = False
        parts.append({"pins": pins, "realign": realign, **cols})
        done += n
    return {k: np.concatenate([p[k] for p in parts])[:count] for k in parts[0]}




_STIM = ("pins", "length", "lines", "pole_pairs", "z_offset", "hall_offset", "realign",
         "hall_tolerance", "hall_misses")


class _RandomBench(wiring.Component):
    """Simulation-only: stimulus ROM → EncoderFrontEnd → compare every output with the expected-
    output ROM on every clock (entry ``t`` is the state during clock ``t``)."""

    compared: Out(32)
    mismatches: Out(32)
    first_mismatch: Out(32, init=0xFFFF_FFFF)
    illegal_seen: Out(32)
    hall_faults_seen: Out(32)
    hall_edges_seen: Out(32)
    hall_misses_seen: Out(32)
    plausibility_seen: Out(32)

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
            dut.hall_tolerance.eq(word.hall_tolerance), dut.hall_misses.eq(word.hall_misses),
            dut.lp_changed.eq(word.lp_changed & (t < n)),
            dut.z_changed.eq(word.z_changed & (t < n)),
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
        for flag, counter in ((dut.hall_edge, self.hall_edges_seen),
                              (dut.hall_miss, self.hall_misses_seen),
                              (dut.plausibility, self.plausibility_seen)):
            with m.If(flag):
                m.d.sync += counter.eq(counter + 1)
        return m


def _compare(vec, *, max_length=255, z_gate=None, name="encoder_random", progress=False,
             label="encoder random"):
    """Gateware :class:`EncoderFrontEnd` against :func:`~foc_servo.sim.models.encoder.front_end`
    on the per-clock stimulus ``vec`` (the columns of :data:`_STIM`), every output on every
    clock. Returns the bench's counters, the model's outputs ``exp`` and timing."""
    n = vec["pins"].size
    exp = model.front_end(vec["pins"], max_length=max_length, z_gate=z_gate,
                          **{k: vec[k] for k in _STIM[1:]})
    dut = EncoderFrontEnd(max_length=max_length, z_gate=z_gate)
    stim_layout = data.StructLayout({
        "pins": 6, "length": dut.length.shape(), "lines": dut.lines.shape(),
        "pole_pairs": dut.pole_pairs.shape(), "z_offset": dut.z_offset.shape(),
        "hall_offset": dut.hall_offset.shape(), "realign": 1,
        "hall_tolerance": dut.hall_tolerance.shape(), "hall_misses": dut.hall_misses.shape(),
        "lp_changed": 1, "z_changed": 1,
    })
    # The configuration's change strobes (the register file's), as the model derives them.
    vec = dict(vec)
    vec["lp_changed"], vec["z_changed"] = model.change_strobes(vec["lines"], vec["pole_pairs"],
                                                               vec["z_offset"])
    exp_layout = data.StructLayout({k: getattr(dut, k).shape() for k in model.OUTPUTS})
    bench = _RandomBench(dut, pack_words(stim_layout, vec, n), stim_layout,
                         pack_words(exp_layout, exp, n + 1), exp_layout)
    clocks = n + 2
    result = {}
    prog = Progress(label, clocks, enabled=progress)

    async def testbench(ctx):
        done = 0
        while done < clocks:
            k = min(4000, clocks - done)
            await ctx.tick().repeat(k)
            done += k
            prog.update(done)
        for key in ("compared", "mismatches", "first_mismatch", "illegal_seen",
                    "hall_faults_seen", "hall_edges_seen", "hall_misses_seen",
                    "plausibility_seen"):
            result[key] = ctx.get(getattr(bench, key))

    sim_s = simulate(bench, [testbench], name=name)
    prog.close()
    first = result["first_mismatch"]
    missing = (n + 1) - result["compared"]
    result.update(
        mismatches=result["mismatches"] + max(missing, 0), vectors=n + 1, clocks=clocks,
        sim_s=sim_s, clocks_per_s=clocks / sim_s if sim_s > 0 else float("inf"),
        first_mismatch=None if first == 0xFFFF_FFFF else int(first), exp=exp)
    return result


def run_random(count=100_000, *, seed=0, progress=False, max_length=255, z_gate=None,
               segment_clocks=(1000, 8000)):
    """Random pin waveforms (:func:`stimulus`) against
    :func:`~foc_servo.sim.models.encoder.front_end`, every output on every clock. Returns
    ``mismatches``, ``vectors`` (clocks compared), ``clocks``, ``sim_s``, ``clocks_per_s``,
    ``first_mismatch``, event tallies (gateware and model) and ``invalid_z_clocks`` (clocks
    with a committed Z offset ≥ cpr)."""
    vec = stimulus(count, seed=seed, max_length=max_length, segment_clocks=segment_clocks)
    r = _compare(vec, max_length=max_length, z_gate=z_gate, progress=progress)
    exp = r["exp"]
    return {
        "mismatches": r["mismatches"],
        "vectors": r["vectors"],
        "clocks": r["clocks"],
        "sim_s": r["sim_s"],
        "clocks_per_s": r["clocks_per_s"],
        "first_mismatch": r["first_mismatch"],
        "illegal_strobes": r["illegal_seen"],
        "illegal_strobes_model": int(exp["illegal"].sum()),
        "hall_fault_episodes": r["hall_faults_seen"],
        "hall_edges": r["hall_edges_seen"],
        "hall_edges_model": int(exp["hall_edge"].sum()),
        "hall_misses": r["hall_misses_seen"],
        "hall_misses_model": int(exp["hall_miss"].sum()),
        "plausibility_strobes": r["plausibility_seen"],
        "plausibility_strobes_model": int(exp["plausibility"].sum()),
        "index_strobes_model": int(exp["index"].sum()),
        "align_events_model": int(np.sum(np.diff(exp["aligned"]) == 1)),
        "config_commits_model": int(np.sum(np.diff(exp["busy"]) == -1)),
        "invalid_z_clocks": int(np.sum((exp["busy"][1:] == 0)
                                       & (vec["z_offset"] >= 4 * vec["lines"]))),
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
        # The change strobes in the first clock (the configuration differs from the reset's).
        first = Signal(init=1)
        m.d.sync += first.eq(0)
        m.d.comb += [
            dut.lp_changed.eq(first & int((lines, pole_pairs) != (dut.lines.init,
                                                                   dut.pole_pairs.init))),
            dut.z_changed.eq(first & int(z_offset != dut.z_offset.init)),
        ]

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


# --- with the motor model: the encoder/Hall plausibility check (issue 6 item 7) -------------

def changes(out, until=None):
    """The per-clock outputs ``out`` (entry ``t``: during clock ``t``, as
    :func:`~foc_servo.sim.models.encoder.front_end` returns them) as a change trace: ``clock``
    and each output, one row per clock whose outputs differ from the previous clock's (as
    :func:`~foc_servo.sim.models.encoder.front_end_changes` returns it), up to clock
    ``until − 1``."""
    n = len(out[model.OUTPUTS[0]]) if until is None else until
    stack = np.stack([np.asarray(out[k][:n], dtype=np.int64) for k in model.OUTPUTS])
    keep = np.ones(n, dtype=bool)
    keep[1:] = np.any(stack[:, 1:] != stack[:, :-1], axis=0)
    rows = {"clock": np.flatnonzero(keep).astype(np.int64)}
    rows.update({k: stack[i, keep] for i, k in enumerate(model.OUTPUTS)})
    return rows


def _merge(groups):
    """Union of per-group change lists ``[(clock, value), ...]`` (each starting at the same
    clock) → (clocks, per-group values forward-filled)."""
    clocks = np.unique(np.concatenate([np.array([c for c, _ in g], dtype=np.int64)
                                       for g in groups]))
    filled = []
    for g in groups:
        gc = np.array([c for c, _ in g], dtype=np.int64)
        gv = np.array([v for _, v in g], dtype=np.int64)
        filled.append(gv[np.searchsorted(gc, clocks, side="right") - 1])
    return clocks, filled


def _append(lst, clock, value):
    """Append a change, replacing one at the same clock; drop it if it changes nothing."""
    if lst and lst[-1][0] == clock:
        lst.pop()
    if not lst or lst[-1][1] != value:
        lst.append((clock, value))


def plant_schedule(plant, until, *, chunk, break_at=None, broken_level=1, hall_bounce=None):
    """Pin-change schedule of a plant's encoder and Hall pins from its ``now`` to ``until``.

    The plant is advanced (gates as they are) in chunks of at most ``chunk`` clocks, each after
    asking :meth:`~foc_servo.sim.pmsm.Plant.sensor_events` for its edges. At clock
    ``break_at`` the encoder's A line breaks (:meth:`~foc_servo.sim.pmsm.Plant.sensor_fault`,
    held at ``broken_level``): the pin takes that level from ``break_at + 1``.

    Parameters
    ----------
    hall_bounce : (int, int) or None
        ``(n, w)``: every Hall change bounces ``n`` times back to the previous code and forward
        again, ``w`` clocks apart (skipped where the next Hall change comes sooner) — Hall
        switches chattering at their threshold.

    Returns
    -------
    (clocks, words) : int64 arrays
        The pins hold ``words[i]`` (A, B, Z, H_a, H_b, H_c in bits 0 … 5) from ``clocks[i]`` on;
        ``clocks[0]`` is the plant's ``now`` at the call.
    """
    lv = plant.sensor_levels()
    t0 = plant.now
    enc = [(t0, int(lv["a"]) | int(lv["b"]) << 1 | int(lv["z"]) << 2)]
    hall = [(t0, int(lv["hall"]))]
    broken = False
    while plant.now < until:
        stop = min(until, plant.now + chunk)
        if break_at is not None and not broken:
            if plant.now >= break_at:
                plant.sensor_fault(enc_a_broken=broken_level)
                broken = True
            else:
                stop = min(stop, break_at)
        ev, levels = plant.sensor_events(stop)
        at = plant.now + 1                    # a level change without an edge (a fault)
        _append(enc, at, int(levels["a"]) | int(levels["b"]) << 1 | int(levels["z"]) << 2)
        _append(hall, at, int(levels["hall"]))
        for c, a, b, z, h in zip(ev["clock"].tolist(), ev["a"].tolist(), ev["b"].tolist(),
                                 ev["z"].tolist(), ev["hall"].tolist()):
            _append(enc, c, a | b << 1 | z << 2)
            _append(hall, c, h)
        plant.advance(stop)
    if hall_bounce is not None:
        n_b, w = hall_bounce
        bounced = [hall[0]]
        for i in range(1, len(hall)):
            c, h = hall[i]
            prev = hall[i - 1][1]
            nxt = hall[i + 1][0] if i + 1 < len(hall) else until
            bounced.append((c, h))
            if c + 2 * n_b * w < nxt:
                for j in range(1, n_b + 1):
                    bounced += [(c + (2 * j - 1) * w, prev), (c + 2 * j * w, h)]
        hall = bounced
    clocks, (e, h) = _merge([enc, hall])
    keep = clocks < until
    return clocks[keep], (e | (h << 3))[keep]


def _strobes(trace, name):
    return trace["clock"][trace[name] == 1]


def run_plant(*, speed_rpm=1000.0, duration_s=20e-3, break_after_s=None, break_phi_deg=None,
              broken_level=1, swing=None, clk_hz=50e6, lines=None, z_count=0, theta_m0=0.0,
              chunk_s=100e-6, length=4, hall_offset_rad=0.0, hall_offset_error_deg=0.0,
              hall_bounce=None, tolerance=8192, misses=1, engine="model", progress=False,
              motor=None):
    """The encoder front end driven by the motor model's encoder and Hall pins.

    Parameters
    ----------
    speed_rpm : float
        Rotor speed (held: a stiff dynamometer), r/min; negative turns backward.
    duration_s : float
        Motor time simulated, s.
    break_after_s, break_phi_deg : float or None
        The encoder's A line breaks (held at ``broken_level``) at ``break_after_s`` (s); with
        ``break_phi_deg`` at the first clock after that where the rotor is ``break_phi_deg``
        electrical degrees past a Hall boundary in its direction of rotation (held rotor).
    swing : (float, float) or None
        ``(amplitude_rad, freq_hz)``: instead of a held speed the free rotor swings as
        ``θ_m0 + amplitude·sin(2π·freq·t)`` (mechanical), driven by the matching load torque:
        a reversal every half period, through standstill.
    clk_hz : float
        System clock (a lower clock with fewer ``lines`` makes a cheaper gateware run).
    lines, z_count, hall_offset_rad
        :class:`~foc_servo.sim.pmsm.Sensors` (``lines=None``: the motor's 5000).
    theta_m0 : float
        Initial mechanical angle, rad (Z at ``z_count``: 0 rad for 0).
    length : int
        Glitch filter length, clocks.
    hall_offset_error_deg : float
        Error of the decoder's Hall offset against the plant's, electrical degrees.
    hall_bounce : (int, int) or None
        See :func:`plant_schedule`.
    tolerance, misses : int
        The check's registers (binary angle; count).
    engine : str
        ``"model"``: the event-driven golden model
        (:func:`~foc_servo.sim.models.encoder.front_end_changes`); ``"gateware"``: the gateware
        compared on every clock with the per-clock model (and the event-driven model checked
        against the per-clock one).

    Returns
    -------
    dict
        ``detected`` (a ``plausibility`` strobe after the break), ``detect_clock``,
        ``detect_latency_s`` (from the break at the pins to the strobe; the protection latch
        adds 1 clock), ``detect_angle_deg`` (electrical rotation in that time),
        ``expected_angle_deg`` (the rotation at which the ``misses``-th missed Hall edge
        comes, from the rotor position at the break: ``N·60° − φ`` if ``60° − φ`` exceeds the
        tolerance, else ``(N + 1)·60° − φ``), ``break_phi_deg`` (φ), ``detect_sectors``
        (detect angle / 60°), ``false_trips`` (strobes before the break, or in a run without a
        break), ``plausibility_strobes``, ``hall_edges``, ``hall_misses``, ``illegal_strobes``,
        ``aligned_clock``, ``aligned_at_break``, ``max_abs_error_deg`` (largest
        ``|hall_error|`` at the aligned Hall edges, before the break), ``clocks``, ``edges``
        (pin changes), ``wall_s``; with the gateware also ``mismatches`` (gateware vs model,
        every output, every clock), ``sparse_mismatches`` (event-driven vs per-clock model
        trace rows), ``sim_s``; and ``trace`` (the change trace of every output).
    """
    from ..motor import DEFAULT_MOTOR
    from ..pmsm import Plant, Sensors

    if engine not in ("model", "gateware"):
        raise ValueError(f"run_plant engine must be 'model' or 'gateware', not {engine!r}")
    motor = DEFAULT_MOTOR if motor is None else motor
    t_wall = time.perf_counter()
    sensors = Sensors(lines=lines, z_count=z_count, hall_offset_rad=hall_offset_rad,
                      noise_lsb=0.0)
    if swing is None:
        omega = speed_rpm * 2 * math.pi / 60
        plant = Plant(motor, clk_hz=clk_hz, sensors=sensors, theta_m0=theta_m0,
                      omega_m0=omega, rotor="held")
    else:
        amp, f = swing
        w = 2 * math.pi * f
        j, b = motor.j_kgm2, motor.b_nms
        plant = Plant(motor, clk_hz=clk_hz, sensors=sensors, theta_m0=theta_m0,
                      omega_m0=amp * w, rotor="free",
                      load_nm=lambda t: j * amp * w * w * math.sin(w * t)
                      - b * amp * w * math.cos(w * t))
        omega = amp * w
    p = motor.pole_pairs
    until = round(duration_s * clk_hz)
    break_at = None
    phi = None
    if break_after_s is not None:
        break_at = round(break_after_s * clk_hz)
        if break_phi_deg is not None:
            if swing is not None:
                raise ValueError("run_plant break_phi_deg needs a held rotor, not a swing")
            # θ_e − offset at the break, in the direction of rotation, mod 60°.
            sgn = 1.0 if omega > 0 else -1.0
            th = math.degrees(p * (theta_m0 + omega * break_at / clk_hz) - hall_offset_rad)
            past = (sgn * th) % 60.0
            extra = (break_phi_deg - past) % 60.0
            break_at += math.ceil(math.radians(extra) / (p * abs(omega)) * clk_hz)
        th = math.degrees(p * (theta_m0 + omega * break_at / clk_hz) - hall_offset_rad)
        phi = ((1.0 if omega > 0 else -1.0) * th) % 60.0
    clocks, words = plant_schedule(plant, until, chunk=max(1, round(chunk_s * clk_hz)),
                                   break_at=break_at, hall_bounce=hall_bounce,
                                   broken_level=broken_level)
    offset = (plant.hall_offset_register()
              + round(hall_offset_error_deg / 360 * ANGLE.turn)) % ANGLE.turn
    cfg = dict(length=length, lines=plant.sensors.lines or motor.encoder_lines,
               pole_pairs=p, z_offset=plant.z_offset_register(), hall_offset=offset,
               hall_tolerance=tolerance, hall_misses=misses)
    res = {}
    trace = model.front_end_changes(clocks, words, until, **cfg)
    if engine == "gateware":
        pins = np.repeat(words, np.diff(np.append(clocks, until)))
        vec = {"pins": pins, "realign": np.zeros(until, dtype=np.int64),
               **{k: np.full(until, v, dtype=np.int64) for k, v in cfg.items()}}
        r = _compare(vec, name="encoder_plant", progress=progress, label="encoder plant")
        dense = changes(r["exp"], until)
        res["sparse_mismatches"] = int(
            len(dense["clock"]) != len(trace["clock"])
            or sum(int(np.any(dense[k] != trace[k])) for k in dense))
        res.update(mismatches=r["mismatches"], first_mismatch=r["first_mismatch"],
                   sim_s=r["sim_s"], gateware_plausibility_strobes=r["plausibility_seen"],
                   gateware_hall_edges=r["hall_edges_seen"])
        trace = dense

    strobes = _strobes(trace, "plausibility")
    onset = None if break_at is None else break_at + 1
    false = strobes if onset is None else strobes[strobes < onset]
    after = strobes if onset is None else strobes[strobes >= onset]
    aligned_rows = trace["clock"][trace["aligned"] == 1]
    aligned_clock = int(aligned_rows[0]) if len(aligned_rows) else None
    edges = _strobes(trace, "hall_edge")
    # hall_error after each aligned edge (one clock later it holds the edge's d).
    err_rows = np.searchsorted(trace["clock"], edges, side="right") - 1
    aligned_edges = trace["aligned"][err_rows] == 1
    if onset is not None:
        aligned_edges &= edges < onset
    errors = trace["hall_error"][err_rows][aligned_edges] * 360.0 / ANGLE.turn
    detect = int(after[0]) if onset is not None and len(after) else None
    w_e = abs(p * omega)
    res.update(
        detected=detect is not None,
        detect_clock=detect,
        detect_latency_s=None if detect is None else (detect - onset) / clk_hz,
        detect_angle_deg=None if detect is None else
        math.degrees(w_e * (detect - onset) / clk_hz),
        break_clock=break_at,
        break_phi_deg=phi,
        expected_angle_deg=None if phi is None else
        (misses * 60.0 - phi if 60.0 - phi > tolerance * 360 / ANGLE.turn
         else (misses + 1) * 60.0 - phi),
        false_trips=int(len(false)),
        plausibility_strobes=int(len(strobes)),
        hall_edges=int(len(edges)),
        hall_misses=int(len(_strobes(trace, "hall_miss"))),
        illegal_strobes=int(len(_strobes(trace, "illegal"))),
        aligned_clock=aligned_clock,
        aligned_at_break=(aligned_clock is not None and onset is not None
                          and aligned_clock < onset),
        max_abs_error_deg=float(np.max(np.abs(errors))) if len(errors) else None,
        clocks=until, edges=int(len(clocks)), trace=trace,
        wall_s=time.perf_counter() - t_wall,
    )
    if res["detect_angle_deg"] is not None:
        res["detect_sectors"] = res["detect_angle_deg"] / 60.0
    return res
