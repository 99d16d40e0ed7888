"""CDR-serialized messages read in place: header stamps and sensor_msgs/Image without deserializing.

A node that subscribes ``raw=True`` keeps the frames it may never use as bytes; these read what it
needs from them (a stamp, a size, a view of the pixels) at a fraction of a deserialization's cost.
"""
from __future__ import annotations

import struct
from typing import Dict, Tuple

from std_msgs.msg import Header

from leapnbv_common.conversions.base import ConversionError
from leapnbv_common.conversions.stamps import NS_PER_S


def serialized_header_stamp_ns(cdr: bytes) -> int:
    """The header stamp of a CDR-serialized message that starts with a std_msgs/Header, without
    deserializing it (a node that subscribes ``raw=True`` keeps frames it may never use as bytes).

    Raises:
        ConversionError: fewer than 12 bytes.
    """
    if len(cdr) < 12:
        raise ConversionError(f"serialized message of {len(cdr)} bytes has no header")
    sec, nanosec = struct.unpack_from("<iI" if cdr[1] == 1 else ">iI", cdr, 4)
    return int(sec) * NS_PER_S + int(nanosec)


def serialized_image_header(cdr: bytes) -> Tuple[Header, int, int]:
    """(header, height, width) of a CDR-serialized sensor_msgs/Image, without copying its pixels.

    Raises:
        ConversionError: the bytes are too short for an Image header.
    """
    try:
        order = "<" if cdr[1] == 1 else ">"
        sec, nanosec, length = struct.unpack_from(order + "iII", cdr, 4)
        end = 16 + length  # the frame_id string, NUL included
        frame_id = bytes(cdr[16:end - 1]).decode("utf-8") if length else ""
        offset = 4 + ((end - 4 + 3) // 4) * 4  # CDR aligns the uint32s to 4 from the payload start
        height, width = struct.unpack_from(order + "II", cdr, offset)
    except (struct.error, IndexError, UnicodeDecodeError) as exc:
        raise ConversionError(f"serialized Image header unreadable: {exc}") from None
    header = Header(frame_id=frame_id)
    header.stamp.sec, header.stamp.nanosec = sec, nanosec
    return header, int(height), int(width)


class SerializedImage:
    """A CDR-serialized sensor_msgs/Image read in place: its header and fields, ``data`` a view into the
    serialized bytes (no copy). It stands in for the Image wherever only those are read: check_image,
    image_size, image_to_numpy, depth_to_metres, and the duplicate-stamp guard (whose fingerprint covers
    the header and the whole serialized message).

    Raises:
        ConversionError: bytes that do not hold a whole Image.
    """

    header: Header
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: memoryview

    def __init__(self, cdr: bytes) -> None:
        self.cdr = cdr
        try:
            order = "<" if cdr[1] == 1 else ">"

            def aligned(pos: int, size: int) -> int:  # CDR aligns from the start of the payload (byte 4)
                return 4 + ((pos - 4 + size - 1) // size) * size

            def string(pos: int) -> Tuple[str, int]:
                (length,) = struct.unpack_from(order + "I", cdr, pos)
                text = bytes(cdr[pos + 4:pos + 4 + max(0, length - 1)]).decode("utf-8")
                return text, pos + 4 + length

            sec, nanosec = struct.unpack_from(order + "iI", cdr, 4)
            frame_id, pos = string(12)
            pos = aligned(pos, 4)
            self.height, self.width = struct.unpack_from(order + "II", cdr, pos)
            self.encoding, pos = string(pos + 8)
            self.is_bigendian = cdr[pos]
            pos = aligned(pos + 1, 4)
            self.step, length = struct.unpack_from(order + "II", cdr, pos)
            pos += 8
        except (struct.error, IndexError, UnicodeDecodeError) as exc:
            raise ConversionError(f"serialized Image unreadable: {exc}") from None
        if pos + length > len(cdr):
            raise ConversionError(f"serialized Image holds {len(cdr) - pos} of its {length} data bytes")
        self.data = memoryview(cdr)[pos:pos + length]
        self.header = Header(frame_id=frame_id)
        self.header.stamp.sec, self.header.stamp.nanosec = sec, nanosec

    @staticmethod
    def get_fields_and_field_types() -> Dict[str, str]:
        """The fields the duplicate-stamp guard fingerprints (contracts.fingerprint), as a message lists its own."""
        return {"header": "std_msgs/Header", "cdr": "sequence<uint8>"}
