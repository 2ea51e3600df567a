# Ref: paper eq. (4)–(6) (CORDIC vector rotation with ±90° pre-rotation), SPEC.md §2.1
"""Pipelined CORDIC rotator: one rotation per clock, shift-add only, gain compensated inside.

The same block serves Park (feed −θ) and inverse Park (feed +θ). The arithmetic, stage by stage
(``W`` = ``width``, ``G`` = ``guard_bits``, ``AW`` = ``angle_width``, ``AG`` = angle guard bits,
``Wz = AW + AG``, ``s = +1`` if θ ≥ 0 else ``−1``, θ read as a signed binary angle in [−π, π)):

1. Pre-rotation by ``s·90°`` (exact, ``W + 1`` bits so that −(−2**(W−1)) does not wrap) and
   ``z0 = θ·2**AG − s·2**(Wz−2)`` (exact: only bit ``AW − 2`` of θ is inverted)::

       x0 = −s·y        y0 = s·x

2. Gain compensation on the input side, ``xc = round_shift(x0·C, F − G)`` (half away from zero),
   where ``C = round(2**F / A_n)`` with ``A_n = Π sqrt(1 + 2**−2i)`` and ``F`` the smallest shift
   giving ``|C·A_n/2**F − 1| ≤ 2**−(W+3)``. The product is an exact canonic-signed-digit shift-add
   sum; the rounding constant (``2**(F−G−1) − [x0 < 0]``, the sign of ``x0·C`` being that of
   ``x0``) is one more term, and the terms are added in a balanced tree, one adder level per
   ``iterations_per_stage`` levels between registers. Exact sums make the tree order irrelevant.
3. ``n = stages`` iterations, ``i = 0 … n−1``, on ``D = W + G + 1``-bit signed data (floor shifts,
   exact adds; the magnitude never exceeds ``√2·2**(W−1+G)`` plus a few LSB, so it cannot wrap)::

       d = +1 if z_i ≥ 0 else −1
       x_{i+1} = x_i − d·(y_i >> i)
       y_{i+1} = y_i + d·(x_i >> i)
       z_{i+1} = z_i − d·round(atan(2**−i)/(2π)·2**Wz)

   The z widths shrink stage by stage (exact interval bounds computed at elaboration); the last
   iteration needs no z.
4. Output: ``saturate(round_shift(x_n, G), signed(W))`` — full-scale corners rotated by 45°
   saturate, never wrap.

:class:`CordicParams` computes every constant and width once; :class:`Cordic` (gateware) and
:mod:`foc_servo.sim.models.cordic` (bit-true golden model) both use it.
"""

import math

from amaranth.hdl import Cat, Const, Module, Mux, Signal, signed, unsigned
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out

from .fixed import is_int, round_shift, saturate

__all__ = ["CordicParams", "Cordic", "rotation_members"]


def _csd(value):
    """Canonic signed digits of a positive integer: list of ``(digit, shift)``, digit ±1."""
    digits, shift = [], 0
    while value:
        if value & 1:
            digit = 2 - (value & 3)     # +1 if the next bit is 0, else −1 (carry propagates)
            digits.append((digit, shift))
            value -= digit
        value >>= 1
        shift += 1
    return digits


def _signed_shape(lo, hi):
    """Narrowest signed shape holding every integer in [lo, hi]."""
    width = 1
    while not (-(1 << (width - 1)) <= lo and hi <= (1 << (width - 1)) - 1):
        width += 1
    return signed(width)


class CordicParams:
    """Constants and widths of a :class:`Cordic` configuration (validated).

    Parameters are those of :class:`Cordic`. All attributes are plain Python integers (or lists of
    them), computed once, so that gateware and golden model cannot disagree.

    Attributes
    ----------
    width, stages, angle_width, guard_bits, iterations_per_stage, tag_width : int
        The (defaulted) parameters.
    angle_guard_bits : int
        ``AG``, extra fraction bits of the z path below the input angle's LSB.
    z_width : int
        ``Wz = angle_width + angle_guard_bits``; a full turn is ``2**Wz`` in the z path.
    data_width : int
        ``D = width + guard_bits + 1``, signed width of x and y in the iterations.
    gain : float
        ``A_n``, the CORDIC gain of ``stages`` iterations.
    gain_shift, gain_constant : int
        ``F`` and ``C = round(2**F / A_n)``.
    gain_digits : list of (int, int)
        Canonic signed digits of ``C``: ``(±1, shift)`` pairs.
    atan : list of int
        ``round(atan(2**−i) / (2π) · 2**Wz)`` for ``i = 0 … stages − 1``.
    z_ranges : list of (int, int)
        Exact range of ``z_i`` for ``i = 0 … stages − 1``.
    tree_levels : int
        Adder levels of the gain-compensation tree.
    latency : int
        Clocks from ``i.valid`` to ``o.valid``.
    """

    def __init__(self, *, width=16, stages=None, angle_width=None, guard_bits=None,
                 iterations_per_stage=1, tag_width=0):
        if not is_int(width) or width < 8:
            raise TypeError(f"Cordic width must be an integer of at least 8, not {width!r}")
        if stages is None:
            stages = width + 2
        if not is_int(stages) or stages < 4:
            raise TypeError(f"Cordic stages must be None or an integer of at least 4, "
                            f"not {stages!r}")
        if angle_width is None:
            angle_width = width
        if not is_int(angle_width) or angle_width < 4:
            raise TypeError(f"Cordic angle_width must be None or an integer of at least 4, "
                            f"not {angle_width!r}")
        if guard_bits is None:
            guard_bits = (stages - 1).bit_length() + 1
        if not is_int(guard_bits) or guard_bits < 0:
            raise TypeError(f"Cordic guard_bits must be None or a non-negative integer, "
                            f"not {guard_bits!r}")
        if not is_int(iterations_per_stage) or iterations_per_stage < 1:
            raise TypeError(f"Cordic iterations_per_stage must be a positive integer, "
                            f"not {iterations_per_stage!r}")
        if not is_int(tag_width) or tag_width < 0:
            raise TypeError(f"Cordic tag_width must be a non-negative integer, not {tag_width!r}")
        if iterations_per_stage > stages:
            raise ValueError(f"Cordic iterations_per_stage must be at most stages = {stages}, "
                             f"not {iterations_per_stage!r}")

        self.width = int(width)
        self.stages = n = int(stages)
        self.angle_width = int(angle_width)
        self.guard_bits = g = int(guard_bits)
        self.iterations_per_stage = int(iterations_per_stage)
        self.tag_width = int(tag_width)
        self.data_width = self.width + g + 1

        # z path: resolve the last rotation atan(2**-(n-1)) ≈ 2**-(n-1) rad ≈ 2**-(n+1.65) turn with
        # a few bits to spare, and keep the summed rounding error of the atan table (≤ n/2 LSB)
        # below that resolution.
        z_width = max(self.angle_width, n + 3 + (n - 1).bit_length())
        self.angle_guard_bits = z_width - self.angle_width
        self.z_width = z_width
        self.atan = [round(math.atan(2.0 ** -i) / (2 * math.pi) * (1 << z_width))
                     for i in range(n)]
        quarter = 1 << (z_width - 2)
        lo, hi = -quarter, quarter - (1 << self.angle_guard_bits)
        self.z_ranges = []
        for a in self.atan:
            self.z_ranges.append((lo, hi))
            lo, hi = min(-a, lo + a), max(hi - a, a - 1)

        # Gain compensation: the smallest F with relative error of C/2**F below 2**-(W+3).
        self.gain = math.prod(math.sqrt(1.0 + 2.0 ** (-2 * i)) for i in range(n))
        f = 1
        while abs(round((1 << f) / self.gain) * self.gain / (1 << f) - 1) > 2.0 ** -(width + 3):
            f += 1
        self.gain_shift = f
        self.gain_constant = round((1 << f) / self.gain)
        self.gain_digits = _csd(self.gain_constant)
        terms = len(self.gain_digits) + (1 if f > g else 0)
        self.tree_levels = (terms - 1).bit_length()
        k = self.iterations_per_stage
        self.latency = -(-(self.tree_levels + n) // k) + 1

    def __repr__(self):
        return (f"CordicParams(width={self.width}, stages={self.stages}, "
                f"angle_width={self.angle_width}, guard_bits={self.guard_bits}, "
                f"iterations_per_stage={self.iterations_per_stage}, tag_width={self.tag_width})")


def rotation_members(width, angle_width, tag_width):
    """Ports of a rotator (:class:`Cordic`, :class:`~.rotator.Rotator`): ``i`` a stream of
    ``{x, y: signed(width), theta: unsigned(angle_width)[, tag]}``, ``o`` a stream of
    ``{x, y[, tag]}``, both always ready."""
    in_fields = {"x": signed(width), "y": signed(width), "theta": unsigned(angle_width)}
    out_fields = {"x": signed(width), "y": signed(width)}
    if tag_width:
        in_fields["tag"] = out_fields["tag"] = unsigned(tag_width)
    return {"i": In(stream.Signature(data.StructLayout(in_fields), always_ready=True)),
            "o": Out(stream.Signature(data.StructLayout(out_fields), always_ready=True))}


class Cordic(wiring.Component):
    """Pipelined CORDIC rotator: ``(x, y)`` rotated by θ, gain compensated, one per clock.

    ``x' = x·cosθ − y·sinθ``, ``y' = x·sinθ + y·cosθ`` (paper eq. (4)–(6) with its ±90°
    pre-rotation). Park is a rotation by −θ, inverse Park by +θ. Shift-add only: no multipliers.

    Parameters
    ----------
    width : int
        ``W``, width of x and y in and out, at least 8. Any Q format (the rotation does not care);
        in the design, Q1.(W−1).
    stages : int or None
        Number of CORDIC iterations ``n``, at least 4; default ``W + 2``
        (16 bits: max error ≈ 1 LSB, RMS ≈ 0.3 LSB against the ideal rotation).
    angle_width : int or None
        Width of θ, a :class:`~foc_servo.hdl.fixed.BinaryAngle` (a full turn is
        ``2**angle_width``), at least 4; default ``W``.
    guard_bits : int or None
        ``G``, fraction bits kept below the output LSB in the iterations;
        default ``ceil(log2(stages)) + 1``.
    iterations_per_stage : int
        ``k``, adder levels (gain-tree levels, then CORDIC iterations) between pipeline registers;
        1 (default) registers every iteration. Larger values cut latency, lengthen the paths.
    tag_width : int
        Width of an opaque ``tag`` carried alongside the data (0: no tag field).

    Members
    -------
    i : In(stream.Signature(data.StructLayout({"x": signed(W), "y": signed(W),
        "theta": unsigned(angle_width)[, "tag": unsigned(tag_width)]}), always_ready=True))
        Vector and angle. θ's signed reading is the angle in [−π, π).
    o : Out(stream.Signature(data.StructLayout({"x": signed(W), "y": signed(W)[,
        "tag": ...]}), always_ready=True))
        Rotated vector, rounded half away from zero, saturated to signed(W) (only a vector
        longer than full scale, e.g. both components at full scale, rotated towards an axis,
        saturates). ``valid`` and ``tag`` follow the data ``latency`` clocks later.

    Attributes
    ----------
    width, stages, angle_width, guard_bits, iterations_per_stage, tag_width : int
        The parameters, defaults resolved.
    latency : int
        Clocks from ``i.valid`` to ``o.valid``:
        ``ceil((tree_levels + stages) / iterations_per_stage) + 1``. A new vector is accepted
        every clock.
    params : CordicParams
        All derived constants and widths.

    Raises
    ------
    TypeError
        A parameter of the wrong type or below its minimum.
    ValueError
        ``iterations_per_stage`` above ``stages``.
    """

    def __init__(self, *, width=16, stages=None, angle_width=None, guard_bits=None,
                 iterations_per_stage=1, tag_width=0):
        p = CordicParams(width=width, stages=stages, angle_width=angle_width,
                         guard_bits=guard_bits, iterations_per_stage=iterations_per_stage,
                         tag_width=tag_width)
        self._params = p
        super().__init__(rotation_members(p.width, p.angle_width, p.tag_width))

    params = property(lambda self: self._params)
    width = property(lambda self: self._params.width)
    stages = property(lambda self: self._params.stages)
    angle_width = property(lambda self: self._params.angle_width)
    guard_bits = property(lambda self: self._params.guard_bits)
    iterations_per_stage = property(lambda self: self._params.iterations_per_stage)
    tag_width = property(lambda self: self._params.tag_width)
    latency = property(lambda self: self._params.latency)

    def elaborate(self, platform):
        m = Module()
        p = self._params
        w, g, dw, n = p.width, p.guard_bits, p.data_width, p.stages
        aw, ag = p.angle_width, p.angle_guard_bits
        f, k = p.gain_shift, p.iterations_per_stage
        fs = 1 << (w - 1)                           # |x0|, |y0| ≤ 2**(W-1)

        # 1. Pre-rotation by s·90° (s = −1 when the top bit of θ is set) and z0.
        pl = self.i.payload
        theta_neg = pl.theta[-1]
        x0 = Signal(signed(w + 1))
        y0 = Signal(signed(w + 1))
        m.d.comb += [
            x0.eq(Mux(theta_neg, pl.y, -pl.y)),
            y0.eq(Mux(theta_neg, -pl.x, pl.x)),
        ]
        # θ − s·quarter turn, read signed in AW − 1 bits: bit AW−2 inverted, top bit dropped.
        z0 = Cat(Const(0, ag), pl.theta[:aw - 2], ~pl.theta[aw - 2]).as_signed()

        # 2. Gain-compensation terms: each node is (sign, value, multiplier, rounding range) and
        #    stands for sign·value = multiplier·x0 + rounding.
        def terms(v0):
            nodes = [(digit, v0 << shift, digit << shift, (0, 0))
                     for digit, shift in p.gain_digits]
            if f > g:
                half = 1 << (f - g - 1)
                nodes.append((+1, Mux(v0[-1], half - 1, half), 0, (half - 1, half)))
            return nodes

        def tree_level(nodes):
            out = []
            for j in range(0, len(nodes) - 1, 2):
                (sa, va, ma, ra), (sb, vb, mb, rb) = nodes[j], nodes[j + 1]
                mult, rnd = ma + mb, (ra[0] + rb[0], ra[1] + rb[1])
                if sa == sb:
                    out.append((sa, va + vb, mult, rnd))
                elif sa > 0:
                    out.append((+1, va - vb, mult, rnd))
                else:
                    out.append((+1, vb - va, mult, rnd))
            if len(nodes) % 2:
                out.append(nodes[-1])
            return out

        def node_shape(node):                       # range of the value: sign·(mult·x0 + rnd)
            sign, _, mult, (rlo, rhi) = node
            vm = abs(mult)
            return _signed_shape(-vm * fs + min(sign * rlo, sign * rhi),
                                 vm * fs + max(sign * rlo, sign * rhi))

        def tree_root(nodes):
            # C > 0, so the root (a sum containing a positive digit) always has sign +1.
            (_, value, _, _), = nodes
            return value >> (f - g) if f > g else value << (g - f)

        # The level sequence: gain-tree levels, then the iterations; a register every k levels.
        state = {"valid": self.i.valid, "z": z0, "xt": terms(x0), "yt": terms(y0)}
        if p.tag_width:
            state["tag"] = pl.tag
        z_shapes = [_signed_shape(lo, hi) for lo, hi in p.z_ranges]
        level_count = p.tree_levels + n
        for level in range(level_count):
            if level < p.tree_levels:
                state["xt"] = tree_level(state["xt"])
                state["yt"] = tree_level(state["yt"])
            else:
                i = level - p.tree_levels
                if i == 0:
                    state["x"] = tree_root(state.pop("xt"))
                    state["y"] = tree_root(state.pop("yt"))
                x, y, z = state["x"], state["y"], state["z"]
                z_neg = z[-1]                       # d_i = −1
                # x ∓ t as x + (t or ~t) + carry: one adder per bit with the inversion in front
                # (x − t = x + ~t + 1), not an adder, a subtractor and a multiplexer.
                ty, tx = y >> i, x >> i
                state["x"] = x + Mux(z_neg, ty, ~ty) + ~z_neg
                state["y"] = y + Mux(z_neg, ~tx, tx) + z_neg
                if i + 1 < n:
                    state["z"] = z + Mux(z_neg, p.atan[i], -p.atan[i])
                else:
                    del state["z"]
            if (level + 1) % k and level + 1 < level_count:
                continue
            # Pipeline register.
            after = level + 1 - p.tree_levels       # iterations done so far (≤ 0: in the tree)
            new = {}
            for name, value in state.items():
                if name == "valid":
                    reg = Signal(name=f"valid_l{level + 1}")
                elif name == "tag":
                    reg = Signal(p.tag_width, name=f"tag_l{level + 1}", reset_less=True)
                elif name == "z":
                    shape = z_shapes[after] if after > 0 else signed(p.z_width - 1)
                    reg = Signal(shape, name=f"z{after}" if after > 0 else f"z0_l{level + 1}",
                                 reset_less=True)
                elif name in ("x", "y"):
                    reg = Signal(signed(dw), name=f"{name}{after}", reset_less=True)
                else:                               # gain-tree nodes
                    regs = []
                    for j, node in enumerate(value):
                        r = Signal(node_shape(node), name=f"{name[0]}c_l{level + 1}_{j}",
                                   reset_less=True)
                        m.d.sync += r.eq(node[1])
                        regs.append((node[0], r, node[2], node[3]))
                    new[name] = regs
                    continue
                m.d.sync += reg.eq(value)
                new[name] = reg
            state = new

        # 4. Output: drop the guard bits (half away from zero), saturate.
        m.d.sync += [
            self.o.valid.eq(state["valid"]),
            self.o.payload.x.eq(saturate(round_shift(state["x"], g), signed(w))),
            self.o.payload.y.eq(saturate(round_shift(state["y"], g), signed(w))),
        ]
        if p.tag_width:
            m.d.sync += self.o.payload.tag.eq(state["tag"])
        return m
