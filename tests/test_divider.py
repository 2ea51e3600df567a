# amaranth: UnusedElaboratable=no
# Ref: SPEC.md §2.3 (paper Fig. 6), M/T speed D_n = k·ΔM/ΔT: the divider.
import random
from fractions import Fraction

import numpy as np
import pytest
from amaranth.back import verilog
from amaranth.hdl import unsigned

from foc_servo.hdl.divider import Divider
from foc_servo.hdl.fixed import shape_range
from foc_servo.sim.harness import simulate
from foc_servo.sim.models import divider as model
from foc_servo.sim.verify import divider as verify

S32_MIN, S32_MAX = -2**31, 2**31 - 1
U32_MAX = 2**32 - 1


def _fields(payload):
    return (payload.quotient, payload.remainder, payload.div0, payload.ovf)


def _run_hw(dut, pairs, *, ready_prob=1.0, valid_prob=1.0, seed=0):
    """Divide ``pairs`` on the gateware; the producer and the consumer may stall at random.

    Returns the results in arrival order and the number of clocks.
    """
    results = []
    rng = random.Random(seed)
    clocks = [0]

    async def producer(ctx):
        for n, d in pairs:
            while rng.random() >= valid_prob:
                await ctx.tick()
            ctx.set(dut.i.payload, {"dividend": n, "divisor": d})
            ctx.set(dut.i.valid, 1)
            await ctx.tick().until(dut.i.ready)
            ctx.set(dut.i.valid, 0)

    async def consumer(ctx):
        while len(results) < len(pairs):
            ready = rng.random() < ready_prob
            ctx.set(dut.o.ready, ready)
            _, _, valid, payload = await ctx.tick().sample(dut.o.valid, dut.o.payload)
            clocks[0] += 1
            if valid and ready:
                results.append(_fields(payload))
            assert clocks[0] < 100 * (len(pairs) + 1) * dut.latency, "divider hangs"

    simulate(dut, [producer, consumer], name="divider_test")
    return results, clocks[0]


def _expected(pairs, **params):
    n, d = (np.array(x, dtype=object) for x in zip(*pairs))
    q, r, z, v = model.divide(n, d, **params)
    return [(int(a), int(b), int(c), int(e)) for a, b, c, e in zip(q, r, z, v)]


# --- parameters -------------------------------------------------------------------------------

@pytest.mark.parametrize("width", [1, 0, -3, 8.0, "32", True, None])
def test_divider_rejects_bad_width(width):
    with pytest.raises(TypeError,
                       match=r"^Divider width must be an integer of at least 2, not .+$"):
        Divider(width=width)


@pytest.mark.parametrize("divisor_width", [1, 0, 16.0, "16", False])
def test_divider_rejects_bad_divisor_width(divisor_width):
    with pytest.raises(TypeError, match=r"^Divider divisor_width must be None or an integer of "
                                        r"at least 2, not .+$"):
        Divider(divisor_width=divisor_width)


@pytest.mark.parametrize("signed", [1, 0, None, "yes"])
def test_divider_rejects_non_bool_signed(signed):
    with pytest.raises(TypeError, match=r"^Divider signed must be a bool, not .+$"):
        Divider(signed=signed)


@pytest.mark.parametrize("quotient_width", [1, 33, 8.0, "8", True])
def test_divider_rejects_bad_quotient_width(quotient_width):
    with pytest.raises(TypeError, match=r"^Divider quotient_width must be None or an integer "
                                        r"from 2 to width 32, not .+$"):
        Divider(signed=False, quotient_width=quotient_width)


def test_divider_rejects_narrow_signed_quotient():
    with pytest.raises(ValueError, match=r"^Divider quotient_width must equal width 32 for a "
                                         r"signed divider, not 16$"):
        Divider(quotient_width=16)
    assert Divider(quotient_width=32).quotient_width == 32


def test_divider_message_names_the_value():
    with pytest.raises(TypeError, match=r"^Divider width must be an integer of at least 2, not 1$"):
        Divider(width=1)


def test_divider_model_and_verify_validate_like_the_gateware():
    with pytest.raises(TypeError, match=r"^Divider divisor_width must be None or an integer of "
                                        r"at least 2, not 1$"):
        model.divide(1, 1, divisor_width=1)
    with pytest.raises(TypeError, match=r"^Divider signed must be a bool, not 0$"):
        verify.run(10, signed=0)
    with pytest.raises(TypeError, match=r"^lanes must be an integer of at least 1, not 0$"):
        verify.run(10, lanes=0)


def test_divider_interface_shapes():
    dut = Divider(width=40, divisor_width=24)
    assert dut.latency == 42 == model.latency(40)
    assert dut.i.payload.dividend.shape().width == 40
    assert dut.i.payload.divisor.shape().width == 24
    assert dut.o.payload.quotient.shape().signed
    assert dut.o.payload.remainder.shape().width == 24
    u = Divider(width=16, signed=False)
    assert u.divisor_width == 16 and not u.signed and u.quotient_width == 16
    assert not u.o.payload.quotient.shape().signed
    n = Divider(width=63, divisor_width=32, signed=False, quotient_width=31)
    assert n.latency == 33 == model.latency(31)
    assert n.i.payload.dividend.shape() == unsigned(63)
    assert n.o.payload.quotient.shape() == unsigned(31)


NARROW = {"width": 40, "divisor_width": 16, "signed": False, "quotient_width": 20}


@pytest.mark.parametrize("params", [{}, {"signed": False}, {"width": 40, "divisor_width": 24},
                                    NARROW])
def test_divider_converts_to_verilog(params):
    text = verilog.convert(Divider(**params), name="divider")
    assert "module divider" in text


# --- golden model against an independent reference --------------------------------------------

def test_divider_model_matches_exact_arithmetic():
    rng = random.Random(1)
    for width, dwidth, is_signed in [(32, 32, True), (40, 24, True), (32, 32, False), (8, 12, True),
                                     (64, 64, True)]:
        lo = -2**(width - 1) if is_signed else 0
        hi = 2**(width - 1) - 1 if is_signed else 2**width - 1
        dlo = -2**(dwidth - 1) if is_signed else 0
        dhi = 2**(dwidth - 1) - 1 if is_signed else 2**dwidth - 1
        pairs = [(rng.randint(lo, hi), rng.randint(dlo, dhi) >> rng.randint(0, dwidth))
                 for _ in range(2000)]
        pairs += [(n, d) for n in (lo, hi, 0, 1) for d in (dlo, dhi, 1, 0)]
        got = _expected(pairs, width=width, divisor_width=dwidth, signed=is_signed)
        for (n, d), (q, r, z, v) in zip(pairs, got):
            if d == 0:
                assert (q, r, z, v) == ((lo if n < 0 else hi), 0, 1, 0)
                continue
            exact = Fraction(n, d)
            q_true = int(exact)                     # int() truncates toward zero
            assert n == q_true * d + r and abs(r) < abs(d) and (r == 0 or (r < 0) == (n < 0))
            assert (q, v) == ((hi, 1) if q_true > hi else (q_true, 0)), (n, d)
            if v:
                assert (n, d, r) == (lo, -1, 0)


def test_divider_model_narrow_quotient_matches_exact_arithmetic():
    """quotient_width < width: floor(n / d) when it fits, else saturated with ovf."""
    rng = random.Random(2)
    w, dw, qw = 40, 16, 20
    pairs = [(rng.randrange(2**w), rng.randrange(2**dw) >> rng.randint(0, dw))
             for _ in range(3000)]
    pairs += [(d * 2**qw + e, d) for d in (1, 2, 3, 2**dw - 1) for e in (-1, 0, 1)]
    pairs += [(0, 0), (2**w - 1, 0), (2**w - 1, 2**dw - 1)]
    got = _expected(pairs, width=w, divisor_width=dw, signed=False, quotient_width=qw)
    hits = 0
    for (n, d), (q, r, z, v) in zip(pairs, got):
        if d == 0:
            assert (q, r, z, v) == (2**qw - 1, 0, 1, 0)
        elif n // d >= 2**qw:
            assert (q, r, z, v) == (2**qw - 1, 0, 0, 1)
            hits += 1
        else:
            assert (q, r, z, v) == (n // d, n % d, 0, 0)
    assert 100 < hits < len(pairs) - 100


def test_divider_model_rejects_out_of_range_operands():
    with pytest.raises(ValueError, match=r"^Divider divisor -1 is outside the range \[0, 255\] "):
        model.divide(5, -1, width=8, signed=False)
    with pytest.raises(ValueError, match=r"^Divider dividend 128 is outside the range "):
        model.divide(128, 1, width=8)


# --- named behaviour ----------------------------------------------------------------------------

def test_divider_by_zero():
    pairs = [(5, 0), (-5, 0), (0, 0), (S32_MIN, 0), (S32_MAX, 0), (1, 0), (-1, 0)]
    results, _ = _run_hw(Divider(), pairs)
    assert results == [(S32_MAX, 0, 1, 0), (S32_MIN, 0, 1, 0), (S32_MAX, 0, 1, 0),
                       (S32_MIN, 0, 1, 0), (S32_MAX, 0, 1, 0), (S32_MAX, 0, 1, 0),
                       (S32_MIN, 0, 1, 0)]
    results, _ = _run_hw(Divider(signed=False), [(5, 0), (0, 0), (U32_MAX, 0)])
    assert results == [(U32_MAX, 0, 1, 0)] * 3
    dut = Divider(width=40, divisor_width=24)
    results, _ = _run_hw(dut, [(-3, 0), (2**39 - 1, 0)])
    assert results == [(-2**39, 0, 1, 0), (2**39 - 1, 0, 1, 0)]


def test_divider_narrow_quotient_saturates():
    """Quotients of 2**quotient_width and more saturate with ovf (remainder 0); one below fits;
    division by zero is div0, not ovf."""
    dut = Divider(**NARROW)
    top = 2**20 - 1
    pairs = [(7 * 2**20 - 1, 7), (7 * 2**20, 7), (2**40 - 1, 2**16 - 1), (2**35 - 1, 2**16 - 1),
             (2**40 - 1, 1), (5, 0), (0, 1), (1000, 7)]
    results, _ = _run_hw(dut, pairs)
    assert results == [(top, 6, 0, 0), (top, 0, 0, 1), (top, 0, 0, 1),
                       ((2**35 - 1) // (2**16 - 1), (2**35 - 1) % (2**16 - 1), 0, 0),
                       (top, 0, 0, 1), (top, 0, 1, 0), (0, 0, 0, 0), (142, 6, 0, 0)]
    assert results == _expected(pairs, **NARROW)


def test_divider_min_by_minus_one():
    results, _ = _run_hw(Divider(), [(S32_MIN, -1), (S32_MIN, 1), (S32_MIN + 1, -1),
                                     (S32_MAX, -1), (S32_MIN, S32_MIN)])
    assert results == [(S32_MAX, 0, 0, 1), (S32_MIN, 0, 0, 0), (S32_MAX, 0, 0, 0),
                       (-S32_MAX, 0, 0, 0), (1, 0, 0, 0)]
    results, _ = _run_hw(Divider(width=40, divisor_width=24), [(-2**39, -1), (-2**39, -2**23)])
    assert results == [(2**39 - 1, 0, 0, 1), (2**16, 0, 0, 0)]


def test_divider_truncates_toward_zero():
    pairs = [(7, 2), (-7, 2), (7, -2), (-7, -2), (1, 3), (-1, 3), (1, -3), (-1, -3),
             (S32_MIN, 3), (S32_MAX, -2), (-100, 7)]
    results, _ = _run_hw(Divider(), pairs)
    assert results == [(3, 1, 0, 0), (-3, -1, 0, 0), (-3, 1, 0, 0), (3, -1, 0, 0),
                       (0, 1, 0, 0), (0, -1, 0, 0), (0, 1, 0, 0), (0, -1, 0, 0),
                       (-715827882, -2, 0, 0), (-1073741823, 1, 0, 0), (-14, -2, 0, 0)]
    results, _ = _run_hw(Divider(signed=False), [(7, 2), (U32_MAX, 2), (U32_MAX, U32_MAX),
                                                 (2**31, 2**31 + 1)])
    assert results == [(3, 1, 0, 0), (2**31 - 1, 1, 0, 0), (1, 0, 0, 0), (0, 2**31, 0, 0)]


@pytest.mark.parametrize("params", [{}, {"signed": False}, {"width": 40, "divisor_width": 24},
                                    {"width": 2}, NARROW])
@pytest.mark.parametrize("operands", [(1000, 7), (5, 0), (-1, -1)])
def test_divider_latency(params, operands):
    """Cycle by cycle: ready only while idle; o.valid exactly `latency` clocks after the
    transfer on i, whatever the operands (division by zero included); idle one clock after the
    result is taken."""
    dut = Divider(**params)
    (lo, hi), (dlo, dhi) = (shape_range(dut.i.payload.dividend.shape()),
                            shape_range(dut.i.payload.divisor.shape()))
    n, d = operands
    n, d = min(max(n, lo), hi), min(max(d, dlo), dhi)
    trace = []

    async def testbench(ctx):
        ctx.set(dut.o.ready, 0)
        ctx.set(dut.i.payload, {"dividend": n, "divisor": d})
        ctx.set(dut.i.valid, 1)
        assert ctx.get(dut.i.ready) and not ctx.get(dut.o.valid)
        await ctx.tick()                                # the transfer on i
        ctx.set(dut.i.payload, {"dividend": 3, "divisor": 1})   # must not be taken
        for _ in range(dut.latency + 2):
            trace.append((ctx.get(dut.i.ready), ctx.get(dut.o.valid)))
            await ctx.tick()
        assert _fields(ctx.get(dut.o.payload)) == _expected(
            [(n, d)], width=dut.width, divisor_width=dut.divisor_width, signed=dut.signed,
            quotient_width=dut.quotient_width)[0]
        ctx.set(dut.i.valid, 0)
        ctx.set(dut.o.ready, 1)
        await ctx.tick()                                # result taken
        assert ctx.get(dut.i.ready) and not ctx.get(dut.o.valid)

    simulate(dut, [testbench], name="divider_latency")
    # trace[k]: (i.ready, o.valid) k + 1 clocks after the clock of the transfer.
    assert trace == [(0, 0)] * (dut.latency - 1) + [(0, 1)] * 3


def test_divider_backpressure():
    """o.ready low: the result and o.valid stay put and i.ready stays low (new operands wait);
    back-to-back divisions then proceed one per latency + 1 clocks."""
    dut = Divider()
    seen = []

    async def testbench(ctx):
        ctx.set(dut.o.ready, 0)
        ctx.set(dut.i.payload, {"dividend": -1000, "divisor": 7})
        ctx.set(dut.i.valid, 1)
        await ctx.tick()
        ctx.set(dut.i.payload, {"dividend": 99, "divisor": 10})     # waits
        await ctx.tick().repeat(dut.latency - 1)
        first = _fields(ctx.get(dut.o.payload))
        assert first == (-142, -6, 0, 0)
        for _ in range(50):                             # stalled consumer
            assert ctx.get(dut.o.valid) and not ctx.get(dut.i.ready)
            assert _fields(ctx.get(dut.o.payload)) == first
            await ctx.tick()
        ctx.set(dut.o.ready, 1)
        await ctx.tick()                                # taken; idle now
        assert ctx.get(dut.i.ready) and not ctx.get(dut.o.valid)
        await ctx.tick()                                # 99 / 10 accepted
        ctx.set(dut.i.valid, 0)
        for k in range(dut.latency + 2):
            if ctx.get(dut.o.valid):
                seen.append((k, _fields(ctx.get(dut.o.payload))))
            await ctx.tick()

    simulate(dut, [testbench], name="divider_backpressure")
    assert seen == [(dut.latency - 1, (9, 9, 0, 0))]

    pairs = [(k * 1234567 - 5, (k % 13) - 6) for k in range(40)]
    results, clocks = _run_hw(dut, pairs)                  # back-to-back, consumer always ready
    assert results == _expected(pairs)
    assert clocks <= len(pairs) * (dut.latency + 1) + 2


@pytest.mark.parametrize("ready_prob,valid_prob", [(0.3, 1.0), (1.0, 0.3), (0.5, 0.5)])
def test_divider_random_handshakes_lose_nothing(ready_prob, valid_prob):
    """Random stalls on both sides: every accepted division gives exactly one result, in order."""
    rng = random.Random(7)
    pairs = [(rng.randint(S32_MIN, S32_MAX), rng.randint(-300, 300)) for _ in range(60)]
    results, _ = _run_hw(Divider(), pairs, ready_prob=ready_prob, valid_prob=valid_prob, seed=3)
    assert results == _expected(pairs)


# --- against the golden model ---------------------------------------------------------------------

@pytest.mark.parametrize("params", [{}, {"signed": False}, {"width": 40, "divisor_width": 24},
                                    NARROW])
def test_divider_random_vs_model(params):
    res = verify.run(2000, seed=1, **params)
    assert res["mismatches"] == 0, res["first_mismatch"]
    assert res["vectors"] > 2000
    assert res["latency_deviations"] == 0
    assert res["clocks_per_division"] == Divider(**params).latency
    assert res["div0_cases"] > 0
    narrow = params.get("quotient_width", 0) not in (0, params.get("width", 32))
    assert (res["ovf_cases"] > 0) == (params.get("signed", True) or narrow)


def test_divider_narrow_vectors_straddle_the_boundary():
    n, d = verify.vectors(5000, seed=2, **NARROW)
    q = np.array([int(a) // int(b) for a, b in zip(n, d) if b], dtype=object)
    assert np.count_nonzero(q == 2**20 - 1) > 50 and np.count_nonzero(q == 2**20) > 50
    cn, cd = verify.corner_cases(**NARROW)
    assert (7 * 2**20, 7) in set(zip(cn, cd)) and (7 * 2**20 - 1, 7) in set(zip(cn, cd))


def test_divider_corner_cases_cover_the_extremes():
    n, d = verify.corner_cases()
    pairs = set(zip(n, d))
    for pair in [(S32_MIN, -1), (S32_MIN, 0), (S32_MAX, S32_MIN), (-7, 2), (0, 0), (1, -1)]:
        assert pair in pairs
    n, d = verify.vectors(20000, seed=5, width=40, divisor_width=24)
    assert n.min() >= -2**39 and n.max() < 2**39 and d.min() >= -2**23 and d.max() < 2**23
    assert 0.005 < np.mean(d == 0) < 0.02
    assert np.mean(np.abs(n) < np.abs(d)) > 0.1
    assert np.count_nonzero((n == -2**39) & (d == -1)) > 100


def test_divider_verify_reports_a_wrong_model(monkeypatch):
    """The in-gateware checker is live: a model off by one in one case is caught and located."""
    real = model.divide

    def off_by_one(dividend, divisor, **params):
        q, r, z, v = real(dividend, divisor, **params)
        q = np.where((dividend == 7) & (divisor == 2), q + 1, q)
        return q, r, z, v

    monkeypatch.setattr(verify.model, "divide", off_by_one)
    res = verify.run(200, seed=0, lanes=4)
    assert res["mismatches"] == 1
    assert res["first_mismatch"]["dividend"] == 7 and res["first_mismatch"]["divisor"] == 2
    assert res["first_mismatch"]["got"]["quotient"] == 3
    assert res["first_mismatch"]["expected"]["quotient"] == 4


@pytest.mark.slow
@pytest.mark.parametrize("params", [{}, {"signed": False}, {"width": 40, "divisor_width": 24},
                                    NARROW])
def test_divider_100k_vs_model(params):
    res = verify.run(100_000, seed=0, **params)
    assert res["mismatches"] == 0, res["first_mismatch"]
    assert res["vectors"] >= 100_000
    assert res["latency_deviations"] == 0
    assert res["clocks_per_division"] == Divider(**params).latency
