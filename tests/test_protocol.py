# Ref: docs/PROTOCOL.md; CRC-16/CCITT-FALSE; COBS (Cheshire & Baker, 1999)
import random

import pytest

from foc_servo.host.protocol import (Client, CobsError, Command, ProtocolViolation, ReplyStatus,
                                     ReplyTimeout, StatusError, Transport, cobs_decode,
                                     cobs_encode, crc16, decode_reply, decode_request,
                                     encode_reply, encode_request, frame)
from foc_servo.sim.link import StandInModel, StandInRegisters
from foc_servo.sim.models.hostlink import LinkModel


def test_crc16_ccitt_false_check_value_and_zero_residue():
    assert crc16(b"123456789") == 0x29B1
    assert crc16(b"") == 0xFFFF
    rng = random.Random(1)
    for _ in range(200):
        p = bytes(rng.getrandbits(8) for _ in range(rng.randrange(40)))
        assert crc16(p + crc16(p).to_bytes(2, "big")) == 0


@pytest.mark.parametrize("data, encoded", [
    (b"\x00", b"\x01\x01"),
    (b"\x00\x00", b"\x01\x01\x01"),
    (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
    (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
    (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
    (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255))),
    (bytes(range(0, 255)), b"\x01\xff" + bytes(range(1, 255))),
    (bytes(range(1, 256)), b"\xff" + bytes(range(1, 255)) + b"\x02\xff"),
    (bytes(range(2, 256)) + b"\x00", b"\xff" + bytes(range(2, 256)) + b"\x01\x01"),
    (bytes(range(3, 256)) + b"\x00\x01", b"\xfe" + bytes(range(3, 256)) + b"\x02\x01"),
])
def test_cobs_reference_vectors(data, encoded):
    assert cobs_encode(data) == encoded
    assert cobs_decode(encoded) == data


def test_cobs_round_trip_random_and_long_runs():
    rng = random.Random(2)
    for _ in range(500):
        n = rng.choice((rng.randrange(10), rng.randrange(600)))
        zero_p = rng.choice((0.0, 0.01, 0.3))
        data = bytes(0 if rng.random() < zero_p else rng.randrange(1, 256) for _ in range(n))
        enc = cobs_encode(data)
        assert 0 not in enc
        assert cobs_decode(enc) == data
    # A 0xFF block at the very end may or may not be followed by an empty 0x01 block.
    assert cobs_decode(b"\xff" + bytes(range(1, 255)) + b"\x01") == bytes(range(1, 255))


def test_cobs_decode_errors():
    with pytest.raises(CobsError, match=r"^COBS frame is empty$"):
        cobs_decode(b"")
    with pytest.raises(CobsError, match=r"^COBS frame contains 0x00 at byte 0$"):
        cobs_decode(b"\x00\x01")
    with pytest.raises(CobsError, match=r"^COBS frame contains 0x00 at byte 2$"):
        cobs_decode(b"\x03\x11\x00")
    with pytest.raises(CobsError,
                       match=r"^COBS block at byte 2 \(code 5\) runs past the end of the frame$"):
        cobs_decode(b"\x02\x11\x05\x01")


def test_documented_example_frames():
    # The examples in docs/PROTOCOL.md.
    write = encode_request(Command.WRITE, 0x01, 0x0100, 1, [0x00001234])
    assert write.hex(" ") == "02 01 00 01 01 34 12 00 00"
    assert frame(write).hex(" ") == "00 03 02 01 05 01 01 34 12 01 03 bd 2c 00"
    read = encode_request(Command.READ, 0x02, 0x0010, 2)
    assert frame(read).hex(" ") == "00 04 01 02 10 04 02 35 14 00"
    reply = encode_reply(Command.READ, 0x02, ReplyStatus.OK, 2, [0xC0DE0010, 0xC0DE0011])
    wire = cobs_encode(reply + crc16(reply).to_bytes(2, "big")) + b"\x00"
    assert wire.hex(" ") == "03 01 02 03 02 10 04 de c0 11 05 de c0 49 34 00"
    ok = encode_reply(Command.WRITE, 0x01, ReplyStatus.OK, 0)
    assert (cobs_encode(ok + crc16(ok).to_bytes(2, "big")) + b"\x00").hex(" ") == \
        "03 02 01 01 03 5e 98 00"


def test_request_reply_codec_and_validation():
    p = encode_request(Command.WRITE, 7, 0x1234, 2, [1, 0xFFFFFFFF])
    r = decode_request(p)
    assert (r.cmd, r.seq, r.addr, r.count, r.data) == (2, 7, 0x1234, 2, (1, 0xFFFFFFFF))
    rep = decode_reply(encode_reply(1, 9, ReplyStatus.OK, 1, [42]))
    assert (rep.cmd, rep.seq, rep.status, rep.info, rep.data) == (1, 9, 0, 1, (42,))
    with pytest.raises(ValueError, match=r"^Request addr must be an integer from 0 to 65535, "
                                         r"not 65536$"):
        encode_request(Command.READ, 0, 0x10000, 1)
    with pytest.raises(ValueError, match=r"^Request count must be an integer from 0 to 255, "
                                         r"not 256$"):
        encode_request(Command.READ, 0, 0, 256)
    with pytest.raises(ValueError, match=r"^Data word must be an integer from 0 to 2\*\*32 - 1, "
                                         r"not -1$"):
        encode_request(Command.WRITE, 0, 0, data=[-1])
    with pytest.raises(ProtocolViolation, match=r"^Reply payload of 5 bytes is not a header plus "
                                                r"whole words$"):
        decode_reply(b"\x00" * 5)


class _ModelTransport(Transport):
    """The link's reply model behind the Transport interface (no gateware)."""

    def __init__(self, max_words=8):
        self.regs = StandInModel()
        self.model = LinkModel(self.regs.read, self.regs.write, max_words=max_words,
                               address_map=StandInRegisters.address_map)
        self.out = bytearray()
        self.mangle = None

    @property
    def drained(self):
        return not self.out

    def write(self, data):
        if self.mangle:
            data = self.mangle(data)
        self.out += self.model.feed(data)

    def read(self, size, timeout_s):
        data = bytes(self.out[:size])
        del self.out[:size]
        return data

    def reset_input(self):
        self.out.clear()


def test_client_read_write_ping_and_burst_split():
    t = _ModelTransport(max_words=8)
    c = Client(t, max_words=8)
    assert c.ping() == 8
    words = list(range(100, 120))
    c.write(0x100, words)                       # split into 8 + 8 + 4
    assert c.read(0x100, 20) == words
    assert c.read(0x10, 2) == [0xC0DE0010, 0xC0DE0011]
    assert t.regs.writes == 20


def test_client_errors_name_status_and_address():
    t = _ModelTransport()
    c = Client(t, max_words=8)
    with pytest.raises(StatusError, match=r"^write of 2 word\(s\) from 0x000F: READ_ONLY at "
                                          r"address 0x0010$") as e:
        c.write(0x000F, [1, 2])
    assert e.value.status == ReplyStatus.READ_ONLY and e.value.addr == 0x10
    assert t.regs.writes == 0                   # all or nothing
    with pytest.raises(StatusError, match=r"^read of 1 word\(s\) from 0x0200: BAD_ADDRESS at "
                                          r"address 0x0200$"):
        c.read(0x200)
    with pytest.raises(ValueError, match=r"^Word count must be an integer from 1 to 1 at "
                                         r"address 0xFFFF, not 2$"):
        c.read(0xFFFF, 2)
    with pytest.raises(ValueError, match=r"^Client max_words must be an integer from 1 to 255, "
                                         r"not 0$"):
        Client(t, max_words=0)


def test_client_bad_crc_reply_and_timeout():
    t = _ModelTransport()
    c = Client(t, timeout_s=0.05)
    t.mangle = lambda d: d[:3] + bytes([d[3] ^ 0x40]) + d[4:]
    with pytest.raises(StatusError, match=r"^read of 1 word\(s\) from 0x0000: BAD_CRC$"):
        c.read(0)
    t.mangle = lambda d: d[:-1]                 # the closing 0x00 lost: no reply at all
    with pytest.raises(ReplyTimeout, match=r"^no complete reply from the drive within 0.05 s$"):
        c.read(0)
    t.mangle = None
    assert c.read(0) == [0]                     # the next frame's leading 0x00 resynchronises
