# Ref: issue 5 item 3 (trace buffer)
"""Clock-by-clock golden model of :class:`~foc_servo.hdl.scope.Scope` (behaviour in
``hdl/scope.py``): capture state machine, decimation, ring buffer, the time-shared source
multiplexer (channel ``c`` of a sample taken ``c`` clocks after its strobe and written into the
RAM one clock later, from the write register) and the read-back window of the single-port RAM (a
read in a write clock reads 0). ``ram`` is validated and kept but changes nothing: both RAMs
behave alike."""

import numpy as np

from ...hdl.scope import DEFAULT_SOURCES, ScopeState, TriggerSource, check_scope

__all__ = ["ScopeModel", "align_sample"]


def align_sample(raw, shape, width):
    """Source value ``raw`` (an integer of ``shape``) MSB-aligned to ``width`` raw bits."""
    bits = int(raw) & ((1 << shape.width) - 1)
    if shape.width >= width:
        return bits >> (shape.width - width)
    return bits << (width - shape.width)


class ScopeModel:
    """Model of :class:`~foc_servo.hdl.scope.Scope` (same parameters and validation).

    Attributes
    ----------
    mem : numpy.ndarray
        The ring, ``(depth, channels)`` raw samples.
    state, done, wr_ptr, filled, post_left, phase, slot : int
        The registers of the same names (``phase``: the channel multiplexed this clock when
        non-zero, ``slot`` its ring address).
    wr : tuple or None
        The write register: ``(slot, channel, sample)`` the RAM writes this clock, or ``None``.
    """

    def __init__(self, *, sources=DEFAULT_SOURCES, channels=4, depth=1024, width=16,
                 decim_width=16, ram="bram"):
        self.sources = check_scope(sources, channels, depth, width, decim_width, ram)
        self.ram = ram
        self.names = tuple(self.sources)
        self.channels, self.depth, self.width = channels, depth, width
        self.abits = depth.bit_length() - 1
        self.mem = np.zeros((depth, channels), dtype=np.int64)
        self.state = ScopeState.IDLE.value
        self.done = 0
        self.wr_ptr = self.filled = self.post_left = self.dcount = 0
        self.phase = self.slot = 0
        self.wr = None
        self.sel = [0] * channels
        self.decim = self.pre = 0
        self.trig_src = TriggerSource.HOST.value
        self.rd_data = 0
        self.captures = self.triggers_ignored = 0

    def sample(self, src, channel):
        """The sample ``channel`` records from the source values ``src`` (dict)."""
        code = self.sel[channel]
        if code < len(self.names):
            name = self.names[code]
            return align_sample(src[name], self.sources[name], self.width)
        return 0

    def sample_word(self, src):
        """The samples each channel would record for the source values ``src`` (dict)."""
        return [self.sample(src, c) for c in range(self.channels)]

    def read(self, index, channel):
        """The sample ``index`` (0 = oldest) of ``channel`` as the window shows it now."""
        if channel >= self.channels:
            return 0
        return int(self.mem[(index + self.wr_ptr) % self.depth, channel])

    def clock(self, inp):
        """``inp``: dict with ``src`` (dict of raw source values), ``sel`` (list), ``strobe``,
        ``decim``, ``pretrigger``, ``trig_src``, ``arm``, ``force``, ``trigger``, ``rd_addr`` for
        the current clock → dict ``state``, ``done``, ``pre_full``, ``rd_data`` seen in it;
        advance one clock."""
        idle = ScopeState.IDLE.value
        pre_s, post_s = ScopeState.PRE.value, ScopeState.POST.value
        full = self.filled >= self.pre
        busy = self.phase != 0
        out = {"state": self.state, "done": int(self.done and not busy and self.wr is None),
               "pre_full": int(self.state == pre_s and full), "rd_data": self.rd_data}

        capturing = self.state != idle
        strobe = bool(inp["strobe"]) and not busy       # ignored while a sample is written
        take = strobe and capturing and self.dcount == 0 and not inp["arm"]

        # The RAM's one port: the registered write of the clock before, or the read-back (word
        # registered, 0 in a write clock).
        addr = inp["rd_addr"]
        channel = addr >> self.abits
        phys = ((addr & (self.depth - 1)) + self.wr_ptr) % self.depth
        self.rd_data = (int(self.mem[phys, channel])
                        if channel < self.channels and self.wr is None else 0)
        if self.wr is not None:
            slot, chan, value = self.wr
            self.mem[slot, chan] = value
        self.wr = None                                  # loaded below by a write
        if inp["arm"]:
            self.phase = 0                               # channels not yet written are dropped
            self.state, self.done, self.filled, self.dcount = pre_s, 0, 0, 0
            self.sel = list(inp["sel"])
            self.decim, self.pre = inp["decim"], inp["pretrigger"]
            self.trig_src = inp["trig_src"]
            return out
        event = bool(inp["force"] or
                     (inp["trigger"] and self.trig_src == TriggerSource.EXTERNAL.value))
        if strobe and capturing:
            self.dcount = 0 if self.dcount >= self.decim else self.dcount + 1
        if busy:                                        # channel `phase` of the last sample
            self.wr = (self.slot, self.phase, self.sample(inp["src"], self.phase))
            self.phase = (self.phase + 1) % self.channels
        if take:                                        # channel 0 now, the others after
            self.wr = (self.wr_ptr, 0, self.sample(inp["src"], 0))
            self.slot, self.phase = self.wr_ptr, 1 % self.channels
            self.wr_ptr = (self.wr_ptr + 1) % self.depth
        if self.state == pre_s:
            if event and full:
                left = self.depth - self.pre - take
                if left == 0:
                    self.state, self.done = idle, 1
                    self.captures += 1
                else:
                    self.state, self.post_left = post_s, left
            else:
                if event:
                    self.triggers_ignored += 1
                if take and self.filled != self.depth - 1:
                    self.filled += 1
        elif self.state == post_s and take:
            self.post_left -= 1
            if self.post_left == 0:
                self.state, self.done = idle, 1
                self.captures += 1
        return out
