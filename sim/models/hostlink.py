# Ref: docs/PROTOCOL.md (framing, commands, status codes, resynchronisation)
"""Bit-true model of :class:`~foc_servo.hdl.hostlink.LinkCore`: wire bytes in → reply bytes
and bus accesses out.

Mirrors the gateware's streaming COBS decoder, its checks in the same order, and its reply
encoding (:func:`foc_servo.host.protocol.encode_reply`, CRC, COBS). The bus slave is given as
two callables, so the model serves the stand-in register bank of :mod:`foc_servo.sim.link` and
any other. It models a host that waits for each reply (no bytes lost while the link is busy).
"""

from ...hdl.hostlink import hostlink_params
from ...host.protocol import (CRC_BYTES, REQUEST_HEADER, Command, ReplyStatus, cobs_encode, crc16,
                              encode_reply)

__all__ = ["LinkModel"]


class LinkModel:
    """Model of the link's protocol engine.

    Parameters
    ----------
    read : callable(addr) -> (int, Status-like int)
        Bus read: the word and the bus status (0 OK, 1 BAD_ADDRESS, 2 READ_ONLY).
    write : callable(addr, word) -> int
        Bus write: the bus status.
    max_words, address_map, counter_width
        As for :class:`~foc_servo.hdl.hostlink.LinkCore`.

    Attributes
    ----------
    counters : dict
        ``frames_ok``, ``crc_errors``, ``framing_errors``, ``rejected`` (unwrapped).
    """

    def __init__(self, read, write, *, max_words=64, address_map=None, counter_width=16):
        p = hostlink_params(max_words=max_words, address_map=address_map,
                            counter_width=counter_width)
        self.max_words = p["max_words"]
        self.address_map = p["address_map"]
        self.max_frame = REQUEST_HEADER + 4 * self.max_words + CRC_BYTES
        self._read, self._write = read, write
        self.counters = dict.fromkeys(("frames_ok", "crc_errors", "framing_errors", "rejected"), 0)
        self._reset()

    def _reset(self):
        self._data = bytearray()        # decoded bytes (all of them; the gateware keeps lmax)
        self._left = 0
        self._ff = False
        self._started = False
        self._bad = False

    def feed(self, data, *, errors=()):
        """Feed wire bytes; return the reply bytes they cause. ``errors``: indices into ``data``
        of bytes the UART received with a framing error (dropped, marking the frame bad)."""
        out = bytearray()
        errors = set(errors)
        for k, b in enumerate(data):
            if k in errors:
                self._bad = True
                continue
            if b == 0:
                if not self._started and not self._bad:
                    self._reset()
                    continue
                if self._left:
                    self._bad = True
                out += self._reply()
                self._reset()
            elif self._left == 0:
                if self._started and not self._ff:
                    self._data.append(0)
                self._left, self._ff, self._started = b - 1, b == 0xFF, True
            else:
                self._left -= 1
                self._data.append(b)
        return bytes(out)

    def _in_map(self, a, write):
        for start, stop, writable in self.address_map:
            if start <= a < stop:
                return (not write) or writable, True
        return False, False

    def _reply(self):
        d, n = self._data, len(self._data)
        cmd = d[0] if n >= 3 else 0
        seq = d[1] if n >= 4 else 0
        words = []
        info = 0
        if self._bad:
            status, cmd, seq = ReplyStatus.BAD_CRC, 0, 0
        elif n < 2 or crc16(d):
            status, cmd, seq = ReplyStatus.BAD_CRC, 0, 0
        elif n < REQUEST_HEADER + CRC_BYTES:
            status = ReplyStatus.BAD_LENGTH
        elif cmd not in (Command.PING, Command.READ, Command.WRITE):
            status = ReplyStatus.BAD_COMMAND
        elif n > self.max_frame:
            status = ReplyStatus.BAD_LENGTH
        elif cmd == Command.PING:
            status = ReplyStatus.OK if n == REQUEST_HEADER + CRC_BYTES else ReplyStatus.BAD_LENGTH
            info = self.max_words if status == ReplyStatus.OK else 0
        else:
            addr, count = d[2] | d[3] << 8, d[4]
            write = cmd == Command.WRITE
            want = REQUEST_HEADER + CRC_BYTES + (4 * count if write else 0)
            if not 1 <= count <= self.max_words or n != want:
                status = ReplyStatus.BAD_LENGTH
            else:
                status, info = self._execute(d, addr, count, write, words)
        if status == ReplyStatus.OK:
            self.counters["frames_ok"] += 1
        elif status == ReplyStatus.BAD_CRC:
            self.counters["framing_errors" if self._bad else "crc_errors"] += 1
        else:
            self.counters["rejected"] += 1
        payload = encode_reply(cmd, seq, status, info, words)
        return cobs_encode(payload + crc16(payload).to_bytes(2, "big")) + b"\x00"

    def _execute(self, d, addr, count, write, words):
        for i in range(count):
            a = addr + i
            ok, exists = self._in_map(a, write) if a < 1 << 16 else (False, False)
            if not exists:
                return ReplyStatus.BAD_ADDRESS, i
            if not ok:
                return ReplyStatus.READ_ONLY, i
        for i in range(count):
            if write:
                off = REQUEST_HEADER + 4 * i
                bus = self._write(addr + i, int.from_bytes(d[off:off + 4], "little"))
            else:
                word, bus = self._read(addr + i)
            if bus:
                words.clear()
                return (ReplyStatus.READ_ONLY if bus == 2 else ReplyStatus.BAD_ADDRESS), i
            if not write:
                words.append(word)
        return ReplyStatus.OK, (count if not write else 0)
