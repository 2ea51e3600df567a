# Ref: SPEC.md §2.3 (paper Fig. 6): M/T speed, n = ΔM·60·f_TCLK/(P_n·ΔT), D_n = k·ΔM/ΔT
"""Bit-true, event-driven golden model of :class:`foc_servo.hdl.mt_speed.MTSpeed`, the ``k``
helper, and an ideal-encoder edge generator.

The model works on integer clock timestamps: it visits only the clocks where something happens
(an edge strobe, an update strobe, the division's result, a reference expiry) and applies there
exactly the gateware's next-state function; in between only TC advances, which is a function of
the clock number (``TC = floor(cycle / tclk_ratio) mod 2**tc_width``, cycle 0 = first clock after
reset). So it reproduces every output of the gateware (value and clock) for runs of millions of
clocks at the cost of the events only: this is what computes the error table over 0.2 …
10 000 r/min, after being checked against the gateware cycle for cycle in
``tests/test_mt_speed.py``.
"""

import math
from dataclasses import dataclass

import numpy as np

from ...hdl.regmap import MT_EDGES_PER_LINE

__all__ = ["MTParams", "k_for", "fresh_speed", "simulate", "ideal_encoder_edges", "STOPPED",
           "BOUND", "FRESH"]

STOPPED, BOUND, FRESH = 0, 1, 2     # WindowMode values


def k_for(lines=5000, tclk_hz=1e6, full_scale_rpm=6000, *, out_width=32, edge_mode="a_rising",
          k_width=None):
    """The ``k`` register value: ``round(60·2**(out_width−1)·f_TCLK / (P·N_M))``.

    ``P = lines·edges_per_line`` (1 for ``"a_rising"``, 4 for ``"x4"``) counted edges per
    revolution, ``N_M = full_scale_rpm`` (r/min) the speed that reads as 1.0 in Q1.(out_width−1).
    Pass the *actual* f_TCLK (:attr:`MTSpeed.tclk_hz`).

    Raises
    ------
    ValueError
        If an argument is not positive, ``edge_mode`` is unknown, ``k`` rounds to 0, or does not
        fit ``k_width`` bits.
    """
    if edge_mode not in ("a_rising", "x4"):
        raise ValueError(f"edge_mode must be 'a_rising' or 'x4', not {edge_mode!r}")
    for name, value in (("lines", lines), ("tclk_hz", tclk_hz),
                        ("full_scale_rpm", full_scale_rpm)):
        if not value > 0:
            raise ValueError(f"{name} must be positive, not {value!r}")
    epl = MT_EDGES_PER_LINE[edge_mode]
    k = round(60 * (1 << (out_width - 1)) * tclk_hz / (lines * epl * full_scale_rpm))
    if k < 1:
        raise ValueError(f"k for {lines} lines, f_TCLK {tclk_hz:g} Hz, {full_scale_rpm:g} r/min "
                         f"rounds to 0: raise f_TCLK or out_width")
    if k_width is not None and k >= 1 << k_width:
        raise ValueError(f"k {k} for {lines} lines, f_TCLK {tclk_hz:g} Hz, {full_scale_rpm:g} "
                         f"r/min does not fit k_width {k_width} bits")
    return k


@dataclass(frozen=True)
class MTParams:
    """The gateware parameters the model needs (:meth:`of` reads them off an :class:`MTSpeed`)."""
    tclk_ratio: int = 1
    tc_width: int = 32
    out_width: int = 16
    k_width: int = 32
    m_width: int = 16

    @classmethod
    def of(cls, dut):
        return cls(dut.tclk_ratio, dut.tc_width, dut.out_width, dut.k_width, dut.m_width)

    @classmethod
    def config(cls, *, clk_hz=50e6, tclk_hz=None, tc_width=32, out_width=32, k_width=None,
               m_width=16):
        """The parameters of ``MTSpeed(**same arguments)`` without building it (no checks)."""
        ratio = 1 if tclk_hz is None else max(1, round(clk_hz / tclk_hz))
        return cls(ratio, tc_width, out_width, out_width + 16 if k_width is None else k_width,
                   m_width)

    def tclk_hz(self, clk_hz):
        """Actual f_TCLK for this system clock."""
        return clk_hz / self.tclk_ratio

    @property
    def quotient_width(self):
        """Quotient bits of the unsigned division: ``min(out_width − 1, k_width + m_width − 1)``."""
        return min(self.out_width - 1, self.k_width + self.m_width - 1)

    @property
    def divide_steps(self):
        """Clocks of the division: one per quotient bit, plus the saturation step."""
        return self.quotient_width + 1

    @property
    def k_chunks(self):
        """Clocks of the product ``k·|ΔM|``: one per 16 bits of ``k``."""
        return -(-self.k_width // 16)

    @property
    def latency(self):
        """:attr:`MTSpeed.latency`: snapshot, first partial product, ``k_chunks`` carry adds,
        ``divide_steps``, output register."""
        return 2 + self.k_chunks + self.divide_steps + 1


def _magnitude(n, d, s_max):
    """The unsigned division ``n / d`` (n, d >= 0) truncated and saturated to ``s_max`` (the
    narrow quotient; ``d = 0`` saturates)."""
    return s_max if d == 0 else min(n // d, s_max)


def fresh_speed(k, dm, dt, *, out_width):
    """The ``speed`` of a fresh window with operands ``k``, ``ΔM = dm``, ``ΔT = dt`` (all
    integers, ``k, dt >= 0``), as the gateware computes it: the unsigned division of ``k·|ΔM|``
    by ΔT, truncated and saturated to ``2**(out_width − 1) − 1`` (ΔT = 0 saturates), then the sign
    of ΔM; a net-zero window (ΔM = 0) reads 0 whatever ΔT."""
    mag = 0 if dm == 0 else _magnitude(k * abs(dm), dt, (1 << (out_width - 1)) - 1)
    return -mag if dm < 0 else mag


def simulate(edge_cycles, edge_neg, update_cycles, *, k, params=MTParams(), end_cycle=None):
    """Outputs of the gateware for the given strobes.

    Parameters
    ----------
    edge_cycles : array of int
        Strictly increasing clock indices of ``edge.step`` strobes (cycle 0 = first clock after
        reset).
    edge_neg : array of bool
        ``edge.neg`` of each strobe.
    update_cycles : array of int
        Strictly increasing clock indices of ``update`` strobes.
    k : int
        The ``k`` register (constant over the run).
    params : MTParams
    end_cycle : int or None
        Outputs whose ``o.valid`` clock is at or after this are not reported (None: all).

    Returns
    -------
    dict of int64 arrays
        ``cycle`` (the clock ``o.valid`` is high), ``speed``, ``stopped``, ``fresh``,
        ``update`` (the accepted update strobe's clock), ``dm``, ``dt`` (the operands: ΔM and ΔT
        for a fresh window; 1 and the ticks elapsed since the reference edge for a bounded
        output), ``t_end`` (absolute TC tick, unwrapped, of the window's last edge; of the update
        for the others).
    """
    r, w, ow, mw = params.tclk_ratio, params.tc_width, params.out_width, params.m_width
    span, wmask = 1 << w, (1 << w) - 1
    s_max = (1 << (ow - 1)) - 1
    m_lo, m_hi = -(1 << (mw - 1)), (1 << (mw - 1)) - 1
    edges = [int(c) for c in edge_cycles]
    negs = [bool(x) for x in edge_neg]
    ups = [int(c) for c in update_cycles]
    if any(b <= a for a, b in zip(edges, edges[1:])) or \
            any(b <= a for a, b in zip(ups, ups[1:])):
        raise ValueError("edge_cycles and update_cycles must be strictly increasing")
    inf = math.inf

    # State. t_ref / t_last are absolute tick numbers (floor(cycle / r)); the hardware keeps them
    # mod 2**w, which the differences below reproduce.
    have_ref = pending = prev_valid = busy = False
    m_acc = t_last = t_ref = prev = 0       # prev: last fresh output, as magnitude and sign
    prev_neg = False
    mode = snap_dm = snap_dt = snap_t = 0
    out_cycle = inf                 # clock in which the result is ready (o.valid − 1)
    up_cycle = 0
    out = {key: [] for key in ("cycle", "speed", "stopped", "fresh", "update", "dm", "dt",
                               "t_end")}
    ie = iu = 0
    ne, nu = len(edges), len(ups)
    while True:
        c_edge = edges[ie] if ie < ne else inf
        c_up = ups[iu] if iu < nu else inf
        c_exp = (t_ref + span) * r - 1 if have_ref else inf
        c = min(c_edge, c_up, c_exp, out_cycle)
        if c == inf or (end_cycle is not None and c >= end_cycle):
            break
        tc = c // r
        step = c == c_edge
        neg = negs[ie] if step else False
        update = c == c_up
        ie += step
        iu += update
        expire = c == c_exp             # tick & (tc + 1 == t_ref mod 2**w), have_ref
        start = update and not busy

        if step:
            m_e = min(max(m_acc + (-1 if neg else 1), m_lo), m_hi)
            tl_e, pend_e = tc, True
        else:
            m_e, tl_e, pend_e = m_acc, t_last, pending

        if start:
            busy = True
            up_cycle = c
            out_cycle = c + params.latency - 1
            if have_ref and pend_e:
                mode, snap_dm, snap_dt, snap_t = FRESH, m_e, (tl_e - t_ref) & wmask, tl_e
                # Valid from the snapshot: an expiry while it is computed invalidates it.
                prev_valid = True
            elif have_ref and prev_valid:
                mode, snap_dm, snap_dt, snap_t = BOUND, 1, (tc - t_ref) & wmask, tc
            else:
                mode, snap_dm, snap_dt, snap_t = STOPPED, 0, 1, tc

        if not have_ref:
            if step:
                t_ref = t_last = tc
                have_ref = True
        elif start and pend_e:
            t_ref = t_last = tl_e
            m_acc, pending = 0, False
        elif expire:
            prev_valid = False
            if pend_e:
                t_ref = t_last = tl_e
                m_acc, pending = 0, False
            else:
                have_ref = False
        else:
            m_acc, t_last, pending = m_e, tl_e, pend_e

        if c == out_cycle:
            # Unsigned division of k·|ΔM| by ΔT, then the sign of ΔM (of the last measurement
            # when bounded).
            q = _magnitude(k * abs(snap_dm), snap_dt, s_max)
            if mode == FRESH:
                speed = fresh_speed(k, snap_dm, snap_dt, out_width=ow)
                prev, prev_neg = abs(speed), snap_dm < 0
                stopped, fresh = 0, 1
            elif mode == BOUND:
                mag = min(q, prev)
                speed = -mag if prev_neg else mag
                stopped, fresh = 0, 0
            else:
                speed, stopped, fresh = 0, 1, 0
            busy = False
            out_cycle = inf
            if end_cycle is None or c + 1 < end_cycle:
                for key, value in (("cycle", c + 1), ("speed", speed), ("stopped", stopped),
                                   ("fresh", fresh), ("update", up_cycle), ("dm", snap_dm),
                                   ("dt", snap_dt), ("t_end", snap_t)):
                    out[key].append(value)
    return {key: np.array(v, dtype=np.int64) for key, v in out.items()}


def ideal_encoder_edges(segments, *, clk_hz, lines=5000, edge_mode="a_rising", phase=0.0):
    """Edge strobes of an ideal encoder following a piecewise-constant speed profile.

    The counted position is ``n(t) = floor(u(t))``, ``u`` the shaft angle in counted edges
    (``lines·edges_per_line`` per turn) plus ``phase``; each change of ``n`` is one strobe,
    ``neg`` set when ``n`` decreases, in the first clock whose sampling instant ``cycle/clk_hz``
    sees the new ``n``.

    Parameters
    ----------
    segments : sequence of (duration_s, speed_rpm)
        Consecutive constant-speed segments, starting at t = 0 (reversals and stops allowed).
    phase : float
        Initial position in counted edges, [0, 1).

    Returns
    -------
    cycles, neg : int64 array, bool array

    Raises
    ------
    ValueError
        If two strobes fall in one clock (speed above one edge per clock).
    """
    epl = MT_EDGES_PER_LINE[edge_mode]
    per_rev = lines * epl
    # Breakpoints of the piecewise-linear position u(t), in counted edges.
    times, pos = [0.0], [float(phase)]
    cand = []
    for duration_s, speed_rpm in segments:
        v = speed_rpm / 60.0 * per_rev              # counted edges per second
        t0, u0 = times[-1], pos[-1]
        u1 = u0 + v * duration_s
        lo, hi = sorted((u0, u1))
        p = np.arange(math.floor(lo), math.floor(hi) + 1, dtype=np.float64)
        if v != 0 and p.size:
            cand.append(np.ceil((t0 + (p - u0) / v) * clk_hz).astype(np.int64))
        times.append(t0 + duration_s)
        pos.append(u1)
    if not cand:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool)
    # A change of n between the samples of clocks c - 1 and c makes a strobe in clock c; the
    # candidates (crossing clocks ± 1 against float rounding) hold every such c.
    c = np.unique(np.concatenate(cand)[:, None] + np.array([-1, 0, 1])[None, :])
    c = c[(c >= 1) & (c < times[-1] * clk_hz)]
    n_now = np.floor(np.interp(c / clk_hz, times, pos))
    n_before = np.floor(np.interp((c - 1) / clk_hz, times, pos))
    step = n_now - n_before
    if np.any(np.abs(step) > 1):
        raise ValueError("two encoder edges in one clock: speed above one edge per clock")
    keep = step != 0
    return c[keep], step[keep] < 0
