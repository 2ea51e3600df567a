# Ref: paper §4, Fig. 8 (response to a step speed command) and Fig. 9 (response to a ramp speed
#      command): rotor speed tracking and α-axis current; issue 6 item 5 (`--plot`, `--csv`)
"""Figures and CSV files of simulated responses.

A *series* is a ``dict`` of equally long 1-D NumPy arrays in SI-ish units named by suffix:
``t_s`` (s, strictly increasing), ``speed_rpm``, ``speed_ref_rpm`` (r/min), ``i_alpha_a`` (A), and
optionally ``i_q_a``, ``i_d_a`` (A). :func:`write_csv` also writes any further 1-D array of the same
length.

The figures are drawn with Matplotlib's object API on an Agg canvas (``matplotlib.figure.Figure``,
no ``pyplot``): no screen, no global state, safe to call from threads (Matplotlib's "Embedding in a
web application server" example, https://matplotlib.org/stable/gallery/user_interfaces/
web_application_server_sgskip.html).
"""

import math
import numbers
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .metrics import _series

__all__ = ["REQUIRED", "OPTIONAL", "UNITS", "plot_response", "write_csv", "read_csv"]

#: Series keys every plot and CSV needs, in column order.
REQUIRED = ("t_s", "speed_rpm", "speed_ref_rpm", "i_alpha_a")
#: Series keys drawn when present.
OPTIONAL = ("i_q_a", "i_d_a")

#: Unit of a series key, from its suffix (longest first); ``-`` when none matches.
UNITS = (("_rad_s", "rad/s"), ("_rpm", "r/min"), ("_nm", "N·m"), ("_rad", "rad"),
         ("_pct", "%"), ("_clk", "clock"), ("_s", "s"), ("_a", "A"), ("_v", "V"))


def unit_of(key):
    """Unit of a series key from its suffix (``speed_rpm`` → ``r/min``; ``-`` if none)."""
    for suffix, unit in UNITS:
        if key.endswith(suffix):
            return unit
    return "-"


def _check_series(series, required=REQUIRED):
    """Validated float arrays of ``series``: the required keys first, then the rest in order."""
    if not isinstance(series, dict):
        raise TypeError(f"series must be a dict of arrays, not {type(series).__name__}")
    missing = [key for key in required if key not in series]
    if missing:
        raise ValueError(f"series lacks {', '.join(missing)} (it has "
                         f"{', '.join(map(str, series)) or 'nothing'})")
    keys = list(required) + [key for key in series if key not in required]
    for key in keys:
        if not isinstance(key, str) or not key or "," in key or "\n" in key:
            raise ValueError(f"series keys must be non-empty strings without commas or "
                             f"newlines, not {key!r}")
    t, _ = _series(series["t_s"], series[keys[1]], keys[1], t_name="t_s")
    return {key: t if key == "t_s" else _series(t, series[key], key, t_name="t_s")[1]
            for key in keys}


def _fmt_ms(value_s):
    return f"{value_s * 1e3:.3g} ms"


def plot_response(series, path, *, title, metrics=None, dpi=120):
    """Draw a speed response like the paper's Fig. 8/9 and write it as a PNG.

    Top axes: speed and its reference (r/min) against time (ms); bottom axes: the α-axis current
    (A), with ``i_q``/``i_d`` when the series has them. With ``metrics`` (a
    :class:`~foc_servo.sim.metrics.StepMetrics`, :class:`~foc_servo.sim.metrics.RampMetrics` or a
    ``dict`` of their keys) the figures are annotated: a text (as the legend's title, outside the
    axes) with every figure present (settling time and its ratio to t_min, overshoot, rise time,
    steady-state and tracking error), and, for a step (``t0_s`` given), dotted lines at
    ``t0 + t_min`` and ``t0 + settle_s`` and an inset that zooms on the final value with the
    ±0.5 % band (``band``, default 0.005).

    Parameters
    ----------
    series : dict of array
        ``t_s``, ``speed_rpm``, ``speed_ref_rpm``, ``i_alpha_a``; optional ``i_q_a``, ``i_d_a``.
    path : str or Path
        PNG file to write (its folder is created).
    title : str
        Figure title.
    metrics : StepMetrics, RampMetrics or dict, optional
    dpi : int
        Resolution (the figure is 9 × 6 in).

    Returns
    -------
    Path
        ``path``.
    """
    data = _check_series(series)
    if not isinstance(title, str):
        raise TypeError(f"title must be a string, not {title!r}")
    if metrics is not None and not isinstance(metrics, dict):
        if not hasattr(metrics, "as_dict"):
            raise TypeError(f"metrics must be a dict or have as_dict(), not {metrics!r}")
        metrics = metrics.as_dict()
    metrics = dict(metrics or {})
    if not isinstance(dpi, numbers.Integral) or not 30 <= dpi <= 600:
        raise ValueError(f"dpi must be an integer from 30 to 600, not {dpi!r}")
    path = Path(path)

    t_ms = data["t_s"] * 1e3
    fig = Figure(figsize=(9, 6), layout="constrained")
    FigureCanvasAgg(fig)
    ax_n, ax_i = fig.subplots(2, 1, sharex=True, height_ratios=(3, 2))
    fig.suptitle(title)

    ax_n.plot(t_ms, data["speed_ref_rpm"], "--", color="tab:gray", lw=1.2, label="reference")
    ax_n.plot(t_ms, data["speed_rpm"], color="tab:blue", lw=1.2, label="speed")
    ax_n.set_ylabel("speed (r/min)")
    ax_n.grid(True, alpha=0.3)

    ax_i.plot(t_ms, data["i_alpha_a"], color="tab:red", lw=0.8, label=r"$i_\alpha$")
    for key, color, label in (("i_q_a", "tab:green", r"$i_q$"), ("i_d_a", "tab:purple", r"$i_d$")):
        if key in data:
            ax_i.plot(t_ms, data[key], color=color, lw=1.0, label=label)
    ax_i.set_ylabel("current (A)")
    ax_i.set_xlabel("time (ms)")
    ax_i.grid(True, alpha=0.3)

    figures = _annotate(ax_n, t_ms, data, metrics)
    # Legends (the figures as the top one's title) outside on the right: the data stay clear.
    for ax, text in ((ax_n, figures), (ax_i, None)):
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small", title=text,
                  title_fontsize="small", alignment="left")

    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, format="png")
    return path


def _num(metrics, key):
    value = metrics.get(key)
    if isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value):
        return float(value)
    return None


def _annotate(ax, t_ms, data, metrics):
    """Draw the step marks and zoom inset on ``ax``; return the figures' text (or ``None``)."""
    lines = []
    settle, tmin = _num(metrics, "settle_s"), _num(metrics, "t_min_s")
    if settle is not None:
        text = f"settling (±{100 * (_num(metrics, 'band') or 0.005):g} %): {_fmt_ms(settle)}"
        ratio = _num(metrics, "settle_ratio")
        lines.append(text + (f" = {ratio:.2f}·t_min" if ratio is not None else ""))
    elif "settle_s" in metrics:
        lines.append("settling: never")
    if tmin is not None:
        lines.append(f"t_min = J·Δω/(T_max − T_load): {_fmt_ms(tmin)}")
    for key, label, unit in (("overshoot_pct", "overshoot", "%"), ("rise_s", "rise 10–90 %", "s"),
                             ("track_err_pct", "tracking error", "%"),
                             ("ss_err_pct", "steady-state error", "%"),
                             ("ss_peak_pct", "steady-state peak error", "%")):
        value = _num(metrics, key)
        if value is not None:
            lines.append(f"{label}: {_fmt_ms(value) if unit == 's' else f'{value:.3g} %'}")
    if _num(metrics, "allowance_s"):
        lines.append(f"(start-up allowance {_fmt_ms(metrics['allowance_s'])})")
    figures = "\n".join(lines) or None

    t0 = _num(metrics, "t0_s")
    if t0 is None:
        return figures
    marks = []
    if tmin is not None:
        marks.append((t0 + tmin, "tab:orange", "t0 + t_min"))
    if settle is not None:
        marks.append((t0 + settle, "tab:green", "settled"))
    for t_s, color, label in marks:
        ax.axvline(t_s * 1e3, ls=":", color=color, lw=1.2, label=label)

    # Zoom on the final value: ±0.5 % is invisible at full scale.
    final = float(data["speed_ref_rpm"][-1])
    if final == 0 or not marks:
        return figures
    band = (_num(metrics, "band") or 0.005) * abs(final)
    start = min(m[0] for m in marks) * 1e3
    inset = ax.inset_axes((0.55, 0.12, 0.42, 0.42))
    sel = t_ms >= start - 0.2 * (t_ms[-1] - start)
    inset.plot(t_ms[sel], data["speed_ref_rpm"][sel], "--", color="tab:gray", lw=1.0)
    inset.plot(t_ms[sel], data["speed_rpm"][sel], color="tab:blue", lw=1.0)
    inset.axhspan(final - band, final + band, color="tab:green", alpha=0.15)
    for t_s, color, _ in marks:
        inset.axvline(t_s * 1e3, ls=":", color=color, lw=1.0)
    inset.set_ylim(final - 4 * band, final + 4 * band)
    inset.set_xlim(t_ms[sel][0], t_ms[-1])
    inset.tick_params(labelsize="x-small")
    inset.set_title(f"±{band:.3g} r/min band", fontsize="x-small")
    return figures


def write_csv(series, path):
    """Write a series as CSV: a header of ``key (unit)`` names, then one row per sample.

    Columns: ``t_s``, ``speed_rpm``, ``speed_ref_rpm``, ``i_alpha_a``, then every other key of
    ``series`` in its order (each a 1-D array as long as ``t_s``; its unit from its suffix, see
    :data:`UNITS`). Numbers are written with 10 significant digits (``t_s`` resolves 20 ns
    clocks up to 100 s). Returns ``path`` as a :class:`~pathlib.Path`.
    """
    data = _check_series(series)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = ",".join(f"{key} ({unit_of(key)})" for key in data)
    np.savetxt(path, np.column_stack(list(data.values())), fmt="%.10g", delimiter=",",
               header=header, comments="", encoding="utf-8")
    return path


def read_csv(path):
    """Read a file written by :func:`write_csv` back into a series ``dict`` (float arrays)."""
    path = Path(path)
    with path.open(encoding="utf-8") as f:
        header = f.readline().rstrip("\n")
    keys = [name.rsplit(" (", 1)[0] for name in header.split(",")]
    table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, encoding="utf-8")
    if table.shape[1] != len(keys):
        raise ValueError(f"{path}: {table.shape[1]} columns but {len(keys)} header names")
    return {key: table[:, i] for i, key in enumerate(keys)}
