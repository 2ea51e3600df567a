# Ref: paper §3 (on-line adjustable parameters); issue 5 item 1; hdl/bus.py (register bus)
"""Clock-by-clock model of :class:`foc_servo.hdl.regs.RegisterFile`, shadowing included.

All values are unsigned bit patterns of the register width (``Register.raw`` gives the signed
value). Per clock: :meth:`RegisterFileModel.outputs` are the register file's outputs during the
clock (registered state, plus the combinational window read data), then
:meth:`RegisterFileModel.step` takes that clock's inputs and computes the state of the next.
"""

from amaranth.utils import ceil_log2

from ...hdl.bus import Status
from ...hdl.fixed import check_choice
from ...hdl.regmap import REGMAP, Access, RegMap
from ...hdl.regs import STAGINGS, export_words, ram_slots, staging_slots

__all__ = ["RegisterFileModel"]


class RegisterFileModel:
    """Bit-true model of the register file built from ``regmap``.

    Attributes
    ----------
    staged : dict
        Staging value of every ``rw`` register (for an immediate one also the active value).
    active : dict
        Active value (the Out member) of every ``rw`` register but the exported ones (of a
        ``derived`` one: ``derived[name].const`` of its raw value).
    strobes : dict
        Strobe outputs during the current clock.
    ack, status, r_data_reg, win_hit
        Bus reply registers (``r_data_reg`` is the register behind the window mux).
    pending, status_p, sel, win_pend
        The access's first-clock registers (t): the read multiplexer runs in t + 1 on the word
        ``sel`` (``(register, k)`` or ``None``), ``ack`` and the reply show in t + 2. (The
        gateware registers a word select and looks the status up from it in t + 1; deciding
        ``status_p`` in t gives the same bus reply.)
    mem, rd_data, run, walk, cnt, load, load_walk, dst, slot, wr_pend, stage_pend, stage_hit
        ``staging="bram"``: the staging RAM (slots: the copied ones, then the immediate
        registers' words; from ``base`` the reset values, then the const words), its read data
        register, and the copy / reset-walk sequencer and access registers of
        :class:`~foc_servo.hdl.regs.RegisterFile` (same names; ``slot`` is the access's RAM
        word). ``staged`` then holds only the immediate registers (whose reads, and the const
        words', come from the RAM); :meth:`staged_value` reads any register's staging value. (The
        gateware's slot is looked up in t + 1 from its word select, not registered; its copy
        loads are enabled by a one-hot shift register rather than ``dst``: the same clocks; with
        ``export`` its compare after a run of exported slots also fires in the reset walk, whose
        loads write reset values into active words that hold them, which the model leaves out.)
    exp_on, exp_index
        ``export``: whether ``dst`` is an exported word and its export index, set with ``dst``;
        :meth:`export_port` is the ``export`` port during the clock, :attr:`export_walk` the
        ``export_walk`` output.
    """

    def __init__(self, regmap=REGMAP, *, staging="ff", copy_last=(), export=(), derived=None):
        if not isinstance(regmap, RegMap):
            raise TypeError(f"RegisterFileModel regmap must be a RegMap, not {regmap!r}")
        check_choice("RegisterFileModel", "staging", staging, STAGINGS)
        self.regmap = regmap
        self.staging = staging
        # derived (RegisterFile's): register name → the active value from the raw bits.
        self._derive = {n: d.const for n, d in (derived or {}).items()}
        self._words = {addr: (r, k) for addr, r, k in regmap.words()}
        self._rw = [r for r in regmap if r.access is Access.RW]
        self._shadowed = [r.name for r in self._rw if r.shadow is not None]
        self.bram = staging == "bram"
        self.slots = staging_slots(regmap, copy_last) if self.bram else []
        self.copied = len(self.slots)
        consts = []
        if self.bram:                   # the immediate words after the copied ones; consts
            # (the copied ones from this module's staging_slots: a test reorders them)
            self.slots += ram_slots(regmap, copy_last)[self.copied:]
            consts = [(a, r, k) for a, r, k in regmap.words() if r.access is Access.CONST]
        self._slot_of = {addr: i for i, (addr, _, _) in enumerate(self.slots)}
        n = len(self.slots)
        self.base = 1 << ceil_log2(n) if n else 0
        self._ram_addr = {**self._slot_of, **{a: self.base + n + j
                                               for j, (a, _, _) in enumerate(consts)}}
        resets = [r.read_word(r.bits(r.reset), k) for _, r, k in self.slots]
        self.mem = (resets + [0] * (self.base - n) + resets
                    + [r.read_word(r.bits(r.reset), k) for _, r, k in consts])
        self.commit_clocks = self.copied + 1
        self.export = tuple(export)
        self.export_words = export_words(regmap, self.export)
        self._export_of = {self._slot_of[a]: j for j, (a, _, _) in enumerate(self.export_words)}
        self.reset()

    def reset(self):
        """The state after a domain reset (the staging RAM keeps its contents)."""
        regmap = self.regmap
        self.active = {r.name: r.bits(r.reset) for r in self._rw}
        self.staged = {n: v for n, v in self.active.items()
                       if not (self.bram and n in self._shadowed)}
        for n in self.export:
            del self.active[n]
        for n, f in self._derive.items():
            self.active[n] = f(self.active[n])
        self.strobes = {r.name: 0 for r in regmap if r.access is Access.STROBE}
        self.ack = 0
        self.status = Status.OK.value
        self.r_data_reg = 0
        self.win_hit = {w.name: 0 for w in regmap.windows}
        self.pending = 0
        self.status_p = Status.OK.value
        self.sel = None
        self.win_pend = dict(self.win_hit)
        # staging="bram": the copy / reset-walk sequencer and the RAM's ports.
        self.run = self.walk = int(self.bram)
        self.cnt = self.dst = self.slot = 0
        self.load = self.load_walk = 0
        self.wr_pend = self.stage_pend = self.stage_hit = 0
        self.rd_data = 0
        self.exp_on = self.exp_index = 0

    def export_port(self):
        """The ``export`` port during this clock: ``(valid, index, data)``; ``(0, 0, 0)`` when
        ``valid`` is low (the gateware's ``index`` and ``data`` then mean nothing: ``data`` is
        the RAM's read data, whose address the model does not follow outside reads it uses)."""
        if self.load and self.exp_on:
            return 1, self.exp_index, self.rd_data
        return 0, 0, 0

    @property
    def export_walk(self):
        """The ``export_walk`` output during this clock: the reset walk reads, or loads its last
        word (``export`` only)."""
        return int(bool(self.walk or self.load_walk))

    @property
    def busy(self):
        """A copy or the reset walk is reading the staging RAM (accesses held off)."""
        return bool(self.run)

    def r_data(self, window_data=None):
        """``bus.r_data`` during this clock; ``window_data`` maps a window name to its
        ``rd_data`` input."""
        out = self.r_data_reg
        if self.stage_hit:
            out = self.rd_data
        for w in self.regmap.windows:
            if self.win_hit[w.name]:
                out = (window_data or {}).get(w.name, 0)
        return out

    def _window(self, addr):
        for w in self.regmap.windows:
            if w.addr <= addr < w.addr + w.size:
                return w
        return None

    def step(self, *, stb, addr, we, w_data, lock=0, commit=0, ro=None, rst=0):
        """Advance one clock with these inputs; ``ro`` maps read-only register names to their
        input bits in this clock (missing: 0); ``rst`` a domain reset in this clock. Returns the
        :class:`~foc_servo.hdl.bus.Status` value the access gets (``None`` if no access
        started). With ``staging="bram"``, :attr:`started` tells whether a copy started."""
        self.started = False
        if rst:
            self.reset()
            return None
        if self.bram:
            start = bool(commit) and not lock and not self.run and not self.pending
            reading = start or bool(self.run)
            self.started = start
        else:
            reading = False
        access = bool(stb) and not self.pending and not self.ack and not reading
        if self.bram:
            self._stage_step(reading, w_data)
        self.ack = self.pending
        for n in self.strobes:
            self.strobes[n] = 0
        if commit and not lock and not self.bram:
            for n in self._shadowed:
                self.active[n] = self.staged[n]
        if self.pending:                      # t + 1: the read multiplexer, status inputs now
            self.status = self.status_p
            self.win_hit = dict(self.win_pend)
            self.stage_hit = self.stage_pend
            self.r_data_reg = 0
            if self.sel is not None:
                r, k = self.sel
                if r.access is Access.RW:
                    bits = self.staged[r.name]
                elif r.access is Access.RO:
                    bits = r.bits((ro or {}).get(r.name, 0))
                elif r.access is Access.CONST:
                    bits = r.bits(r.reset)
                else:
                    bits = 0
                self.r_data_reg = r.read_word(bits, k)
        self.pending = int(access)
        self.stage_pend = 0
        if not access:
            return None
        self.status_p, self.sel = Status.BAD_ADDRESS.value, None
        for n in self.win_pend:
            self.win_pend[n] = 0
        hit = self._words.get(addr)
        if hit is not None:
            r, k = hit
            if we:
                if r.access is Access.STROBE:
                    self.status_p = Status.OK.value
                    self.strobes[r.name] = w_data & 1
                elif r.access is Access.RW:
                    self.status_p = Status.OK.value
                    if addr in self._slot_of:           # "bram": the RAM in t + 1
                        self.slot = self._slot_of[addr]
                        self.wr_pend = 1
                    if r.shadow is None or not self.bram:
                        self.staged[r.name] = r.write_word(self.staged[r.name], k, w_data)
                    if r.shadow is None:
                        self.active[r.name] = self._derive.get(r.name, int)(
                            self.staged[r.name])
                else:
                    self.status_p = Status.READ_ONLY.value
            else:
                self.status_p = Status.OK.value
                if addr in self._ram_addr:
                    self.slot = self._ram_addr[addr]
                    self.stage_pend = 1
                else:
                    self.sel = (r, k)
        else:
            w = self._window(addr)
            if w is not None:
                if we:
                    self.status_p = Status.READ_ONLY.value
                else:
                    self.status_p = Status.OK.value
                    self.win_pend[w.name] = 1
        return self.status_p

    def _stage_step(self, reading, w_data):
        """``staging="bram"``: the staging RAM's read and write in this clock and the copy /
        reset-walk sequencer (all from the state at the start of the clock)."""
        n = len(self.slots)
        raddr = self.slot if self.pending else self.cnt + (self.base if self.walk else 0)
        new_rd = self.mem[raddr]                      # read before this clock's write
        if self.load:
            if self.load_walk:
                self.mem[self.dst] = self.rd_data
            elif self.dst not in self._export_of:     # a copied slot (exported: on the port)
                _, r, k = self.slots[self.dst]
                if r.name in self._derive:            # (one word)
                    self.active[r.name] = self._derive[r.name](r.write_word(0, 0, self.rd_data))
                else:
                    self.active[r.name] = r.write_word(self.active[r.name], k, self.rd_data)
        if self.wr_pend:                              # t + 1 of a write: w_data still held
            _, r, k = self.slots[self.slot]
            self.mem[self.slot] = r.read_word(r.write_word(0, k, w_data), k)
        self.rd_data = new_rd
        self.wr_pend = 0
        if reading:
            self.load, self.load_walk, self.dst = 1, self.walk, self.cnt
            self.exp_on = int(self.cnt in self._export_of)
            self.exp_index = self._export_of.get(self.cnt, 0)
            if self.cnt == (n if self.walk else self.copied) - 1:
                self.cnt, self.run, self.walk = 0, 0, 0
            else:
                self.cnt, self.run = self.cnt + 1, 1
        else:
            self.load = self.load_walk = 0

    def staged_value(self, name):
        """What a read of ``rw`` register ``name`` returns (its staging value) as bits."""
        r = self.regmap[name]
        if not (self.bram and r.shadow is not None):
            return self.staged[name]
        bits = 0
        for k in range(r.words):
            bits = r.write_word(bits, k, self.mem[self._slot_of[r.addr + k]])
        return bits
