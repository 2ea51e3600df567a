# Ref: paper §3 (on-line adjustable parameters); issue 5 item 1; hdl/bus.py (register bus)
"""Clock-by-clock model of :class:`foc_servo.hdl.regs.RegisterFile`, shadowing included.

All values are unsigned bit patterns of the register width (``Register.raw`` gives the signed
value). Per clock: :meth:`RegisterFileModel.outputs` are the register file's outputs during the
clock (registered state, plus the combinational window read data), then
:meth:`RegisterFileModel.step` takes that clock's inputs and computes the state of the next.
"""

from ...hdl.bus import Status
from ...hdl.regmap import REGMAP, Access, RegMap

__all__ = ["RegisterFileModel"]


class RegisterFileModel:
    """Bit-true model of the register file built from ``regmap``.

    Attributes
    ----------
    staged : dict
        Staging value of every ``rw`` register (for an immediate one also the active value).
    active : dict
        Active value (the Out member) of every ``rw`` register.
    strobes : dict
        Strobe outputs during the current clock.
    ack, status, r_data_reg, win_hit
        Bus reply registers (``r_data_reg`` is the register behind the window mux).
    pending, status_p, sel, win_pend
        The access's first-clock registers (t): the read multiplexer runs in t + 1 on the word
        ``sel`` (``(register, k)`` or ``None``), ``ack`` and the reply show in t + 2.
    """

    def __init__(self, regmap=REGMAP):
        if not isinstance(regmap, RegMap):
            raise TypeError(f"RegisterFileModel regmap must be a RegMap, not {regmap!r}")
        self.regmap = regmap
        self._words = {addr: (r, k) for addr, r, k in regmap.words()}
        self._rw = [r for r in regmap if r.access is Access.RW]
        self._shadowed = [r.name for r in self._rw if r.shadow is not None]
        self.staged = {r.name: r.bits(r.reset) for r in self._rw}
        self.active = dict(self.staged)
        self.strobes = {r.name: 0 for r in regmap if r.access is Access.STROBE}
        self.ack = 0
        self.status = Status.OK.value
        self.r_data_reg = 0
        self.win_hit = {w.name: 0 for w in regmap.windows}
        self.pending = 0
        self.status_p = Status.OK.value
        self.sel = None
        self.win_pend = dict(self.win_hit)

    def r_data(self, window_data=None):
        """``bus.r_data`` during this clock; ``window_data`` maps a window name to its
        ``rd_data`` input."""
        out = self.r_data_reg
        for w in self.regmap.windows:
            if self.win_hit[w.name]:
                out = (window_data or {}).get(w.name, 0)
        return out

    def _window(self, addr):
        for w in self.regmap.windows:
            if w.addr <= addr < w.addr + w.size:
                return w
        return None

    def step(self, *, stb, addr, we, w_data, lock=0, commit=0, ro=None):
        """Advance one clock with these inputs; ``ro`` maps read-only register names to their
        input bits in this clock (missing: 0). Returns the :class:`~foc_servo.hdl.bus.Status`
        value the access gets (``None`` if no access started)."""
        access = bool(stb) and not self.pending and not self.ack
        self.ack = self.pending
        for n in self.strobes:
            self.strobes[n] = 0
        if commit and not lock:
            for n in self._shadowed:
                self.active[n] = self.staged[n]
        if self.pending:                      # t + 1: the read multiplexer, status inputs now
            self.status = self.status_p
            self.win_hit = dict(self.win_pend)
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
                    self.staged[r.name] = r.write_word(self.staged[r.name], k, w_data)
                    if r.shadow is None:
                        self.active[r.name] = self.staged[r.name]
                else:
                    self.status_p = Status.READ_ONLY.value
            else:
                self.status_p = Status.OK.value
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
