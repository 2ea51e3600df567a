# Ref: SPEC.md §2.4 (paper Fig. 7, SVPWM) and §2.5 (DC-bus compensation)
"""Bit-true golden models of :mod:`foc_servo.hdl.svpwm` (numpy int64, vectorised), plus the
textbook sector + dwell-time formulation and the float ideal the tests compare them with.

* :func:`svpwm` — min–max zero-sequence injection, exactly as the gateware computes it.
* :func:`svpwm_sector` — the textbook: sector from the sign tests of u_β, √3·u_α − u_β and
  −√3·u_α − u_β, dwell times T1, T2 of the two adjacent active vectors from a per-sector table,
  T0 = 1 − T1 − T2 split equally between 000 and 111 (T1, T2 scaled by 1/(T1 + T2) when it exceeds
  1), each phase's duty the sum of the times it is high. Same integer steps for ``u_β/√3`` and for
  the final rounding, so it must equal :func:`svpwm` bit for bit.
* :func:`svpwm_ideal` — real-valued duties (no quantisation at all).
* :func:`dcbus_gain`, :func:`dcbus_apply` — DC-bus compensation.
* :func:`pwm_high_clocks`, :func:`pwm_levels` — the timer's output for given active compares.
"""

import numpy as np
from amaranth.hdl import signed

from ...hdl.fixed import round_shift_np, saturate_np

__all__ = ["GUARD_BITS", "svpwm_constants", "svpwm", "svpwm_sector", "svpwm_ideal",
           "vector_of_duties", "dcbus_gain", "dcbus_apply", "pwm_high_clocks", "pwm_levels"]

GUARD_BITS = 8
GAIN_FRAC = 16


def svpwm_constants(width, frac=None):
    """``(F, k_frac, k)``: ``F = frac + 8`` (``frac`` default ``width − 1``), ``k_frac = width + 2``,
    ``k = round(2**(8 + k_frac) / √3)`` (float: exact at these sizes)."""
    k_frac = width + 2
    frac = width - 1 if frac is None else frac
    return frac + GUARD_BITS, k_frac, int(np.rint(2.0 ** (GUARD_BITS + k_frac) / np.sqrt(3)))


def _a_s(alpha, beta, width):
    _, k_frac, k = svpwm_constants(width)
    a = np.asarray(alpha, dtype=np.int64) << GUARD_BITS
    s = np.asarray(round_shift_np(np.asarray(beta, dtype=np.int64) * k, k_frac), dtype=np.int64)
    return a, s


def _counts(numerators, d, scale):
    scale = np.asarray(scale, dtype=np.int64)
    return [(scale * n + d) // (2 * d) for n in numerators]


def svpwm(alpha, beta, scale, *, width=16, frac=None):
    """Duties of :class:`~foc_servo.hdl.svpwm.SVPWM` by min–max injection.

    Parameters
    ----------
    alpha, beta : array of int
        Raw commands of ``width`` bits, ``frac`` fractional (default ``width − 1``).
    scale : int or array of int
        Count of a 100 % duty.

    Returns
    -------
    dict
        ``"a"``, ``"b"``, ``"c"``: int64 counts in ``[0, scale]``; ``"overmod"``: 0/1.
    """
    frac = svpwm_constants(width, frac)[0]
    a, s = _a_s(alpha, beta, width)
    q = np.stack([a, s, -s])
    mx, mn = q.max(axis=0), q.min(axis=0)
    spread = mx - mn
    d = np.maximum(spread, 1 << frac)
    da, db, dc = _counts([d + 2 * q[k] - mx - mn for k in range(3)], d, scale)
    return {"a": da, "b": db, "c": dc, "overmod": (spread > (1 << frac)).astype(np.int64)}


# Phases high during each basic vector V1 … V6 (V1 = 100 along phase A, then every 60°).
_VECTORS = np.array([[1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 1, 1], [0, 0, 1], [1, 0, 1]])
# Textbook sector number from the sign bits
# N = [u_β > 0] + 2·[√3u_α − u_β > 0] + 4·[−√3u_α − u_β > 0]
# (N = 0 only for the zero vector: any sector then gives T1 = T2 = 0).
_SECTOR_OF_N = np.array([1, 2, 6, 1, 4, 3, 5, 1])


def _dwell(sector, x, y, z):
    """Textbook dwell times (T1 of V_k, T2 of V_k+1) for sector k, from X = 2u_β/√3,
    Y = u_α + u_β/√3, Z = u_β/√3 − u_α (fractions of the period)."""
    t1 = np.select([sector == k for k in range(1, 7)], [-z, y, x, z, -y, -x])
    t2 = np.select([sector == k for k in range(1, 7)], [x, z, -y, -x, -z, y])
    return t1, t2


def svpwm_sector(alpha, beta, scale, *, width=16):
    """Duties by the textbook sector + dwell-time formulation, in the same integers as
    :func:`svpwm`. Returns its dict plus ``"sector"`` (1 … 6), ``"t1"``, ``"t2"`` (``2**F`` =
    one period, before overmodulation scaling)."""
    frac = svpwm_constants(width)[0]
    one = 1 << frac
    a, s = _a_s(alpha, beta, width)
    # Sign tests on u_β ∝ S, √3u_α − u_β ∝ A − S, −√3u_α − u_β ∝ −A − S.
    n = (s > 0).astype(int) + 2 * (a - s > 0) + 4 * (-a - s > 0)
    sector = _SECTOR_OF_N[n]
    t1, t2 = _dwell(sector, 2 * s, a + s, s - a)
    d = np.maximum(t1 + t2, one)                # overmodulation: T1, T2 scaled by 1/(T1 + T2)
    # Duty of x = T0/2 + (T1 if x high in V_k) + (T2 if x high in V_k+1), with T0 = D − T1 − T2:
    # numerators over 2·D.
    v1 = _VECTORS[sector - 1].T
    v2 = _VECTORS[sector % 6].T
    nums = [d - t1 - t2 + 2 * (v1[k] * t1 + v2[k] * t2) for k in range(3)]
    da, db, dc = _counts(nums, d, scale)
    return {"a": da, "b": db, "c": dc, "overmod": (t1 + t2 > one).astype(np.int64),
            "sector": sector, "t1": t1, "t2": t2}


def svpwm_ideal(alpha, beta, *, width=16):
    """Real-valued duties (fractions of the period) for raw commands, and the overmod flag."""
    u_a = np.asarray(alpha, dtype=np.float64) / 2.0 ** (width - 1)
    u_b = np.asarray(beta, dtype=np.float64) / 2.0 ** (width - 1)
    q = np.stack([u_a, u_b / np.sqrt(3), -u_b / np.sqrt(3)])
    mx, mn = q.max(axis=0), q.min(axis=0)
    d = np.maximum(mx - mn, 1.0)
    duties = 0.5 + (q - (mx + mn) / 2) / d
    return duties, mx - mn > 1.0


def vector_of_duties(da, db, dc):
    """The (u_α, u_β) the duties produce (fractions of (2/3)·U_dc; duties as fractions)."""
    da, db, dc = (np.asarray(x, dtype=np.float64) for x in (da, db, dc))
    return da - (db + dc) / 2, (db - dc) * np.sqrt(3) / 2


def dcbus_gain(u_rated, u_dc, *, gain_limit_raw):
    """Gain of :class:`~foc_servo.hdl.svpwm.DCBusCompensation` (UQ2.16) and the ``limited`` flag:
    ``round(U_rated·2**16 / U_dc)`` half up, limited; ``U_dc = 0`` gives the limit."""
    r = np.asarray(u_rated, dtype=np.int64)
    u = np.asarray(u_dc, dtype=np.int64)
    safe = np.where(u == 0, 1, u)
    q = ((r << (GAIN_FRAC + 1)) + u) // (2 * safe)
    over = (u == 0) | (q > gain_limit_raw)
    return np.where(over, gain_limit_raw, q), over.astype(np.int64)


def dcbus_apply(u, gain, *, out_width=16):
    """``sat(round_shift(u · gain, 16))`` to ``signed(out_width)``."""
    prod = np.asarray(u, dtype=np.int64) * np.asarray(gain, dtype=np.int64)
    return np.asarray(saturate_np(round_shift_np(prod, GAIN_FRAC), signed(out_width)),
                      dtype=np.int64)


def pwm_high_clocks(compare, half_period, symmetric):
    """Clocks a phase is high in one period of :class:`~foc_servo.hdl.svpwm.PWMTimer` with active
    ``compare``: ``2·min(c, N)`` symmetric, ``min(c, 2N)`` asymmetric."""
    c = np.asarray(compare, dtype=np.int64)
    n = half_period
    return np.where(np.asarray(symmetric, dtype=bool), 2 * np.minimum(c, n), np.minimum(c, 2 * n))


def pwm_levels(compare, half_period, symmetric):
    """Level of a phase at every position ``0 … 2N−1`` of a period (bool array)."""
    n = half_period
    pos = np.arange(2 * n)
    if symmetric:
        c = min(int(compare), n)
        return (pos + c >= n) & (pos < n + c)
    return pos < min(int(compare), 2 * n)
