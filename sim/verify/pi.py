# Ref: paper eq. (7)–(9); SPEC.md §2.2
"""Gateware :class:`~foc_servo.hdl.pi.PI` against its golden model over seeded random vectors.

The stimulus is a sequence of segments of a few hundred samples, each with its own gains, limits
and error pattern (random, small, one-signed runs then a sign change, full scale, square wave),
preceded by named corner cases, with random ``clear`` pulses that land while a sample is in flight.
"""

import numpy as np

from amaranth.hdl import signed

from ...hdl.fixed import UQ, shape_range
from ...hdl.pi import PI
from ..harness import Progress, simulate
from ..models.pi import PIModel

__all__ = ["run", "stimulus"]

# Kinds of error pattern of a segment.
_PATTERNS = ("uniform", "small", "windup", "fullscale", "square")

PI_LATENCY = 6          # checked against PI.latency in run(); clear offsets span 0 … latency-1
CLOCK_HZ = 50e6


def _log_uniform(rng, lo, hi):
    """Integer in [lo, hi], log-uniformly distributed over its magnitude (lo, hi ≥ 0)."""
    bits = rng.uniform(0, np.log2(hi + 1))
    return int(min(max(int(2.0 ** bits) - 1, lo), hi))


def _gain(rng, fmt):
    lo, hi = fmt.min_raw, fmt.max_raw
    kind = rng.choice(["zero", "max", "uniform", "log", "log", "log"])
    if kind == "zero":
        return 0
    if kind == "max":
        return hi
    if kind == "uniform":
        return int(rng.integers(lo, hi + 1))
    v = _log_uniform(rng, 0, hi)
    if fmt.signed and rng.random() < 0.1:
        v = -v
    return v


def _limits(rng, width):
    lo_min, hi_max = shape_range(signed(width))
    kind = rng.choice(["full", "sym", "sym", "asym", "narrow", "equal", "inverted"],
                      p=[0.2, 0.25, 0.15, 0.15, 0.12, 0.08, 0.05])
    if kind == "full":
        return lo_min, hi_max
    if kind == "sym":
        a = _log_uniform(rng, 1, hi_max)
        return -a, a
    if kind == "asym":
        lo, hi = sorted(int(x) for x in rng.integers(lo_min, hi_max + 1, 2))
        return lo, hi
    if kind == "narrow":
        lo = int(rng.integers(lo_min, hi_max - 16))
        return lo, lo + int(rng.integers(0, 17))
    if kind == "equal":
        v = int(rng.integers(lo_min, hi_max + 1))
        return v, v
    lo, hi = sorted(int(x) for x in rng.integers(lo_min, hi_max + 1, 2))
    return max(hi, lo + 1), lo                                           # lim_lo > lim_hi


def _errors(rng, width, n, pattern):
    """(ref, fb) arrays of ``n`` samples of the error ``pattern``."""
    lo, hi = -(1 << (width - 1)), (1 << (width - 1)) - 1
    if pattern == "uniform":
        return rng.integers(lo, hi + 1, n), rng.integers(lo, hi + 1, n)
    if pattern == "fullscale":
        choices = np.array([lo, hi, 0, -1, 1, lo + 1, hi - 1])
        return rng.choice(choices, n), rng.choice(choices, n)
    ref = rng.integers(lo // 2, hi // 2 + 1, n)
    amp = _log_uniform(rng, 1, hi // 2)
    if pattern == "small":
        err = np.round(rng.normal(0, amp, n)).astype(np.int64)
    elif pattern == "windup":
        # One-signed error for most of the segment, then the sign changes (recovery).
        split = int(rng.integers(n // 2, n))
        sign = 1 if rng.random() < 0.5 else -1
        err = sign * rng.integers(1, amp + 1, n)
        err[split:] = -sign * rng.integers(1, max(amp // 4, 1) + 1, n - split)
    else:                                                                # square
        period = int(rng.integers(2, 60))
        err = amp * np.where((np.arange(n) // period) % 2 == 0, 1, -1)
    fb = np.clip(ref - err, lo, hi)
    return ref, fb


def _segment(rng, width, kp_format, kx_format, n, pattern=None):
    if pattern is None:
        pattern = rng.choice(_PATTERNS, p=[0.2, 0.25, 0.3, 0.1, 0.15])
    ref, fb = _errors(rng, width, n, pattern)
    kp, kx = _gain(rng, kp_format), _gain(rng, kx_format)
    lim_lo, lim_hi = _limits(rng, width)
    if pattern == "windup" and rng.random() < 0.7:
        # Make the integrator reach its limit within the segment: a useful kx, moderate kp.
        kx = max(kx, _log_uniform(rng, 1 << max(kx_format.frac - 8, 0),
                                  min(1 << max(kx_format.frac - 2, 0), kx_format.max_raw)))
        kp = min(kp, min(1 << max(kp_format.frac, 0), kp_format.max_raw))
    const = np.ones(n, dtype=np.int64)
    return ref, fb, kp * const, kx * const, lim_lo * const, lim_hi * const


def _corners(width, kp_format, kx_format):
    """Named corner segments: list of (name, ref, fb, kp, kx, lim_lo, lim_hi) arrays."""
    lo, hi = -(1 << (width - 1)), (1 << (width - 1)) - 1
    kp_max, kx_max = kp_format.max_raw, kx_format.max_raw
    kp_one = min(1 << max(kp_format.frac, 0), kp_max)
    kx_small = min(1 << max(kx_format.frac - 6, 0), kx_max)
    out = []

    def seg(name, ref, fb, kp, kx, lim_lo, lim_hi):
        ref = np.asarray(ref, dtype=np.int64)
        c = np.ones(len(ref), dtype=np.int64)
        out.append((name, ref, np.asarray(fb, dtype=np.int64) * c,
                    kp * c, kx * c, lim_lo * c, lim_hi * c))

    fs_ref = np.array([hi, lo, hi, lo, lo, hi, hi, hi, lo, lo])
    fs_fb = np.array([lo, hi, lo, hi, lo, hi, hi, lo, lo, hi])
    seg("error_saturation_max_gains", fs_ref, fs_fb, kp_max, kx_max, lo, hi)
    seg("error_saturation_unit_gain", fs_ref, fs_fb, kp_one, kx_small, lo, hi)
    seg("error_saturation_zero_gains", fs_ref, fs_fb, 0, 0, lo, hi)
    # Windup: a long one-signed error pins the output, then the sign changes (recovery); both
    # directions; then the output pinned by P alone while I holds (conditional integration).
    a, b = max(hi // 8, 1), max(hi // 32, 1)
    for sign in (1, -1):
        seg(f"windup_recovery_{'pos' if sign > 0 else 'neg'}",
            np.zeros(300, dtype=np.int64), np.r_[np.full(250, -sign * a), np.full(50, sign * b)],
            kp_one, kx_small, -(hi // 4), hi // 4)
    seg("held_by_proportional", np.zeros(120, dtype=np.int64),
        np.r_[np.full(100, -a), np.full(20, b)], min(4 * kp_one, kp_max), kx_small,
        -(hi // 16), hi // 16)
    ramp = np.linspace(-(hi // 4), hi // 4, 20).round().astype(np.int64)
    seg("limits_equal", ramp, np.zeros(20, dtype=np.int64), kp_one, kx_small, hi // 64, hi // 64)
    seg("limits_inverted", ramp, np.zeros(20, dtype=np.int64), kp_one, kx_small, hi // 16,
        -(hi // 16))
    return out


def stimulus(count, *, seed=0, width=16, kp_format=UQ(16, 8), kx_format=UQ(16, 16),
             clear_rate=1 / 400):
    """Corner cases followed by ``count`` seeded random samples, plus random ``clear`` samples
    (about ``clear_rate · count`` extra samples, abandoned by a ``clear`` pulse, not compared).

    Returns
    -------
    dict of numpy int64 arrays, one entry per sample
        ``ref``, ``fb``, ``kp``, ``kx``, ``lim_lo``, ``lim_hi``; ``clear_at`` (−1, or the clock
        after acceptance at which a ``clear`` pulse abandons this sample) and ``clear_len``; and
        ``n_corner``, the number of corner samples at the start.
    """
    rng = np.random.default_rng(seed)
    parts = [c[1:] for c in _corners(width, kp_format, kx_format)]
    n_corner = sum(len(p[0]) for p in parts)
    n_clear = int(rng.binomial(count, clear_rate)) if count else 0
    done = 0
    while done < count + n_clear:
        n = min(int(rng.integers(50, 400)), count + n_clear - done)
        parts.append(_segment(rng, width, kp_format, kx_format, n))
        done += n
    keys = ("ref", "fb", "kp", "kx", "lim_lo", "lim_hi")
    stim = {k: np.concatenate([p[j] for p in parts]).astype(np.int64) for j, k in enumerate(keys)}
    total = len(stim["ref"])
    clear = np.zeros(total, dtype=bool)
    clear[n_corner + rng.choice(count + n_clear, n_clear, replace=False)] = True
    stim["clear_at"] = np.where(clear, rng.integers(0, PI_LATENCY, total), -1)
    stim["clear_len"] = rng.integers(1, 4, total)
    stim["n_corner"] = n_corner
    return stim



def run(count=100_000, *, seed=0, progress=False, **params):
    """Simulate :class:`PI` against :class:`PIModel` on the corner cases plus ``count`` random
    samples; ``params`` go to both (``width``, ``kp_format``, ``kx_format``, ``int_guard``).

    Every compared sample checks ``o.payload``, ``sat``, ``integrator`` and that ``o.valid`` is
    high exactly ``latency`` clocks after acceptance. A sample with a ``clear`` pulse checks
    instead that no strobe comes, inputs are accepted during ``clear``, and output, ``sat`` and
    integrator read 0 afterwards.

    Returns
    -------
    dict
        ``mismatches``, ``vectors`` (compared samples), ``clocks``, ``sim_s``, ``clocks_per_s``,
        ``saturated_samples`` (output clamped), ``windup_samples`` (integrator clamped or held),
        ``held_samples`` (held by conditional integration), ``recoveries`` (output pinned with a
        wound-up integrator, then inside the limits on the first sample after the error changed
        sign), ``error_saturations`` (``ref − fb`` saturated), ``clears``, ``first_mismatch``.
    """
    dut = PI(**params)
    if dut.latency != PI_LATENCY:
        raise RuntimeError(f"PI latency {dut.latency} differs from the verifier's {PI_LATENCY}")
    model = PIModel(**params)
    w = dut.width
    stim = stimulus(count, seed=seed, width=w, kp_format=dut.kp_format,
                    kx_format=dut.kx_format)
    cols = {k: stim[k].tolist() for k in ("ref", "fb", "kp", "kx", "lim_lo", "lim_hi",
                                          "clear_at", "clear_len")}
    total = len(cols["ref"])

    # Expected results from the model (None for a sample abandoned by clear).
    expected = []
    figures = dict(saturated_samples=0, windup_samples=0, held_samples=0, recoveries=0,
                   error_saturations=0, clears=0)
    prev = None
    for k in range(total):
        if cols["clear_at"][k] >= 0:
            model.clear()
            expected.append(None)
            figures["clears"] += 1
            prev = None
            continue
        out, sat = model.step(cols["ref"][k], cols["fb"][k], cols["kp"][k], cols["kx"][k],
                              cols["lim_lo"][k], cols["lim_hi"][k])
        last = model.last
        expected.append((out, sat, model.integrator))
        figures["saturated_samples"] += sat
        figures["windup_samples"] += bool(last["clamped"] or last["held"])
        figures["held_samples"] += bool(last["held"])
        figures["error_saturations"] += last["e"] != cols["ref"][k] - cols["fb"][k]
        if (prev is not None and prev["sat"] and (prev["clamped"] or prev["held"])
                and not sat and last["e"] * prev["e"] < 0):
            figures["recoveries"] += 1
        prev = last

    result = {"mismatches": 0, "first_mismatch": None}
    clocks = 0

    def mismatch(k, what, got, want):
        result["mismatches"] += 1
        if result["first_mismatch"] is None:
            result["first_mismatch"] = {"sample": k, "what": what, "got": got, "expected": want,
                                        **{c: cols[c][k] for c in cols}}

    bar = Progress("pi", total, enabled=progress)

    period = 1 / CLOCK_HZ

    # One wake-up per sample: the testbench sleeps whole clock periods and acts a quarter period
    # after the edges (the simulator keeps time in integer femtoseconds: no drift). ~35 % faster
    # than awaiting each tick.
    async def testbench(ctx):
        nonlocal clocks
        gains = None
        await ctx.tick()
        await ctx.delay(period / 4)
        ctx.set(dut.i.valid, 1)
        for k in range(total):
            g = (cols["kp"][k], cols["kx"][k], cols["lim_lo"][k], cols["lim_hi"][k])
            if g != gains:
                gains = g
                ctx.set(dut.kp, g[0])
                ctx.set(dut.kx, g[1])
                ctx.set(dut.lim_lo, g[2])
                ctx.set(dut.lim_hi, g[3])
            ctx.set(dut.i.payload, {"ref": cols["ref"][k], "fb": cols["fb"][k]})
            # The DUT is idle here: the next edge accepts the sample.
            want = expected[k]
            if want is None:
                at, length = cols["clear_at"][k], cols["clear_len"][k]
                if at:
                    await ctx.delay(at * period)
                ctx.set(dut.clear, 1)
                for _ in range(length):
                    if not ctx.get(dut.i.ready):
                        mismatch(k, "ready during clear", 0, 1)
                    await ctx.delay(period)
                ctx.set(dut.clear, 0)
                clocks += at + length
                got = (ctx.get(dut.o.valid), ctx.get(dut.o.payload), ctx.get(dut.sat),
                       ctx.get(dut.integrator), ctx.get(dut.i.ready))
                if got != (0, 0, 0, 0, 1):
                    mismatch(k, "after clear (valid, out, sat, integrator, ready)", got,
                             (0, 0, 0, 0, 1))
            else:
                await ctx.delay(PI_LATENCY * period)
                clocks += PI_LATENCY
                got = (ctx.get(dut.o.valid), ctx.get(dut.o.payload), ctx.get(dut.sat),
                       ctx.get(dut.integrator))
                if got != (1, *want):
                    mismatch(k, "(valid, out, sat, integrator)", got, (1, *want))
            if not k & 1023:
                bar.update(k)
        bar.close()

    sim_s = simulate(dut, [testbench], clock_hz=CLOCK_HZ, name="pi")
    result.update(vectors=total - figures["clears"], clocks=clocks, sim_s=sim_s,
                  clocks_per_s=clocks / sim_s if sim_s else 0.0, **figures)
    return result
