# Ref: issue 6 item 3
"""Simulation engines for the whole controller behind one API (see :mod:`.base`).

``make_engine("pysim" | "compiled", **top_kwargs)``: Amaranth's simulator (the reference) or a
Verilator model of the generated Verilog (fast, cached between runs).
"""

from .base import Engine, RunResult, SimTop

__all__ = ["ENGINES", "make_engine", "Engine", "RunResult", "SimTop"]

#: Engine kinds.
ENGINES = ("pysim", "compiled")


def make_engine(kind, *, progress=True, **top_kwargs):
    """An :class:`~.base.Engine` of ``kind`` on a :class:`~.base.SimTop` built from ``top_kwargs``.

    Parameters
    ----------
    kind : str
        ``"pysim"`` (:class:`~.pysim.PysimEngine`) or ``"compiled"``
        (:class:`~.compiled.CompiledEngine`).
    progress : bool
        Show the compiled engine's build progress on stderr (ignored by pysim).
    **top_kwargs
        :class:`~foc_servo.hdl.top.Top` parameters (``clk_hz``, ``pwm_hz``, ``baud``, …).

    Raises
    ------
    ValueError
        An unknown ``kind``; and whatever :class:`~foc_servo.hdl.top.Top` raises.
    """
    if kind == "pysim":
        from .pysim import PysimEngine
        return PysimEngine(SimTop(**top_kwargs))
    if kind == "compiled":
        from .compiled import CompiledEngine
        return CompiledEngine(SimTop(**top_kwargs), progress=progress)
    raise ValueError(f"Engine kind must be one of {', '.join(repr(k) for k in ENGINES)}, "
                     f"not {kind!r}")
