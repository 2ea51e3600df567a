# Ref: issue 6 item 4 (rise time, settling into ±0.5 %, overshoot, steady-state error, ramp
#      tracking, load-step dip and recovery, t_min = J·Δω/(T_max − T_load)) and the targets'
#      JSON keys; paper §4 / Fig. 8–9 (step 0 → 1667 r/min: response < 1 ms, overshoot < 0.5 %,
#      steady-state error < 0.01 %; ramp to 500 r/min: tracking error < 5 %, steady-state
#      error ≈ 0.02 %); conventions as MATLAB stepinfo / python-control step_info
#      (https://python-control.readthedocs.io/en/latest/generated/control.matlab.stepinfo.html)
"""Response metrics of simulated (or measured) time series: plain NumPy, physical units.

Every function takes a time vector ``t`` (s, strictly increasing, finite) and a signal ``y`` of the
same length (any physical unit; r/min for speed), and returns plain floats, ``None`` where a
quantity does not exist in the record (a step that never settles), or a small named tuple / frozen
dataclass. Times returned are **relative to the event** (the step instant ``t0``, the load step
``t_step``), in s. Percentages are in %, not fractions.

Definitions (the conventions of MATLAB's ``stepinfo`` / python-control's ``step_info``, with the
final value taken as the *reference* ``y1``, not the record's last sample):

* **Crossing times** are linearly interpolated between the two samples that bracket the
  threshold, so the metrics resolve finer than the sampling interval.
* **Rise time** (:func:`rise_time`): with ``p = (y − y0)/(y1 − y0)`` (0 before, 1 after the step:
  negative steps work the same), ``t90 − t10`` where ``t10`` is the first time ``p`` reaches 0.1 at
  or after ``t0`` and ``t90`` the first time after ``t10`` it reaches 0.9. ``None`` if it never
  does.
* **Settling time** (:func:`settling_time`): ``t_s − t0`` where ``t_s`` is the last entry into
  ``|y − target| ≤ band·|target|`` after which ``y`` never leaves the band up to the end of the
  record; ``0.0`` if ``y`` is in the band at every sample from ``t0`` on; ``None`` if the last
  sample is outside it, or if ``y`` stays in the band for less than ``hold_s`` before the record
  ends (a record cannot show that ``y`` *never* leaves the band: an oscillation wider than the
  band that happens to be inside it at the last sample would otherwise "settle" there).
  :func:`step_metrics` uses its steady-state window as ``hold_s``. The band is relative to the
  *target* (±0.5 % of 1667 r/min = ±8.3 r/min), not to the step height.
* **Overshoot** (:func:`overshoot_pct`): ``100·max(0, max p − 1)`` over ``t ≥ t0``: the largest
  excursion beyond the reference in the step's direction, in % of the step height ``|y1 − y0|``
  (= % of the final value for a step from 0).
* **Steady-state error** (:func:`steady_state_error`): over the last ``window_s`` of the record,
  ``e = ref − y``; ``mean_pct = 100·|⟨e⟩| / ⟨|ref|⟩`` and ``peak_pct = 100·max|e| / ⟨|ref|⟩``,
  ``⟨·⟩`` the **time-weighted** (trapezoidal) mean over the window, so non-uniform sampling is
  weighted correctly; ``mean_err`` is ``⟨e⟩`` with its sign (positive: ``y`` below ``ref``).
* **Ramp tracking error** (:func:`ramp_tracking_error`): ``100·max|ref − y| / full_scale`` over
  ``t_start + allowance_s ≤ t ≤ t_end``. The default start-up allowance is **0 s** (none: the
  start-up lag of the loop is part of the tracking error); a caller that excludes a start-up
  transient must pass and state its ``allowance_s``.
* **Load step** (:func:`load_step`): over ``t ≥ t_step``, the sample where ``|ref − y|`` is largest;
  ``dip_rpm = ref − y`` there (signed: positive when the speed falls below the reference),
  ``dip_pct = 100·dip_rpm/|ref|``, ``t_dip_s`` its time after ``t_step``; ``recovery_s`` the
  settling time (definition above, with ``hold_s``) into ``±band·|ref|`` measured from
  ``t_step``.
* **Speed ripple** (:func:`speed_ripple`): over the last ``window_s``, ``pkpk = max y − min y``,
  ``mean = ⟨y⟩``, ``rms = √⟨(y − ⟨y⟩)²⟩`` (time-weighted as above).
* **t_min** (:func:`t_min`): the physical floor of a current-limited speed step,
  ``J·|Δω| / (T_max − T_load)`` (host/tuning.py :func:`~foc_servo.host.tuning.t_min_s` computes it
  in r/min; this is the same function in rad/s); ``settle_ratio = settle_s / t_min_s``.

Errors: :exc:`TypeError` for a value of the wrong type (not a real number or array of them),
:exc:`ValueError` for a well-typed but unusable one (empty, lengths that differ, ``t`` not strictly
increasing, NaN/inf, a window longer than the record, a step of height 0); each message names the
parameter and the value.
"""

import dataclasses
import math
import numbers
from typing import NamedTuple

import numpy as np

from ..host.tuning import t_min_s as _t_min_from_rpm

__all__ = ["RPM_PER_RAD_S", "rpm_to_rad_s", "rad_s_to_rpm", "t_min",
           "rise_time", "settling_time", "overshoot_pct", "steady_state_error",
           "ramp_tracking_error", "load_step", "speed_ripple",
           "SteadyStateError", "LoadStep", "Ripple", "StepMetrics", "RampMetrics",
           "step_metrics", "ramp_metrics"]

#: r/min per rad/s: 60/(2π).
RPM_PER_RAD_S = 60.0 / (2.0 * math.pi)


def rpm_to_rad_s(speed_rpm):
    """Convert a speed from r/min to rad/s (mechanical): ``n·2π/60``; a float for a scalar, an
    array for an array."""
    if np.ndim(speed_rpm):
        return np.asarray(speed_rpm, dtype=float) / RPM_PER_RAD_S
    return float(speed_rpm) / RPM_PER_RAD_S


def rad_s_to_rpm(omega_rad_s):
    """Convert a speed from rad/s to r/min (mechanical): ``ω·60/(2π)``; a float for a scalar, an
    array for an array."""
    if np.ndim(omega_rad_s):
        return np.asarray(omega_rad_s, dtype=float) * RPM_PER_RAD_S
    return float(omega_rad_s) * RPM_PER_RAD_S


def t_min(j_kgm2, delta_omega_rad_s, t_max_nm, t_load_nm=0.0):
    """Physical floor of a current-limited speed step, ``t_min = J·|Δω| / (T_max − T_load)``, s.

    Parameters
    ----------
    j_kgm2 : float
        Total inertia (rotor + load), kg·m², > 0.
    delta_omega_rad_s : float
        Speed change Δω, rad/s (mechanical; its magnitude is used).
    t_max_nm : float
        Largest torque the speed loop may command (``K_t`` × its current limit), N·m, > 0.
    t_load_nm : float
        Load torque opposing the step, N·m; must be below ``t_max_nm``.

    Raises
    ------
    ValueError
        A parameter not finite or out of range, or ``t_load_nm ≥ t_max_nm`` (the motor cannot
        accelerate: no finite ``t_min``).
    """
    if (not isinstance(delta_omega_rad_s, numbers.Real) or isinstance(delta_omega_rad_s, bool)
            or not math.isfinite(delta_omega_rad_s)):
        raise ValueError(f"delta_omega_rad_s must be a finite number of rad/s, "
                         f"not {delta_omega_rad_s!r}")
    return _t_min_from_rpm(j_kgm2, delta_omega_rad_s * RPM_PER_RAD_S, t_max_nm, t_load_nm)


# --- input checking --------------------------------------------------------------------------

def _array(name, value):
    try:
        arr = np.asarray(value)
    except Exception:                                # ragged nested sequences and the like
        raise TypeError(f"{name} must be an array of real numbers, not {value!r}") from None
    if arr.dtype == bool or not (np.issubdtype(arr.dtype, np.integer)
                                 or np.issubdtype(arr.dtype, np.floating)):
        raise TypeError(f"{name} must be an array of real numbers, not {_short(value)}")
    if arr.ndim != 1 or arr.size < 2:
        raise ValueError(f"{name} must be a one-dimensional array of at least 2 samples, not an "
                         f"array of shape {arr.shape}")
    arr = arr.astype(float)
    bad = np.flatnonzero(~np.isfinite(arr))
    if bad.size:
        raise ValueError(f"{name} must be finite, not {name}[{bad[0]}] = {arr[bad[0]].item()!r}")
    return arr


def _short(value):
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _series(t, y, y_name="y", t_name="t"):
    """Validated float copies of ``t`` (strictly increasing) and ``y`` (same length)."""
    t = _array(t_name, t)
    y = _array(y_name, y)
    if t.size != y.size:
        raise ValueError(f"{t_name} and {y_name} must have the same length, not {t.size} and "
                         f"{y.size}")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        k = bad[0] + 1
        raise ValueError(f"{t_name} must be strictly increasing, not {t_name}[{k}] = "
                         f"{t[k].item()!r} s after {t_name}[{k - 1}] = {t[k - 1].item()!r} s")
    return t, y


def _real(name, value):
    if not isinstance(value, numbers.Real) or isinstance(value, bool):
        raise TypeError(f"{name} must be a real number, not {value!r}")
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, not {float(value)!r}")
    return float(value)


def _positive(name, value, unit=""):
    value = _real(name, value)
    if value <= 0:
        unit = f" {unit}" if unit else ""
        raise ValueError(f"{name} must be above 0{unit}, not {value!r}{unit}")
    return value


def _ref(ref, t, name="ref"):
    """``ref`` as an array like ``t``: a scalar is broadcast, an array must match."""
    if isinstance(ref, numbers.Real) and not isinstance(ref, bool):
        return np.full(t.size, _real(name, ref))
    _, arr = _series(t, ref, name)
    return arr


def _start(t, t0, name="t0"):
    """Index of the first sample at or after ``t0`` (``t0=None``: 0)."""
    if t0 is None:
        return 0, float(t[0])
    t0 = _real(name, t0)
    if not t[0] <= t0 <= t[-1]:
        raise ValueError(f"{name} must be within the record, {t[0].item()!r} to "
                         f"{t[-1].item()!r} s, not {t0!r} s")
    return int(np.searchsorted(t, t0, side="left")), t0


def _window(t, window_s):
    """Index of the first sample of the last ``window_s`` of the record."""
    window_s = _positive("window_s", window_s, "s")
    span = t[-1] - t[0]
    # A relative tolerance keeps a window of exactly the record (or a grid multiple) whole.
    slack = 1e-9 * max(abs(t[0]), abs(t[-1]), span)
    if window_s > span + slack:
        raise ValueError(f"window_s {window_s!r} s is longer than the record "
                         f"({span.item()!r} s from t[0] to t[-1])")
    k = int(np.searchsorted(t, t[-1] - window_s - slack, side="left"))
    if t.size - k < 2:
        raise ValueError(f"window_s {window_s!r} s holds fewer than 2 samples; the sample "
                         f"interval at the end is {(t[-1] - t[-2]).item()!r} s")
    return k


def _tmean(t, x):
    """Time-weighted (trapezoidal) mean of ``x`` over ``t[0]..t[-1]``."""
    return float(np.sum(0.5 * (x[1:] + x[:-1]) * np.diff(t)) / (t[-1] - t[0]))


def _cross(t, x, k, level):
    """Time at which ``x`` reaches ``level`` between samples ``k − 1`` and ``k`` (linear)."""
    if k == 0 or x[k] == x[k - 1]:
        return float(t[k])
    frac = (level - x[k - 1]) / (x[k] - x[k - 1])
    return float(t[k - 1] + min(max(frac, 0.0), 1.0) * (t[k] - t[k - 1]))


def _step_levels(y0, y1):
    y0, y1 = _real("y0", y0), _real("y1", y1)
    if y0 == y1:
        raise ValueError(f"y1 must differ from y0 (a step of height 0 has no rise or overshoot), "
                         f"not both {y0!r}")
    return y0, y1


# --- metrics ---------------------------------------------------------------------------------

def rise_time(t, y, *, y0, y1, t0=None):
    """10–90 % rise time of a step from ``y0`` to ``y1``, s (``None`` if it never reaches 90 %).

    Parameters
    ----------
    t, y : array
        Time (s, strictly increasing) and response (any unit).
    y0, y1 : float
        Levels before and after the step (``y1 < y0`` for a negative step), the unit of ``y``.
    t0 : float, optional
        Step instant, s; the search starts at the first sample at or after it (default ``t[0]``).
        If the response is already at 10 % there, ``t10`` is that sample's time.
    """
    t, y = _series(t, y)
    y0, y1 = _step_levels(y0, y1)
    k0, _ = _start(t, t0)
    p = (y - y0) / (y1 - y0)
    hit10 = np.flatnonzero(p[k0:] >= 0.1)
    if not hit10.size:
        return None
    k10 = k0 + int(hit10[0])
    t10 = float(t[k10]) if k10 == k0 else _cross(t, p, k10, 0.1)
    hit90 = np.flatnonzero(p[k10:] >= 0.9)
    if not hit90.size:
        return None
    k90 = k10 + int(hit90[0])
    t90 = float(t[k90]) if k90 == k0 else _cross(t, p, k90, 0.9)
    return t90 - t10


def settling_time(t, y, *, target, band=0.005, t0=None, hold_s=0.0):
    """Time from ``t0`` to the last entry into ``target ± band·|target|``, s.

    ``0.0`` if ``y`` is inside the band at every sample from ``t0`` on; ``None`` if the record
    ends outside the band, or inside it for less than ``hold_s`` (never settles, as far as the
    record shows). The entry is interpolated between the last sample outside and the first
    inside.

    Parameters
    ----------
    t, y : array
        Time (s, strictly increasing) and response.
    target : float
        Final value (the reference), unit of ``y``; not 0 (the band is relative to it).
    band : float
        Half-width of the band as a fraction of ``|target|`` (0.005 = ±0.5 %), 0 < band < 1.
    t0 : float, optional
        Step instant, s (default ``t[0]``).
    hold_s : float
        Shortest time in the band before the end of the record that counts as settled, s (≥ 0;
        default 0: the last sample decides).
    """
    t, y = _series(t, y)
    target = _real("target", target)
    hold_s = _real("hold_s", hold_s)
    if hold_s < 0:
        raise ValueError(f"hold_s must be at least 0 s, not {hold_s!r} s")
    band = _real("band", band)
    if not 0 < band < 1:
        raise ValueError(f"band must be a fraction above 0 and below 1, not {band!r}")
    if target == 0:
        raise ValueError("target must not be 0: the band is a fraction of |target|")
    k0, t0 = _start(t, t0)
    tol = band * abs(target)
    dev = y[k0:] - target
    out = np.flatnonzero(np.abs(dev) > tol)
    if not out.size:
        entry = t0
    elif out[-1] == dev.size - 1:
        return None
    else:
        last = int(out[-1])
        entry = _cross(t, y, k0 + last + 1, target + math.copysign(tol, dev[last]))
    if t[-1] - entry < hold_s:
        return None
    return entry - t0


def overshoot_pct(t, y, *, y0, y1, t0=None):
    """Largest excursion beyond ``y1`` in the step's direction, % of ``|y1 − y0|`` (≥ 0).

    Parameters as :func:`rise_time`; samples from the first at or after ``t0`` count. The peak
    is the largest *sample* (not interpolated).
    """
    t, y = _series(t, y)
    y0, y1 = _step_levels(y0, y1)
    k0, _ = _start(t, t0)
    p = (y[k0:] - y0) / (y1 - y0)
    return max(0.0, 100.0 * (float(p.max()) - 1.0))


class SteadyStateError(NamedTuple):
    """Result of :func:`steady_state_error`."""
    mean_pct: float     #: 100·|⟨ref − y⟩| / ⟨|ref|⟩, %
    peak_pct: float     #: 100·max|ref − y| / ⟨|ref|⟩, %
    mean_err: float     #: ⟨ref − y⟩, unit of y (positive: y below ref)


def steady_state_error(t, y, ref, *, window_s):
    """Mean and peak error over the last ``window_s`` of the record, in % of the reference.

    Parameters
    ----------
    t, y : array
        Time (s) and response.
    ref : float or array
        Reference (a constant, or an array like ``y``); its time-weighted mean magnitude over the
        window must not be 0.
    window_s : float
        Length of the window at the end of the record, s (> 0, at most the record's length, at
        least 2 samples).

    Returns
    -------
    SteadyStateError
        ``(mean_pct, peak_pct, mean_err)``; see the module docstring.
    """
    t, y = _series(t, y)
    ref = _ref(ref, t)
    k = _window(t, window_s)
    tw, err = t[k:], ref[k:] - y[k:]
    scale = _tmean(tw, np.abs(ref[k:]))
    if scale == 0:
        raise ValueError("ref must not be 0 over the window: an error in % of it is undefined")
    mean_err = _tmean(tw, err)
    return SteadyStateError(100.0 * abs(mean_err) / scale,
                            100.0 * float(np.abs(err).max()) / scale, mean_err)


def ramp_tracking_error(t, y, ref, *, t_start, t_end, full_scale, allowance_s=0.0):
    """Largest ``|ref − y|`` during a ramp, in % of ``full_scale``.

    The samples counted are those with ``t_start + allowance_s ≤ t ≤ t_end``.

    Parameters
    ----------
    t, y : array
        Time (s) and response.
    ref : array or float
        Reference, like ``y``.
    t_start, t_end : float
        Start and end of the ramp, s (``t_start < t_end``, both within the record).
    full_scale : float
        The 100 % value, unit of ``y`` (500 r/min for the paper's ramp), > 0.
    allowance_s : float
        Start-up allowance excluded after ``t_start``, s (≥ 0, default 0: none). State it when
        reporting a figure measured with one.
    """
    t, y = _series(t, y)
    ref = _ref(ref, t)
    _, t_start = _start(t, t_start, "t_start")
    _, t_end = _start(t, t_end, "t_end")
    if t_end <= t_start:
        raise ValueError(f"t_end must be after t_start ({t_start!r} s), not {t_end!r} s")
    full_scale = _positive("full_scale", full_scale, "")
    allowance_s = _real("allowance_s", allowance_s)
    if not 0 <= allowance_s < t_end - t_start:
        raise ValueError(f"allowance_s must be at least 0 s and shorter than the ramp "
                         f"({t_end - t_start!r} s), not {allowance_s!r} s")
    sel = (t >= t_start + allowance_s) & (t <= t_end)
    if not sel.any():
        raise ValueError(f"no sample between t_start + allowance_s = {t_start + allowance_s!r} s "
                         f"and t_end = {t_end!r} s")
    return 100.0 * float(np.abs(ref[sel] - y[sel]).max()) / full_scale


class LoadStep(NamedTuple):
    """Result of :func:`load_step`."""
    dip_rpm: float      #: ref − y at the largest deviation after the step (unit of y; + = below)
    dip_pct: float      #: 100·dip_rpm/|ref|, %
    t_dip_s: float      #: time of the largest deviation after t_step, s
    recovery_s: float   #: time from t_step to the last entry into ±band·|ref| (None: never)


def load_step(t, y, *, t_step, ref, band=0.005, hold_s=0.0):
    """Speed dip and recovery after a load-torque step at ``t_step`` (speed ``y`` held at ``ref``).

    Parameters
    ----------
    t, y : array
        Time (s) and speed (r/min, or any unit: ``dip_rpm`` is then in that unit).
    t_step : float
        Instant of the load step, s (within the record).
    ref : float
        Speed reference (constant), not 0.
    band : float
        Recovery band as a fraction of ``|ref|`` (0.005 = ±0.5 %), 0 < band < 1.
    hold_s : float
        As in :func:`settling_time`: time in the band at the end of the record needed to count
        as recovered, s.

    Returns
    -------
    LoadStep
        ``(dip_rpm, dip_pct, t_dip_s, recovery_s)``; see the module docstring.
    """
    t, y = _series(t, y)
    ref = _real("ref", ref)
    if ref == 0:
        raise ValueError("ref must not be 0: the dip and the band are relative to |ref|")
    k0, t_step = _start(t, t_step, "t_step")
    err = ref - y[k0:]
    k = int(np.argmax(np.abs(err)))
    dip = float(err[k])
    recovery = settling_time(t, y, target=ref, band=band, t0=t_step, hold_s=hold_s)
    return LoadStep(dip, 100.0 * dip / abs(ref), float(t[k0 + k]) - t_step, recovery)


class Ripple(NamedTuple):
    """Result of :func:`speed_ripple` (all in the unit of y)."""
    pkpk: float         #: max − min over the window
    rms: float          #: √⟨(y − ⟨y⟩)²⟩
    mean: float         #: ⟨y⟩


def speed_ripple(t, y, *, window_s):
    """Peak-to-peak and rms ripple of ``y`` over the last ``window_s`` of the record.

    Returns
    -------
    Ripple
        ``(pkpk, rms, mean)``, time-weighted means (module docstring).
    """
    t, y = _series(t, y)
    k = _window(t, window_s)
    tw, yw = t[k:], y[k:]
    mean = _tmean(tw, yw)
    rms = math.sqrt(max(_tmean(tw, (yw - mean) ** 2), 0.0))
    return Ripple(float(yw.max() - yw.min()), rms, mean)


# --- bundles ---------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class StepMetrics:
    """The step experiment's figures (issue 6 targets); :meth:`as_dict` for ``--json``.

    Attributes
    ----------
    settle_s : float or None
        Settling time into ±band of ``y1`` after ``t0_s``, s.
    t_min_s : float or None
        Physical floor ``J·|Δω|/(T_max − T_load)``, s (``None`` without ``j_kgm2``).
    settle_ratio : float or None
        ``settle_s / t_min_s``.
    overshoot_pct : float
        %, of the step height.
    ss_err_pct, ss_peak_pct : float
        Steady-state mean and peak error over the last ``window_s``, % of ``y1``.
    rise_s : float or None
        10–90 % rise time, s.
    t0_s : float
        Step instant, s (for plots: the t_min and settling marks are drawn from it).
    band : float
        The settling band, fraction of ``|y1|``.
    """
    settle_s: float
    t_min_s: float
    settle_ratio: float
    overshoot_pct: float
    ss_err_pct: float
    ss_peak_pct: float
    rise_s: float
    t0_s: float
    band: float

    def as_dict(self):
        """The figures as a ``dict`` (``None`` where absent), keys as the attribute names."""
        return dataclasses.asdict(self)


def step_metrics(t, y, *, y0, y1, t0=None, window_s, band=0.005, hold_s=None, t_min_s=None,
                 j_kgm2=None, t_max_nm=None, t_load_nm=0.0):
    """All step-response figures of a speed step ``y0 → y1`` (r/min) at ``t0``.

    Parameters
    ----------
    t, y : array
        Time (s) and speed (r/min).
    y0, y1 : float
        Speed before and reference after the step, r/min.
    t0 : float, optional
        Step instant, s (default ``t[0]``).
    window_s : float
        Steady-state window at the end of the record, s.
    band : float
        Settling band, fraction of ``|y1|`` (0.005 = ±0.5 %).
    hold_s : float, optional
        Time in the band before the end of the record needed to count as settled
        (:func:`settling_time`), s; default ``window_s``: ``y`` must have settled by the start of
        the steady-state window.
    t_min_s : float, optional
        The step's physical floor (:func:`t_min`), s, > 0; or let it be computed from:
    j_kgm2, t_max_nm, t_load_nm : float, optional
        Inertia (kg·m²), the speed loop's torque limit and the load torque (N·m): ``t_min`` of a
        step of ``|y1 − y0|`` r/min; ``j_kgm2`` and ``t_max_nm`` both or neither, and not with
        ``t_min_s``. With none of them ``t_min_s`` and ``settle_ratio`` are ``None``.

    Returns
    -------
    StepMetrics
    """
    t, y = _series(t, y)
    y0, y1 = _step_levels(y0, y1)
    _, t0 = _start(t, t0)
    if (j_kgm2 is None) != (t_max_nm is None):
        raise ValueError(f"j_kgm2 and t_max_nm must be given both or neither, not "
                         f"j_kgm2={j_kgm2!r} and t_max_nm={t_max_nm!r}")
    tmin = None
    if t_min_s is not None:
        if j_kgm2 is not None:
            raise ValueError("t_min_s and j_kgm2/t_max_nm must not both be given")
        tmin = _positive("t_min_s", t_min_s, "s")
    elif j_kgm2 is not None:
        tmin = t_min(j_kgm2, (y1 - y0) / RPM_PER_RAD_S, t_max_nm, t_load_nm)
    settle = settling_time(t, y, target=y1, band=band, t0=t0,
                           hold_s=window_s if hold_s is None else hold_s)
    ss = steady_state_error(t, y, y1, window_s=window_s)
    return StepMetrics(
        settle_s=settle, t_min_s=tmin,
        settle_ratio=None if settle is None or tmin is None else settle / tmin,
        overshoot_pct=overshoot_pct(t, y, y0=y0, y1=y1, t0=t0),
        ss_err_pct=ss.mean_pct, ss_peak_pct=ss.peak_pct,
        rise_s=rise_time(t, y, y0=y0, y1=y1, t0=t0), t0_s=t0, band=float(band))


@dataclasses.dataclass(frozen=True)
class RampMetrics:
    """The ramp experiment's figures (issue 6 targets); :meth:`as_dict` for ``--json``.

    Attributes
    ----------
    track_err_pct : float
        Largest ``|ref − y|`` during the ramp, % of ``full_scale``.
    ss_err_pct, ss_peak_pct : float
        Steady-state mean and peak error over the last ``window_s``, % of the final reference.
    t_start_s, t_end_s : float
        The ramp's start and end, s.
    allowance_s : float
        Start-up allowance excluded from ``track_err_pct``, s.
    full_scale : float
        The 100 % of ``track_err_pct`` (unit of y).
    """
    track_err_pct: float
    ss_err_pct: float
    ss_peak_pct: float
    t_start_s: float
    t_end_s: float
    allowance_s: float
    full_scale: float

    def as_dict(self):
        """The figures as a ``dict``, keys as the attribute names."""
        return dataclasses.asdict(self)


def ramp_metrics(t, y, ref, *, window_s, t_start=None, t_end=None, full_scale=None,
                 allowance_s=0.0):
    """Tracking and steady-state figures of a speed ramp (``ref`` an array, r/min).

    Parameters
    ----------
    t, y, ref : array
        Time (s), speed and its reference (r/min).
    window_s : float
        Steady-state window at the end of the record, s; it must lie after ``t_end``.
    t_start, t_end : float, optional
        Ramp start and end, s. By default from ``ref``: ``t_start`` is the last sample before
        ``ref`` first leaves ``ref[0]``, ``t_end`` the first sample at which ``ref`` equals its
        final value ``ref[-1]`` (the reference must change).
    full_scale : float, optional
        100 % of the tracking error (default ``|ref[-1]|``, the ramp's target: 500 r/min).
    allowance_s : float
        Start-up allowance, s (default 0: none).

    Returns
    -------
    RampMetrics
    """
    t, y = _series(t, y)
    if isinstance(ref, numbers.Real) and not isinstance(ref, bool):
        raise TypeError(f"ref must be an array like y for a ramp, not {float(ref)!r}")
    ref = _ref(ref, t)
    if t_start is None or t_end is None:
        moved = np.flatnonzero(ref != ref[0])
        if not moved.size:
            raise ValueError(f"ref never changes (constant {ref[0].item()!r}): no ramp to measure")
        if t_start is None:
            t_start = float(t[max(int(moved[0]) - 1, 0)])
        if t_end is None:
            t_end = float(t[int(np.flatnonzero(ref == ref[-1])[0])])
    if full_scale is None:
        full_scale = abs(float(ref[-1]))
    track = ramp_tracking_error(t, y, ref, t_start=t_start, t_end=t_end, full_scale=full_scale,
                                allowance_s=allowance_s)
    k = _window(t, window_s)
    if t[k] < t_end:
        raise ValueError(f"window_s {window_s!r} s reaches back into the ramp (it ends at "
                         f"{t_end!r} s, the record at {t[-1].item()!r} s)")
    ss = steady_state_error(t, y, ref, window_s=window_s)
    return RampMetrics(track_err_pct=track, ss_err_pct=ss.mean_pct, ss_peak_pct=ss.peak_pct,
                       t_start_s=float(t_start), t_end_s=float(t_end),
                       allowance_s=float(allowance_s), full_scale=float(full_scale))
