# Ref: paper eq. (1), (4)–(9), Fig. 7; SPEC.md §2 (current loop); issue 5 item 4
"""Gateware :class:`~foc_servo.hdl.foc.CurrentLoop` against its golden model, sample by sample.

The stimulus (per-sample inputs and configuration) and the golden model's expected outputs sit in
ROMs of a simulation-only wrapper. The wrapper presents the next sample as soon as the loop can
accept it (back to back, one every ``latency`` clocks), holds the configuration of the sample in
flight, and on every duty transfer compares all outputs (duties, overmodulation, phase currents,
i_α, i_β, i_d, i_q, u_d, u_q, u_α, u_β, PI and DC-bus flags, U_dc) with the expected word and
checks the latency; the testbench only ticks the clock. PI state carries across the whole
sequence, as it does in the model.
"""

import numpy as np
from amaranth.hdl import Module, Mux, Signal, signed, unsigned
from amaranth.lib import data, wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import Out

from ...hdl.fixed import Q, UQ, shape_range
from ...hdl.foc import CurrentLoop
from ..harness import Progress, simulate
from ..models.foc import CONFIG_FIELDS, SAMPLE_FIELDS, CurrentLoopModel

__all__ = ["run", "stimulus", "CHECKED_OUTPUTS"]

#: Outputs compared on every sample (gateware member or duty field ↔ model key).
CHECKED_OUTPUTS = ("duty_a", "duty_b", "duty_c", "overmod", "a", "b", "c", "i_alpha", "i_beta",
                   "i_d", "i_q", "u_d", "u_q", "u_alpha", "u_beta", "sat_d", "sat_q",
                   "dc_limited", "udc")


def _input_shapes(dut):
    """Shape of every per-sample and configuration input of ``dut`` (the engine's current loop
    has ``lead_k`` in place of ``theta_lead``)."""
    shapes = {}
    for name in SAMPLE_FIELDS + CONFIG_FIELDS + ("lead_k",):
        if name in ("ia", "ib", "udc"):
            shapes[name] = signed(dut.adc_width)
        elif name in dut.signature.members:
            shapes[name] = getattr(dut, name).shape()
    return shapes


def _output_shapes(dut):
    w = dut.width
    shapes = {name: signed(w) for name in CHECKED_OUTPUTS}
    shapes.update({f"duty_{p}": unsigned(dut.count_width) for p in "abc"})
    shapes.update({name: unsigned(1) for name in ("overmod", "sat_d", "sat_q", "dc_limited")})
    shapes["udc"] = signed(dut.adc_width)
    return shapes


def _log_uniform(rng, hi):
    return int(min(max(int(2.0 ** rng.uniform(0, np.log2(hi + 1))) - 1, 0), hi))


def stimulus(count, *, seed=0, width=16, adc_width=16, angle_width=16, count_width=16,
             clarke_gain_format=Q(18, 15), kp_format=UQ(16, 8), kx_format=UQ(16, 16)):
    """Seeded sample sequence: ``count`` random samples, then the corner cases.

    Random samples come in segments of 20 … 200 sharing a configuration (gains drawn
    log-uniformly, zero or at the maximum; limits full, symmetric, asymmetric, narrow or inverted;
    feed-forward scales zero, random or maximal; U_rated and the SVPWM scale typical, random or
    extreme) and a mode (closed loop, open loop, disabled; feed-forward on or off; the bits also
    toggle within a segment). θ rotates at a random speed or jumps at random; the phase codes are
    a balanced sinusoid at θ plus noise, or uniform over the whole range; U_dc near U_rated or
    anywhere (negative codes included); the references, speed and open-loop commands are random.
    Corner cases: full-scale codes and commands at the axes and at 45° (the CORDIC saturates),
    θ at the quarter turns and −π, U_dc and U_rated at 0 and full scale, SVPWM scale 0 and full,
    speed ±full scale with maximal feed-forward, inverted and zero-width limits.

    Returns
    -------
    dict of int64 arrays
        Every name of ``SAMPLE_FIELDS`` and ``CONFIG_FIELDS``.
    """
    rng = np.random.default_rng(seed)
    c_lo, c_hi = shape_range(signed(adc_width))
    w_lo, w_hi = shape_range(signed(width))
    turn = 1 << angle_width
    unity = 1 << clarke_gain_format.frac
    g_fit = int(min(round(unity * 2.0 ** (width - adc_width)), clarke_gain_format.max_raw))
    cw_max = (1 << count_width) - 1
    cols = {k: [] for k in SAMPLE_FIELDS + CONFIG_FIELDS}

    def gain(fmt):
        kind = rng.integers(6)
        if kind == 0:
            return 0
        if kind == 1:
            return fmt.max_raw
        return _log_uniform(rng, fmt.max_raw)

    def limits():
        kind = rng.choice(["full", "sym", "sym", "asym", "narrow", "inverted"],
                          p=[0.2, 0.35, 0.1, 0.15, 0.1, 0.1])
        if kind == "full":
            return w_lo, w_hi
        if kind == "sym":
            a = _log_uniform(rng, w_hi)
            return -a, a
        lo, hi = sorted(int(x) for x in rng.integers(w_lo, w_hi + 1, 2))
        if kind == "narrow":
            hi = min(lo + int(rng.integers(0, 64)), w_hi)
        if kind == "inverted":
            lo, hi = hi, lo
        return lo, hi

    done = 0
    while done < count:
        n = min(int(rng.integers(20, 201)), count - done)
        cfg = {}
        for p in "ab":
            kind = rng.integers(4)
            cfg[f"gain_{p}"] = (int(rng.choice([-1, 1]) * g_fit * rng.uniform(0.5, 1.5)) if kind
                                else int(rng.integers(clarke_gain_format.min_raw,
                                                      clarke_gain_format.max_raw + 1)))
            cfg[f"gain_{p}"] = int(np.clip(cfg[f"gain_{p}"], clarke_gain_format.min_raw,
                                           clarke_gain_format.max_raw))
            cfg[f"offset_{p}"] = (int(rng.integers(-200, 201)) if rng.integers(4)
                                  else int(rng.integers(2 * c_lo, 2 * c_hi + 2)))
        for ax in "dq":
            cfg[f"kp_{ax}"], cfg[f"kx_{ax}"] = gain(kp_format), gain(kx_format)
            cfg[f"lim_lo_{ax}"], cfg[f"lim_hi_{ax}"] = limits()
        for f in ("ff_l", "ff_psi"):
            kind = rng.integers(4)
            cfg[f] = (0, (1 << 16) - 1, _log_uniform(rng, (1 << 16) - 1),
                      int(rng.integers(0, 1 << 16)))[kind]
        kind = rng.integers(5)
        cfg["u_rated"] = ((int(rng.integers(1000, c_hi + 1)),) * 3 +
                          (int(rng.integers(0, 1 << adc_width)), int(rng.choice([0, c_hi]))))[kind]
        kind = rng.integers(5)
        cfg["scale"] = ((min(2500, cw_max),) * 2 + (int(rng.integers(0, cw_max + 1)),) +
                        (0, cw_max))[kind]
        for k, val in cfg.items():
            cols[k].append(np.full(n, val, dtype=np.int64))

        mode = rng.choice(["closed", "closed", "closed", "open", "off"])
        enable = np.full(n, mode != "off", dtype=np.int64)
        ol = np.full(n, mode == "open", dtype=np.int64)
        ff = np.full(n, rng.random() < 0.5, dtype=np.int64)
        for bits in (enable, ol, ff):
            flips = rng.random(n) < 0.02
            bits[flips] ^= 1
        cols["enable"].append(enable)
        cols["ol_enable"].append(ol)
        cols["ff_enable"].append(ff)

        if rng.random() < 0.7:
            step = int(rng.integers(-turn // 16, turn // 16 + 1))
            theta = (int(rng.integers(0, turn)) + step * np.arange(n)) % turn
        else:
            theta = rng.integers(0, turn, n)
        cols["theta"].append(theta)
        cols["theta_lead"].append(np.full(n, 0) if rng.random() < 0.5
                                  else rng.integers(0, turn, n))
        if rng.random() < 0.7:
            amp = rng.uniform(0, 1.2) * c_hi
            ph = theta * 2 * np.pi / turn + rng.uniform(-0.5, 0.5)
            noise = rng.normal(0, 30, (2, n))
            ia = amp * np.cos(ph) + cfg["offset_a"] + noise[0]
            ib = amp * np.cos(ph - 2 * np.pi / 3) + cfg["offset_b"] + noise[1]
            cols["ia"].append(np.clip(np.rint(ia), c_lo, c_hi).astype(np.int64))
            cols["ib"].append(np.clip(np.rint(ib), c_lo, c_hi).astype(np.int64))
        else:
            cols["ia"].append(rng.integers(c_lo, c_hi + 1, n))
            cols["ib"].append(rng.integers(c_lo, c_hi + 1, n))
        if rng.random() < 0.7:
            udc = cfg["u_rated"] * rng.uniform(0.4, 1.3) + rng.normal(0, 50, n)
            cols["udc"].append(np.clip(np.rint(udc), c_lo, c_hi).astype(np.int64))
        else:
            cols["udc"].append(rng.integers(c_lo, c_hi + 1, n))
        for name in ("id_ref", "iq_ref", "ol_ud", "ol_uq"):
            if rng.random() < 0.5:
                cols[name].append(np.full(n, int(rng.integers(w_lo, w_hi + 1))))
            else:
                scale_ = 1 << int(rng.integers(0, width))
                cols[name].append(np.clip(rng.integers(-scale_, scale_, n), w_lo, w_hi))
        spd = (int(rng.integers(-(1 << 31), 1 << 31)) if rng.random() < 0.5
               else int(rng.choice([-(1 << 31), (1 << 31) - 1, 0])))
        cols["speed"].append(np.full(n, spd) if rng.random() < 0.6
                             else rng.integers(-(1 << 31), 1 << 31, n))
        done += n

    # Corner cases, one sample each (closed loop with maximal feed-forward, then open loop).
    corners = []
    base = {"gain_a": g_fit, "gain_b": g_fit, "offset_a": 0, "offset_b": 0,
            "kp_d": kp_format.max_raw, "kx_d": kx_format.max_raw, "lim_lo_d": w_lo,
            "lim_hi_d": w_hi, "kp_q": kp_format.max_raw, "kx_q": kx_format.max_raw,
            "lim_lo_q": w_lo, "lim_hi_q": w_hi, "ff_l": (1 << 16) - 1, "ff_psi": (1 << 16) - 1,
            "u_rated": c_hi, "scale": cw_max, "theta_lead": 0, "id_ref": 0, "iq_ref": 0,
            "enable": 1, "ol_enable": 0, "ff_enable": 1, "ol_ud": 0, "ol_uq": 0, "udc": c_hi,
            "speed": 0}
    angles = [0, turn // 8, turn // 4, turn // 2, 3 * turn // 4, turn - 1]
    for theta in angles:
        for ia, ib in ((c_hi, c_hi), (c_lo, c_lo), (c_hi, c_lo), (0, 0)):
            for spd in (-(1 << 31), (1 << 31) - 1):
                corners.append({**base, "theta": theta, "ia": ia, "ib": ib, "speed": spd,
                                "id_ref": w_hi, "iq_ref": w_lo})
        for ud, uq in ((w_lo, w_lo), (w_hi, w_hi), (w_lo, 0), (0, w_hi)):
            for udc, rated in ((0, c_hi), (c_lo, c_hi), (c_hi, 0), (1, c_hi), (c_hi, c_hi)):
                corners.append({**base, "theta": theta, "ia": 0, "ib": 0, "ol_enable": 1,
                                "ol_ud": ud, "ol_uq": uq, "udc": udc, "u_rated": rated,
                                "scale": (0, cw_max)[udc & 1], "theta_lead": turn // 2})
    for lo, hi in ((w_hi, w_lo), (0, 0), (5, 5)):
        corners.append({**base, "theta": 0, "ia": c_hi, "ib": 0, "lim_lo_d": lo, "lim_hi_d": hi,
                        "lim_lo_q": lo, "lim_hi_q": hi})
    for k in cols:
        cols[k].append(np.array([c[k] for c in corners], dtype=np.int64))
    return {k: np.concatenate(v).astype(np.int64) for k, v in cols.items()}


def _pack(layout, columns, n):
    """Pack integer columns (dict name → array, ``n`` long) into raw words of ``layout``."""
    words = [0] * n
    for name, field in layout:
        mask = (1 << field.width) - 1
        vals = (np.asarray(columns[name], dtype=np.int64) & mask).tolist()
        words = [w | (v << field.offset) for w, v in zip(words, vals)]
    return words


class _CurrentLoopBench(wiring.Component):
    """Simulation-only wrapper: sample ROM → CurrentLoop → compare with the expected-output ROM.

    ``mismatches`` counts samples whose outputs differ from the expected word (plus surplus
    results); ``latency_errors`` duty transfers not exactly ``latency`` clocks after their
    sample; ``overruns`` samples the loop dropped.
    """

    accepted: Out(32)
    received: Out(32)
    mismatches: Out(32)
    latency_errors: Out(32)
    first_mismatch: Out(32, init=0xFFFF_FFFF)

    def __init__(self, dut, in_layout, stim_words, out_layout, exp_words):
        self._dut = dut
        self._in_layout = in_layout
        self._stim = stim_words
        self._out_layout = out_layout
        self._exp = exp_words
        super().__init__()

    def elaborate(self, platform):
        m = Module()
        m.submodules.dut = dut = self._dut
        n = len(self._stim)
        m.submodules.stim = stim = Memory(shape=unsigned(self._in_layout.size), depth=n,
                                          init=self._stim)
        m.submodules.exp = exp = Memory(shape=unsigned(self._out_layout.size), depth=n,
                                        init=self._exp)
        srd = stim.read_port(domain="comb")
        erd = exp.read_port(domain="comb")

        running = self.accepted < n
        accept = running & (~dut.busy | dut.done)
        held = Signal(self._in_layout)          # the configuration of the sample in flight
        word = data.View(self._in_layout, Mux(accept, srd.data, held.as_value()))
        m.d.comb += [srd.addr.eq(self.accepted), erd.addr.eq(self.received)]
        with m.If(accept):
            m.d.sync += [held.eq(srd.data), self.accepted.eq(self.accepted + 1)]
        m.d.comb += [
            dut.i.valid.eq(accept),           # never offered while busy: no overruns
            dut.i.payload.ia.eq(word.ia),
            dut.i.payload.ib.eq(word.ib),
            dut.i.payload.udc.eq(word.udc),
            dut.o.ready.eq(1),
        ]
        for name, _ in self._in_layout:
            if name not in ("ia", "ib", "udc"):
                m.d.comb += getattr(dut, name).eq(word[name])

        # Latency: clocks since the sample was accepted.
        since = Signal(16)
        m.d.sync += since.eq(Mux(accept, 1, since + 1))

        # Capture the duties on the transfer; compare everything one clock later, when every
        # status register of this sample has settled (and none of the next sample's has).
        duties = Signal(data.StructLayout({p: unsigned(dut.count_width) for p in "abc"}))
        udc = Signal(signed(dut.adc_width))     # the next sample may replace it on the transfer
        check = Signal()
        m.d.sync += check.eq(dut.done)
        with m.If(dut.done):
            m.d.sync += [duties.eq(dut.o.payload), udc.eq(dut.udc.payload)]
            with m.If(since != dut.latency):
                m.d.sync += self.latency_errors.eq(self.latency_errors + 1)
        got = Signal(self._out_layout)
        for name, _ in self._out_layout:
            if name.startswith("duty_"):
                value = duties[name[-1]]
            elif name in ("a", "b", "c"):
                value = dut.phase.payload[name]
            elif name == "udc":
                value = udc
            else:
                value = getattr(dut, name)
            m.d.comb += got[name].eq(value)
        with m.If(check):
            m.d.sync += self.received.eq(self.received + 1)
            bad = (self.received >= n) | (got.as_value() != erd.data)
            with m.If(bad):
                m.d.sync += self.mismatches.eq(self.mismatches + 1)
                with m.If(self.mismatches == 0):
                    m.d.sync += self.first_mismatch.eq(self.received)
        return m


def run(count=100_000, *, seed=0, progress=False, **params):
    """Simulate :class:`CurrentLoop` on ``count`` seeded random samples plus the corner cases and
    compare every output of every sample with :class:`CurrentLoopModel`.

    Parameters
    ----------
    count : int
        Random samples (the corner cases come on top).
    **params
        :class:`CurrentLoop` parameters.

    Returns
    -------
    dict
        ``mismatches`` (samples with any output wrong or missing), ``vectors`` (samples),
        ``clocks``, ``sim_s``, ``clocks_per_s``, ``latency`` and ``stage_latency``,
        ``latency_errors`` (transfers not ``latency`` clocks after their sample), ``overruns``
        (must be 0: the bench never offers a sample early), ``first_mismatch`` (index or
        ``None``), and coverage counts over the samples: ``closed_loop``, ``open_loop``,
        ``feedforward``, ``pi_saturated``, ``overmodulated``, ``dc_limited``.
    """
    dut = CurrentLoop(**params)
    model_params = {k: v for k, v in params.items() if k != "count_width"}
    stim_params = {k: v for k, v in params.items()
                   if k in ("width", "adc_width", "angle_width", "count_width",
                            "clarke_gain_format", "kp_format", "kx_format")}
    vec = stimulus(count, seed=seed, **stim_params)
    n = vec["ia"].size
    exp = CurrentLoopModel(**model_params).run(**vec)

    in_layout = data.StructLayout(_input_shapes(dut))
    out_layout = data.StructLayout(_output_shapes(dut))
    bench = _CurrentLoopBench(dut, in_layout, _pack(in_layout, vec, n), out_layout,
                              _pack(out_layout, exp, n))
    clocks = n * dut.latency + 4
    result = {}
    prog = Progress("current loop", clocks, enabled=progress)

    async def testbench(ctx):
        await prog.ticks(ctx, clocks)
        for name in ("received", "mismatches", "latency_errors", "first_mismatch"):
            result[name] = ctx.get(getattr(bench, name))
        result["overruns"] = ctx.get(dut.overruns)

    sim_s = simulate(bench, [testbench], name="foc")
    prog.close()
    missing = n - min(result["received"], n)
    first = result["first_mismatch"]
    if first == 0xFFFF_FFFF and missing:
        first = result["received"]
    closed = (vec["enable"] != 0) & (vec["ol_enable"] == 0)
    return {
        "mismatches": result["mismatches"] + missing,
        "vectors": n,
        "clocks": clocks,
        "sim_s": sim_s,
        "clocks_per_s": clocks / sim_s if sim_s > 0 else float("inf"),
        "latency": dut.latency,
        "stage_latency": dut.stage_latency,
        "latency_errors": result["latency_errors"],
        "overruns": result["overruns"],
        "first_mismatch": None if first == 0xFFFF_FFFF else int(first),
        "closed_loop": int(closed.sum()),
        "open_loop": int((vec["ol_enable"] != 0).sum()),
        "feedforward": int((closed & (vec["ff_enable"] != 0)).sum()),
        "pi_saturated": int(((exp["sat_d"] != 0) | (exp["sat_q"] != 0)).sum()),
        "overmodulated": int(exp["overmod"].sum()),
        "dc_limited": int(exp["dc_limited"].sum()),
    }
