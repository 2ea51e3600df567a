# Ref: docs/PROTOCOL.md (host link framing); CRC-16/CCITT-FALSE; COBS (Cheshire & Baker, 1999)
"""The host link protocol in pure Python: CRC, COBS, request/reply codec and a client.

This module is the golden model of the framing: the gateware (:mod:`foc_servo.hdl.hostlink`)
imports its constants (commands, status codes, header sizes) and the tests compare the gateware's
reply bytes with :func:`encode_reply` byte for byte. It imports no gateware.

Frames on the wire: ``COBS(payload + CRC16_BE(payload)) + 0x00``; the host also sends ``0x00``
before every frame (resynchronisation). Decoded payloads:

* request: ``cmd u8, seq u8, addr u16 LE, count u8, data (4·count bytes, u32 LE, writes only)``
* reply: ``cmd u8, seq u8, status u8, info u8, data (4·info bytes, u32 LE, OK reads only)``

See ``docs/PROTOCOL.md`` for the rules (which frame gets which reply).
"""

import enum
import struct
import time
from dataclasses import dataclass, field

__all__ = [
    "Command", "ReplyStatus", "REQUEST_HEADER", "REPLY_HEADER", "CRC_BYTES", "ADDR_SPACE",
    "crc16", "cobs_encode", "cobs_decode", "CobsError", "frame", "encode_request",
    "decode_request", "encode_reply", "decode_reply", "Request", "Reply",
    "LinkError", "StatusError", "ReplyTimeout", "ProtocolViolation",
    "Transport", "SerialTransport", "Client",
]

#: Decoded request header: cmd, seq, addr (2), count.
REQUEST_HEADER = 5
#: Decoded reply header: cmd, seq, status, info.
REPLY_HEADER = 4
#: CRC-16 bytes after the payload (big endian, so the CRC over payload + CRC is 0).
CRC_BYTES = 2
#: Number of word addresses (16-bit addresses).
ADDR_SPACE = 1 << 16


class Command(enum.IntEnum):
    """Request command byte."""
    PING = 0x00     #: no access; the reply's ``info`` is the link's ``max_words``
    READ = 0x01     #: read ``count`` words from ``addr``, ``addr + 1``, …
    WRITE = 0x02    #: write ``count`` words to ``addr``, ``addr + 1``, … (all or nothing)


class ReplyStatus(enum.IntEnum):
    """Reply status byte."""
    OK = 0
    BAD_CRC = 1         #: CRC mismatch, or the frame was damaged (COBS, UART framing error)
    BAD_LENGTH = 2      #: frame too short, too long, or count out of 1 … max_words
    BAD_COMMAND = 3     #: unknown command byte
    BAD_ADDRESS = 4     #: no register at ``addr + info`` (or the burst runs past 0xFFFF)
    READ_ONLY = 5       #: write to a read-only register at ``addr + info``


def _crc_table():
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
        table.append(crc & 0xFFFF)
    return table


_CRC_TABLE = _crc_table()


def crc16(data, crc=0xFFFF):
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final XOR).

    ``crc16(b"123456789") == 0x29B1``; ``crc16(p + crc16(p).to_bytes(2, "big")) == 0``.
    """
    for b in data:
        crc = ((crc << 8) & 0xFFFF) ^ _CRC_TABLE[((crc >> 8) ^ b) & 0xFF]
    return crc


class CobsError(ValueError):
    """A byte string that is not a valid COBS encoding."""


def cobs_encode(data):
    """COBS-encode ``data`` (no delimiter). Blocks of 254 non-zero bytes get code 0xFF; a frame
    ending right after such a block gets no extra 0x01 block (the gateware encodes the same way).
    """
    data = bytes(data)
    out = bytearray()
    p, n = 0, len(data)
    while True:
        q = p
        while q < n and q - p < 254 and data[q] != 0:
            q += 1
        out.append(q - p + 1)
        out += data[p:q]
        if q - p == 254:
            if q == n:
                break
            p = q
        elif q == n:
            break
        else:
            p = q + 1               # skip the zero the code byte stands for
    return bytes(out)


def cobs_decode(data):
    """Decode a COBS frame (without the 0x00 delimiter); accepts both ends of a 0xFF block.

    Raises
    ------
    CobsError
        If ``data`` contains 0x00, is empty, or a block runs past its end.
    """
    data = bytes(data)
    if not data:
        raise CobsError("COBS frame is empty")
    out = bytearray()
    p = 0
    prev = 0xFF
    while p < len(data):
        code = data[p]
        if code == 0:
            raise CobsError(f"COBS frame contains 0x00 at byte {p}")
        if p and prev != 0xFF:
            out.append(0)
        block = data[p + 1:p + code]
        if len(block) != code - 1:
            raise CobsError(f"COBS block at byte {p} (code {code}) runs past the end of the frame")
        if 0 in block:
            raise CobsError(f"COBS frame contains 0x00 at byte {p + 1 + block.index(0)}")
        out += block
        prev = code
        p += code
    return bytes(out)


def frame(payload):
    """A payload as sent on the wire: ``0x00, COBS(payload + CRC), 0x00``."""
    payload = bytes(payload)
    return b"\x00" + cobs_encode(payload + crc16(payload).to_bytes(2, "big")) + b"\x00"


def _check_words(words):
    for w in words:
        if not isinstance(w, int) or not 0 <= w < 1 << 32:
            raise ValueError(f"Data word must be an integer from 0 to 2**32 - 1, not {w!r}")


@dataclass(frozen=True)
class Request:
    """A decoded request (see :func:`decode_request`)."""
    cmd: int
    seq: int
    addr: int
    count: int
    data: tuple = ()


@dataclass(frozen=True)
class Reply:
    """A decoded reply: ``info`` is the word count of ``data`` for OK reads, the index of the
    offending word for BAD_ADDRESS / READ_ONLY, ``max_words`` for a ping, else 0."""
    cmd: int
    seq: int
    status: int
    info: int
    data: tuple = field(default=())


def encode_request(cmd, seq, addr=0, count=None, data=()):
    """The decoded payload (without CRC) of a request. ``count`` defaults to ``len(data)``."""
    data = tuple(data)
    _check_words(data)
    if count is None:
        count = len(data)
    for name, value, hi in (("cmd", cmd, 0xFF), ("seq", seq, 0xFF), ("addr", addr, 0xFFFF),
                            ("count", count, 0xFF)):
        if not isinstance(value, int) or not 0 <= value <= hi:
            raise ValueError(f"Request {name} must be an integer from 0 to {hi}, not {value!r}")
    return (struct.pack("<BBHB", cmd, seq, addr, count)
            + b"".join(struct.pack("<I", w) for w in data))


def decode_request(payload):
    """Inverse of :func:`encode_request` for a well-formed payload (any trailing bytes that do not
    make a whole word are ignored)."""
    cmd, seq, addr, count = struct.unpack_from("<BBHB", payload)
    body = payload[REQUEST_HEADER:]
    data = struct.unpack_from(f"<{len(body) // 4}I", body)
    return Request(cmd, seq, addr, count, data)


def encode_reply(cmd, seq, status, info=0, data=()):
    """The decoded payload (without CRC) of a reply."""
    data = tuple(data)
    _check_words(data)
    return struct.pack("<BBBB", cmd, seq, int(status), info) + b"".join(
        struct.pack("<I", w) for w in data)


def decode_reply(payload):
    """Decode a reply payload whose CRC has been checked and removed.

    Raises
    ------
    ProtocolViolation
        If the payload is shorter than a header or its data is not whole words.
    """
    if len(payload) < REPLY_HEADER or (len(payload) - REPLY_HEADER) % 4:
        raise ProtocolViolation(f"Reply payload of {len(payload)} bytes is not a header plus "
                                f"whole words")
    cmd, seq, status, info = payload[:REPLY_HEADER]
    body = payload[REPLY_HEADER:]
    return Reply(cmd, seq, status, info, struct.unpack(f"<{len(body) // 4}I", body))


class LinkError(Exception):
    """Base class of the host link's errors."""


class StatusError(LinkError):
    """The drive answered with an error status.

    Attributes
    ----------
    status : ReplyStatus
    addr : int or None
        The offending word address for BAD_ADDRESS / READ_ONLY, else ``None``.
    """

    def __init__(self, status, request, info):
        self.status = ReplyStatus(status)
        self.request = request
        self.addr = None
        what = {Command.READ: "read", Command.WRITE: "write"}.get(request.cmd, "ping")
        where = ""
        if self.status in (ReplyStatus.BAD_ADDRESS, ReplyStatus.READ_ONLY):
            self.addr = request.addr + info
            where = f" at address 0x{self.addr:04X}"
        super().__init__(f"{what} of {request.count} word(s) from 0x{request.addr:04X}: "
                         f"{self.status.name}{where}")


class ReplyTimeout(LinkError):
    """No (complete) reply within the timeout."""


class ProtocolViolation(LinkError):
    """A reply that does not fit the request (wrong length, garbled frame)."""


class Transport:
    """What :class:`Client` needs from a byte pipe (a serial port, the simulator).

    ``write(data)`` sends bytes; ``read(size, timeout_s)`` returns up to ``size`` bytes (at
    least one unless ``timeout_s`` seconds pass without any); ``reset_input()`` drops unread
    bytes. ``drained`` is true when the transport knows that no more bytes can come (a simulated
    link that has gone idle), so a reader need not wait for its timeout.
    """

    drained = False

    def write(self, data):
        raise NotImplementedError

    def read(self, size, timeout_s):
        raise NotImplementedError

    def reset_input(self):
        raise NotImplementedError


class SerialTransport(Transport):
    """A :class:`Transport` over a ``serial.Serial`` (pyserial) port, real or a pty."""

    def __init__(self, port):
        self.port = port

    def write(self, data):
        self.port.write(data)
        self.port.flush()

    def read(self, size, timeout_s):
        self.port.timeout = timeout_s
        data = self.port.read(1)            # wait for the first byte, then take what is there
        if data and size > 1:
            data += self.port.read(min(size - 1, self.port.in_waiting))
        return data

    def reset_input(self):
        self.port.reset_input_buffer()


class Client:
    """Reads and writes registers through a :class:`Transport`.

    Parameters
    ----------
    transport : Transport
    timeout_s : float
        Time to wait for a reply, in seconds (the whole reply; the default suits 115 200 baud
        and a 64-word burst, ~25 ms, with margin).
    max_words : int
        Longest burst sent in one frame; longer reads and writes are split (each frame is
        all-or-nothing, the whole call is not).

    Sequence numbers run 1 … 255 and wrap to 1; 0 is never used by the client (the link's
    BAD_CRC replies to damaged frames carry seq 0).
    """

    def __init__(self, transport, *, timeout_s=0.5, max_words=64):
        if not isinstance(max_words, int) or not 1 <= max_words <= 255:
            raise ValueError(f"Client max_words must be an integer from 1 to 255, "
                             f"not {max_words!r}")
        self.transport = transport
        self.timeout_s = timeout_s
        self.max_words = max_words
        self._seq = 0
        self._rx = bytearray()

    def _next_seq(self):
        self._seq = self._seq % 255 + 1
        return self._seq

    def _read_frame(self, deadline):
        """The next nonempty frame's bytes (without delimiter), or raise ReplyTimeout."""
        while True:
            end = self._rx.find(0)
            if end == 0:
                del self._rx[0]
                continue
            if end > 0:
                raw = bytes(self._rx[:end])
                del self._rx[:end + 1]
                return raw
            data = self.transport.read(256, max(deadline - time.monotonic(), 0.0))
            if data:
                self._rx += data
            elif time.monotonic() >= deadline or self.transport.drained:
                raise ReplyTimeout(f"no complete reply from the drive within {self.timeout_s} s")

    def transact(self, request_payload, request):
        """Send one request payload, return the matching :class:`Reply` (OK or not)."""
        self._rx.clear()
        self.transport.reset_input()
        self.transport.write(frame(request_payload))
        deadline = time.monotonic() + self.timeout_s
        while True:
            raw = self._read_frame(deadline)
            try:
                payload = cobs_decode(raw)
            except CobsError:
                continue
            if len(payload) < REPLY_HEADER + CRC_BYTES or crc16(payload):
                continue                    # garbled: ignore, the timeout catches a lost reply
            reply = decode_reply(payload[:-CRC_BYTES])
            if reply.status == ReplyStatus.BAD_CRC and reply.seq == 0:
                raise StatusError(ReplyStatus.BAD_CRC, request, 0)
            if reply.seq != request.seq or reply.cmd != request.cmd:
                continue                    # a stale reply to an earlier request
            return reply

    def _checked(self, cmd, addr, count, data=()):
        seq = self._next_seq()
        request = Request(cmd, seq, addr, count, tuple(data))
        reply = self.transact(encode_request(cmd, seq, addr, count, data), request)
        if reply.status != ReplyStatus.OK:
            raise StatusError(reply.status, request, reply.info)
        return reply

    def ping(self):
        """Check the link; return the drive's maximum burst length in words."""
        return self._checked(Command.PING, 0, 0).info

    def read(self, addr, n=1):
        """Read ``n`` consecutive words from ``addr``; a list of ints."""
        _check_range(addr, n)
        out = []
        while n:
            k = min(n, self.max_words)
            reply = self._checked(Command.READ, addr, k)
            if len(reply.data) != k or reply.info != k:
                raise ProtocolViolation(f"read of {k} word(s) from 0x{addr:04X} returned "
                                        f"{len(reply.data)}")
            out += reply.data
            addr, n = addr + k, n - k
        return out

    def write(self, addr, words):
        """Write ``words`` (ints, 0 … 2**32 - 1) to ``addr``, ``addr + 1``, …"""
        words = list(words)
        _check_words(words)
        _check_range(addr, len(words))
        while words:
            k = min(len(words), self.max_words)
            self._checked(Command.WRITE, addr, k, words[:k])
            addr, words = addr + k, words[k:]


def _check_range(addr, n):
    if not isinstance(addr, int) or not 0 <= addr < ADDR_SPACE:
        raise ValueError(f"Address must be an integer from 0 to 0xFFFF, not {addr!r}")
    if not isinstance(n, int) or n < 1 or addr + n > ADDR_SPACE:
        raise ValueError(f"Word count must be an integer from 1 to {ADDR_SPACE - addr} at "
                         f"address 0x{addr:04X}, not {n!r}")
