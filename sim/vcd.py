# Ref: issue 6 item 5 (`--vcd FILE.vcd`, GTKWave-readable); IEEE 1364-2005 §18 (the VCD format)
"""A small value-change-dump writer for closed-loop runs, independent of the engine.

The pins come from the co-simulation's event logs (every change of the pins the plant and the host
drive, and of the pins the gateware drives: gates, UART, ADC chip select, LEDs), the analog
quantities (speed, currents, U_dc) from its per-sample record as ``real`` variables. So the same
file comes out of the Amaranth simulator and the compiled engine, and GTKWave shows the gate
pattern beside the motor's currents.
"""

import numpy as np

__all__ = ["write_vcd"]


#: Identifier characters: printable ASCII without ``#`` and ``$`` (legal, but easily misread as a
#: time stamp or a keyword by simple readers).
_ID_CHARS = "".join(chr(c) for c in range(33, 127) if chr(c) not in "#$")


def _ident(k):
    """Short VCD identifier number ``k``."""
    chars = []
    k += 1
    while k:
        k, r = divmod(k - 1, len(_ID_CHARS))
        chars.append(_ID_CHARS[r])
    return "".join(chars)


def write_vcd(path, *, clk_hz, digital=(), analog=(), timescale_ns=1, module="foc_servo"):
    """Write a VCD file.

    Parameters
    ----------
    path : str or Path
    clk_hz : float
        Clock of the digital change times.
    digital : iterable of (name, width, clocks, values, initial)
        A pin (or bus) and its changes: ``values[k]`` from clock ``clocks[k]`` on (the time of a
        clock is ``clock / clk_hz``); ``initial`` at time 0.
    analog : iterable of (name, t_s, values)
        A real-valued quantity sampled at times ``t_s`` (s).
    timescale_ns : int
        VCD time unit, ns (1: exact to the nanosecond at any clock of 1 GHz or below).

    Returns
    -------
    int
        Number of value changes written.
    """
    if not isinstance(clk_hz, (int, float)) or not clk_hz > 0:
        raise ValueError(f"write_vcd clk_hz must be a positive number, not {clk_hz!r}")
    unit = timescale_ns * 1e-9
    times, order, texts = [], [], []
    header = ["$version foc-servo closed-loop simulation $end",
              f"$timescale {timescale_ns}ns $end", f"$scope module {module} $end"]
    init = []
    k = 0
    for name, width, clocks, values, initial in digital:
        ident = _ident(k)
        k += 1
        header.append(f"$var wire {width} {ident} {name} $end")
        fmt = ((lambda v, i=ident: f"{v & 1}{i}") if width == 1 else
               (lambda v, i=ident, w=width: f"b{v & ((1 << w) - 1):b} {i}"))
        init.append(fmt(int(initial)))
        clocks = np.asarray(clocks, dtype=np.int64)
        values = np.asarray(values, dtype=np.int64)
        t = np.rint(clocks / clk_hz / unit).astype(np.int64)
        times.append(t)
        texts.extend(fmt(int(v)) for v in values)
        order.append(np.full(len(t), k, dtype=np.int64))
    for name, t_s, values in analog:
        ident = _ident(k)
        k += 1
        header.append(f"$var real 64 {ident} {name} $end")
        values = np.asarray(values, dtype=float)
        t_s = np.asarray(t_s, dtype=float)
        if len(values):
            init.append(f"r{values[0]:.9g} {ident}")
        times.append(np.rint(t_s / unit).astype(np.int64))
        texts.extend(f"r{v:.9g} {ident}" for v in values)
        order.append(np.full(len(t_s), k, dtype=np.int64))
    header += ["$upscope $end", "$enddefinitions $end"]
    t = np.concatenate(times) if times else np.zeros(0, np.int64)
    o = np.concatenate(order) if order else np.zeros(0, np.int64)
    idx = np.lexsort((o, t))
    with open(path, "w") as f:
        f.write("\n".join(header) + "\n#0\n$dumpvars\n" + "\n".join(init) + "\n$end\n")
        last = 0
        lines = []
        for i in idx:
            ti = int(t[i])
            if ti != last:
                lines.append(f"#{ti}")
                last = ti
            lines.append(texts[i])
        f.write("\n".join(lines) + ("\n" if lines else ""))
    return len(idx)
