"""Plain CDR (XCDR1, little-endian) as ROS 2 puts it on the wire: a 4-byte encapsulation header
(``00 01 00 00``) and then every primitive aligned to its own size, counted from the end of that header.

Strings are a uint32 length that includes the terminating NUL, the bytes and the NUL; sequences
are a uint32 element count followed by the elements; fixed-size arrays have no count.
"""

from __future__ import annotations

import struct

from ..messages import MessageError

#: CDR_LE encapsulation, no options
ENCAPSULATION = b"\x00\x01\x00\x00"

#: ROS primitive type -> struct format character (little-endian)
PRIMITIVES: dict[str, str] = {
    "bool": "?", "byte": "B", "char": "B", "uint8": "B", "int8": "b",
    "uint16": "H", "int16": "h", "uint32": "I", "int32": "i",
    "uint64": "Q", "int64": "q", "float32": "f", "float64": "d",
}


class CdrError(MessageError):
    """A payload that is not valid CDR for the expected type."""


class CdrWriter:
    """Appends CDR values to a growing buffer."""

    def __init__(self) -> None:
        self.buffer = bytearray(ENCAPSULATION)

    def align(self, size: int) -> None:
        self.buffer += b"\x00" * (-(len(self.buffer) - len(ENCAPSULATION)) % size)

    def primitive(self, kind: str, value) -> None:
        fmt = PRIMITIVES[kind]
        size = struct.calcsize(fmt)
        self.align(size)
        self.buffer += struct.pack("<" + fmt, value)

    def primitives(self, kind: str, values) -> None:
        """A run of primitives of one type (the body of an array or sequence)."""
        values = list(values)
        if not values:
            return
        fmt = PRIMITIVES[kind]
        self.align(struct.calcsize(fmt))
        self.buffer += struct.pack(f"<{len(values)}{fmt}", *values)

    def string(self, value: str) -> None:
        data = value.encode()
        self.primitive("uint32", len(data) + 1)
        self.buffer += data + b"\x00"

    def blob(self, data: bytes) -> None:
        """A ``uint8[]`` sequence."""
        self.primitive("uint32", len(data))
        self.buffer += data

    def getvalue(self) -> bytes:
        return bytes(self.buffer)


class CdrReader:
    """Reads CDR values from a payload, checking every bound."""

    def __init__(self, data: bytes | bytearray | memoryview) -> None:
        self.data = memoryview(bytes(data))
        if len(self.data) < len(ENCAPSULATION):
            raise CdrError(f"CDR payload of {len(self.data)} bytes has no encapsulation header")
        if bytes(self.data[:2]) != ENCAPSULATION[:2]:
            raise CdrError(f"unsupported CDR encapsulation {bytes(self.data[:2]).hex()} (want little-endian CDR)")
        self.offset = len(ENCAPSULATION)

    def align(self, size: int) -> None:
        self.offset += -(self.offset - len(ENCAPSULATION)) % size

    def _take(self, size: int) -> memoryview:
        end = self.offset + size
        if size < 0 or end > len(self.data):
            raise CdrError(f"truncated CDR payload: need {size} bytes at offset {self.offset}, have {len(self.data)}")
        view = self.data[self.offset:end]
        self.offset = end
        return view

    def primitive(self, kind: str):
        fmt = PRIMITIVES[kind]
        size = struct.calcsize(fmt)
        self.align(size)
        return struct.unpack("<" + fmt, self._take(size))[0]

    def primitives(self, kind: str, count: int) -> list:
        if count == 0:
            return []
        fmt = PRIMITIVES[kind]
        size = struct.calcsize(fmt)
        self.align(size)
        return list(struct.unpack(f"<{count}{fmt}", self._take(size * count)))

    def count(self) -> int:
        n = self.primitive("uint32")
        if n > len(self.data):
            raise CdrError(f"sequence length {n} exceeds the payload")
        return n

    def string(self) -> str:
        n = self.count()
        raw = bytes(self._take(n))
        if n == 0:
            return ""
        if raw[-1] != 0:
            raise CdrError("CDR string is not NUL-terminated")
        try:
            return raw[:-1].decode()
        except UnicodeDecodeError:
            raise CdrError("CDR string is not valid UTF-8") from None

    def blob(self) -> bytes:
        return bytes(self._take(self.count()))

    def done(self) -> None:
        """Only alignment padding may be left once the message is read."""
        if len(self.data) - self.offset >= 8:
            raise CdrError(f"{len(self.data) - self.offset} trailing bytes after the message")
