# amaranth: UnusedElaboratable=no
# Ref: SPEC.md §2.3 (encoder A/B/Z + Hall, ×4 position counter); §4 (synchronisers, glitch filters);
#      issue 6 item 7 (encoder/Hall plausibility check)
import numpy as np
import pytest
from amaranth.back import verilog
from amaranth.hdl import Cat, Module, ResetInserter, Signal
from amaranth.lib import wiring

import foc_servo.hdl.encoder as hdl_encoder
import foc_servo.sim.verify.encoder as verify_encoder
from foc_servo.hdl.encoder import (HALL_CODES, EncoderFrontEnd, GlitchFilter, HallPlausibility,
                                   HallSensor, QuadratureDecoder, angle_constants, divide_angle,
                                   hall_boundaries, hall_centres)
from foc_servo.sim.harness import simulate
from foc_servo.sim.models import encoder as model

AB = ((0, 0), (1, 0), (1, 1), (0, 1))       # quadrature state of phase 0 … 3


@pytest.fixture(params=[True, False], ids=["fold_reload", "reload_select"])
def fold_form(request, monkeypatch):
    """Both forms of the glitch filter's counter (``fold_reload``, the iCE40's and the default;
    ``rem − 1`` and a select, the ECP5's and the Spartan-7's): the default of the filter's and
    the front end's constructors (also where sim.verify.encoder builds them) set to one, the
    test run once with each."""
    for cls in (GlitchFilter, EncoderFrontEnd):
        monkeypatch.setitem(cls.__init__.__kwdefaults__, "fold_reload", request.param)
    return request.param


@pytest.fixture(params=[True, False], ids=["complement", "difference"])
def complement_form(request, monkeypatch):
    """Both forms of the plausibility check's differences (``complement``: ``~d`` and
    ``d_prev − d``, the iCE40's and the front end's default; ``d`` and ``d − d_prev`` behind an
    operand select, the ECP5's and the Spartan-7's): the default of the check's and the front
    end's constructors (also where sim.verify.encoder builds the front end) set to one, the
    test run once with each."""
    monkeypatch.setitem(HallPlausibility.__init__.__kwdefaults__, "complement", request.param)
    monkeypatch.setitem(EncoderFrontEnd.__init__.__kwdefaults__, "plausibility_complement",
                        request.param)
    return request.param


def pins(a=0, b=0, z=0, hall=HALL_CODES[0]):
    return a | (b << 1) | (z << 2) | (hall << 3)


def run_front_end(dut, pin_words, **config):
    """Drive an EncoderFrontEnd one clock per entry of ``pin_words`` (config constant) and return
    the outputs before the first edge and after each one, as the model's ``front_end`` does."""
    names = model.OUTPUTS
    rec = {k: [] for k in names}

    lp, zc = (int(s[0]) for s in model.change_strobes(
        config.get("lines", 5000), config.get("pole_pairs", 4), config.get("z_offset", 0)))

    async def testbench(ctx):
        for key, value in config.items():
            ctx.set(getattr(dut, key), value)
        ctx.set(dut.lp_changed, lp)             # the register file's change strobes
        ctx.set(dut.z_changed, zc)
        for word in list(pin_words) + [pin_words[-1]]:
            for k in names:
                rec[k].append(ctx.get(getattr(dut, k)))
            ctx.set(Cat(dut.a, dut.b, dut.z, dut.hall), int(word))
            await ctx.tick()
            ctx.set(dut.lp_changed, 0)
            ctx.set(dut.z_changed, 0)

    simulate(dut, [testbench], name="test_encoder")
    return {k: np.array(v[:len(pin_words) + 1], dtype=np.int64) for k, v in rec.items()}


def walk_pins(steps, *, dwell=1, start=0, z_at=None, hall=HALL_CODES[0]):
    """Pin words of a walk of ±1/0 ``steps``, ``dwell`` clocks per state; Z high at position
    ``z_at``."""
    pos, out = start, []
    for s in [0] + list(steps):
        pos += s
        a, b = AB[pos % 4]
        out.extend([pins(a, b, int(z_at is not None and pos == z_at), hall)] * dwell)
    return out


# --- parameters -----------------------------------------------------------------------------

def test_glitch_filter_parameter_validation():
    with pytest.raises(TypeError, match=r"^GlitchFilter width must be an integer from 1 to 64, "
                                        r"not 0$"):
        GlitchFilter(width=0)
    with pytest.raises(TypeError, match=r"^GlitchFilter max_length must be an integer from 1 to "
                                        r"65535, not 'x'$"):
        GlitchFilter(max_length="x")
    with pytest.raises(TypeError, match=r"^EncoderFrontEnd max_length must be an integer from 1 "
                                        r"to 65535, not True$"):
        EncoderFrontEnd(max_length=True)


def test_glitch_filter_fold_reload_validation_and_default():
    assert GlitchFilter().fold_reload is True
    assert GlitchFilter(fold_reload=False).fold_reload is False
    assert EncoderFrontEnd.__init__.__kwdefaults__["fold_reload"] is True
    with pytest.raises(TypeError, match="GlitchFilter fold_reload must be a bool, not 0"):
        GlitchFilter(fold_reload=0)


def test_quadrature_z_gate_validation():
    with pytest.raises(TypeError, match=r"^QuadratureDecoder z_gate must be None or an integer "
                                        r"from 0 to 3, not 4$"):
        QuadratureDecoder(z_gate=4)
    with pytest.raises(TypeError, match=r"^EncoderFrontEnd z_gate must be None or an integer "
                                        r"from 0 to 3, not '1'$"):
        EncoderFrontEnd(z_gate="1")


# --- glitch filter --------------------------------------------------------------------------

@pytest.mark.usefixtures("fold_form")
def test_glitch_filter_every_length_and_width_cycle_by_cycle():
    """Lengths 0 … 8, pulses of 1 … length + 3 clocks of both polarities: the output matches
    the model on every clock, a pulse is passed iff it lasts ≥ max(length, 1) clocks, and then
    exactly max(length, 1) clocks after it starts."""
    dut = GlitchFilter(width=2, max_length=8)
    errors = []

    async def testbench(ctx):
        ref = model.GlitchFilterModel(2)
        for length in range(9):
            ctx.set(dut.length, length)
            for pol in (0, 1):
                for w in range(1, length + 4):
                    base = 0b11 if pol else 0b00
                    # The lead-in lets the output settle on `base` (from 0 at reset).
                    wave = [base] * (length + 3) + [base ^ 0b01] * w + [base] * (length + 3)
                    seen_at = None
                    for t, word in enumerate(wave):
                        ctx.set(dut.i, word)
                        await ctx.tick()
                        want = ref.tick(word, length)
                        got = ctx.get(dut.o)
                        if got != want:
                            errors.append(("model", length, w, t, got, want))
                        if seen_at is None and t >= length + 3 and (got ^ base) & 1:
                            seen_at = t
                    start = length + 3
                    if w >= max(length, 1):
                        if seen_at != start + max(length, 1) - 1:
                            errors.append(("latency", length, w, seen_at))
                    elif seen_at is not None:
                        errors.append(("short pulse passed", length, w, seen_at))

    simulate(dut, [testbench], name="test_glitch_filter")
    assert errors == []


@pytest.mark.usefixtures("fold_form")
def test_glitch_filter_random_with_length_changes_vs_model():
    rng = np.random.default_rng(3)
    n = 3000
    words = (rng.random(n) < 0.5).astype(int) * 5 + (rng.random(n) < 0.2).astype(int) * 2
    lengths = np.repeat(rng.integers(0, 8, n // 100), 100)
    dut = GlitchFilter(width=3, max_length=7)
    got = []

    async def testbench(ctx):
        for word, length in zip(words.tolist(), lengths.tolist()):
            ctx.set(dut.i, word)
            ctx.set(dut.length, length)
            await ctx.tick()
            got.append(ctx.get(dut.o))

    simulate(dut, [testbench], name="test_glitch_filter_random")
    ref = model.GlitchFilterModel(3)
    want = [ref.tick(w, ln) for w, ln in zip(words.tolist(), lengths.tolist())]
    assert got == want
    assert len(set(got)) == 4         # every output combination occurred


@pytest.mark.usefixtures("fold_form")
def test_glitch_filter_targets_through_front_end():
    """Pulses on A, B, Z and a Hall input at lengths 0 … 6 and 20: never a short one counted,
    never a long one missed, exact threshold at max(length, 1)."""
    r = verify_encoder.run_events(lengths=[0, 1, 2, 3, 4, 6, 20], seed=5)
    assert r["glitch_pulses"] > 100
    assert r["glitch_short_counted"] == 0
    assert r["glitch_long_missed"] == 0
    assert r["glitch_threshold_errors"] == 0
    assert r["illegal_detected"] == r["illegal_injected"] > 0
    assert r["hall_fault_detected"] == r["hall_fault_injected"] > 0
    assert r["hall_fault_false"] == 0


# --- quadrature decoder ---------------------------------------------------------------------

def test_quadrature_latency_cycle_by_cycle():
    """A pin change reaches count, step, up and a_rise exactly latency + max(length, 1) − 1
    clocks later; the strobes last one clock."""
    for length in (0, 1, 3):
        dut = EncoderFrontEnd(max_length=7)
        settle = length + 8
        wave = [pins(0, 0)] * settle + [pins(1, 0)] * 12
        out = run_front_end(dut, wave, length=length)
        lat = dut.latency + max(length, 1) - 1
        # The pin changes during clock `settle`; out[t + 1] is after edge t.
        new = settle + lat
        assert out["count"][new - 1] == 0 and out["count"][new] == 1
        assert out["step"][new - 1] == 0 and out["step"][new] == 1 and out["step"][new + 1] == 0
        assert out["a_rise"][new] == 1 and out["up"][new] == 1


def test_quadrature_direction_a_rise_and_wrap_at_cpr():
    """lines = 3 (cpr 12): 30 counts forward then 30 back; count wraps at exactly 12; a_rise
    once per line in each direction; up follows the direction."""
    dut = EncoderFrontEnd()
    steps = [1] * 30 + [-1] * 30
    wave = [pins()] * 100 + walk_pins(steps, dwell=2)      # lines = 3 committed in the lead-in
    wave += [wave[-1]] * 8
    out = run_front_end(dut, wave, lines=3)
    want = model.front_end(wave, lines=3)
    for k in model.OUTPUTS:
        np.testing.assert_array_equal(out[k], want[k], err_msg=k)
    counts = out["count"][out["step"] == 1]
    assert counts.max() == 11
    np.testing.assert_array_equal(counts[:14], [(k + 1) % 12 for k in range(14)])
    np.testing.assert_array_equal(counts[30:34], [5, 4, 3, 2])   # 30 mod 12 = 6, going back
    ups = out["up"][out["step"] == 1]
    assert ups[:30].all() and not ups[30:].any()
    # A rises on reaching positions 1, 5, …, 29 going forward and 26, 22, …, 2 going back.
    assert out["a_rise"].sum() == 8 + 7


def test_quadrature_illegal_transition_strobe_without_count():
    dut = EncoderFrontEnd()
    wave = [pins(0, 0)] * 10 + [pins(1, 1)] * 3 + [pins(0, 1)] * 3 + [pins(1, 0)] * 8
    out = run_front_end(dut, wave)
    assert out["illegal"].sum() == 2 and out["step"].sum() == 1   # 00→11 and 01→10 illegal
    assert out["count"][-1] == 1                 # 11 → 01 is one count forward
    np.testing.assert_array_equal(out["illegal"], model.front_end(wave)["illegal"])


# --- index ----------------------------------------------------------------------------------

def test_index_first_z_aligns_and_loads_offset():
    """The first Z sets aligned, clears count and loads e with z_offset; theta switches from the
    Hall centre to floor(e·2**16 / cpr) one clock later (``theta_latency``: the decoder's angle
    registered); a second Z only strobes index."""
    dut = EncoderFrontEnd()
    z_offset = 7777
    steps = [1] * 10 + [-1] * 8 + [1] * 10
    wave = [pins()] * 100 + walk_pins(steps, dwell=2, start=-4, z_at=0)
    wave += [wave[-1]] * 8
    out = run_front_end(dut, wave, z_offset=z_offset, hall_offset=1000)
    want = model.front_end(wave, z_offset=z_offset, hall_offset=1000)
    for k in model.OUTPUTS:
        np.testing.assert_array_equal(out[k], want[k], err_msg=k)
    first = int(np.argmax(out["aligned"]))
    assert out["index"][first] == 1 and out["count"][first] == 0 and out["e"][first] == z_offset
    assert out["theta"][first] == (hall_centres()[0] + 1000) % 65536
    assert out["theta"][first + 1] == (z_offset << 16) // 20000
    assert EncoderFrontEnd.theta_latency == EncoderFrontEnd.latency + 1
    # Later index events (passing Z again going back and forth) do not realign.
    assert out["index"].sum() >= 2
    e = out["e"][first:]
    cnt = out["count"][first:]
    np.testing.assert_array_equal(e, (4 * cnt + z_offset) % 20000)


def test_index_gated_marks_same_state_in_both_directions():
    """With z_gate, Z (two counts wide) is only taken in the gated state: aligning from either
    side gives count 0 at the same A/B state."""
    gate = 2                                     # (A, B) = (1, 0): phase 1
    for direction in (1, -1):
        dut = EncoderFrontEnd(z_gate=gate)
        start = -6 if direction == 1 else 6
        pos, wave = start, [pins()] * 10
        for _ in range(12):
            a, b = AB[pos % 4]
            wave += [pins(a, b, int(pos in (0, 1)))] * 2
            pos += direction
        wave += [wave[-1]] * 8
        out = run_front_end(dut, wave)
        np.testing.assert_array_equal(out["aligned"],
                                      model.front_end(wave, z_gate=gate)["aligned"])
        first = int(np.argmax(out["aligned"]))
        assert out["count"][first] == 0
        # The count afterwards is the position relative to phase 1 (position 1).
        last = out["count"][-1]
        want = (pos - direction - 1) % 20000
        assert last == want, (direction, last, want)


def test_index_realign_and_config_change_drop_alignment():
    """realign: the next Z realigns; a new z_offset applies at once (still aligned); a new line
    count or pole-pair count clears the alignment after config_latency clocks."""
    dut = EncoderFrontEnd()
    rec = []

    async def testbench(ctx):
        word = Cat(dut.a, dut.b, dut.z, dut.hall)

        async def tick(k=1):
            for _ in range(k):
                await ctx.tick()
                rec.append({n: ctx.get(getattr(dut, n)) for n in ("aligned", "e", "count",
                                                                  "busy", "theta")})

        ctx.set(word, pins())
        await tick(10)
        ctx.set(word, pins(z=1))
        await tick(6)
        ctx.set(word, pins(1, 0))
        await tick(6)
        assert rec[-1]["aligned"] == 1 and rec[-1]["count"] == 1 and rec[-1]["e"] == 4
        ctx.set(dut.z_offset, 100)
        ctx.set(dut.z_changed, 1)
        await tick(1)
        ctx.set(dut.z_changed, 0)
        assert rec[-1]["busy"] == 1
        await tick(dut.config_latency - 2)
        assert rec[-1]["e"] == 4 and rec[-1]["busy"] == 1
        await tick(1)
        assert rec[-1]["e"] == 104 and rec[-1]["aligned"] == 1 and rec[-1]["busy"] == 0
        assert rec[-1]["theta"] == (4 << 16) // 20000           # theta: a clock later
        ctx.set(dut.realign, 1)
        await tick(1)
        ctx.set(dut.realign, 0)
        assert rec[-1]["aligned"] == 0
        assert rec[-1]["theta"] == (104 << 16) // 20000
        ctx.set(word, pins(1, 0, 1))
        await tick(6)
        assert rec[-1]["aligned"] == 1 and rec[-1]["count"] == 0 and rec[-1]["e"] == 100
        ctx.set(dut.lines, 1024)
        ctx.set(dut.lp_changed, 1)
        await tick(1)
        ctx.set(dut.lp_changed, 0)
        await tick(dut.config_latency - 1)
        assert rec[-1]["aligned"] == 0 and rec[-1]["busy"] == 0 and rec[-1]["count"] == 0
        ctx.set(dut.lines, 1)                   # cpr 4 ≤ pole_pairs: invalid
        ctx.set(dut.lp_changed, 1)
        await tick(1)
        ctx.set(dut.lp_changed, 0)
        await tick(dut.config_latency - 1)
        assert ctx.get(dut.config_error) == 1
        ctx.set(word, pins(1, 0, 0))
        await tick(4)
        ctx.set(word, pins(1, 0, 1))
        await tick(6)
        assert rec[-1]["aligned"] == 0          # never aligns while the config is invalid

    simulate(dut, [testbench], name="test_encoder_realign")


def test_angle_constants_match_divmod():
    assert angle_constants(5000, 4, 0) == (13, 2144, 0, 0, True)
    qp, rp, qz, rz, ok = angle_constants(997, 7, 3000)
    assert divmod(7 << 16, 3988) == (qp, rp) and divmod(3000 << 16, 3988) == (qz, rz) and ok
    assert angle_constants(3, 12, 0)[4] is False        # pole_pairs ≥ cpr
    # cpr = 0: every step "fits", the remainder is n·2**16 mod 2**18 (invalid: config_error).
    assert angle_constants(0, 1, 0)[:2] == (0xFFFF, 1 << 16)


async def _strobed_clock(ctx, dut, dec, names, pins, cfg, lp, zc):
    """One clock of the decoder ``dut`` and its model ``dec`` with the pins ``(a, b, z)``, the
    configuration ``cfg`` (lines, pole_pairs, z_offset) and its change strobes: ``names``'
    outputs of both after it, (gateware, model)."""
    a, b, zz = pins
    for port, v in ((dut.a, a), (dut.b, b), (dut.z, zz), (dut.lines, cfg[0]),
                    (dut.pole_pairs, cfg[1]), (dut.z_offset, cfg[2]),
                    (dut.lp_changed, lp), (dut.z_changed, zc)):
        ctx.set(port, v)
    await ctx.tick()
    dec.tick(a, b, zz, lines=cfg[0], pole_pairs=cfg[1], z_offset=cfg[2],
             lp_changed=lp, z_changed=zc)
    return (tuple(ctx.get(getattr(dut, k)) for k in names),
            tuple(int(getattr(dec, k)) for k in names))


def test_decoder_invalid_configurations_theta_vs_model():
    """Invalid configurations (z_offset or pole_pairs ≥ cpr, lines 0) leave whatever the 16
    division steps give, remainders ≥ cpr included: the decoder's theta, e, count, busy and
    config_error follow the model clock for clock through a sequence of them (and valid ones
    in between), with counting pins."""
    dut = QuadratureDecoder()
    configs = [(1, 1, 5), (1, 3, 0), (0, 1, 0), (3, 12, 7), (997, 7, 3000), (2, 1, 200000),
               (5000, 4, 19999), (1, 1, 3), (65535, 255, 262139), (7, 40, 1)]
    dec = model.QuadratureDecoderModel()
    names = ("theta", "e", "count", "busy", "config_error", "aligned")
    mism = []

    async def testbench(ctx):
        pos = 0
        prev = (5000, 4, 0)
        for lines, pp, z in configs:
            ctx.set(dut.lines, lines)
            ctx.set(dut.pole_pairs, pp)
            ctx.set(dut.z_offset, z)
            ctx.set(dut.lp_changed, (lines, pp) != prev[:2])
            ctx.set(dut.z_changed, z != prev[2])
            prev = (lines, pp, z)
            for k in range(dut.config_latency + 40):
                if k == 1:
                    ctx.set(dut.lp_changed, 0)
                    ctx.set(dut.z_changed, 0)
                pos += 1 if k % 3 else -1
                a, b = AB[pos % 4]
                zz = int(k == dut.config_latency + 10)
                ctx.set(dut.a, a)
                ctx.set(dut.b, b)
                ctx.set(dut.z, zz)
                await ctx.tick()
                dec.tick(a, b, zz, lines=lines, pole_pairs=pp, z_offset=z)
                got = tuple(ctx.get(getattr(dut, n)) for n in names)
                want = tuple(int(getattr(dec, n)) for n in names)
                if got != want:
                    mism.append(((lines, pp, z), k, got, want))

    simulate(dut, [testbench], name="test_encoder_invalid_theta")
    assert not mism, mism[:3]


def test_decoder_change_strobes_in_and_out_of_a_sequence_vs_model():
    """Configuration changes with their strobes at random clocks, many of them while a sequence
    runs (joined in its first clock / up to its 19th, or run again after its commit), ``lines``
    changes in the middle of a division included: every output follows the model clock for
    clock."""
    rng = np.random.default_rng(21)
    n = 6000
    dut = QuadratureDecoder()
    dec = model.QuadratureDecoderModel()
    names = ("theta", "e", "count", "busy", "config_error", "aligned", "step", "up", "index")
    cases = {"idle": 0, "lp_join": 0, "lp_again": 0, "z_join": 0, "z_again": 0, "lp_at_2": 0,
             "z_at_take_p": 0, "z_after_take_p": 0}
    mism = []
    choices = [(5000, 4, 0), (5000, 4, 777), (997, 7, 3000), (1024, 5, 10), (64, 3, 255),
               (3, 12, 7)]

    async def testbench(ctx):
        pos = 0
        cfg = [5000, 4, 0]
        for t in range(n):
            lp = zc = 0
            edge = dec.timer in (1, 2, dec.TAKE_P, dec.TAKE_P + 1)    # the windows' ends
            if rng.random() < (0.4 if edge else 0.05):
                new = choices[rng.integers(len(choices))]
                which = rng.integers(1, 8)              # any non-empty subset of the three
                for k in range(3):
                    if which >> k & 1:
                        cfg[k] = new[k]
                lp = int((cfg[0], cfg[1]) != (ctx.get(dut.lines), ctx.get(dut.pole_pairs)))
                zc = int(cfg[2] != ctx.get(dut.z_offset))
                timer = dec.timer
                if lp:
                    cases["idle" if not timer else "lp_join" if timer == 1 else "lp_again"] += 1
                    cases["lp_at_2"] += timer == 2
                if zc and timer:
                    cases["z_join" if timer <= dec.TAKE_P else "z_again"] += 1
                    cases["z_at_take_p"] += timer == dec.TAKE_P
                    cases["z_after_take_p"] += timer == dec.TAKE_P + 1
            if rng.random() < 0.6:
                pos += 1 if rng.random() < 0.7 else -1
            a, b = AB[pos % 4]
            zz = int(pos % 40 == 0)
            got, want = await _strobed_clock(ctx, dut, dec, names, (a, b, zz), cfg, lp, zc)
            if got != want:
                mism.append((t, got, want))

    simulate(dut, [testbench], name="test_encoder_change_strobes")
    assert not mism, mism[:3]
    assert min(cases.values()) >= 3, cases


@pytest.mark.parametrize("kind, at, runs", [("lp", 1, 1), ("lp", 2, 2), ("z", 19, 1),
                                            ("z", 20, 2)])
def test_decoder_strobe_while_busy_joins_or_runs_again(kind, at, runs):
    """A z_offset change starts a sequence; a second change arrives ``at`` clocks later (the
    sequence's timer): joined (one sequence) up to the clock its input is read, else run again
    after the commit (two); every output as the model's, clock for clock, counting pins."""
    dut = QuadratureDecoder()
    dec = model.QuadratureDecoderModel()
    names = ("theta", "e", "count", "busy", "config_error", "aligned")
    mism, busy = [], []

    async def testbench(ctx):
        pos, cfg = 0, [5000, 4, 0]
        for t in range(3 * dut.config_latency + 40):
            lp = zc = 0
            if t == 20:
                cfg[2], zc = 1234, 1
            if t == 20 + at:
                if kind == "lp":
                    cfg[0], cfg[1], lp = 997, 7, 1
                else:
                    cfg[2], zc = 3000, 1
            pos += 1 if t % 3 else 0
            a, b = AB[pos % 4]
            zz = int(t == 5)
            got, want = await _strobed_clock(ctx, dut, dec, names, (a, b, zz), cfg, lp, zc)
            busy.append(got[3])
            if got != want:
                mism.append((t, got, want))

    simulate(dut, [testbench], name="test_encoder_strobe_while_busy")
    assert not mism, mism[:3]
    assert sum(busy) == runs * (dut.config_latency - 1)


def test_decoder_reset_configuration_needs_no_strobe():
    """``lines_init`` … ``z_offset_init``: the inputs hold the reset configuration from reset on
    without a strobe (a register file's reset values): no sequence, the angle exact at once;
    an invalid one is a config_error from reset. Parameters checked."""
    with pytest.raises(TypeError, match=r"^EncoderFrontEnd pole_pairs_init must be an integer "
                                        r"from 0 to 255, not 256$"):
        EncoderFrontEnd(pole_pairs_init=256)
    with pytest.raises(TypeError, match=r"^QuadratureDecoder z_offset_init must be an integer "
                                        r"from 0 to 262143, not 'x'$"):
        QuadratureDecoder(z_offset_init="x")
    for cfg in ((997, 7, 3000), (0, 4, 0)):
        dut = QuadratureDecoder(lines_init=cfg[0], pole_pairs_init=cfg[1], z_offset_init=cfg[2])
        dec = model.QuadratureDecoderModel(lines=cfg[0], pole_pairs=cfg[1], z_offset=cfg[2])
        names = ("theta", "e", "count", "busy", "config_error", "aligned")
        mism, seen = [], set()

        async def testbench(ctx):
            pos = 0
            for t in range(300):
                pos += 1 if t % 4 else 0
                a, b = AB[pos % 4]
                zz = int(t == 30)
                ctx.set(dut.a, a)
                ctx.set(dut.b, b)
                ctx.set(dut.z, zz)
                await ctx.tick()
                dec.tick(a, b, zz, lines=cfg[0], pole_pairs=cfg[1], z_offset=cfg[2])
                got = tuple(ctx.get(getattr(dut, k)) for k in names)
                seen.add(got[3:6])
                if got != tuple(int(getattr(dec, k)) for k in names):
                    mism.append((t, got))

        simulate(dut, [testbench], name="test_encoder_reset_config")
        assert not mism, mism[:3]
        assert seen == ({(0, 0, 0), (0, 0, 1)} if cfg[0] else {(0, 1, 0)}), seen


def test_decoder_register_copy_in_consecutive_clocks_is_one_sequence():
    """A register file's copy announces lines, pole_pairs and z_offset in three consecutive
    clocks: one sequence (busy for config_latency − 1 clocks), the position cleared, the new
    angle exact at the next index."""
    dut = QuadratureDecoder()
    busy = []

    async def testbench(ctx):
        await ctx.tick().repeat(4)
        for port, v, strobe in ((dut.lines, 997, dut.lp_changed),
                                (dut.pole_pairs, 7, dut.lp_changed),
                                (dut.z_offset, 3000, dut.z_changed)):
            ctx.set(port, v)
            ctx.set(dut.lp_changed, 0)
            ctx.set(dut.z_changed, 0)
            ctx.set(strobe, 1)
            await ctx.tick()
            busy.append(ctx.get(dut.busy))
        ctx.set(dut.lp_changed, 0)
        ctx.set(dut.z_changed, 0)
        for _ in range(2 * dut.config_latency):
            await ctx.tick()
            busy.append(ctx.get(dut.busy))
        ctx.set(dut.z, 1)                       # align at count 0, then one count forward
        await ctx.tick().repeat(2)
        ctx.set(dut.a, 1)
        await ctx.tick().repeat(2)
        assert ctx.get(dut.aligned) == 1 and ctx.get(dut.count) == 1
        e = (7 + 3000) % (4 * 997)
        assert ctx.get(dut.e) == e and ctx.get(dut.theta) == (e << 16) // (4 * 997)

    simulate(dut, [testbench], name="test_encoder_copy_sequence")
    assert sum(busy) == dut.config_latency - 1 and busy[:3] == [1, 1, 1]


def test_divide_angle_is_divmod_for_every_valid_dividend():
    """The decoder's 16-step restoring division equals divmod(n·2**16, cpr) whenever n < cpr,
    over the whole range of cpr (random cases plus the extremes)."""
    rng = np.random.default_rng(5)
    cases = [(0, 4), (3, 4), (1, 4 * 65535), (4 * 65535 - 1, 4 * 65535), (255, 256)]
    for _ in range(20000):
        cpr = 4 * int(rng.integers(1, 1 << 16))
        cases.append((int(rng.integers(0, cpr)), cpr))
    for n, cpr in cases:
        assert divide_angle(n, cpr) == divmod(n << 16, cpr), (n, cpr)



def test_divide_angle_remainder_is_a_multiple_of_four_in_any_configuration():
    """The decoder keeps Rp, Rz, Rp − cpr, Rz − cpr and rm divided by 4 (``rp4``, …): the
    divisions' remainders are multiples of 4 for every dividend and cpr = 4·lines, valid or
    not (n ≥ cpr, lines = 0), as the gateware's 18-bit working register leaves them, so
    nothing is lost (random 18-bit dividends, every width of lines, the extremes)."""
    rng = np.random.default_rng(8)
    cases = [(0, 0), ((1 << 18) - 1, 0), ((1 << 18) - 1, 4), (255, 4 * 65535), (7, 4 * 65535)]
    for _ in range(20000):
        cases.append((int(rng.integers(0, 1 << 18)), 4 * int(rng.integers(0, 1 << 16))))
    for n, cpr in cases:
        assert divide_angle(n, cpr)[1] % 4 == 0, (n, cpr)


# --- Hall -----------------------------------------------------------------------------------

def test_hall_sector_order_centres_and_fault():
    dut = HallSensor()
    got = {}

    async def testbench(ctx):
        ctx.set(dut.offset, 65000)
        for code in range(8):
            ctx.set(dut.h, code)
            await ctx.tick()
            got[code] = (ctx.get(dut.sector), ctx.get(dut.theta), ctx.get(dut.fault),
                         ctx.get(dut.valid))

    simulate(dut, [testbench], name="test_hall")
    centres = hall_centres()
    assert centres == (5461, 16384, 27307, 38229, 49152, 60075)
    for k, code in enumerate(HALL_CODES):
        assert got[code] == (k, (centres[k] + 65000) % 65536, 0, 1)
    assert got[0][2] == 1 and got[7][2] == 1
    assert got[7][:2] == got[6][:2]              # 111 holds the last valid sector (6 → 4)
    # The ideal code of each sector's angles is its code, 000 and 111 never occur.
    theta = np.arange(0, 65536, 7)
    np.testing.assert_array_equal(model.hall_sector(model.hall_code(theta)), theta * 6 >> 16)


def test_hall_angle_before_first_index_then_encoder():
    dut = EncoderFrontEnd()
    hall = HALL_CODES[3]
    wave = [pins(hall=hall)] * 100 + [pins(z=1, hall=hall)] * 6
    out = run_front_end(dut, wave, z_offset=5000)
    before = out["theta"][~out["aligned"].astype(bool)][-1]
    after = out["theta"][-1]
    assert out["hall_sector"][-1] == 3 and before == hall_centres()[3]
    assert out["aligned"][-1] == 1 and after == (5000 << 16) // 20000


# --- encoder/Hall plausibility --------------------------------------------------------------

B = hall_boundaries()
TURN = 1 << 16


def run_plausibility(steps, hold_clocks=3):
    """Drive a HallPlausibility with ``steps`` (dicts of inputs, each held ``hold_clocks``
    clocks; unspecified inputs keep their value) and return per-step outputs
    ``(edge, miss, fault, error)`` OR-ed (strobes) / last (error) over the step, after checking
    every clock against the golden model."""
    dut = HallPlausibility()
    ref = model.HallPlausibilityModel()
    state = {"theta": 0, "aligned": 0, "restart": 0, "sector": 0, "valid": 0, "hold": 0,
             "offset": 0, "tolerance": 8192, "misses": 2}
    per_step, errors = [], []

    async def testbench(ctx):
        clock = 0
        for step in steps:
            state.update(step)
            acc = [0, 0, 0, 0]
            for _ in range(hold_clocks):
                for k, v in state.items():
                    ctx.set(getattr(dut, k), v)
                await ctx.tick()
                ref.tick(**state)
                got = (ctx.get(dut.edge), ctx.get(dut.miss), ctx.get(dut.fault),
                       ctx.get(dut.error))
                want = (ref.edge, ref.miss, ref.fault, ref.error)
                if got != want:
                    errors.append((clock, got, want))
                acc = [acc[0] | got[0], acc[1] | got[1], acc[2] | got[2], got[3]]
                clock += 1
            per_step.append(tuple(acc))

    simulate(dut, [testbench], name="test_plausibility")
    assert errors == []
    return per_step


def test_hall_boundaries_are_the_sector_starts():
    """Boundary k is the binary angle nearest to k·60°, within one LSB of the first angle of
    sector k (the ideal Hall code's)."""
    assert B == (0, 10923, 21845, 32768, 43691, 54613)
    for k, b in enumerate(B):
        assert abs(b - k * TURN / 6) <= 0.5
        first = next(t for t in range(b - 2, b + 3) if model.hall_sector(model.hall_code(t)) == k)
        assert abs(first - b) <= 1


@pytest.mark.parametrize("complement", [False, True])
def test_plausibility_theta_registered_matches_the_default_block(complement):
    """With ``theta_registered`` the block takes the angle one clock late (the front end's
    register, with ``complement`` one stored inverted as the front end's) and gives the default
    block's outputs, clock for clock, on random inputs (edges in consecutive clocks,
    alignment, restarts and tolerances included; with ``complement`` also ``d − d_prev`` at
    −180° and the tolerance at its edges, where ``d_prev − d`` must compare alike)."""
    plain = HallPlausibility(complement=False)
    late = HallPlausibility(theta_registered=True, complement=complement)
    assert (plain.theta_registered, late.theta_registered) == (False, True)
    assert (plain.complement, late.complement) == (False, complement)
    rng = np.random.default_rng(11)
    n = 3000
    stim = {"theta": rng.integers(0, TURN, n), "sector": rng.integers(0, 6, n),
            "aligned": rng.random(n) < 0.5, "restart": rng.random(n) < 0.05,
            "valid": rng.random(n) < 0.95, "hold": rng.random(n) < 0.02,
            "offset": rng.integers(0, TURN, n), "tolerance": rng.integers(0, TURN, n),
            "misses": rng.integers(0, 16, n)}
    # θ from a few values a boundary step apart or half a turn apart, so that d − d_prev is
    # often exactly ±(60°·k) or −180° (the one x with −x = x), and tolerances at 180° ± 1
    # and at those magnitudes.
    few = np.array([0, 1, 32767, 32768, 32769, TURN - 1] + list(B))
    part = rng.random(n) < 0.5
    stim["theta"] = np.where(part, (few[rng.integers(0, len(few), n)]
                                    + rng.choice(B, n)) % TURN, stim["theta"])
    stim["offset"] = np.where(part, rng.choice([0, 0, 1, 32768], n), stim["offset"])
    stim["tolerance"] = np.where(part, rng.choice([0, 1, 10922, 10923, 21845, 32767, 32768,
                                                   32769], n), stim["tolerance"])
    outs = ("edge", "miss", "fault", "error")
    got = {"plain": [], "late": []}
    theta_q = Signal(16, init=TURN - 1 if complement else 0, reset_less=complement)

    class Pair(wiring.Component):
        def __init__(self):
            super().__init__({})

        def elaborate(self, platform):
            m = Module()
            m.submodules.plain, m.submodules.late = plain, late
            m.d.sync += theta_q.eq(plain.theta)
            m.d.comb += late.theta.eq(theta_q)
            for name in stim:
                if name != "theta":
                    m.d.comb += getattr(late, name).eq(getattr(plain, name))
            return m

    async def testbench(ctx):
        for t in range(n):
            for name, v in stim.items():
                ctx.set(getattr(plain, name), int(v[t]))
            await ctx.tick()
            got["plain"].append(tuple(ctx.get(getattr(plain, k)) for k in outs))
            got["late"].append(tuple(ctx.get(getattr(late, k)) for k in outs))

    simulate(Pair(), [testbench], name="test_plausibility_theta_registered")
    assert got["late"] == got["plain"]
    assert sum(e for e, *_ in got["plain"]) > 100
    assert sum(m for _, m, *_ in got["plain"]) > 100


def test_plausibility_complement_must_be_a_bool():
    with pytest.raises(TypeError, match=r"^HallPlausibility complement must be a bool, not 1$"):
        HallPlausibility(complement=1)
    with pytest.raises(TypeError, match=r"^EncoderFrontEnd plausibility_complement must be a "
                                        r"bool, not None$"):
        EncoderFrontEnd(plausibility_complement=None)
    assert HallPlausibility.__init__.__kwdefaults__["complement"] is False
    assert EncoderFrontEnd.__init__.__kwdefaults__["plausibility_complement"] is True


@pytest.mark.usefixtures("complement_form")
def test_plausibility_relative_check_at_half_a_turn_and_the_tolerance_edges():
    """The relative check's ``|d − d_prev|`` where the complement form compares
    ``|d_prev − d|``: at −180° (d − d_prev = −32768, whose negation is itself) and ±1 of the
    tolerance on both sides, against the model clock for clock (run_plausibility)."""
    t0 = 777
    v = {"valid": 1, "misses": 1}
    out = run_plausibility([
        {**v, "sector": 0, "theta": t0},
        {"sector": 1, "theta": t0 + B[1]},                      # first edge: no check
        {"tolerance": 32767, "sector": 2, "theta": t0 + B[2] + 32768},   # −180°: miss
        {"tolerance": 32768, "sector": 3, "theta": t0 + B[3] + 32768},   # 0 after: pass
        {"sector": 4, "theta": t0 + B[4]},                      # −180° again, tol 180°: pass
        {"tolerance": 100, "sector": 5, "theta": t0 + B[5] + 100},      # +100: pass
        {"sector": 0, "theta": t0 + 99},                        # −1: pass
        {"sector": 1, "theta": t0 + B[1] + 200},                # +101: miss
        {"sector": 2, "theta": t0 + B[2] + 99},                 # −101: miss
        {"sector": 3, "theta": t0 + B[3] - 1},                  # −100: pass
    ])
    edge, miss, fault, _ = (list(x) for x in zip(*out))
    assert edge == [0] + [1] * 9
    assert miss == [0, 0, 1, 0, 0, 0, 0, 1, 1, 0]


def test_plausibility_theta_registered_must_be_a_bool():
    with pytest.raises(TypeError,
                       match=r"^HallPlausibility theta_registered must be a bool, not 1$"):
        HallPlausibility(theta_registered=1)


@pytest.mark.usefixtures("complement_form")
def test_plausibility_latency_cycle_by_cycle():
    """An edge into a sector seen in clock t shows on ``edge``/``miss``/``fault`` in t + 3,
    once; ``error`` holds its d from t + 2 (one clock before the check's strobes)."""
    dut = HallPlausibility()
    seen = []

    async def testbench(ctx):
        ctx.set(dut.aligned, 1)
        ctx.set(dut.valid, 1)
        ctx.set(dut.misses, 1)
        ctx.set(dut.theta, B[3])                  # far from the 0 → 1 boundary: a miss
        await ctx.tick().repeat(3)
        ctx.set(dut.sector, 1)                    # the edge, in this clock
        for _ in range(5):
            seen.append((ctx.get(dut.edge), ctx.get(dut.miss), ctx.get(dut.fault),
                         ctx.get(dut.error)))
            await ctx.tick()

    simulate(dut, [testbench], name="test_plausibility_latency")
    assert HallPlausibility.latency == model.HallPlausibilityModel.LATENCY == 3
    err = B[3] - B[1]
    assert seen == [(0, 0, 0, 0)] * 2 + [(0, 0, 0, err), (1, 1, 1, err), (0, 0, 0, err)]
    assert EncoderFrontEnd.plausibility_latency == EncoderFrontEnd.latency + 3


@pytest.mark.usefixtures("complement_form")
def test_plausibility_absolute_check_threshold_count_and_reset():
    al = {"aligned": 1, "valid": 1}
    out = run_plausibility([
        {**al, "sector": 0, "theta": B[0] + 4000},
        {"sector": 1, "theta": B[1] + 8192},                    # |d| = tolerance: pass
        {"sector": 2, "theta": B[2] - 8193},                    # miss 1
        {"sector": 3, "theta": B[3] + 100},                     # pass: count back to 0
        {"sector": 4, "theta": B[4] + 20000},                   # miss 1
        {"sector": 5, "theta": B[5] - 30000},                   # miss 2: fault
        {"sector": 0, "theta": B[0] + 32768},                   # miss 3 (|d| = 180°): fault
        {"sector": 5, "theta": (B[0] - 36) % TURN},             # backward at B[0]: pass
        {"sector": 3, "theta": B[4]},                           # skips a sector: miss 1
        {"misses": 0, "sector": 4, "theta": B[4]},              # pass (0 acts as 1) ...
        {"sector": 0, "theta": B[0]},                           # skip: miss → fault at once
        {"offset": 1000, "sector": 1, "theta": B[1] + 1000 - 8193},   # offset moves the edge
    ])
    edge, miss, fault, err = (list(x) for x in zip(*out))
    assert edge == [0] + [1] * 11
    assert miss == [0, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 1]
    assert fault == [0, 0, 0, 0, 0, 1, 1, 0, 0, 0, 1, 1]
    assert err[1] == 8192 and err[2] == -8193 and err[6] == -32768 and err[7] == -36
    assert err[8] == err[7]                                     # a skip leaves the error
    assert err[11] == -8193


@pytest.mark.usefixtures("complement_form")
def test_plausibility_tolerance_edges():
    """``|d| > tolerance`` at its edges: d = ±tolerance passes, one more misses; tolerance 0
    passes only d = 0; tolerance ≥ 180° never misses (|d| ≤ 180°)."""
    al = {"aligned": 1, "valid": 1, "misses": 1}
    out = run_plausibility([
        {**al, "sector": 0, "theta": B[0]},
        {"sector": 1, "theta": B[1] - 8192},                    # d = −tolerance: pass
        {"sector": 2, "theta": B[2] + 8193},                    # d = tolerance + 1: miss
        {"tolerance": 0, "sector": 3, "theta": B[3]},           # d = 0: pass
        {"sector": 4, "theta": B[4] - 1},                       # |d| = 1: miss
        {"tolerance": 32768, "sector": 5, "theta": B[5] + 32768},   # |d| = 180°: pass
        {"tolerance": 32767, "sector": 0, "theta": B[0] + 32768},   # miss
        {"tolerance": 65535, "sector": 1, "theta": B[1] - 32767},   # pass
    ])
    edge, miss, fault, err = (list(x) for x in zip(*out))
    assert edge == [0] + [1] * 7
    assert miss == [0, 0, 1, 0, 1, 0, 1, 0]
    assert err[1] == -8192 and err[5] == -32768


@pytest.mark.usefixtures("complement_form")
def test_plausibility_relative_check_before_alignment():
    t0 = 12345                                                  # unknown encoder offset
    v = {"valid": 1}
    out = run_plausibility([
        {**v, "sector": 0, "theta": t0},
        {"sector": 1, "theta": t0 + B[1]},                      # first edge: no check
        {"sector": 2, "theta": t0 + B[2] + 5000},               # advanced 60° + 27°: pass
        {"sector": 3, "theta": t0 + B[2] + 5000},               # encoder stuck: miss 1
        {"sector": 2, "theta": t0 + B[2] + 5000},               # reversal: no check
        {"sector": 1, "theta": t0 + B[1] - 20},                 # backward across 2: pass
        {"sector": 0, "theta": t0 + B[1] - 20},                 # stuck: miss 1
        {"sector": 5, "theta": t0 + B[1] - 20},                 # stuck: miss 2 → fault
        {"restart": 1},                                         # the reference may move
        {"restart": 0, "sector": 4, "theta": 999},              # not compared: no miss
        {"sector": 3, "theta": 999 - (B[5] - B[4])},            # compared again: pass
        {"aligned": 1, "theta": B[3] + 50},                     # aligned: the angle jumps
        {"sector": 2, "theta": B[3] - 30},                      # absolute only: pass
        {"hold": 1, "sector": 1, "theta": 0},                   # held: no edge
    ])
    edge, miss, fault, _ = (list(x) for x in zip(*out))
    assert edge == [0, 1, 1, 1, 1, 1, 1, 1, 0, 1, 1, 0, 1, 0]
    assert miss == [0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 0, 0, 0, 0]
    assert fault == [0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0]


@pytest.mark.usefixtures("complement_form")
def test_plausibility_random_inputs_every_clock_against_model():
    """Inputs changed in every clock (Hall edges in consecutive clocks, adjacent or not, both
    directions, alignment and restart toggling, small tolerances and every ``misses``): the
    gateware follows the golden model clock for clock (the registered ``d − d_prev`` forwards
    the ``d`` of an edge one clock ahead)."""
    rng = np.random.default_rng(17)
    n = 3000
    sector = np.cumsum(rng.choice([0, 0, 1, -1, 2, 3], size=n)) % 6
    steps = [{"sector": int(sector[k]),
              "theta": int(rng.integers(0, TURN)) if rng.random() < 0.3
              else int(B[sector[k]] + rng.integers(-9000, 9000)) % TURN,
              "aligned": int(rng.random() < 0.5), "restart": int(rng.random() < 0.05),
              "valid": int(rng.random() < 0.97), "hold": int(rng.random() < 0.02),
              "offset": int(rng.choice([0, 0, 123, 65000])),
              "tolerance": int(rng.choice([0, 4096, 8192, 40000])),
              "misses": int(rng.integers(0, 16))} for k in range(n)]
    out = run_plausibility(steps, hold_clocks=1)
    edge, miss, fault, _ = (np.array(x) for x in zip(*out))
    assert edge.sum() > 1000 and miss.sum() > 300 and fault.sum() > 50
    assert (miss & ~edge.astype(bool)).sum() == 0


def _plant_gateware(lines=64, **kw):
    """A plant-driven gateware run at a reduced scale: 100 kHz clock, 64-line encoder (one
    count 5.6° electrical), filter length 1: a 500th of the clocks of 50 MHz."""
    r = verify_encoder.run_plant(clk_hz=1e5, lines=lines, length=1, engine="gateware", **kw)
    assert r["mismatches"] == 0, r["first_mismatch"]           # gateware = per-clock model
    assert r["sparse_mismatches"] == 0                          # = event-driven model
    return r


@pytest.mark.parametrize("speed_rpm, theta_m0, phi_deg, aligned, misses", [
    (1000.0, -0.05, 30.0, True, 1),       # Z passed before the break: absolute check
    (-1000.0, -0.05, 5.0, False, 2),      # backward, Z a turn away: relative check
])
def test_plausibility_plant_broken_a_line_trips(speed_rpm, theta_m0, phi_deg, aligned, misses):
    """Encoder A broken at 1000 r/min (rotor held): no illegal transition, yet the check trips
    at the rotation the Hall edges predict, N·60° − φ when the first edge after the break is
    beyond the tolerance, else (N + 1)·60° − φ: N = 1 (the default), φ = 30°: 90°;
    N = 2, φ = 5°: 115°."""
    r = _plant_gateware(speed_rpm=speed_rpm, theta_m0=theta_m0, duration_s=25e-3,
                        break_after_s=8e-3, break_phi_deg=phi_deg, misses=misses)
    assert r["aligned_at_break"] is aligned
    assert r["illegal_strobes"] == 0 and r["false_trips"] == 0
    assert r["detected"]
    assert r["expected_angle_deg"] == pytest.approx({1: 90.0, 2: 115.0}[misses], abs=0.5)
    # One count (5.6°) of dither/quantisation plus the front end's 5 clocks (0.2°).
    assert abs(r["detect_angle_deg"] - r["expected_angle_deg"]) < 6.0
    assert r["detect_sectors"] <= 0.75 + misses


def test_plausibility_plant_healthy_turns_and_reversals_no_trip():
    """No miss at all without the fault: a turn forward (aligning on the way; Z and Hall
    offsets) and a turn back at 3000 r/min (a 32-line encoder: 16 clocks per count), and a
    rotor swinging through standstill with its turning points just past Hall boundaries, Hall
    switches chattering (3 bounces of 20 clocks at every edge) and the decoder's Hall offset 10°
    off."""
    sector_m = np.pi / 12                                      # one Hall sector, mechanical
    runs = [
        _plant_gateware(lines=32, speed_rpm=3000.0, theta_m0=-0.3, duration_s=22e-3,
                        z_count=17, hall_offset_rad=0.4),
        _plant_gateware(lines=32, speed_rpm=-3000.0, theta_m0=0.2, duration_s=21e-3),
        _plant_gateware(swing=(1.5 * sector_m + 0.002, 40.0), theta_m0=2.5 * sector_m,
                        duration_s=32e-3, hall_bounce=(3, 20), hall_offset_error_deg=10.0),
    ]
    for r in runs:
        assert r["plausibility_strobes"] == 0 and r["hall_misses"] == 0
    assert runs[0]["hall_edges"] >= 24 and runs[1]["hall_edges"] >= 24
    assert runs[0]["aligned_clock"] is not None
    # From the centre up (2 boundaries), down (4), up (4): 10 crossings, 6 bounces each where
    # the next crossing is not too close (the two at a turning point are 0.8 ms apart).
    assert runs[2]["hall_edges"] >= 50
    assert runs[2]["aligned_clock"] is None


def test_plausibility_plant_full_scale_model():
    """50 MHz, 5000 lines, 1000 r/min, the event-driven golden model (bit-exact with the
    gateware: the tests above): A broken past Z, both directions, N = 1 and 2; the tripping
    rotation equals the predicted one within 0.1° (a count is 0.072°, 5 clocks 0.13°)."""
    for speed, phi, misses in ((1000.0, 10.0, 1), (-1000.0, 30.0, 2)):
        r = verify_encoder.run_plant(speed_rpm=speed, theta_m0=-0.05 * np.sign(speed),
                                     duration_s=13e-3, break_after_s=2.5e-3,
                                     break_phi_deg=phi, misses=misses)
        assert r["aligned_at_break"] and r["illegal_strobes"] == 0 and r["false_trips"] == 0
        assert r["detected"] and abs(r["detect_angle_deg"] - r["expected_angle_deg"]) < 0.1
        assert r["max_abs_error_deg"] < 0.1                       # one count: 0.072°


@pytest.mark.slow
def test_plausibility_plant_full_scale_sweep_and_no_false_trips():
    """Full scale: the tripping rotation for break positions every 5° of a sector (2.5° …
    57.5°, N = 1 and 2 alternately) in both directions, aligned or not; no trip over 3 turns
    each way at 1000 r/min, at 5000 r/min, at 5 r/min, and over swings through standstill with
    chattering Halls and a 10° Hall offset error."""
    sector_m = np.pi / 12
    for speed in (1000.0, -1000.0):
        for th0 in (-0.05, 0.05):
            for phi in np.arange(2.5, 60.0, 5.0):      # not at the threshold 60° − 45°
                misses = 1 + int(phi) % 2                   # N = 1 and 2 alternately
                r = verify_encoder.run_plant(speed_rpm=speed, theta_m0=th0, duration_s=16e-3,
                                             break_after_s=3e-3, break_phi_deg=float(phi),
                                             misses=misses)
                assert r["false_trips"] == 0 and r["illegal_strobes"] == 0
                assert abs(r["detect_angle_deg"] - r["expected_angle_deg"]) < 0.2, (speed, phi)
    healthy = [
        dict(speed_rpm=1000.0, theta_m0=-0.3, duration_s=185e-3),
        dict(speed_rpm=-1000.0, theta_m0=0.2, duration_s=185e-3, z_count=4321,
             hall_offset_rad=-1.0),
        dict(speed_rpm=5000.0, duration_s=40e-3),
        dict(speed_rpm=5.0, theta_m0=-0.01, duration_s=2.0, chunk_s=10e-3),   # 2 sectors/s
        dict(swing=(1.5 * sector_m + 0.0005, 2.0), theta_m0=2.5 * sector_m, duration_s=1.1,
             hall_bounce=(3, 500), hall_offset_error_deg=10.0),
    ]
    for kw in healthy:
        r = verify_encoder.run_plant(**kw)
        assert r["plausibility_strobes"] == 0 and r["hall_misses"] == 0, kw
        assert r["hall_edges"] >= (3 if kw.get("speed_rpm") == 5.0 else 12), kw


# --- electrical angle -----------------------------------------------------------------------

def test_angle_no_drift_forward_back_random_walk():
    r = verify_encoder.run_drift(6000)
    assert r["checked"] > 3 * 6000
    assert (r["angle_drift_counts"], r["theta_errors"], r["count_errors"]) == (0, 0, 0)


def test_angle_no_drift_odd_lines_and_pole_pairs():
    r = verify_encoder.run_drift(3000, lines=997, pole_pairs=13, z_offset=3987)
    assert (r["angle_drift_counts"], r["theta_errors"], r["count_errors"]) == (0, 0, 0)


def test_angle_no_drift_checker_detects_a_wrong_increment(monkeypatch):
    """The drift check can fail: with the step quotient Qp off by one the checker sees it."""
    real = hdl_encoder.angle_constants

    def skewed(lines, pole_pairs, z_offset):
        qp, *rest = real(lines, pole_pairs, z_offset)
        return (qp + 1, *rest)

    monkeypatch.setattr(hdl_encoder, "angle_constants", skewed)
    # The default configuration: the skewed reset constants are never recomputed.
    r = verify_encoder.run_drift(500, z_offset=0)
    assert r["theta_errors"] > 0


def test_angle_no_drift_model_against_exact_formula():
    """The golden model's Bresenham angle equals floor(e·2**16/cpr) over a long random walk."""
    rng = np.random.default_rng(11)
    for lines, pp, z in ((5000, 4, 0), (7, 13, 5), (65535, 255, 262139)):
        dec = model.QuadratureDecoderModel(lines=lines, pole_pairs=pp, z_offset=z)
        cpr = 4 * lines
        dec.tick(0, 0, 1, lines=lines, pole_pairs=pp, z_offset=z)     # align at position 0
        pos = 0
        steps = rng.choice([-1, 1, 1], size=20000) * np.repeat(rng.choice([-1, 1], 200), 100)
        for s in steps.tolist():
            pos += s
            a, b = AB[pos % 4]
            dec.tick(a, b, 0, lines=lines, pole_pairs=pp, z_offset=z)
            e = (pp * pos + z) % cpr
            assert (dec.count, dec.e, dec.theta) == (pos % cpr, e, model.theta_exact(e, cpr))


# --- whole front end against the model ------------------------------------------------------

@pytest.mark.usefixtures("complement_form")
@pytest.mark.parametrize("z_gate", [None, 0])
def test_front_end_random_pins_vs_model(z_gate):
    r = verify_encoder.run_random(3000, seed=2, z_gate=z_gate)
    assert r["mismatches"] == 0 and r["vectors"] == 3001
    assert r["illegal_strobes"] == r["illegal_strobes_model"] > 0
    assert r["index_strobes_model"] > 0


@pytest.mark.usefixtures("complement_form")
def test_front_end_short_segments_invalid_configurations_vs_model():
    """Many short configuration segments (invalid ones included) in a short run: the default
    run above sees one segment only. Catches the session-3 regression (the pipelined output
    sum compared ``em`` with an unsigned ``cpr − z_offset``, which wraps for a committed
    ``z_offset ≥ cpr``: 401 mismatches here, 5 127 in the 100 000-vector run)."""
    r = verify_encoder.run_random(6000, seed=3, segment_clocks=(300, 800))
    assert r["invalid_z_clocks"] > 200            # the stimulus does reach the failing case
    assert r["config_commits_model"] >= 10
    assert r["mismatches"] == 0 and r["vectors"] == 6001
    assert 0 < r["hall_misses_model"] < r["hall_edges_model"]


def test_front_end_plausibility_complement_is_the_difference_form_clock_for_clock():
    """The two forms of the plausibility check's differences in two front ends on the same
    random pins and configuration (Hall edges at any clock, invalid codes, alignment, realign,
    configuration changes with their strobes, tolerances at their edges) and synchronous resets
    in the middle of the run: every output equal in every clock (the complement form's
    reset_less angle register ``theta_q`` is not read in the clocks after a reset)."""
    on = EncoderFrontEnd(max_length=7, plausibility_complement=True)
    off = EncoderFrontEnd(max_length=7, plausibility_complement=False)
    assert (on.plausibility_complement, off.plausibility_complement) == (True, False)
    ins = ("a", "b", "z", "hall", "length", "lines", "pole_pairs", "z_offset", "hall_offset",
           "hall_tolerance", "hall_misses", "lp_changed", "z_changed", "realign")
    outs = model.OUTPUTS

    rst = Signal()

    class Pair(wiring.Component):
        def __init__(self):
            super().__init__({})

        def elaborate(self, platform):
            m = Module()
            m.submodules.on, m.submodules.off = on, off
            m.d.comb += [getattr(off, k).eq(getattr(on, k)) for k in ins]
            return ResetInserter(rst)(m)        # a synchronous reset of both

    rng = np.random.default_rng(23)
    n = 6000
    mism, resets, edges, aligned_resets = [], [], [0], [0]

    async def testbench(ctx):
        pos, hall_k = 0, 0
        ctx.set(on.lines, 16)
        ctx.set(on.length, 1)
        for t in range(n):
            pos += int(rng.choice([0, 0, 1, -1]))
            a, b = AB[pos % 4]
            if rng.random() < 0.05:
                hall_k = (hall_k + int(rng.choice([1, -1, 1, 2]))) % 6
            code = HALL_CODES[hall_k] if rng.random() > 0.01 else int(rng.choice([0, 7]))
            ctx.set(Cat(on.a, on.b, on.z, on.hall), a | (b << 1) | ((pos % 16 == 0) << 2)
                    | (code << 3))
            ctx.set(on.hall_tolerance, int(rng.choice([0, 1, 5461, 10922, 32767, 32768])))
            if rng.random() < 0.01:
                ctx.set(on.hall_offset, int(rng.integers(0, TURN)))
            ctx.set(on.realign, int(rng.random() < 0.002))
            ctx.set(on.hall_misses, int(rng.integers(0, 4)))
            lp = rng.random() < 0.002
            zc = rng.random() < 0.003
            if lp:
                ctx.set(on.lines, int(rng.choice([0, 1, 16, 16, 17, 17])))
                ctx.set(on.pole_pairs, int(rng.choice([0, 1, 3, 3, 4, 70])))
            if zc:
                ctx.set(on.z_offset, int(rng.integers(0, 80)))
            ctx.set(on.lp_changed, int(lp))
            ctx.set(on.z_changed, int(zc))
            reset = t % 397 in (300, 301)
            ctx.set(rst, int(reset))
            resets.append(reset)
            aligned_resets[0] += reset and ctx.get(on.aligned)
            await ctx.tick()
            got_on = tuple(ctx.get(getattr(on, k)) for k in outs)
            got_off = tuple(ctx.get(getattr(off, k)) for k in outs)
            if got_on != got_off:
                mism.append((t, got_on, got_off))
            edges[0] += ctx.get(on.hall_edge)

    simulate(Pair(), [testbench], name="test_front_end_plausibility_complement")
    assert mism == []
    assert sum(resets) >= 20 and aligned_resets[0] >= 4 and edges[0] > 50


def test_front_end_converts_to_verilog():
    text = verilog.convert(EncoderFrontEnd(z_gate=3), name="encoder")
    assert "module encoder" in text


@pytest.mark.slow
def test_front_end_100k_random_vectors_and_targets():
    r = verify_encoder.run(100_000, seed=0)
    assert r["mismatches"] == 0
    rr = r["random"]
    assert rr["plausibility_strobes"] == rr["plausibility_strobes_model"] > 0
    assert 0 < rr["hall_misses_model"] < rr["hall_edges_model"]
    assert r["angle_drift_counts"] == 0
    assert r["glitch_short_counted"] == 0 and r["glitch_long_missed"] == 0
    assert r["illegal_detected"] == r["illegal_injected"]
    assert r["hall_fault_detected"] == r["hall_fault_injected"]


@pytest.mark.slow
def test_angle_no_drift_million_counts():
    r = verify_encoder.run_drift(1_000_000)
    assert (r["angle_drift_counts"], r["theta_errors"], r["count_errors"]) == (0, 0, 0)
    assert r["checked"] >= 3_000_000
