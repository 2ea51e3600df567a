# Ref: docs/AREA.md §7.64; hdl/engine_mt.py
"""M/T speed's arithmetic on the engine interpreter (the prototype of docs/AREA.md §7.64): the
piece :func:`foc_servo.hdl.engine_mt.mt_program` run on :class:`.engine.EngineModel`, one run
per M/T update, fed with the operands the gateware's window logic would give it
(:func:`~foc_servo.hdl.engine_mt.mt_operands`)."""

import numpy as np

from ...hdl.engine_mt import MT_OUTS, mt_k_slices, mt_k_words, mt_operands, mt_program
from .engine import EngineModel, _complete, _signed

__all__ = ["EngineMTModel"]


class EngineMTModel:
    """One :meth:`update` per accepted M/T update; the register file (``r.mt_pm``, the last
    output's magnitude) and the output register ``mtspd`` persist between updates, as they
    would in the engine.

    Attributes
    ----------
    engine : EngineModel
    speed : int
        The last output (signed 32 bits; 0 at power-up).
    trace : list of dict
        :meth:`EngineModel.run`'s trace of the last update.
    """

    def __init__(self, *, program=None, out_widths=MT_OUTS):
        self.program = program if program is not None else mt_program()
        # k as the program reads it: the slices mkl, mkh or the words mtk0, mtk1
        # (mt_arith's k); a combined program (its run at the label ``mt``) with every output.
        self.k_words = "mtk0" in self.program.specials
        self.engine = EngineModel(self.program, out_widths=out_widths)
        self.start = self.program.labels.get("mt", 0)
        self.trace = []

    @property
    def speed(self):
        return _signed(self.engine.outs["mtspd"], 32)

    def update(self, k, mode, dm, dt):
        """One update: ``mode`` (``STOPPED``, ``BOUND``, ``FRESH`` of
        :mod:`~foc_servo.sim.models.mt_speed`) with ``simulate``'s operands ``dm``, ``dt`` →
        the signed speed."""
        kspec = mt_k_words(int(k)) if self.k_words else mt_k_slices(int(k))
        spec = {**kspec, **mt_operands(mode, dm, dt, self.speed)}
        self.trace = self.engine.run(*_complete(self.program, spec, {}), start=self.start)
        return self.speed

    def replay(self, out, k):
        """The speeds of every output of :func:`~foc_servo.sim.models.mt_speed.simulate`'s
        result ``out`` (same ``k``), recomputed here from its operands: an int64 array to
        compare with ``out["speed"]``."""
        modes = np.where(out["stopped"] == 1, 0, np.where(out["fresh"] == 1, 2, 1))
        return np.array([self.update(k, int(mo), int(dm), int(dt))
                         for mo, dm, dt in zip(modes, out["dm"], out["dt"])], dtype=np.int64)
