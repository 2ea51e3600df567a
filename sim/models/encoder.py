# Ref: SPEC.md §2.3 (encoder A/B/Z + Hall, ×4 position counter); §4 (synchronisers, glitch filters);
#      issue 6 item 7 (encoder/Hall plausibility check)
"""Bit-true, clock-by-clock golden model of :mod:`foc_servo.hdl.encoder`.

The blocks are stateful, so the models are small classes with a ``tick(...)`` method that takes
the inputs seen during one clock and returns the outputs after the clock edge (every output of
the gateware is a register or a function of registers only). The stateless pieces are vectorised
numpy functions: :func:`theta_exact` (the exact angle formula the drift check compares with),
:func:`hall_sector`, :func:`hall_code`.

:func:`front_end` runs :class:`EncoderFrontEndModel` over per-clock input arrays;
:func:`front_end_changes` runs it over a schedule of pin changes (a plant's sensor events),
skipping the clocks in which nothing can change, and returns the outputs where they change.
"""

import numpy as np

from ...hdl.encoder import (ANGLE, CPR_WIDTH, DIVISION_STEPS, HALL_CODES, angle_constants,
                            hall_boundaries, hall_centres, quadrature_phase)

__all__ = [
    "theta_exact", "hall_sector", "hall_code", "GlitchFilterModel", "QuadratureDecoderModel",
    "HallSensorModel", "HallPlausibilityModel", "EncoderFrontEndModel", "front_end",
    "front_end_changes", "change_strobes", "OUTPUTS",
]

#: Outputs of :class:`EncoderFrontEndModel` (the gateware member names).
OUTPUTS = ("count", "e", "theta", "step", "up", "a_rise", "illegal", "index", "aligned", "busy",
           "config_error", "hall_sector", "hall_valid", "hall_fault", "hall_edge", "hall_miss",
           "plausibility", "hall_error", "ready")

_TURN = ANGLE.turn
_CODE_TO_SECTOR = np.full(8, -1, dtype=np.int64)
for _k, _c in enumerate(HALL_CODES):
    _CODE_TO_SECTOR[_c] = _k


def theta_exact(e, cpr):
    """Exact electrical angle ``floor(e·2**16 / cpr)`` of an electrical position ``e`` in
    [0, cpr) (int64 arrays or integers)."""
    out = (np.asarray(e, dtype=np.int64) << ANGLE.width) // np.asarray(cpr, dtype=np.int64)
    return int(out) if np.ndim(out) == 0 else out


def hall_sector(code):
    """Sector 0 … 5 of Hall codes (bit 0 = H_a), −1 for the invalid codes 000 and 111."""
    out = _CODE_TO_SECTOR[np.asarray(code, dtype=np.int64) & 7]
    return int(out) if np.ndim(out) == 0 else out


def hall_code(theta):
    """Ideal Hall code at electrical angles ``theta`` (raw binary angles of 16 bits): sector
    ``floor(theta·6 / 2**16)``."""
    sector = (np.asarray(theta, dtype=np.int64) % ANGLE.turn) * 6 >> ANGLE.width
    out = np.asarray(HALL_CODES, dtype=np.int64)[sector]
    return int(out) if np.ndim(out) == 0 else out


class GlitchFilterModel:
    """Model of :class:`~foc_servo.hdl.encoder.GlitchFilter` (``width`` bits packed in an
    integer)."""

    def __init__(self, width=1):
        self.width = width
        self.o = 0
        self.rem = [0] * width

    def tick(self, i, length):
        o = self.o
        for k in range(self.width):
            ik, ok = (i >> k) & 1, (o >> k) & 1
            if ik == ok:
                self.rem[k] = length
            elif self.rem[k] <= 1:
                self.o ^= 1 << k
                self.rem[k] = length
            else:
                self.rem[k] -= 1
        return self.o


class HallSensorModel:
    """Model of :class:`~foc_servo.hdl.encoder.HallSensor`."""

    def __init__(self):
        self.centres = hall_centres(ANGLE.width)
        self.sector = 0
        self.theta = self.centres[0]
        self.valid = 0
        self.fault = 0

    def tick(self, h, offset, hold=0):
        self.fault = int(not hold and h in (0, 7))
        k = int(_CODE_TO_SECTOR[h])
        if k >= 0:
            self.sector = k
            self.theta = (self.centres[k] + offset) % _TURN
            self.valid = 1


class HallPlausibilityModel:
    """Model of :class:`~foc_servo.hdl.encoder.HallPlausibility`: the check as if it took all
    its inputs in one clock, run on the inputs delayed by the gateware's pipeline (``latency − 1``
    clocks) except ``tolerance`` and ``misses``, which the gateware's check takes in its own
    clock; ``error`` (the gateware's clock-2 register ``d_q``) is written one clock before the
    check, from the inputs delayed by one clock."""

    #: Clocks from the inputs to the outputs (``HallPlausibility.latency``).
    LATENCY = 3

    def __init__(self):
        self.bounds = hall_boundaries(ANGLE.width)
        self.sector_q = self.have_q = self.aligned_q = self.dir_q = self.d_q = 0
        self.ref_ok = self.count = 0
        self.edge = self.miss = self.fault = self.error = 0
        # The pipeline's reset state: inputs that make no edge and no jump.
        self._pipe = [dict(theta=0, aligned=0, restart=0, sector=0, valid=0, hold=0,
                           offset=0)] * (self.LATENCY - 1)

    def tick(self, *, theta, aligned, restart, sector, valid, hold, offset, tolerance=8192,
             misses=1):
        self._pipe.append(dict(theta=theta, aligned=aligned, restart=restart, sector=sector,
                               valid=valid, hold=hold, offset=offset))
        self._check(**self._pipe.pop(0), tolerance=tolerance, misses=misses)
        self._error(**self._pipe[0])

    def _edge(self, sector, hold):
        """``(edge, fwd, adjacent)`` of ``sector`` after the state of the last checked inputs."""
        edge = bool(self.have_q and not hold and sector != self.sector_q)
        fwd = sector == (0 if self.sector_q == 5 else self.sector_q + 1)
        bwd = sector == (5 if self.sector_q == 0 else self.sector_q - 1)
        return edge, fwd, fwd or bwd

    def _d(self, theta, sector, fwd, offset):
        return (theta - self.bounds[sector if fwd else self.sector_q] - offset) % _TURN

    def _error(self, *, theta, aligned, restart, sector, valid, hold, offset):
        # The gateware writes d of an edge between adjacent sectors into ``error`` one clock
        # before its check (its clock 2): the inputs that the next clock checks.
        edge, fwd, adjacent = self._edge(sector, hold)
        if edge and adjacent:
            d = self._d(theta, sector, fwd, offset)
            self.error = d - _TURN if d >= _TURN >> 1 else d

    def _check(self, *, theta, aligned, restart, sector, valid, hold, offset, tolerance, misses):
        turn, half = _TURN, _TURN >> 1

        def mag(x):
            return turn - x if x >= half else x

        edge, fwd, adjacent = self._edge(sector, hold)
        d = self._d(theta, sector, fwd, offset)
        dd = (d - self.d_q) % turn
        jump = bool(restart) or aligned != self.aligned_q
        abs_miss = bool(aligned) and mag(d) > tolerance
        rel_check = (not aligned and bool(self.ref_ok) and not jump and int(fwd) == self.dir_q
                     and adjacent)
        rel_miss = rel_check and mag(dd) > tolerance
        miss = edge and (not adjacent or abs_miss or rel_miss)
        passed = (edge and adjacent and (bool(aligned) or rel_check) and not abs_miss
                  and not rel_miss)

        need = 1 if misses == 0 else misses
        self.edge, self.miss = int(edge), int(miss)
        self.fault = int(miss and self.count + 1 >= need)
        if edge:
            self.dir_q, self.ref_ok = int(fwd), int(adjacent and not restart)
            if adjacent:
                self.d_q = d
        elif jump:
            self.ref_ok = 0
        if miss:
            self.count = min(self.count + 1, 15)
        elif passed:
            self.count = 0
        self.sector_q, self.have_q, self.aligned_q = sector, int(valid and not hold), aligned


class QuadratureDecoderModel:
    """Model of :class:`~foc_servo.hdl.encoder.QuadratureDecoder`, configuration sequencer and
    division timing included.

    The configuration sequence is modelled register by register (the division's working
    registers, each constant taken in the clock the gateware takes it, from the inputs of that
    clock), so the model follows the gateware also when an input changes in the middle of a
    sequence. ``lp_changed`` / ``z_changed`` (the strobes) default to a compare of the inputs
    with those of the previous clock (the first: the constructor's values): the register
    file's ``changed`` strobes."""

    IDLE = 0
    #: The gateware's ``timer`` values: ``pole_pairs`` read (1), the first constants (2), the
    #: step constants replaced and ``z_offset`` read (``TAKE_P``), ``z_offset < cpr`` (``TAKE_P
    #: + 1``), the commit (``COMMIT``).
    TAKE_P = DIVISION_STEPS + 3
    COMMIT = 2 * DIVISION_STEPS + 5

    def __init__(self, *, z_gate=None, lines=5000, pole_pairs=4, z_offset=0):
        m18 = (1 << CPR_WIDTH) - 1
        self.z_gate = z_gate
        self._in = (lines, pole_pairs, z_offset)
        qp, rp, qz, rz, self.valid = angle_constants(lines, pole_pairs, z_offset)
        cpr = 4 * lines
        self.qp, self.rp, self.qz = qp, rp, qz
        self.n_rp, self.n_pp, self.n_rz = (rp - cpr) & m18, (pole_pairs - cpr) & m18, \
            (rz - cpr) & m18
        self.cpr_z, self.cpr_m1, self.z_q, self.pp_c = cpr - z_offset, (cpr - 1) & m18, \
            z_offset, pole_pairs
        self.pp_ok = self.z_ok = 0
        self.timer = self.wr = self.wq = self.dividing = 0
        self.lp_run = self.lp_again = self.z_again = False
        self.a_prev = self.b_prev = self.zc_prev = 0
        self.count = self.em = self.thm = self.rm = 0
        self.step = self.up = self.a_rise = self.illegal = self.index = self.aligned = 0

    @property
    def busy(self):
        return int(self.timer != self.IDLE)

    @property
    def config_error(self):
        return int(not self.valid)

    @property
    def e(self):
        m18 = (1 << CPR_WIDTH) - 1
        return (self.em - self.cpr_z if self.em >= self.cpr_z else self.em + self.z_q) & m18

    @property
    def theta(self):
        carry = (self.rm + self.n_rz) >> CPR_WIDTH
        return (self.thm + self.qz + carry) % _TURN

    @staticmethod
    def _step(up, x, step, n_step, mask):
        """The gateware's modular step of ``x`` by ``±step`` (``n_step`` = step − cpr): the
        new value and the carry-in (up: the wrap; down: no wrap)."""
        wrap = ((x + n_step) >> CPR_WIDTH) & 1 if up else int(x < step)
        operand = n_step if wrap else step
        return ((x + operand) if up else (x - operand)) & mask, int(up == wrap)

    def tick(self, a, b, z, *, hold=0, lines=5000, pole_pairs=4, z_offset=0, realign=0,
             lp_changed=None, z_changed=None):
        m18, aw = (1 << CPR_WIDTH) - 1, ANGLE.width
        if lp_changed is None:
            lp_changed = (lines, pole_pairs) != self._in[:2]
        if z_changed is None:
            z_changed = z_offset != self._in[2]
        self._in = (lines, pole_pairs, z_offset)
        cpr = (4 * lines) & m18
        t, busy = self.timer, self.timer != self.IDLE

        # Configuration sequencer (the gateware's registers, from this clock's inputs).
        commit = busy and t == self.COMMIT
        lp_run, lp_again, z_again = self.lp_run, self.lp_again, self.z_again
        timer, wr, wq, dividing = t, self.wr, self.wq, self.dividing
        if not busy:
            req_lp = lp_changed or self.lp_again
            if req_lp or z_changed or self.z_again:
                lp_run, lp_again, z_again, timer, wr = req_lp, False, False, 1, 0
        else:
            if lp_changed:
                if t == 1:
                    lp_run = True
                else:
                    lp_again = True
            if z_changed and t > self.TAKE_P:
                z_again = True
            timer = self.IDLE if commit else t + 1
        if t in (2, self.TAKE_P + 1):
            dividing = 1
        elif t in (self.TAKE_P - 1, self.COMMIT - 1):
            dividing = 0
        sub_t = self.wr << 1 if self.dividing else self.wr
        diff = sub_t - cpr
        fits = int(diff >= 0)
        if self.dividing:
            wr = (diff if fits else sub_t) & m18
            wq = ((self.wq << 1) | fits) & ((1 << aw) - 1)
        new = {}
        if t == 1:
            new.update(cpr_m1=~diff & m18)
            wr = pole_pairs
        elif t == 2:
            new.update(n_pp=diff & m18, pp_c=self.wr & 0xFF, pp_ok=int(diff < 0))
        elif t == self.TAKE_P:
            new.update(n_rp=diff & m18, qp=self.wq, rp=self.wr)
            wr = z_offset
        elif t == self.TAKE_P + 1:
            new.update(z_ok=int(diff < 0))
        new_valid = lines != 0 and pole_pairs != 0 and self.pp_ok and self.z_ok
        restart = commit and (self.lp_run or self.lp_again or not new_valid)
        if commit:
            new.update(z_q=z_offset, qz=self.wq, n_rz=diff & m18, valid=bool(new_valid),
                       cpr_z=cpr - z_offset)
        counting = self.valid and not (busy and self.lp_run) and not self.lp_again

        # Quadrature decoding (from the registers before this edge).
        delta = (quadrature_phase(a, b) - quadrature_phase(self.a_prev, self.b_prev)) % 4
        fwd = not hold and delta == 1
        bwd = not hold and delta == 3
        zc = z if self.z_gate is None else int(z and ((a << 1) | b) == self.z_gate)
        index = not hold and zc and not self.zc_prev
        step, a_rise = int(fwd or bwd), int((fwd or bwd) and a and not self.a_prev)
        illegal = int(not hold and delta == 2)

        count, em, thm, rm, aligned = self.count, self.em, self.thm, self.rm, self.aligned
        if counting and (fwd or bwd):
            if fwd:
                count = 0 if self.count == self.cpr_m1 else (self.count + 1) & m18
            else:
                count = self.cpr_m1 if self.count == 0 else (self.count - 1) & m18
            em, _ = self._step(fwd, self.em, self.pp_c, self.n_pp, m18)
            rm, cin = self._step(fwd, self.rm, self.rp, self.n_rp, m18)
            qp = self.qp if fwd else self.qp ^ ((1 << aw) - 1)
            thm = (self.thm + qp + cin) % _TURN
        if self.valid and index and (not self.aligned or realign):
            aligned, count, em, thm, rm = 1, 0, 0, 0, 0
        elif realign:
            aligned = 0
        if restart:
            aligned, count, em, thm, rm = 0, 0, 0, 0, 0

        for k, v in new.items():
            setattr(self, k, v)
        self.timer, self.wr, self.wq, self.dividing = timer, wr, wq, dividing
        self.lp_run, self.lp_again, self.z_again = lp_run, lp_again, z_again
        self.count, self.em, self.thm, self.rm, self.aligned = count, em, thm, rm, aligned
        self.step, self.a_rise, self.illegal, self.index = step, a_rise, illegal, int(index)
        if step:
            self.up = int(fwd)
        self.a_prev, self.b_prev, self.zc_prev = a, b, zc


class EncoderFrontEndModel:
    """Model of :class:`~foc_servo.hdl.encoder.EncoderFrontEnd`."""

    SYNC_STAGES = 2

    def __init__(self, *, max_length=255, z_gate=None, lines_init=5000, pole_pairs_init=4,
                 z_offset_init=0):
        self.max_length = max_length
        self.sync = [0] * self.SYNC_STAGES
        self.filter = GlitchFilterModel(6)
        self.decoder = QuadratureDecoderModel(z_gate=z_gate, lines=lines_init,
                                              pole_pairs=pole_pairs_init, z_offset=z_offset_init)
        self.hall = HallSensorModel()
        self.plausibility = HallPlausibilityModel()
        self.settle = 0
        self.ready = 0
        self.theta_q = self.aligned_q = 0

    def tick(self, pins, *, length=0, lines=5000, pole_pairs=4, z_offset=0, hall_offset=0,
             realign=0, hall_tolerance=8192, hall_misses=1, lp_changed=None, z_changed=None):
        """One clock. ``pins`` packs A, B, Z, H_a, H_b, H_c in bits 0 … 5; ``lp_changed`` /
        ``z_changed`` default to the changes of the inputs (:meth:`QuadratureDecoderModel.tick`).
        """
        hold = not self.ready
        d, h = self.decoder, self.hall
        self.plausibility.tick(theta=d.theta, aligned=d.aligned,
                               restart=int(d.busy or d.config_error), sector=h.sector,
                               valid=h.valid, hold=hold, offset=hall_offset,
                               tolerance=hall_tolerance, misses=hall_misses)
        self.theta_q, self.aligned_q = d.theta, d.aligned     # registered (theta_latency)
        flt = self.filter.o
        self.decoder.tick(flt & 1, (flt >> 1) & 1, (flt >> 2) & 1, hold=hold, lines=lines,
                          pole_pairs=pole_pairs, z_offset=z_offset, realign=realign,
                          lp_changed=lp_changed, z_changed=z_changed)
        self.hall.tick(flt >> 3, hall_offset, hold=hold)
        self.filter.tick(self.sync[-1], length)
        self.sync = [pins] + self.sync[:-1]
        if not self.ready:
            if self.settle + 1 >= length + 4:
                self.ready = 1
            self.settle += 1

    def values(self):
        """The outputs as a tuple in the order of :data:`OUTPUTS`."""
        d, h, p = self.decoder, self.hall, self.plausibility
        return (d.count, d.e, self.theta_q if self.aligned_q else h.theta, d.step, d.up, d.a_rise,
                d.illegal, d.index, d.aligned, d.busy, d.config_error, h.sector, h.valid,
                h.fault, p.edge, p.miss, p.fault, p.error, self.ready)

    def outputs(self):
        return dict(zip(OUTPUTS, self.values()))


def change_strobes(lines, pole_pairs, z_offset, *, init=(5000, 4, 0)):
    """The decoder's ``lp_changed`` and ``z_changed`` for per-clock configuration arrays (a
    register file's ``changed`` strobes): high in each clock whose value differs from the
    previous clock's (clock 0: from ``init``, the gateware's reset values)."""
    cols = [np.asarray(v, dtype=np.int64) for v in (lines, pole_pairs, z_offset)]
    n = max(c.size for c in cols)
    cols = [np.broadcast_to(c, (n,)) if c.ndim == 0 else c for c in cols]
    ch = [np.diff(c, prepend=i) != 0 for c, i in zip(cols, init)]
    return (ch[0] | ch[1]).astype(np.int64), ch[2].astype(np.int64)


_CONFIG = ("length", "lines", "pole_pairs", "z_offset", "hall_offset", "realign",
           "hall_tolerance", "hall_misses")
_DEFAULTS = {"length": 0, "lines": 5000, "pole_pairs": 4, "z_offset": 0, "hall_offset": 0,
             "realign": 0, "hall_tolerance": 8192, "hall_misses": 1}


def front_end(pins, *, max_length=255, z_gate=None, **config):
    """Run :class:`EncoderFrontEndModel` over ``n`` clocks.

    Parameters
    ----------
    pins : int array (n,)
        A, B, Z, H_a, H_b, H_c in bits 0 … 5, one entry per clock.
    **config : int or int array (n,)
        ``length``, ``lines``, ``pole_pairs``, ``z_offset``, ``hall_offset``, ``realign``,
        ``hall_tolerance``, ``hall_misses``: a constant or one value per clock (defaults as the
        gateware's).

    Returns
    -------
    dict of int64 arrays (n + 1,)
        Every output of :data:`OUTPUTS`; entry 0 is the reset state, entry ``t + 1`` the value
        after clock edge ``t``.
    """
    unknown = set(config) - set(_CONFIG)
    if unknown:
        raise TypeError(f"front_end got unknown configuration {sorted(unknown)!r}")
    pins = np.asarray(pins, dtype=np.int64)
    n = pins.size
    cols = {}
    for key in _CONFIG:
        v = np.asarray(config.get(key, _DEFAULTS[key]), dtype=np.int64)
        cols[key] = (np.broadcast_to(v, (n,)) if v.ndim == 0 else v).tolist()
    model = EncoderFrontEndModel(max_length=max_length, z_gate=z_gate)
    out = {k: np.empty(n + 1, dtype=np.int64) for k in OUTPUTS}
    first = model.outputs()
    for k in OUTPUTS:
        out[k][0] = first[k]
    pin_list = pins.tolist()
    arrays = [out[k] for k in OUTPUTS]
    for t in range(n):
        model.tick(pin_list[t], **{key: cols[key][t] for key in _CONFIG})
        o = model.outputs()
        for arr, k in zip(arrays, OUTPUTS):
            arr[t + 1] = o[k]
    return out


def front_end_changes(clocks, words, until, *, max_length=255, z_gate=None, **config):
    """Run :class:`EncoderFrontEndModel` over a schedule of pin changes, clock-exact, fast.

    The pins hold ``words[i]`` from clock ``clocks[i]`` on (``clocks`` increasing, the first 0:
    the levels at reset). With the configuration constant, once the pins have been still for
    ``max(length, 1) + 8`` clocks (two synchroniser flops, the filter, the decoder, the
    three-clock plausibility check and their strobes settle in ``max(length, 1) + 7``) and no
    configuration change is in progress, no state changes until the next pin change: those
    clocks are skipped. So the cost is ``max(length, 1) + 8`` model clocks per edge, not one
    per clock (a 1000 r/min run of a 5000-line encoder at 50 MHz at ``length`` 4: 12 model
    clocks per 150 real ones).

    Parameters
    ----------
    clocks, words : int arrays
        Pin-change schedule; words pack A, B, Z, H_a, H_b, H_c in bits 0 … 5.
    until : int
        Clocks to run (the last one is ``until − 1``).
    **config : int
        As :func:`front_end`, constants only.

    Returns
    -------
    dict of int64 arrays
        ``clock`` and every output of :data:`OUTPUTS`, one row per clock whose outputs differ
        from the previous clock's (the first row: clock 0, the reset state); the outputs are
        those seen during that clock (``front_end``'s entry ``clock``).
    """
    unknown = set(config) - set(_CONFIG)
    if unknown:
        raise TypeError(f"front_end_changes got unknown configuration {sorted(unknown)!r}")
    cfg = {k: int(config.get(k, _DEFAULTS[k])) for k in _CONFIG}
    clocks = np.asarray(clocks, dtype=np.int64)
    words = np.asarray(words, dtype=np.int64)
    if clocks.size == 0 or clocks[0] != 0 or np.any(np.diff(clocks) <= 0):
        raise ValueError("front_end_changes clocks must be increasing and start at 0")
    settle = max(cfg["length"], 1) + 5 + HallPlausibilityModel.LATENCY
    model = EncoderFrontEndModel(max_length=max_length, z_gate=z_gate)
    times, rows = [], []

    def record(t):
        v = model.values()
        if v != rows[-1]:
            times.append(t)
            rows.append(v)

    change_at = clocks.tolist() + [until]
    word_list = words.tolist()
    t = 0
    times.append(0)
    rows.append(model.values())
    for i, word in enumerate(word_list):
        end = min(change_at[i + 1], until)
        still = 0
        while t < end:
            if still >= settle and model.ready and not model.decoder.busy:
                t = end                 # nothing changes until the next pin change
                break
            model.tick(word, **cfg)
            t += 1
            still += 1
            record(t)
        if t >= until:
            break
    table = np.array(rows, dtype=np.int64).reshape(len(rows), len(OUTPUTS))
    clock = np.asarray(times, dtype=np.int64)
    keep = clock < until
    return {"clock": clock[keep], **{k: table[keep, i] for i, k in enumerate(OUTPUTS)}}
