"""The register bus between the host link (master) and the register file (slave).

A deliberately small bus, written on ``amaranth.lib.wiring`` (amaranth-soc is not on PyPI):

* The master drives ``addr``, ``we`` and ``w_data`` with ``stb`` high and holds them until the
  slave answers with ``ack`` (at the earliest one clock later). With ``ack`` the slave gives
  ``r_data`` (reads) and ``status`` (every access). One access at a time.
* ``status``: :class:`Status` — ``OK``; ``BAD_ADDRESS`` (no register there: a write changes
  nothing, a read returns 0); ``READ_ONLY`` (a write to a read-only register changes nothing).
* ``lock``: the master holds it high from the first to the last access of one host frame. The
  register file applies staged writes to the control path only at a loop boundary while ``lock`` is
  low, so the registers written by one frame (a burst) take effect together, never half-applied.

Registers are up to :data:`DATA_WIDTH` bits per address; wider ones span consecutive addresses,
low word first.
"""

from amaranth.lib import enum, wiring
from amaranth.lib.wiring import In, Out

__all__ = ["ADDR_WIDTH", "DATA_WIDTH", "Status", "RegBusSignature", "WordWriteSignature"]

ADDR_WIDTH = 16
DATA_WIDTH = 32


class Status(enum.Enum, shape=2):
    """Outcome of one bus access (also the per-register status a host reply carries)."""
    OK = 0
    BAD_ADDRESS = 1
    READ_ONLY = 2


class RegBusSignature(wiring.Signature):
    """Register bus, seen from the master (the host link). The register file takes
    ``In(RegBusSignature())`` (the flipped view)."""

    def __init__(self, *, addr_width=ADDR_WIDTH, data_width=DATA_WIDTH):
        if not isinstance(addr_width, int) or not 1 <= addr_width <= 32:
            raise TypeError(f"RegBusSignature addr_width must be an integer from 1 to 32, "
                            f"not {addr_width!r}")
        if not isinstance(data_width, int) or not 8 <= data_width <= 64:
            raise TypeError(f"RegBusSignature data_width must be an integer from 8 to 64, "
                            f"not {data_width!r}")
        super().__init__({
            "addr": Out(addr_width),
            "we": Out(1),
            "w_data": Out(data_width),
            "stb": Out(1),
            "lock": Out(1),
            "ack": In(1),
            "r_data": In(data_width),
            "status": In(Status),
        })


class WordWriteSignature(wiring.Signature):
    """A RAM write port, seen from the writer: ``valid`` (write in this clock), ``index`` (the
    word, ``range(depth)``) and ``data`` (``width`` bits). The register file's ``export`` port
    (:class:`~.regs.RegisterFile`) is ``Out`` of it, the loop engine's configuration RAM
    (:class:`~.engine.Engine`) takes ``In`` of it.

    Parameters
    ----------
    depth : int
        Words the index addresses (at least 1).
    width : int
        Bits of ``data`` (default :data:`DATA_WIDTH`).
    """

    def __init__(self, depth, *, width=DATA_WIDTH):
        if not isinstance(depth, int) or depth < 1:
            raise TypeError(f"WordWriteSignature depth must be a positive integer, "
                            f"not {depth!r}")
        if not isinstance(width, int) or not 1 <= width <= 64:
            raise TypeError(f"WordWriteSignature width must be an integer from 1 to 64, "
                            f"not {width!r}")
        self.depth, self.width = depth, width
        super().__init__({"valid": Out(1), "index": Out(range(depth)), "data": Out(width)})

    def __repr__(self):
        return f"WordWriteSignature({self.depth}, width={self.width})"
