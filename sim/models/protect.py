# Ref: issue 4 item 8 (protection and fault latch); issue 6 item 7 (encoder/Hall plausibility)
"""Bit-true, cycle-true golden model of :class:`foc_servo.hdl.protect.Protection`.

The latch is sequential, so the model steps clock by clock (a plain Python loop over int64
arrays); the comparisons are vectorised first.
"""

import numpy as np

from ...hdl.protect import FAULTS

__all__ = ["INPUTS", "protect_np", "pack_flags", "unpack_flags"]

#: Per-clock input columns of :func:`protect_np` (registers are columns too).
INPUTS = ("fault_n", "oc_comp", "i_valid", "a", "b", "c", "udc_valid", "udc", "speed_valid",
          "speed", "encoder_illegal", "hall_invalid", "encoder_hall", "oc_limit", "ov_limit",
          "uv_limit", "uv_enable", "os_limit", "mask", "clear")

_BIT = {name: 1 << k for k, name in enumerate(FAULTS)}


def pack_flags(names):
    """Integer of the cause flags ``names`` (bit order of ``FAULT_LAYOUT``)."""
    return sum(_BIT[n] for n in names)


def unpack_flags(value):
    """Names of the cause flags set in ``value``."""
    return tuple(n for n in FAULTS if int(value) & _BIT[n])


def protect_np(cols):
    """Outputs of the protection block, clock by clock.

    Parameters
    ----------
    cols : dict of array-like
        One entry per name in :data:`INPUTS`, each as long as the run: the inputs as set during
        each clock (``mask`` as an integer of flags; currents, U_dc and speed as signed integers).

    Returns
    -------
    dict of int64 arrays
        ``trip``, ``present``, ``first``, ``seen`` (flag integers) and ``uv_armed``, as seen
        during each clock (the state before that clock's edge), starting from reset.
    """
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
    b = _BIT
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
        cause = 0
        if not lists["fault_n"][t]:
            cause |= b["external"]
        if now["oc_a"]:
            cause |= b["overcurrent_a"]
        if now["oc_b"]:
            cause |= b["overcurrent_b"]
        if now["oc_c"]:
            cause |= b["overcurrent_c"]
        if lists["oc_comp"][t]:
            cause |= b["overcurrent_comparator"]
        if now["ov"]:
            cause |= b["overvoltage"]
        if uv_en and armed and now["uv"]:
            cause |= b["undervoltage"]
        if now["os"]:
            cause |= b["overspeed"]
        if lists["encoder_illegal"][t]:
            cause |= b["encoder"]
        if lists["hall_invalid"][t]:
            cause |= b["hall"]
        if lists["encoder_hall"][t]:
            cause |= b["encoder_hall"]

        # The clock edge.
        if lists["clear"][t] and present == 0:
            latched, first, seen = 0, 0, 0
        elif present:
            if not latched:
                first = present
            latched, seen = 1, seen | present
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
