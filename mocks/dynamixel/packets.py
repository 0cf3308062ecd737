"""Dynamixel Protocol 2.0 framing: CRC-16 (poly 0x8005), byte stuffing, packet build and stream parsing.

Packet: ``FF FF FD 00 | ID | LEN_L LEN_H | INST | PARAMS... | CRC_L CRC_H`` where LEN counts INST, PARAMS
and CRC after stuffing (``FF FF FD`` inside INST..PARAMS gets an extra ``FD``). The CRC covers the stuffed
bytes from the first header byte up to the last parameter."""

from __future__ import annotations

from dataclasses import dataclass

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
INST_STATUS = 0x55


def _make_table() -> list[int]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return table


_CRC_TABLE = _make_table()


def crc16(data: bytes | bytearray, crc: int = 0) -> int:
    """CRC-16/BUYPASS (poly 0x8005, init 0, no reflection), as Protocol 2.0 uses."""
    for b in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ b) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Insert ``FD`` after every ``FF FF FD`` in the instruction+parameter bytes. The two bytes before
    ``body`` on the wire (LEN_H, ID...) never form ``FF FF`` with it in practice, but the spec only looks
    inside the body, and so do we."""
    out = bytearray()
    for b in body:
        out.append(b)
        if b == 0xFD and len(out) >= 3 and out[-2] == 0xFF and out[-3] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    out = bytearray()
    i = 0
    n = len(body)
    while i < n:
        b = body[i]
        out.append(b)
        if b == 0xFD and i + 1 < n and body[i + 1] == 0xFD and len(out) >= 3 and out[-2] == 0xFF and out[-3] == 0xFF:
            i += 1  # drop the stuffing byte
        i += 1
    return bytes(out)


def build(dxl_id: int, inst: int, params: bytes = b"", *, stuffing: bool = True) -> bytes:
    body = bytes([inst]) + bytes(params)
    if stuffing:
        body = stuff(body)
    length = len(body) + 2
    head = HEADER + bytes([dxl_id, length & 0xFF, length >> 8])
    pkt = head + body
    crc = crc16(pkt)
    return pkt + bytes([crc & 0xFF, crc >> 8])


def status(dxl_id: int, error: int, params: bytes = b"") -> bytes:
    """A status packet: instruction 0x55, error byte, parameters."""
    return build(dxl_id, INST_STATUS, bytes([error]) + bytes(params))


@dataclass(frozen=True)
class Packet:
    dxl_id: int
    inst: int
    params: bytes  # unstuffed
    raw: bytes  # as on the wire
    crc_ok: bool = True


class StreamParser:
    """Feeds raw bytes, yields complete packets. Garbage before a header is dropped (counted)."""

    MAX_LEN = 1024

    def __init__(self) -> None:
        self.buf = bytearray()
        self.dropped = 0

    def feed(self, data: bytes) -> list[Packet]:
        self.buf.extend(data)
        out: list[Packet] = []
        while True:
            i = self.buf.find(HEADER[:3])
            if i < 0:
                keep = 2 if self.buf.endswith(b"\xff\xff") else (1 if self.buf.endswith(b"\xff") else 0)
                self.dropped += len(self.buf) - keep
                del self.buf[: len(self.buf) - keep]
                return out
            if i:
                self.dropped += i
                del self.buf[:i]
            if len(self.buf) < 7:
                return out
            if self.buf[3] != 0x00:  # FF FF FD FD is stuffing, not a header; FF FF FD xx is garbage
                self.dropped += 1
                del self.buf[:1]
                continue
            length = self.buf[5] | (self.buf[6] << 8)
            if length < 3 or length > self.MAX_LEN:
                self.dropped += 1
                del self.buf[:1]
                continue
            total = 7 + length
            if len(self.buf) < total:
                return out
            raw = bytes(self.buf[:total])
            del self.buf[:total]
            crc_ok = crc16(raw[:-2]) == (raw[-2] | (raw[-1] << 8))
            body = unstuff(raw[7:-2])
            out.append(Packet(raw[4], body[0] if body else 0, body[1:], raw, crc_ok))
