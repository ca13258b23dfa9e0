"""One artifact as one object: its zarr group's files in an uncompressed zip.

On an object store every request costs a round trip, and a zarr group is several objects (a
`zarr.json` per group and array, a chunk per array). Packed into one zip (the layout zarr's
own `ZipStore` reads), an artifact is published by one create-only PUT, which an object store
applies whole or not at all, and read by one GET. The group's `zarr.json` is the zip's first
member, so its attributes (what a cache-hit check reads) sit in the object's first bytes and a
ranged GET of the head returns them without the arrays. That member's local header also
carries the zip's total length (an extra field, which zip readers skip), so the same GET tells
whether the object is whole: the object store's counterpart of the local store's stat of every
chunk file.
"""

from __future__ import annotations

import io
import struct
import zipfile
from collections.abc import Mapping

__all__ = ["FIRST", "first_member", "pack", "unpack"]

#: The member a packed group starts with: the group's own metadata and attributes.
FIRST = "zarr.json"
#: A zip local file header: signature, versions, flags, method, time, date, crc, sizes, lengths.
_LOCAL = struct.Struct("<4sHHHHHIIIHH")
_SIGNATURE = b"PK\x03\x04"
#: Members carry a fixed timestamp: a group's bytes depend on its files only.
_EPOCH = (1980, 1, 1, 0, 0, 0)
#: The extra field (id, length, total bytes of the zip) on the first member.
_LENGTH = struct.Struct("<HHQ")
_LENGTH_ID = 0x6565


def _zip(files: Mapping[str, bytes], names: list[str], total: int) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as zf:
        for name in names:
            info = zipfile.ZipInfo(name, _EPOCH)
            if name == FIRST:
                info.extra = _LENGTH.pack(_LENGTH_ID, _LENGTH.size - 4, total)
            zf.writestr(info, files[name])
    return out.getvalue()


def pack(files: Mapping[str, bytes]) -> bytes:
    """The zip of a group's files (relative path → bytes), `zarr.json` first, then in order."""
    names = [FIRST] + [n for n in files if n != FIRST]
    total = len(_zip(files, names, 0))  # the length field is fixed-width: same total
    return _zip(files, names, total)


def first_member(head: bytes) -> tuple[bytes, int] | int:
    """(the first member's bytes, the zip's length as written) from the object's first bytes;
    when `head` is too short, how many bytes are needed instead. ValueError when `head` is not
    a packed group."""
    if len(head) < _LOCAL.size:
        raise ValueError("not a packed zarr group: shorter than a zip header")
    sig, _, flags, method, _, _, _, size, _, name_len, extra_len = _LOCAL.unpack_from(head)
    start = _LOCAL.size + name_len + extra_len
    if sig != _SIGNATURE or method != zipfile.ZIP_STORED or flags & 0x08:
        raise ValueError("not a packed zarr group: no stored first member")
    if head[_LOCAL.size:_LOCAL.size + name_len] != FIRST.encode("ascii"):
        raise ValueError(f"not a packed zarr group: the first member is not {FIRST}")
    if len(head) < start + size:
        return start + size
    extra = head[_LOCAL.size + name_len:start]
    if len(extra) < _LENGTH.size or _LENGTH.unpack_from(extra)[0] != _LENGTH_ID:
        raise ValueError("not a packed zarr group: its length is not recorded")
    return head[start:start + size], _LENGTH.unpack_from(extra)[2]


def unpack(data: bytes) -> dict[str, bytes]:
    """Every member (relative path → bytes); zipfile checks each member's CRC as it reads it."""
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        return {name: zf.read(name) for name in zf.namelist()}
