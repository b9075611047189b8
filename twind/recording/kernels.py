"""The numba kernels of :mod:`twind.recording.fastread`: a decompressed MCAP chunk's records
indexed, and its SampleBlock messages scanned and their samples copied out, slot by slot.

Compiled on first use and cached on disk (``cache=True``), and run without the GIL
(``nogil=True``), so that the reader's worker threads run them beside the decompression;
what they do not handle (a malformed field, another channel's name, several runs of samples)
they report for the reader's Python path. A channel id's slot follows the reader's
convention: ``>= 0`` a wanted block channel, -1 read by Python, -2 ignored, -3 not defined.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray


@nb.njit(cache=True, nogil=True)
def _index_records(buf: NDArray[np.uint8]) -> tuple[NDArray, NDArray, NDArray, int]:
    """Opcode, content offset and content length of every record of a decompressed chunk;
    and how many there are (-1 if the last is cut)."""
    n = buf.size
    # count first: arrays sized for the worst case (9-byte records) would be fresh memory to
    # fault in on every chunk, which costs more than this pass
    k = 0
    i = 0
    while i + 9 <= n:
        length = 0
        for b in range(8):
            length |= np.int64(buf[i + 1 + b]) << (8 * b)
        if length < 0 or i + 9 + length > n:
            break
        k += 1
        i += 9 + length
    ops = np.empty(k, np.uint8)
    starts = np.empty(k, np.int64)
    lens = np.empty(k, np.int64)
    i = 0
    for r in range(k):
        length = 0
        for b in range(8):
            length |= np.int64(buf[i + 1 + b]) << (8 * b)
        ops[r] = buf[i]
        starts[r] = i + 9
        lens[r] = length
        i += 9 + length
    return ops, starts, lens, k if i == n else -1


@nb.njit(cache=True, nogil=True)
def _varint(buf: NDArray[np.uint8], i: int, end: int) -> tuple[int, int]:
    value = 0
    shift = 0
    while True:
        if i >= end or shift > 63:
            return -1, -1
        byte = np.int64(buf[i])
        i += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, i
        shift += 7


@nb.njit(cache=True, nogil=True)
def _f8(buf: NDArray[np.uint8], i: int) -> float:
    return buf[i:i + 8].copy().view(np.float64)[0]




@nb.njit(cache=True, nogil=True)
def _scan_blocks(buf: NDArray[np.uint8], ops: NDArray, starts: NDArray, lens: NDArray,
                 count: int, kinds: NDArray[np.int64], names: NDArray[np.uint8],
                 name_lens: NDArray[np.int64], n_slots: int):
    """The SampleBlocks of one chunk's wanted channels, their samples copied out grouped by
    slot (in record order within a slot).

    Returns ``status, bad, out, first, meta_i, meta_f``: status 0 if every wanted block was
    scanned, 1 if the chunk needs the Python path (a name, run or field the kernel does not
    handle; ``bad`` is the record), 2 if a message refers to a channel not defined.
    ``first[s]:first[s + 1]`` are slot ``s``'s entries of ``meta_i`` (rows: record, sequence,
    number of samples, message data start, data length, slot) and ``meta_f`` (rows: GPS
    start, rate); ``out`` holds their samples in that order.
    """
    empty = np.empty(0, np.float64)
    first = np.zeros(n_slots + 1, np.int64)
    m = 0
    for r in range(count):
        if ops[r] == 5:
            m += 1
    mi = np.empty((6, m), np.int64)
    mf = np.empty((2, m), np.float64)
    s_off = np.empty(m, np.int64)
    k = 0
    for r in range(count):
        if ops[r] != 5:
            continue
        a = starts[r]
        if lens[r] < 22:
            return 1, r, empty, first, mi[:, :0], mf[:, :0]
        cid = np.int64(buf[a]) | (np.int64(buf[a + 1]) << 8)
        slot = kinds[cid] if cid < kinds.size else -3
        if slot == -3:
            return 2, r, empty, first, mi[:, :0], mf[:, :0]
        if slot < 0:
            continue
        end = a + lens[r]
        ok, g, rt, sq, off, nbytes = _parse_block(buf, a + 22, end, names[slot],
                                                  name_lens[slot])
        if not ok:
            return 1, r, empty, first, mi[:, :0], mf[:, :0]
        mi[0, k] = r
        mi[1, k] = sq
        mi[2, k] = nbytes // 8
        mi[3, k] = a + 22
        mi[4, k] = end - a - 22
        mi[5, k] = slot
        mf[0, k] = g
        mf[1, k] = rt
        s_off[k] = off
        first[slot + 1] += 1
        k += 1
    for s in range(n_slots):
        first[s + 1] += first[s]
    out, gi, gf = _grouped(buf, mi[:, :k], mf[:, :k], s_off[:k], first, n_slots)
    return 0, -1, out, first, gi, gf


@nb.njit(cache=True, nogil=True)
def _parse_block(buf: NDArray[np.uint8], i: int, end: int, name: NDArray[np.uint8],
                 name_len: int):  # noqa: ANN202 - (ok, gps, rate, sequence, offset, nbytes)
    """The fields of one SampleBlock message in ``buf[i:end]``: GPS start, rate, sequence,
    and where its samples' bytes lie; ``ok`` False for what the kernel does not handle (a
    malformed field, another channel's name, more than one run of samples)."""
    g = 0.0
    rt = 0.0
    sq = 0
    runs = 0
    off = 0
    nbytes = 0
    ok = True
    while i < end and ok:
        key, i = _varint(buf, i, end)
        if key < 0:
            ok = False
            break
        fld = key >> 3
        wire = key & 7
        if wire == 0:
            v, i = _varint(buf, i, end)
            if v < 0:
                ok = False
            elif fld == 4:
                sq = v
        elif wire == 1:
            if i + 8 > end:
                ok = False
                break
            if fld == 2:
                g = _f8(buf, i)
            elif fld == 3:
                rt = _f8(buf, i)
            elif fld == 5:
                runs += 1
                off = i
                nbytes = 8
            i += 8
        elif wire == 2:
            ln, i = _varint(buf, i, end)
            if ln < 0 or i + ln > end:
                ok = False
                break
            if fld == 1 and ln != 0:
                # the channel name must be the topic's (an empty name means the topic's)
                if ln != name_len:
                    ok = False
                else:
                    for b in range(ln):
                        if buf[i + b] != name[b]:
                            ok = False
                            break
            elif fld == 5:
                if ln % 8:
                    ok = False
                elif ln:
                    runs += 1
                    off = i
                    nbytes = ln
            i += ln
        elif wire == 5:
            i += 4
        else:
            ok = False
    return ok and i == end and runs <= 1, g, rt, sq, off, nbytes


@nb.njit(cache=True, nogil=True)
def _grouped(buf: NDArray[np.uint8], mi: NDArray[np.int64], mf: NDArray[np.float64],
             s_off: NDArray[np.int64], first: NDArray[np.int64], n_slots: int
             ):  # noqa: ANN202 - (samples, meta_i, meta_f)
    """The scanned blocks' samples and metadata reordered slot by slot (`first`: each
    slot's start), the samples copied out of the chunk."""
    k = mi.shape[1]
    fill = first[:n_slots].copy()
    order = np.empty(k, np.int64)
    total = 0
    for j in range(k):
        s = mi[5, j]
        order[fill[s]] = j
        fill[s] += 1
        total += mi[2, j]
    out = np.empty(total, np.float64)
    raw = out.view(np.uint8)
    gi = np.empty((6, k), np.int64)
    gf = np.empty((2, k), np.float64)
    pos = 0
    for q in range(k):
        j = order[q]
        n = mi[2, j] * 8
        raw[pos:pos + n] = buf[s_off[j]:s_off[j] + n]
        pos += n
        gi[:, q] = mi[:, j]
        gf[:, q] = mf[:, j]
    return out, gi, gf
