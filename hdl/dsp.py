# Ref: Lattice FPGA-TN-02205 (ECP5 sysDSP: MULT18X18D, 18 × 18 signed or unsigned)
"""Products split into hard-multiplier-sized partial products, for pipelined multipliers.

A product wider than the FPGA's multiplier (18 × 18 on the ECP5, 16 × 16 on the iCE40 UP5K) is
mapped by yosys onto several multipliers whose partial products are summed by carry chains in the
*same* clock as the multipliers: at 100 MHz on the ECP5 a ``MULT18X18D`` (≈ 4 ns) plus one or two
wide adders does not fit. :func:`partial_products` splits ``a · b`` into products of at most
18 × 18 signed bits that each map onto one multiplier, so that a design can register them and add
them up in the next clock. The sum of the parts is exactly ``a · b`` (bit-true: a two's-complement
value is the sum of its unsigned low chunks and its signed top chunk, each shifted).
"""

from amaranth.hdl import Mux, Shape, Signal, Value

__all__ = ["CHUNK", "chunks", "partial_products", "partial_sum", "registered_products",
           "round_shift_signed", "saturate_bits"]

#: Width of the unsigned low chunks: 17 unsigned bits are an 18-bit signed multiplier operand.
CHUNK = 17


def chunks(value, *, chunk=CHUNK):
    """Split ``value`` into ``[(part, shift)]`` with ``value == Σ part · 2**shift``.

    Low parts are unsigned ``chunk``-bit slices; the top part keeps ``value``'s signedness and
    is at most ``chunk + 1`` bits when signed (an 18-bit signed operand), ``chunk`` when unsigned.
    """
    value = Value.cast(value)
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


def partial_products(a, b, *, chunk=CHUNK):
    """``[(product, shift)]`` with ``a · b == Σ product · 2**shift``; each product is at most
    18 × 18 signed bits (one ECP5 ``MULT18X18D``). Register the products, then add them with
    :func:`partial_sum` in the next clock."""
    return [(pa * pb, sa + sb) for pa, sa in chunks(a, chunk=chunk)
            for pb, sb in chunks(b, chunk=chunk)]


def partial_sum(products):
    """``Σ product · 2**shift`` of (registered) partial products."""
    total = None
    for p, s in products:
        term = Value.cast(p) << s
        total = term if total is None else total + term
    return total


def registered_products(m, a, b, *, enable, name, domain="sync"):
    """Registers (in ``m``'s ``domain``, loading while ``enable``) holding the partial products
    of ``a · b``; returns ``[(register, shift)]`` for :func:`partial_sum`."""
    regs = []
    for n, (prod, shift) in enumerate(partial_products(a, b)):
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
