"""Minimal libpcap reader: UDP payloads from Ethernet/IPv4 captures, with IPv4 reassembly.

Supports classic pcap files (micro- or nanosecond timestamps, either byte order) with link types
Ethernet (1, optional 802.1Q VLAN tags), raw IPv4 (101, 228) and Linux cooked capture (113, 276).
Records are walked header by header (a loop over packets, not points); payload decoding is left
to the sensor modules, which stack equal-size payloads into numpy arrays.
"""

from __future__ import annotations

import struct
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mi_lidar.core.errors import LogFormatError, TruncatedLogWarning, unreadable

PCAP_MAGIC = {
    b"\xd4\xc3\xb2\xa1": ("<", 1e-6),
    b"\xa1\xb2\xc3\xd4": (">", 1e-6),
    b"\x4d\x3c\xb2\xa1": ("<", 1e-9),
    b"\xa1\xb2\x3c\x4d": (">", 1e-9),
}
_LINK_HEADER = {1: 14, 101: 0, 228: 0, 113: 16, 276: 20}
_MAX_RECORD = 1 << 18
_ETH_IPV4, _ETH_VLAN = 0x0800, (0x8100, 0x88A8)
_UDP = 17


@dataclass
class UdpPackets:
    """UDP datagrams of one capture, in file order.

    Attributes:
        times: (P,) float64 capture timestamps (s since the Unix epoch).
        dst_ports: (P,) int64 UDP destination ports.
        payloads: P byte strings (UDP payloads).
        offsets: (P,) int64 byte offset of each packet's pcap record in the file.
    """

    times: np.ndarray
    dst_ports: np.ndarray
    payloads: list[bytes]
    offsets: np.ndarray

    def select(self, port: int | None, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stack the payloads of ``size`` bytes (on ``port`` when given).

        Returns:
            ``(data, times, offsets)``: (P', size) uint8 payloads, their (P',) capture times (s)
            and (P',) record offsets.
        """
        keep = [
            i for i, p in enumerate(self.payloads) if len(p) == size and (port is None or self.dst_ports[i] == port)
        ]
        data = np.frombuffer(b"".join(self.payloads[i] for i in keep), dtype=np.uint8).reshape(len(keep), size)
        return data, self.times[keep], self.offsets[keep]


def _ipv4_udp(path: Path, offset: int, ip: bytes, fragments: dict) -> tuple[int, bytes] | None:
    """Return ``(dst_port, payload)`` of an IPv4 packet, reassembling fragments; None otherwise."""
    if len(ip) < 20 or ip[0] >> 4 != 4:
        return None
    ihl = (ip[0] & 0x0F) * 4
    total = struct.unpack_from(">H", ip, 2)[0]
    if ihl < 20 or total < ihl or total > len(ip) or ip[9] != _UDP:
        return None
    flags_frag = struct.unpack_from(">H", ip, 6)[0]
    more, frag_offset = bool(flags_frag & 0x2000), (flags_frag & 0x1FFF) * 8
    body = ip[ihl:total]
    if more or frag_offset:
        key = (ip[12:20], ip[4:6])
        parts = fragments.setdefault(key, {})
        parts[frag_offset] = (body, more)
        if all(m for _, m in parts.values()):
            return None
        position, chunks = 0, []
        for start in sorted(parts):
            if start != position:
                return None
            chunks.append(parts[start][0])
            position += len(parts[start][0])
        del fragments[key]
        body = b"".join(chunks)
    if len(body) < 8:
        raise LogFormatError(f"{path}: record at byte {offset}: UDP header truncated ({len(body)} bytes; expected 8)")
    dst_port, length = struct.unpack_from(">HH", body, 2)
    if length < 8 or length > len(body):
        raise LogFormatError(
            f"{path}: record at byte {offset}: UDP length field {length} does not fit the {len(body)}-byte datagram"
        )
    return dst_port, body[8:length]


def _network_layer(link: int, frame: bytes) -> bytes | None:
    """The IPv4 packet inside a link-layer frame, or None for other protocols."""
    if link == 1:
        if len(frame) < 14:
            return None
        ethertype, start = struct.unpack_from(">H", frame, 12)[0], 14
        while ethertype in _ETH_VLAN and len(frame) >= start + 4:
            ethertype, start = struct.unpack_from(">H", frame, start + 2)[0], start + 4
        return frame[start:] if ethertype == _ETH_IPV4 else None
    if link in (113, 276):
        header = _LINK_HEADER[link]
        protocol = struct.unpack_from(">H", frame, 14 if link == 113 else 0)[0] if len(frame) >= header else 0
        return frame[header:] if protocol == _ETH_IPV4 else None
    return frame


def _cut_short(path: Path, offset: int, what: str, first: bool) -> None:
    """Warn that the capture ends inside its last record (``what``, at byte ``offset``), or refuse it when that
    record is its ``first``: a capture stopped mid-write keeps the records before the cut."""
    if first:
        raise LogFormatError(f"{path}: byte {offset}: the first {what} is cut short at end of file: copy it again")
    warnings.warn(
        f"{path}: byte {offset}: the capture ends inside its last {what} (a capture stopped mid-write, or a "
        "partial copy?): reading the records before it",
        TruncatedLogWarning,
        stacklevel=3,
    )


def read_udp(path: str | Path) -> UdpPackets:
    """Read every UDP datagram of a pcap file.

    Args:
        path: A classic libpcap capture (not pcapng).

    Returns:
        The datagrams in file order. A capture whose last record is cut short (a capture stopped
        mid-write, as tcpdump killed leaves it) gives the records before it, with a
        :class:`~mi_lidar.core.errors.TruncatedLogWarning` naming the byte offset.

    Raises:
        LogFormatError: Missing file, unknown magic or link type, a cut-short first record (names its
            byte offset), or a record longer than 256 KiB (corrupt length field).
    """
    path = Path(path)
    if not path.is_file():
        raise LogFormatError(f"{path}: no such pcap file")
    try:
        data = path.read_bytes()
    except PermissionError as exc:
        raise unreadable(path) from exc
    if len(data) < 24:
        raise LogFormatError(f"{path}: {len(data)} bytes is shorter than the 24-byte pcap global header")
    if data[:4] not in PCAP_MAGIC:
        hint = " (this looks like pcapng; convert it with `editcap -F pcap`)" if data[:4] == b"\x0a\x0d\x0d\x0a" else ""
        raise LogFormatError(f"{path}: byte 0: unknown pcap magic {data[:4].hex()}{hint}")
    order, tick = PCAP_MAGIC[data[:4]]
    link = struct.unpack_from(order + "I", data, 20)[0] & 0x0FFFFFFF
    if link not in _LINK_HEADER:
        raise LogFormatError(f"{path}: byte 20: link type {link}; expected Ethernet (1), raw IP (101) or Linux SLL")
    record = struct.Struct(order + "IIII")
    times, ports, payloads, offsets, fragments = [], [], [], [], {}
    offset = 24
    while offset < len(data):
        if offset + 16 > len(data):
            _cut_short(path, offset, f"record header ({len(data) - offset} of 16 bytes)", offset == 24)
            break
        seconds, fraction, captured, _ = record.unpack_from(data, offset)
        if captured > _MAX_RECORD:
            raise LogFormatError(f"{path}: byte {offset}: record length {captured} is implausible (corrupt file?)")
        end = offset + 16 + captured
        if end > len(data):
            _cut_short(path, offset, f"record of {captured} bytes ({len(data) - offset - 16} present)", offset == 24)
            break
        ip = _network_layer(link, data[offset + 16 : end])
        datagram = None if ip is None else _ipv4_udp(path, offset, ip, fragments)
        if datagram is not None:
            times.append(seconds + fraction * tick)
            ports.append(datagram[0])
            payloads.append(datagram[1])
            offsets.append(offset)
        offset = end
    return UdpPackets(
        times=np.array(times, dtype=np.float64),
        dst_ports=np.array(ports, dtype=np.int64),
        payloads=payloads,
        offsets=np.array(offsets, dtype=np.int64),
    )
