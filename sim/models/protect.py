# Ref: issue 4 item 8 (protection and fault latch); issue 6 item 7 (encoder/Hall plausibility)
"""Bit-true, cycle-true golden model of :class:`foc_servo.hdl.protect.Protection`.

The latch is sequential, so the model steps clock by clock (a plain Python loop over int64
arrays); the comparisons are vectorised first. Both forms of the limits (``limits="ports"``:
a comparator per cause; ``"ram"``: the limit RAM and the sequential compare, the class
docstring's "Sequential compare").
"""

import numpy as np
from amaranth.hdl import signed

from ...hdl.protect import FAULTS, LIMITS, STEPS

__all__ = ["INPUTS", "RAM_INPUTS", "protect_np", "pack_flags", "unpack_flags"]

#: Per-clock input columns of :func:`protect_np` (registers are columns too).
INPUTS = ("fault_n", "oc_comp", "i_valid", "a", "b", "c", "udc_valid", "udc", "speed_valid",
          "speed", "encoder_illegal", "hall_invalid", "encoder_hall", "oc_limit", "ov_limit",
          "uv_limit", "uv_enable", "os_limit", "mask", "clear")

#: The columns with ``limits="ram"`` / ``"ram16"``: the limit write port (``lim_valid``,
#: ``lim_index``, ``lim_data``: the 32-bit word, unsigned) in place of the four limits.
RAM_INPUTS = tuple(k for k in INPUTS if k not in LIMITS) + ("lim_valid", "lim_index",
                                                            "lim_data")

_BIT = {name: 1 << k for k, name in enumerate(FAULTS)}


def pack_flags(names):
    """Integer of the cause flags ``names`` (bit order of ``FAULT_LAYOUT``)."""
    return sum(_BIT[n] for n in names)


def unpack_flags(value):
    """Names of the cause flags set in ``value``."""
    return tuple(n for n in FAULTS if int(value) & _BIT[n])


def _causes(now, pins, t, uv_checked):
    """The cause flags of clock ``t``: the sampled verdicts ``now`` (``oc_a`` … ``os``, held
    between samples), the pin columns of ``pins`` in clock ``t``, and the under-voltage verdict
    only while ``uv_checked`` (enabled and armed)."""
    b = _BIT
    cause = 0 if pins["fault_n"][t] else b["external"]
    for p in "abc":
        if now[f"oc_{p}"]:
            cause |= b[f"overcurrent_{p}"]
    for flag, name in ((pins["oc_comp"][t], "overcurrent_comparator"), (now["ov"], "overvoltage"),
                       (uv_checked and now["uv"], "undervoltage"), (now["os"], "overspeed"),
                       (pins["encoder_illegal"][t], "encoder"), (pins["hall_invalid"][t], "hall"),
                       (pins["encoder_hall"][t], "encoder_hall")):
        if flag:
            cause |= b[name]
    return cause


def _latch(clear, present, latched, first, seen):
    """The latch, ``first`` and ``seen`` after a clock edge: cleared by ``clear`` while no
    cause is present, else set by any present cause (``first`` the set that set it)."""
    if clear and present == 0:
        return 0, 0, 0
    if present:
        return 1, (first if latched else present), seen | present
    return latched, first, seen


def protect_np(cols, *, limits="ports", current_width=16, udc_shape=signed(16), speed_width=16,
               limit_init=None):
    """Outputs of the protection block, clock by clock.

    Parameters
    ----------
    cols : dict of array-like
        One entry per name in :data:`INPUTS` (``limits="ram"``: :data:`RAM_INPUTS`), each as
        long as the run: the inputs as set during each clock (``mask`` as an integer of flags;
        currents, U_dc and speed as signed integers).
    limits : str
        The block's form (``Protection(limits=...)``).
    current_width, udc_shape, speed_width, limit_init
        ``limits="ram"``: the block's parameters (the limit RAM's width and initial words).

    Returns
    -------
    dict of int64 arrays
        ``trip``, ``present``, ``first``, ``seen`` (flag integers) and ``uv_armed``, as seen
        during each clock (the state before that clock's edge), starting from reset.
    """
    if limits != "ports":
        return _protect_ram(cols, current_width, udc_shape, speed_width, limit_init,
                            wide=limits == "ram")
    c = {k: np.asarray(cols[k], dtype=np.int64) for k in INPUTS}
    n = c["fault_n"].size
    # Verdicts of each sample (vectorised); meaningful only where the sample is valid.
    oc = {p: np.abs(c[p]) > c["oc_limit"] for p in "abc"}
    ov = c["udc"] > c["ov_limit"]
    uv = c["udc"] < c["uv_limit"]
    arm = c["udc"] > c["uv_limit"]
    os_ = np.abs(c["speed"]) > c["os_limit"]

    lists = {k: c[k].tolist() for k in ("fault_n", "oc_comp", "i_valid", "udc_valid",
                                        "speed_valid", "encoder_illegal", "hall_invalid",
                                        "encoder_hall", "uv_enable", "mask", "clear")}
    oc_l = {p: oc[p].tolist() for p in "abc"}
    ov_l, uv_l, arm_l, os_l = ov.tolist(), uv.tolist(), arm.tolist(), os_.tolist()

    out = {k: np.zeros(n, dtype=np.int64) for k in ("trip", "present", "first", "seen",
                                                    "uv_armed")}
    o_trip, o_present, o_first, o_seen, o_armed = ([0] * n for _ in range(5))
    held = {"oc_a": 0, "oc_b": 0, "oc_c": 0, "ov": 0, "uv": 0, "os": 0}
    armed = latched = present = first = seen = 0
    for t in range(n):
        o_trip[t] = int(latched or present != 0)
        o_present[t], o_first[t], o_seen[t], o_armed[t] = present, first, seen, armed

        iv, uvv, sv = lists["i_valid"][t], lists["udc_valid"][t], lists["speed_valid"][t]
        now = {}
        for p in "abc":
            now[f"oc_{p}"] = oc_l[p][t] if iv else held[f"oc_{p}"]
        now["ov"] = ov_l[t] if uvv else held["ov"]
        now["uv"] = uv_l[t] if uvv else held["uv"]
        now["os"] = os_l[t] if sv else held["os"]
        uv_en = lists["uv_enable"][t]
        cause = _causes(now, lists, t, uv_en and armed)

        # The clock edge.
        latched, first, seen = _latch(lists["clear"][t], present, latched, first, seen)
        if not uv_en:
            armed = 0
        elif uvv and arm_l[t]:
            armed = 1
        held = {k: int(v) for k, v in now.items()}
        present = cause & lists["mask"][t]

    out["trip"][:] = o_trip
    out["present"][:] = o_present
    out["first"][:] = o_first
    out["seen"][:] = o_seen
    out["uv_armed"][:] = o_armed
    return out


def _limit_value(word, index, width, udc_signed, os_width=None):
    """The limit the RAM word ``word`` (``limit_wr.data``) at ``index`` stands for in the
    ``width``-bit comparator (the over-speed limit's: ``os_width`` if given): its low bits, as
    a signed value for a U_dc limit of a signed U_dc."""
    if LIMITS[index] == "os_limit" and os_width is not None:
        width = os_width
    v = int(word) & ((1 << width) - 1)
    if udc_signed and LIMITS[index] in ("ov_limit", "uv_limit") and v >> (width - 1):
        v -= 1 << width
    return v


def _protect_ram(cols, current_width, udc_shape, speed_width, limit_init, wide=True):
    """:func:`protect_np` for ``limits="ram"`` (``wide``) or ``"ram16"``: the limit RAM
    (written at the end of a ``lim_valid`` clock) and the step sequencer (requests, the first
    requested step taken in a clock without a write, its word read and its operand taken from
    the payload then, compared in the next clock). ``"ram16"``: the currents' and U_dc's limits
    are the words' low ``max(current_width, udc width)`` bits."""
    n_bits = max(current_width, udc_shape.width, speed_width)
    m_bits = n_bits if wide else min(n_bits, max(current_width, udc_shape.width))
    u_signed = udc_shape.signed
    if limit_init is None:
        lo = -(1 << (udc_shape.width - 1)) if u_signed else 0
        hi = (1 << (udc_shape.width - 1)) - 1 if u_signed else (1 << udc_shape.width) - 1
        limit_init = ((1 << current_width) - 1, hi & 0xFFFF_FFFF, lo & 0xFFFF_FFFF,
                      (1 << speed_width) - 1)
    ram = [_limit_value(w, k, m_bits, u_signed, n_bits) for k, w in enumerate(limit_init)]
    c = {k: np.asarray(cols[k], dtype=np.int64).tolist() for k in RAM_INPUTS}
    n = len(c["fault_n"])
    names = [s[0] for s in STEPS]
    src_valid = {"i": "i_valid", "udc": "udc_valid", "speed": "speed_valid"}
    word = [LIMITS.index(lim) for _, _, lim in STEPS]
    out = {k: [0] * n for k in ("trip", "present", "first", "seen", "uv_armed")}
    held = {"oc_a": 0, "oc_b": 0, "oc_c": 0, "ov": 0, "uv": 0, "os": 0}
    pend = [0] * len(STEPS)
    go = None                       # the step compared in this clock, its limit and operand
    go_limit = go_value = 0
    armed = latched = present = first = seen = 0
    for t in range(n):
        out["trip"][t] = int(latched or present != 0)
        out["present"][t], out["first"][t], out["seen"][t] = present, first, seen
        out["uv_armed"][t] = armed

        # This clock's compare (the step taken in the last clock, on that clock's payload).
        now = dict(held)
        arm_now = 0
        if go is not None:
            name = names[go]
            lim, v = go_limit, go_value
            if name.startswith("oc_") or name == "os":
                verdict = abs(v) > lim
            elif name in ("ov", "arm"):
                verdict = v > lim
            else:                   # uv
                verdict = v < lim
            if name == "arm":
                arm_now = int(verdict)
            else:
                now[name] = int(verdict)
        uv_en = c["uv_enable"][t]
        cause = _causes(now, c, t, uv_en and armed)

        # The sequencer: this clock's requests, the first one taken unless the RAM is written.
        want = [pend[k] or c[src_valid[s[1]]][t] for k, s in enumerate(STEPS)]
        pick = None
        if not c["lim_valid"][t]:
            pick = next((k for k in range(len(STEPS)) if want[k]), None)

        # The clock edge.
        latched, first, seen = _latch(c["clear"][t], present, latched, first, seen)
        if not uv_en:
            armed = 0
        elif arm_now:
            armed = 1
        held = now
        present = cause & c["mask"][t]
        pend = [int(want[k] and k != pick) for k in range(len(STEPS))]
        go = pick
        if pick is not None:
            go_limit = ram[word[pick]]
            name = names[pick]
            go_value = c[name[-1] if name.startswith("oc_") else
                         "speed" if name == "os" else "udc"][t]
        if c["lim_valid"][t]:
            k = c["lim_index"][t]
            ram[k] = _limit_value(c["lim_data"][t], k, m_bits, u_signed, n_bits)
    return {k: np.asarray(v, dtype=np.int64) for k, v in out.items()}
