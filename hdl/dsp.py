# Ref: Lattice FPGA-TN-02205 (ECP5 sysDSP: MULT18X18D, 18 × 18 signed or unsigned); Lattice
#      FPGA-TN-02007 (iCE40 DSP: SB_MAC16, 16 × 16); Xilinx UG479 (DSP48E1: 25 × 18)
"""Products split into hard-multiplier-sized partial products, for pipelined multipliers.

A product wider than the FPGA's multiplier (18 × 18 on the ECP5, 16 × 16 on the iCE40 UP5K) is
mapped by yosys onto several multipliers whose partial products are summed by carry chains in the
*same* clock as the multipliers: at 100 MHz on the ECP5 a ``MULT18X18D`` (≈ 4 ns) plus one or two
wide adders does not fit. :func:`partial_products` splits ``a · b`` into products of at most
``mul_width × mul_width`` signed bits that each map onto one multiplier, so that a design can
register them and add them up in the next clock. The sum of the parts is exactly ``a · b``
(bit-true: a two's-complement value is the sum of its unsigned low chunks and its signed top
chunk, each shifted), whatever ``mul_width``: it changes the netlist, never a result.

``mul_width`` is the signed operand width of the target's multiplier: 18 (:data:`MUL_WIDTH`) on
the ECP5 and on Xilinx parts (a DSP48E1 takes 25 × 18). The low chunks are ``mul_width − 1``
unsigned bits (a signed ``mul_width``-bit operand once Amaranth sign-extends them: it multiplies
an unsigned by a signed value as signed, one bit wider), the top chunk at most ``mul_width``
signed bits. ``None``: no split, each product stays whole and is registered whole (the same
clocks), and the synthesiser maps it onto its multipliers itself.

``None`` is the iCE40's setting. Its ``SB_MAC16`` is 16 × 16 with a signedness per operand, and
yosys' ``mul2dsp`` (``synth_ice40 -dsp``) already splits a wide product into 16-bit *unsigned*
low pieces and a signed top piece, each one ``SB_MAC16``, pieces narrower than 2 bits into LUTs.
A split here cannot do as well: a 16-bit unsigned chunk times a signed one is a 17-bit signed
operand in Amaranth, so the chunks must be 15 bits at ``mul_width = 16``, which makes more
pieces, and every piece of at least 2 × 2 bits with an 11-bit product takes a whole
``SB_MAC16`` (measured, ``synth_ice40 -dsp`` per block, mul_width 18 / 16 / ``None``: SVPWM 1 673 /
1 756 / 1 367 LUT4 and 8 / 10 / 8 DSP; Clarke 453 / 614 / 461 LUT4, 8 / 8 / 9 DSP; DC bus 344 /
374 / 312, 6 / 4 / 4; docs/AREA.md §7.4). The split exists for the ECP5's 100 MHz; the iCE40 runs
at 33–50 MHz, where a whole 16 × 16-piece product and its adders fit one clock.

The blocks that use this module (:class:`~.clarke.Clarke`, :class:`~.pi.PI`,
:class:`~.svpwm.SVPWM`, :class:`~.svpwm.DCBusCompensation`, and :class:`~.foc.CurrentLoop`,
:class:`~.servo.Servo` and :class:`~.top.Top` above them) take it as a constructor parameter.
"""

import numbers

from amaranth.hdl import Mux, Shape, Signal, Value

__all__ = ["MUL_WIDTH", "MUL_WIDTH_RANGE", "check_mul_width", "chunks", "partial_products",
           "partial_sum", "registered_products", "round_shift_signed", "saturate_bits"]

#: Default signed multiplier operand width: one ECP5 ``MULT18X18D`` (18 × 18).
MUL_WIDTH = 18

#: The integer ``mul_width`` values accepted (inclusive); ``None`` is accepted too (no split).
MUL_WIDTH_RANGE = (8, 25)


def check_mul_width(owner, mul_width):
    """Validate a ``mul_width`` constructor parameter of ``owner`` (a class name for the
    message); returns it.

    Raises
    ------
    TypeError
        If ``mul_width`` is neither ``None`` nor an integer from ``MUL_WIDTH_RANGE[0]`` to
        ``MUL_WIDTH_RANGE[1]``.
    """
    if mul_width is None:
        return None
    lo, hi = MUL_WIDTH_RANGE
    if (not isinstance(mul_width, numbers.Integral) or isinstance(mul_width, bool)
            or not lo <= mul_width <= hi):
        raise TypeError(f"{owner} mul_width must be None or an integer from {lo} to {hi} (the "
                        f"signed operand width of the hard multiplier: 18 ECP5 / Xilinx; None: "
                        f"products not split, iCE40), not {mul_width!r}")
    return int(mul_width)


def chunks(value, *, mul_width=MUL_WIDTH):
    """Split ``value`` into ``[(part, shift)]`` with ``value == Σ part · 2**shift``.

    Low parts are unsigned ``mul_width − 1``-bit slices; the top part keeps ``value``'s
    signedness and is at most ``mul_width`` bits when signed, ``mul_width − 1`` when unsigned:
    each part is a signed ``mul_width``-bit multiplier operand. ``mul_width=None``: one part,
    ``value`` itself.
    """
    mul_width = check_mul_width("chunks", mul_width)
    value = Value.cast(value)
    if mul_width is None:
        return [(value, 0)]
    chunk = mul_width - 1
    shape = value.shape()
    width = shape.width
    top = chunk + 1 if shape.signed else chunk
    parts, lo = [], 0
    while width - lo > top:
        parts.append((value[lo:lo + chunk], lo))
        lo += chunk
    part = value[lo:]
    parts.append((part.as_signed() if shape.signed else part, lo))
    return parts


def partial_products(a, b, *, mul_width=MUL_WIDTH):
    """``[(product, shift)]`` with ``a · b == Σ product · 2**shift``; each product is at most
    ``mul_width × mul_width`` signed bits (one ECP5 ``MULT18X18D`` at 18); ``mul_width=None``:
    ``[(a · b, 0)]``. Register the products, then add them with :func:`partial_sum` in the next
    clock."""
    return [(pa * pb, sa + sb) for pa, sa in chunks(a, mul_width=mul_width)
            for pb, sb in chunks(b, mul_width=mul_width)]


def partial_sum(products):
    """``Σ product · 2**shift`` of (registered) partial products."""
    total = None
    for p, s in products:
        term = Value.cast(p) << s
        total = term if total is None else total + term
    return total


def registered_products(m, a, b, *, enable, name, domain="sync", mul_width=MUL_WIDTH):
    """Registers (in ``m``'s ``domain``, loading while ``enable``) holding the partial products
    of ``a · b`` (:func:`partial_products` at ``mul_width``); returns ``[(register, shift)]`` for
    :func:`partial_sum`."""
    regs = []
    for n, (prod, shift) in enumerate(partial_products(a, b, mul_width=mul_width)):
        reg = Signal(prod.shape(), name=f"{name}{n}")
        with m.If(enable):
            m.d[domain] += reg.eq(prod)
        regs.append((reg, shift))
    return regs


def round_shift_signed(value, shift, negative):
    """:func:`~.fixed.round_shift` (half away from zero) with the sign supplied: ``negative``
    must equal ``value < 0`` whenever ``value != 0`` (it may be anything for 0, which rounds to
    0 either way). With the sign of a product known from its factors, the rounding is one adder
    behind the partial products instead of a sum, then its sign, then the rounding adder."""
    value = Value.cast(value)
    if shift <= 0:
        return value << -shift
    return (value + (1 << (shift - 1)) - negative) >> shift


def saturate_bits(value, shape):
    """:func:`~.fixed.saturate` of a signed ``value`` to a signed ``shape`` by bit tests: it
    overflows when its bits above the top bit of ``shape`` are not all copies of its sign. Same
    result as ``saturate``, but AND/OR trees instead of two magnitude comparators (carry chains)
    behind whatever produced ``value``."""
    value = Value.cast(value)
    shape = Shape.cast(shape)
    if not (value.shape().signed and shape.signed):
        raise TypeError(f"saturate_bits needs a signed value and shape, not {value.shape()!r} "
                        f"and {shape!r}")
    n = shape.width
    if value.shape().width <= n:
        return value.as_signed()
    sign = value[-1]
    top = value[n - 1:]
    hi, lo = (1 << (n - 1)) - 1, -(1 << (n - 1))
    over = ~sign & top.any()            # positive, above hi
    under = sign & ~top.all()           # negative, below lo
    return Mux(over, hi, Mux(under, lo, value[:n])).as_signed()
