"""The depth codecs of ``.oni`` recordings: one frame <-> its record's payload bytes.

Frames are (H, W) uint16 depth in millimetres; payloads are ``bytes`` (or a flat uint8 array).
Three codecs, keyed by name in :data:`CODECS` (name -> the four-character id in the file):
``"none"`` (raw little-endian uint16), ``"16z"`` (OpenNI's lossless ``16zP``: differences between
neighbouring pixels in nibbles, runs of equal pixels collapsed; values up to 32767 mm) and
``"16zt"`` (OpenNI's ``16zT``: the frame's distinct values in a table, then ``16zP`` over table
indices; any uint16 value, at most 32768 distinct values per frame).  Nothing here knows the
container: :mod:`hw.oni_format` reads it, :mod:`hw.oni` writes it.
"""

from __future__ import annotations

import struct

import numpy as np
from numba import njit

from hw.errors import FrameError

# --- codec names ----------------------------------------------------------------------------------
#: codec name -> the four-character id stored in the NodeAdded record
CODECS: dict[str, bytes] = {"none": b"NONE", "16z": b"16zP", "16zt": b"16zT"}
_CODEC_NAMES = {value: key for key, value in CODECS.items()}
#: Largest depth value (mm) the 16z codec can store.
MAX_16Z_VALUE = 0x7FFF
#: Most distinct depth values one 16zt frame can hold (its indices are 16z-coded, so < 0x8000).
MAX_16ZT_VALUES = MAX_16Z_VALUE + 1


# --- 16z depth coding ---------------------------------------------------------------------------
def encode_16z(depth: np.ndarray) -> bytes:
    """OpenNI's lossless ``16zP`` coding of a depth image.

    ``depth``: (H, W) or flat uint16, values 0..32767 (mm).  Returns the payload bytes the
    OniFile player decodes back to exactly ``depth``.  Layout: the first pixel as little-endian
    uint16, then tokens over the differences ``d = previous - current``: a byte
    ``(d1 + 6) << 4 | (d2 + 6)`` for two differences in -6..6; low nibble ``0xD`` for a single
    one; low nibble ``0xF`` or a whole ``0xFF`` byte introduces a larger step, ``d + 192`` (one
    byte, |d| <= 63) or the new value big-endian (two bytes, < 0x8000); ``0xE0 + n`` repeats
    the previous pixel 2n times.  Pixels are paired in order so that the whole encoding is a
    few vectorised passes (about 10 ms for VGA).
    """
    values = np.ascontiguousarray(depth, dtype=np.uint16).ravel()
    if values.size == 0:
        return b""
    top = int(values.max())
    if top > MAX_16Z_VALUE:
        raise FrameError(
            f"depth value {top} mm does not fit the 16z codec (at most {MAX_16Z_VALUE} mm); "
            "clip the image or write it with codec='none'"
        )
    first = struct.pack("<H", int(values[0]))
    v = values.astype(np.int32)
    diffs = v[:-1] - v[1:]
    news = v[1:]
    count = diffs.size
    n_pairs = count // 2
    parts = [first]
    if n_pairs:
        parts.append(_encode_pairs(diffs[: 2 * n_pairs].reshape(-1, 2),
                                   news[: 2 * n_pairs].reshape(-1, 2)))
    if count % 2:
        d, new = int(diffs[-1]), int(news[-1])
        if abs(d) <= 6:
            parts.append(bytes([((d + 6) << 4) | 0x0D]))
        elif abs(d) <= 63:
            parts.append(bytes([0xFF, d + 192]))
        else:
            parts.append(bytes([0xFF, new >> 8, new & 0xFF]))
    return b"".join(parts)


def encode_16zt(depth: np.ndarray) -> bytes:
    """OpenNI's lossless ``16zT`` coding ("16z with embedded table") of a depth image.

    ``depth``: (H, W) or flat uint16 (mm, any value 0..65535) with at most
    :data:`MAX_16ZT_VALUES` distinct values.  Layout (little-endian): the table length ``n``
    (uint16), the ``n`` distinct values in increasing order (uint16 each), then the
    :func:`encode_16z` stream of the image of table indices (first index as uint16, then
    tokens).  A VGA Kinect frame has a few hundred distinct values, so the table costs ~1 KB and
    neighbouring indices differ by 0 or 1 where raw millimetres jump by a quantisation step.
    Raises :class:`FrameError` for more distinct values than the index stream can address.
    """
    values = np.ascontiguousarray(depth, dtype=np.uint16).ravel()
    if values.size == 0:
        return b""
    present = np.zeros(0x10000, dtype=bool)
    present[values] = True
    table = np.flatnonzero(present).astype("<u2")
    if table.size > MAX_16ZT_VALUES:
        raise FrameError(
            f"the frame has {table.size} distinct depth values; the 16zt codec holds at most "
            f"{MAX_16ZT_VALUES} per frame (real depth has a few thousand at most): write it "
            "with codec='16z' (values <= 32767 mm) or codec='none'"
        )
    lookup = (np.cumsum(present) - 1).astype(np.uint16)  # value -> its index in the table
    return struct.pack("<H", table.size) + table.tobytes() + encode_16z(lookup[values])


def _encode_pairs(d: np.ndarray, new: np.ndarray) -> bytes:
    """Tokens for pairs of differences ``d`` (P, 2) int32 with new values ``new`` (P, 2)."""
    small = np.abs(d) <= 6
    medium = ~small & (np.abs(d) <= 63)
    big = ~small & ~medium
    a_s, b_s = small[:, 0], small[:, 1]
    out = np.zeros((d.shape[0], 7), dtype=np.uint8)
    use = np.zeros((d.shape[0], 7), dtype=bool)

    def token(col: int, first_slot: int, rows: np.ndarray) -> None:
        # a large step's token: d + 192 (1 byte) or the new value big-endian (2 bytes)
        m = rows & medium[:, col]
        out[m, first_slot] = (d[m, col] + 192).astype(np.uint8)
        use[m, first_slot] = True
        g = rows & big[:, col]
        out[g, first_slot] = (new[g, col] >> 8).astype(np.uint8)
        out[g, first_slot + 1] = (new[g, col] & 0xFF).astype(np.uint8)
        use[g, first_slot] = use[g, first_slot + 1] = True

    # small, small: one byte
    ss = a_s & b_s
    out[ss, 0] = (((d[ss, 0] + 6) << 4) | (d[ss, 1] + 6)).astype(np.uint8)
    use[ss, 0] = True
    # small, large: (a + 6) << 4 | 0xF, then b's token
    sl = a_s & ~b_s
    out[sl, 0] = (((d[sl, 0] + 6) << 4) | 0x0F).astype(np.uint8)
    use[sl, 0] = True
    token(1, 1, sl)
    # large first: 0xFF + a's token, then b as a single small (low nibble 0xD) or 0xFF + token
    la = ~a_s
    out[la, 0] = 0xFF
    use[la, 0] = True
    token(0, 1, la)
    width_a = np.where(medium[:, 0], 1, 2)  # bytes of a's token
    ls = la & b_s
    rows = np.nonzero(ls)[0]
    out[rows, 1 + width_a[rows]] = (((d[rows, 1] + 6) << 4) | 0x0D).astype(np.uint8)
    use[rows, 1 + width_a[rows]] = True
    ll = la & ~b_s
    for w in (1, 2):  # where b's token starts depends on the width of a's
        rows_w = ll & (width_a == w)
        out[rows_w, 1 + w] = 0xFF
        use[rows_w, 1 + w] = True
        token(1, 2 + w, rows_w)

    # runs of (0, 0) pairs collapse to 0xE0 + n (n <= 15 pairs)
    zero = ss & (d[:, 0] == 0) & (d[:, 1] == 0)
    if zero.any():
        idx = np.arange(zero.size)
        starts = zero & ~np.concatenate(([False], zero[:-1]))
        ends = zero & ~np.concatenate((zero[1:], [False]))
        run_start = np.maximum.accumulate(np.where(starts, idx, 0))
        pos = idx - run_start
        emit = zero & ((pos % 15 == 14) | ends)
        use[zero, 0] = False
        out[emit, 0] = (0xE0 + pos[emit] % 15 + 1).astype(np.uint8)
        use[emit, 0] = True
    return out[use].tobytes()



# --- decoding -------------------------------------------------------------------------------------
def decode_frame(payload: np.ndarray | bytes, shape: tuple[int, int], codec: str) -> np.ndarray:
    """One frame's payload (uint8 array or bytes) coded with ``codec`` ("none", "16z", "16zt")
    -> (H, W) uint16 mm.  Raises :class:`FrameError` when it does not decode to exactly
    ``shape``."""
    raw = np.frombuffer(payload, dtype=np.uint8) if isinstance(payload, bytes) else payload
    height, width = shape
    count = height * width
    if codec == "none":
        if raw.size != 2 * count:
            raise FrameError(f"{raw.size} bytes of raw depth, expected {2 * count} for "
                             f"{width}x{height}")
        return raw.view("<u2").astype(np.uint16).reshape(shape)
    if codec == "16z":
        return _decode_16z_checked(raw, count).reshape(shape)
    if codec == "16zt":
        if raw.size < 2:
            raise FrameError("a 16zT frame shorter than its table length")
        n = int(raw[0]) | int(raw[1]) << 8
        if raw.size < 2 + 2 * n:
            raise FrameError(f"a 16zT frame of {raw.size} bytes cannot hold its {n}-entry table")
        table = raw[2: 2 + 2 * n].view("<u2").astype(np.uint16)
        indices = _decode_16z_checked(raw[2 + 2 * n:], count)
        if n == 0 or int(indices.max()) >= n:
            raise FrameError(f"a 16zT frame indexes past the end of its {n}-entry table")
        return table[indices].reshape(shape)
    raise FrameError(f"codec {codec!r}: choose one of {sorted(CODECS)}")


def _decode_16z_checked(raw: np.ndarray, count: int) -> np.ndarray:
    out = np.empty(count, dtype=np.uint16)
    got = _decode_16z(np.ascontiguousarray(raw), out)
    if got != count:
        what = "more" if got < 0 else str(got)
        raise FrameError(f"the 16z stream decodes to {what} pixels, expected {count}")
    return out


@njit(cache=True, nogil=True)
def _decode_16z(data, out):  # pragma: no cover - compiled
    """Decode a 16zP stream ``data`` (N,) uint8 into ``out`` (M,) uint16; returns the number of
    pixels written, or -1 if the stream is truncated or holds more than M pixels."""
    n_in = data.size
    n_out = out.size
    if n_in < 2 or n_out < 1:
        return -1
    last = np.int64(data[0]) | (np.int64(data[1]) << 8)
    out[0] = last
    o = 1
    i = 2
    while i < n_in:
        c = np.int64(data[i])
        i += 1
        if c >= 0xE0 and c != 0xFF:  # 0xE0 + n: n pairs equal to the last pixel
            run = 2 * (c - 0xE0)
            if o + run > n_out:
                return -1
            for _ in range(run):
                out[o] = last
                o += 1
            continue
        big = c == 0xFF
        if not big:  # high nibble: a step of 6 - nibble
            if o >= n_out:
                return -1
            last = (last - ((c >> 4) - 6)) & 0xFFFF
            out[o] = last
            o += 1
            low = c & 0x0F
            if low == 0x0D:  # a lone step
                continue
            if low != 0x0F:  # a second small step
                if o >= n_out:
                    return -1
                last = (last - (low - 6)) & 0xFFFF
                out[o] = last
                o += 1
                continue
        # a large step: d + 192 (one byte, top bit set) or the new value big-endian (two bytes)
        if i >= n_in or o >= n_out:
            return -1
        b = np.int64(data[i])
        i += 1
        if b & 0x80:
            last = (last - (b - 192)) & 0xFFFF
        else:
            if i >= n_in:
                return -1
            last = (b << 8) | np.int64(data[i])
            i += 1
        out[o] = last
        o += 1
    return o
