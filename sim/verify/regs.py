# Ref: issue 5 item 1 (register file, shadowing); hdl/bus.py (register bus)
"""Gateware :class:`~foc_servo.hdl.regs.RegisterFile` against its model, clock by clock.

Seeded random bus traffic (reads and writes of every kind of register, bad addresses, read-only
writes, scope-window reads, back-to-back and spaced accesses), host frames (``lock`` high over 1 …
8 accesses), random ``commit`` strobes and changing status inputs. Every clock the whole
output state — ``ack``, ``status``, ``r_data``, every strobe and every active register value — is
compared with :class:`~foc_servo.sim.models.regs.RegisterFileModel`. To keep Python out of the
way, a simulation-only wrapper packs all inputs into one signal and all outputs into another (one
``ctx.set`` and one ``ctx.get`` per clock); the window is backed by a real memory.
"""

import random

from amaranth.hdl import Cat, Elaboratable, Module, Mux, ResetInserter, Signal
from amaranth.lib.memory import Memory

from ...hdl.bus import Status
from ...hdl.regmap import REGMAP, Access
from ...hdl.regs import RegisterFile
from ..harness import Progress, simulate
from ..models.regs import RegisterFileModel

__all__ = ["run", "window_word", "Bench"]

#: Clocks the random master holds ``stb`` without an ``ack`` before it gives the access up
#: (counted in ``stuck``; a copy holds an access off for ≈ 50 clocks, the reset walk for 63).
HOLD_LIMIT = 1000


def window_word(offset):
    """Content of the stand-in memory behind a window at word ``offset``."""
    return (offset * 0x9E3779B1 + 0x5BD1E995) & 0xFFFFFFFF


def _bits(port):
    return port.as_value() if hasattr(port, "as_value") else port


class Bench(Elaboratable):
    """Simulation-only wrapper: ``stim`` drives every input, ``outs`` packs every output.

    ``stim`` = Cat(addr, we, w_data, stb, lock, commit, rst, *ro registers); ``outs`` = Cat(ack,
    status, r_data, *strobes, *rw registers (not the exported ones), and with ``export`` the
    port's valid, index, data, the last two as 0 while valid is low, and ``export_walk``), in :attr:`stim_fields` /
    :attr:`out_fields` order (name, offset, width). ``rst`` resets the register file (a ``ResetInserter``: the staging
    RAM keeps its contents, as block RAM does).
    """

    def __init__(self, regmap=REGMAP, *, staging="ff", copy_last=(), export=(), derived=None):
        self.regmap = regmap
        self.dut = RegisterFile(regmap, staging=staging, copy_last=copy_last, export=export,
                                derived=derived)
        exp = ([("export_valid", 1), ("export_index", len(self.dut.export.index)),
                ("export_data", 32), ("export_walk", 1)] if export else [])
        ro = [r for r in regmap if r.access is Access.RO]
        self.stim_fields = self._fields([("addr", 16), ("we", 1), ("w_data", 32), ("stb", 1),
                                         ("lock", 1), ("commit", 1), ("rst", 1),
                                         *((r.name, r.width) for r in ro)])
        self.out_fields = self._fields([("ack", 1), ("status", 2), ("r_data", 32),
                                        *((r.name, 1) for r in regmap
                                          if r.access is Access.STROBE),
                                        *((r.name, len(_bits(getattr(self.dut, r.name))))
                                          for r in regmap
                                          if r.access is Access.RW and r.name not in export),
                                        *exp])
        self.stim = Signal(sum(w for _, _, w in self.stim_fields))
        self.outs = Signal(sum(w for _, _, w in self.out_fields))

    @staticmethod
    def _fields(pairs):
        out, off = [], 0
        for name, width in pairs:
            out.append((name, off, width))
            off += width
        return out

    def elaborate(self, platform):
        m = Module()
        dut = self.dut
        rst = Signal()
        m.submodules.dut = ResetInserter(rst)(dut)
        bus = dut.bus
        sinks = [bus.addr, bus.we, bus.w_data, bus.stb, bus.lock, dut.commit, rst]
        sinks += [_bits(getattr(dut, name)) for name, _, _ in self.stim_fields[7:]]
        m.d.comb += Cat(*sinks).eq(self.stim)
        m.d.comb += self.outs.eq(Cat(bus.ack, bus.status, bus.r_data,
                                     *(_bits(getattr(dut, name)) if hasattr(dut, name) else
                                       Mux(dut.export.valid,
                                           getattr(dut.export, name[len("export_"):]), 0)
                                       for name, _, _ in self.out_fields[3:])))
        for w in self.regmap.windows:
            mem = Memory(shape=32, depth=w.size, init=[window_word(a) for a in range(w.size)])
            m.submodules[f"{w.name}_mem"] = mem
            rd = mem.read_port()
            m.d.comb += [rd.addr.eq(getattr(dut, f"{w.name}_rd_addr")),
                         getattr(dut, f"{w.name}_rd_data").eq(rd.data)]
        return m

    @staticmethod
    def pack(fields, values):
        word = 0
        for name, off, width in fields:
            v = values.get(name)
            if v:
                word |= (v & ((1 << width) - 1)) << off
        return word

    def unpack(self, fields, word):
        return {name: (word >> off) & ((1 << width) - 1) for name, off, width in fields}


def _accesses(regmap, count, rng):
    """``count`` random accesses ``(addr, we, w_data)``; first a read of every register word."""
    words = regmap.words()
    used = {a for a, _, _ in words}
    for w in regmap.windows:
        used |= set(range(w.addr, w.addr + w.size))
    near = sorted({a + d for a, _, _ in words for d in (-1, 1)} - used)
    near = [a for a in near if 0 <= a < 1 << 16]
    rw = [(a, r, k) for a, r, k in words if r.access is Access.RW]

    def data():
        kind = rng.random()
        if kind < 0.4:
            return rng.getrandbits(32)
        if kind < 0.6:
            return rng.choice((0, 1, 0xFFFFFFFF, 0x7FFFFFFF, 0x80000000, 0xFFFF, 0x8000))
        return rng.getrandbits(rng.randint(1, 20)) * rng.choice((1, -1)) & 0xFFFFFFFF

    out = [(a, 0, 0) for a, _, _ in words]
    while len(out) < count + len(words):
        kind = rng.random()
        if kind < 0.45:
            addr = rng.choice(words)[0]
        elif kind < 0.65:
            addr = rng.choice(rw)[0]
        elif kind < 0.75 and regmap.windows:
            w = rng.choice(regmap.windows)
            addr = w.addr + rng.randrange(w.size)
        elif kind < 0.87 and near:
            addr = rng.choice(near)
        else:
            addr = rng.getrandbits(16)
        out.append((addr, int(rng.random() < 0.5), data()))
    return out[:count + len(words)] if count else out


def _with_status(cycles, ro_regs, rng):
    """``cycles`` (from :func:`_cycles`) with the status inputs: one random ``ro`` register
    takes a random value in 10 % of the clocks. Yields ``(cycle, status)``; the cycle holds the
    status values too."""
    ro = {r.name: 0 for r in ro_regs}
    for cyc in cycles:
        if rng.random() < 0.1:
            r = rng.choice(ro_regs)
            ro[r.name] = rng.getrandbits(r.width)
        cyc.update(ro)
        yield cyc, ro


def _cycles(regmap, accesses, rng, seen, *, commit_p, rst_p):
    """Per-clock input dicts (without ro) for ``accesses``: frames of 1 … 8 accesses under
    ``lock``, 0 … 3 idle clocks between accesses (30 %), ``commit`` (probability ``commit_p``)
    and ``rst`` (``rst_p``) at random in any clock. The master holds ``stb`` until the ``ack``
    clock (``seen["ack"]``: the expected ``ack`` of the clock last yielded), as the host link
    does; a reset in the middle of an access leaves ``stb`` held and the access is taken again."""
    i = 0
    while i < len(accesses):
        n = rng.randint(1, 8)
        frame = accesses[i:i + n]
        i += n
        framed = rng.random() < 0.7
        for j, (addr, we, w_data) in enumerate(frame):
            for _ in range(HOLD_LIMIT):                 # stb clock … ack clock (stb held)
                yield dict(addr=addr, we=we, w_data=w_data, stb=1, lock=int(framed),
                           commit=int(rng.random() < commit_p), rst=int(rng.random() < rst_p))
                if seen["ack"]:
                    break
            else:
                seen["stuck"] += 1                      # no ack: give the access up
            gap = 0 if rng.random() < 0.7 else rng.randint(1, 3)
            for _ in range(gap):
                yield dict(addr=addr, we=rng.getrandbits(1), w_data=w_data, stb=0,
                           lock=int(framed and j < len(frame) - 1),
                           commit=int(rng.random() < commit_p), rst=int(rng.random() < rst_p))


def run(count=100_000, *, seed=0, progress=False, regmap=REGMAP, staging="ff", copy_last=(),
        export=(), derived=None, commit_p=None, rst_p=0.0):
    """Simulate the register file on ``count`` random bus accesses (plus a read of every register
    word first) and compare every clock with the model.

    ``staging`` / ``copy_last`` / ``export`` / ``derived``: the
    :class:`~foc_servo.hdl.regs.RegisterFile` parameters (the ``export`` port compared as an output, its ``valid`` clocks counted in
    ``export_writes``);
    ``commit_p``: the probability of ``commit`` in a clock (default 0.15 for ``"ff"``, 0.02 for
    ``"bram"``, whose copy takes ``commit_clocks``); ``rst_p``: of a reset in a clock.

    Returns
    -------
    dict
        ``mismatches`` (clocks whose outputs differ), ``vectors`` (bus accesses), ``clocks``,
        ``sim_s``, ``clk_per_s``, ``reads``, ``writes``, ``bad_address``, ``read_only``,
        ``window_reads``, ``commits_applied``, ``commits_locked`` (commit strobes ignored under
        ``lock``), ``strobe_pulses``, ``resets``, ``copies`` (copies started, ``"bram"``),
        ``held`` (clocks with ``stb`` high held off by a copy or the reset walk), ``stuck``
        (accesses given up after :data:`HOLD_LIMIT` clocks without ``ack``), ``first_mismatch``
        (None or a description).
    """
    if commit_p is None:
        commit_p = 0.02 if staging == "bram" else 0.15
    rng = random.Random(seed)
    bench = Bench(regmap, staging=staging, copy_last=copy_last, export=export, derived=derived)
    model = RegisterFileModel(regmap, staging=staging, copy_last=copy_last, export=export,
                              derived=derived)
    accesses = _accesses(regmap, count, rng)
    ro_regs = [r for r in regmap if r.access is Access.RO]
    windows = regmap.windows
    fig = dict(mismatches=0, vectors=len(accesses), clocks=0, reads=0, writes=0, bad_address=0,
               read_only=0, window_reads=0, commits_applied=0, commits_locked=0,
               strobe_pulses=0, resets=0, copies=0, held=0, stuck=0, export_writes=0,
               first_mismatch=None)
    out_fields = bench.out_fields
    strobe_names = [n for n, _, _ in out_fields[3:] if n in model.strobes]
    bar = Progress("regs", len(accesses), enabled=progress)

    rest_fields = out_fields[3:]
    cache = {"state": None, "word": 0}

    def expected(win_data):
        # The strobes and active values change rarely: repack them only when they do.
        port = (*model.export_port(), model.export_walk) if export else ()
        state = (tuple(model.strobes.values()), tuple(model.active.values()), port)
        if state != cache["state"]:
            cache["state"] = state
            exp = dict(zip(("export_valid", "export_index", "export_data", "export_walk"), port))
            cache["word"] = bench.pack(rest_fields, {**model.strobes, **model.active, **exp})
        return (cache["word"] | model.ack | model.status << 1
                | model.r_data(win_data) << 3)

    async def testbench(ctx):
        prev_addr = 0
        done = 0
        seen = {"ack": 0, "stuck": 0}
        for cyc, ro in _with_status(_cycles(regmap, accesses, rng, seen, commit_p=commit_p,
                                            rst_p=rst_p), ro_regs, rng):
            ctx.set(bench.stim, bench.pack(bench.stim_fields, cyc))
            got = ctx.get(bench.outs)
            win_data = {w.name: window_word(prev_addr & (w.size - 1)) for w in windows}
            want = expected(win_data)
            if got != want:
                fig["mismatches"] += 1
                if fig["first_mismatch"] is None:
                    g, e = bench.unpack(out_fields, got), bench.unpack(out_fields, want)
                    diff = {k: (g[k], e[k]) for k in g if g[k] != e[k]}
                    fig["first_mismatch"] = f"clock {fig['clocks']}: (got, expected) {diff}"
            seen["ack"] = model.ack
            if cyc["stb"] and model.busy and not model.pending and not model.ack:
                fig["held"] += 1
            if model.ack:
                done += 1
                if done % 1000 == 0:
                    bar.update(done)
            fig["strobe_pulses"] += sum(model.strobes[n] for n in strobe_names)
            if cyc["commit"] and not cyc["rst"]:
                fig["commits_locked" if cyc["lock"] else "commits_applied"] += 1
            fig["resets"] += cyc["rst"]
            if export:
                fig["export_writes"] += model.export_port()[0]
            status = model.step(**{k: cyc[k] for k in ("stb", "addr", "we", "w_data", "lock",
                                                       "commit", "rst")}, ro=ro)
            fig["copies"] += model.started
            if status is not None:
                fig["writes" if cyc["we"] else "reads"] += 1
                if status == Status.BAD_ADDRESS.value:
                    fig["bad_address"] += 1
                elif status == Status.READ_ONLY.value:
                    fig["read_only"] += 1
                elif any(model.win_hit.values()):
                    fig["window_reads"] += 1
            prev_addr = cyc["addr"]
            fig["clocks"] += 1
            await ctx.tick()

        fig["stuck"] = seen["stuck"]

    fig["sim_s"] = simulate(bench, [testbench], name="regs")
    bar.close()
    fig["clk_per_s"] = fig["clocks"] / fig["sim_s"] if fig["sim_s"] else 0.0
    return fig


class ExportBench(Elaboratable):
    """Simulation-only: two register files on the same inputs, one built with ``export`` and a
    consumer RAM written from its ``export`` port (initialised with ``export_init``), one built
    without (``ref``, the exported registers as flip-flops). ``outs`` = Cat(ack, r_data of
    both, the RAM's words, the reference's exported registers); ``late`` delays the RAM's
    write by a clock (a broken consumer, for the test that the comparison can fail)."""

    def __init__(self, regmap=REGMAP, *, export, copy_last=(), late=False, mirror=False):
        self.regmap = regmap
        # (mirror: ``export`` names the registers of ``RegisterFile(mirror=...)`` instead, the
        # consumer RAM written from its ``mirror`` port)
        self.mirror = mirror
        self.dut = RegisterFile(regmap, staging="bram", copy_last=copy_last,
                                **{"mirror" if mirror else "export": export})
        self.ref = RegisterFile(regmap, staging="bram", copy_last=copy_last)
        self.words = self.dut.mirror_words if mirror else self.dut.export_words
        self.late = late
        ro = [r for r in regmap if r.access is Access.RO]
        self.stim_fields = Bench._fields([("addr", 16), ("we", 1), ("w_data", 32), ("stb", 1),
                                          ("lock", 1), ("commit", 1), ("rst", 1),
                                          *((r.name, r.width) for r in ro)])
        regs = list(dict.fromkeys(r.name for _, r, _ in self.words))
        self.out_fields = Bench._fields([("ack", 1), ("r_data", 32), ("ref_ack", 1),
                                         ("ref_r_data", 32),
                                         *((f"ram{j}", 32) for j in range(len(self.words))),
                                         *((n, regmap[n].width) for n in regs)])
        self.stim = Signal(sum(w for _, _, w in self.stim_fields))
        self.outs = Signal(sum(w for _, _, w in self.out_fields))

    pack = staticmethod(Bench.pack)
    unpack = Bench.unpack

    def elaborate(self, platform):
        m = Module()
        rst = Signal()
        m.submodules.dut = ResetInserter(rst)(self.dut)
        m.submodules.ref = ResetInserter(rst)(self.ref)
        ram = Memory(shape=32, depth=len(self.words),
                     init=self.dut.mirror_init if self.mirror else self.dut.export_init)
        m.submodules.ram = ram
        wr = ram.write_port()
        port = self.dut.mirror if self.mirror else self.dut.export
        if self.late:
            for name in ("valid", "index", "data"):
                late = Signal.like(getattr(port, name), name=f"late_{name}")
                m.d.sync += late.eq(getattr(port, name))
                m.d.comb += getattr(wr, {"valid": "en", "index": "addr"}.get(name, name)).eq(late)
        else:
            m.d.comb += [wr.en.eq(port.valid), wr.addr.eq(port.index), wr.data.eq(port.data)]
        words = []
        for j in range(len(self.words)):
            rd = ram.read_port(domain="comb")
            m.d.comb += rd.addr.eq(j)
            words.append(rd.data)
        for dut in (self.dut, self.ref):
            bus = dut.bus
            sinks = [bus.addr, bus.we, bus.w_data, bus.stb, bus.lock, dut.commit, rst]
            sinks += [_bits(getattr(dut, name)) for name, _, _ in self.stim_fields[7:]]
            m.d.comb += Cat(*sinks).eq(self.stim)
        for w in self.regmap.windows:
            for tag, dut in (("dut", self.dut), ("ref", self.ref)):
                mem = Memory(shape=32, depth=w.size,
                             init=[window_word(a) for a in range(w.size)])
                m.submodules[f"{tag}_{w.name}_mem"] = mem
                rd = mem.read_port()
                m.d.comb += [rd.addr.eq(getattr(dut, f"{w.name}_rd_addr")),
                             getattr(dut, f"{w.name}_rd_data").eq(rd.data)]
        m.d.comb += self.outs.eq(Cat(self.dut.bus.ack, self.dut.bus.r_data, self.ref.bus.ack,
                                     self.ref.bus.r_data, *words,
                                     *(_bits(getattr(self.ref, n))
                                       for n, _, _ in self.out_fields[4 + len(words):])))
        return m


def run_export(count=5000, *, seed=0, regmap=REGMAP, export, copy_last=(), commit_p=0.02,
               rst_p=0.002, late=False, mirror=False):
    """Random host traffic, frames, commits and resets (as :func:`run`) into a register file
    with ``export`` and one without: every clock the consumer RAM written from the export port
    must hold what the other's flip-flops hold (the exported registers' words in their read
    format), except for a word between a reset and its rewrite by the reset walk (the
    flip-flops take the reset value in the reset clock, the RAM from the walk: counted in
    ``excused``); the two files' ``ack`` and ``r_data`` must agree too.

    ``mirror``: ``export`` names immediate registers, mirrored instead (``RegisterFile(mirror=
    ...)``): the RAM written from the ``mirror`` port must hold in every clock what the
    flip-flops held in the clock before (one clock late, the documented difference).

    Returns
    -------
    dict
        ``mismatches`` (clocks with a difference), ``clocks``, ``changes`` (clocks in which an
        exported flip-flop word changed), ``commits`` (strobes with ``lock`` low), ``resets``,
        ``excused`` (word-clocks excused after a reset), ``first_mismatch``.
    """
    rng = random.Random(seed)
    bench = ExportBench(regmap, export=export, copy_last=copy_last, late=late, mirror=mirror)
    accesses = _accesses(regmap, count, rng)
    ro_regs = [r for r in regmap if r.access is Access.RO]
    words = bench.words
    # The walk writes exported word j (slot i) in clock 2 + i after the reset clock: excused
    # until then (clocks 1 … 2 + i after the reset clock).
    slot_of = {a: i for i, (a, _, _) in enumerate(bench.dut._slots)}
    rewrite = [2 + slot_of[a] + (1 if mirror else 0) for a, _, _ in words]
    fig = dict(mismatches=0, clocks=0, changes=0, commits=0, resets=0, excused=0,
               first_mismatch=None)

    async def testbench(ctx):
        seen = {"ack": 0, "stuck": 0}
        since_rst = None                # clocks since the last reset clock
        prev = None
        for cyc, _ in _with_status(_cycles(regmap, accesses, rng, seen, commit_p=commit_p,
                                           rst_p=rst_p), ro_regs, rng):
            ctx.set(bench.stim, bench.pack(bench.stim_fields, cyc))
            got = bench.unpack(bench.out_fields, ctx.get(bench.outs))
            now = [r.read_word(got[r.name], k) for _, r, k in words]
            want = prev if mirror and prev is not None else now
            bad = [j for j, (a, r, k) in enumerate(words)
                   if got[f"ram{j}"] != want[j]
                   and not (since_rst is not None and since_rst <= rewrite[j])]
            fig["excused"] += sum(1 for j in range(len(words))
                                  if since_rst is not None and since_rst <= rewrite[j])
            if bad or got["ack"] != got["ref_ack"] or got["r_data"] != got["ref_r_data"]:
                fig["mismatches"] += 1
                if fig["first_mismatch"] is None:
                    fig["first_mismatch"] = (
                        f"clock {fig['clocks']}: words "
                        f"{[(words[j][1].name, got[f'ram{j}'], want[j]) for j in bad]}, "
                        f"ack {got['ack']}/{got['ref_ack']}, "
                        f"r_data {got['r_data']:#x}/{got['ref_r_data']:#x}")
            fig["changes"] += prev is not None and now != prev
            prev = now
            seen["ack"] = got["ack"]
            fig["resets"] += cyc["rst"]
            fig["commits"] += cyc["commit"] and not cyc["lock"] and not cyc["rst"]
            since_rst = 0 if cyc["rst"] else (None if since_rst is None else since_rst + 1)
            fig["clocks"] += 1
            await ctx.tick()

    simulate(bench, [testbench], name="regs_export")
    return fig
