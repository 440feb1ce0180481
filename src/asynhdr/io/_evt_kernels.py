"""Numba kernels of the Prophesee EVT 2.0 / 2.1 / 3.0 codec.

Every decoder works on a block of payload words and carries its state (time
base, current row, vector base, ...) in a small ``int64`` array, so that a file
can be decoded block by block with the same result as in one piece. A decoder
returns ``(status, pos, n_events, n_triggers)``:

- ``STATUS_DONE``: every word of the block was consumed;
- ``STATUS_FULL``: the event buffer reached ``limit`` (or has no room for the
  next word's events) or the trigger buffer is full; decoding resumes at word
  ``pos`` after the caller has made room;
- ``STATUS_BAD_X`` / ``STATUS_BAD_Y``: word ``pos`` produces an event outside
  the sensor; the offending pixel is left in ``state[S_ERR_X]``, ``state[S_ERR_Y]``;
- ``STATUS_NEED_BASE`` (EVT 3.0 only): word ``pos`` is a vector word and the
  state's vector base is marked unknown (``state[S3_HAS_BASE] == -1``); the
  caller fills in the base (:func:`evt3_state_at`) and resumes at ``pos``.

EVT 3.0 can also be decoded in parallel: :func:`evt3_state_at` finds the decoder
state at any word of a block from the words before it (scanning backwards to the
last row, vector base and time words), so that the parts of a block can be
decoded independently; :mod:`asynhdr.io.prophesee` joins the parts.

Numba does not check array bounds: every index below is guarded explicitly.
The layouts follow Prophesee's published format pages (EVT 2.0, EVT 2.1,
EVT 3.0) and the behaviour of OpenEB's decoders (time-high loop detection,
words before the first time-high word dropped).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = [
    "EVT2_STATE_SIZE",
    "EVT3_STATE_SIZE",
    "EVT21_STATE_SIZE",
    "STATUS_BAD_TIME",
    "STATUS_BAD_X",
    "STATUS_BAD_Y",
    "STATUS_DONE",
    "STATUS_FULL",
    "STATUS_NEED_BASE",
    "S_ERR_X",
    "S_ERR_Y",
    "decode_evt2",
    "decode_evt3",
    "decode_evt3_sparse",
    "decode_evt21",
    "encode_evt2",
    "encode_evt3",
    "evt3_sparse",
    "evt3_state_at",
]

STATUS_DONE = 0
STATUS_FULL = 1
STATUS_BAD_X = 2
STATUS_BAD_Y = 3
STATUS_BAD_TIME = 4
STATUS_NEED_BASE = 5

# Slots shared by every decoder state.
S_STARTED = 0  # 1 once the first time-high word has been seen
S_ERR_X = 1
S_ERR_Y = 2

# EVT 3.0 decoder state.
S3_LOOP = 3  # number of 24-bit time wraps
S3_HIGH = 4  # last TIME_HIGH value (12 bits)
S3_LOW = 5  # last TIME_LOW value (12 bits)
S3_Y = 6  # row from the last EVT_ADDR_Y
S3_ROW_OK = 7  # 1 after a CD EVT_ADDR_Y (type 0), 0 after a non-CD one (type 1)
S3_BASE_X = 8  # vector base column
S3_BASE_P = 9  # vector polarity, +1 or -1
S3_HAS_BASE = 10  # 1 once a VECT_BASE_X has been seen; -1: unknown (parallel decoding)
EVT3_STATE_SIZE = 11

# EVT 2.0 decoder state.
S2_BASE = 3  # time base in µs: (TIME_HIGH << 6) + loop shift
S2_SHIFT = 4  # accumulated loop shift in µs (multiples of 2**34)
EVT2_STATE_SIZE = 5

# EVT 2.1 decoder state.
S21_LAST = 3  # last timestamp in µs, loop count in bits 34 and up
EVT21_STATE_SIZE = 4

# EVT 2.0: a TIME_HIGH word carries bits 33..6 of the time; OpenEB counts a loop
# when the time base falls by at least (2**28 - 1) * 2**6 - 10000 µs.
_EVT2_MAX_TIMESTAMP = ((1 << 28) - 1) << 6
_EVT2_LOOP_THRESHOLD = 10000
_EVT2_TIME_LOOP = _EVT2_MAX_TIMESTAMP + (1 << 6)
# EVT 2.1 uses the same 34-bit time base; a loop is counted only on a full wrap.
_EVT21_HIGH_MASK = ((1 << 28) - 1) << 6


def _bit_tables() -> tuple[np.ndarray, np.ndarray]:
    """Population count and set-bit offsets (ascending) of every 12-bit mask."""
    masks = np.arange(4096)
    bits = (masks[:, None] >> np.arange(12)[None, :]) & 1
    pop = bits.sum(axis=1).astype(np.uint8)
    offsets = np.zeros((4096, 12), dtype=np.uint8)
    for m in range(4096):
        where = np.flatnonzero(bits[m])
        offsets[m, : where.size] = where
    return pop, offsets.reshape(-1)


_POP12, _BITS12 = _bit_tables()


@njit(cache=True, nogil=True, boundscheck=False)
def _first_bit_at_or_above(mask, start):
    """Lowest set bit of ``mask`` at position >= ``start`` (``start`` >= 0), or -1."""
    for i in range(start, 64):
        if (mask >> i) & 1:
            return i
    return -1


def _evt3_decoder(skip_repeated_high: bool):
    """The EVT 3.0 decoder, compiled with or without the steps over repeated TIME_HIGH
    words and monitoring groups of :data:`decode_evt3_sparse` (a constant of the compiled
    code: the other variant's code is left out)."""

    @njit(cache=True, nogil=True, boundscheck=False)
    def decode_evt3(words, pos, state, width, height, events, n_ev, limit, triggers, n_tr, tr_at):
        """Decode EVT 3.0 16-bit words from ``pos``; see the module docstring for the contract.

        Time is ``t = loop * 2**24 + TIME_HIGH * 2**12 + TIME_LOW`` µs. A TIME_HIGH that
        falls by at least 2048 (half its range) counts one 24-bit wrap, and a changed
        TIME_HIGH resets TIME_LOW to 0 until the next TIME_LOW word (OpenEB's rule). A
        TIME_LOW word always sets the low bits, even when that steps back in time.
        Events need a CD row (EVT_ADDR_Y) first, vectors a VECT_BASE_X, as in OpenEB.
        ``tr_at[j]`` receives the event count ``n_ev`` at which trigger ``j`` was
        decoded, for every trigger with ``j < tr_at.shape[0]`` (pass an empty array
        when not needed). The buffer keeps 32 spare records (one 32-column vector group).

        Word types are told apart by a tree of bit tests, and the common word groups
        (TIME_LOW + row + column of a lone event; a 32-column vector group) are taken in
        one step (a third faster on sparse streams than one switch). Conditional
        selects written without branches are turned back into branches by the
        compiler, and gain nothing here. Array indices are unsigned (``np.uint64``) so
        that numba leaves out its negative-index wraparound, and ``pos``, ``n_ev`` are
        clamped at 0 first: the loop runs a quarter to a third faster for it.
        """
        n = words.shape[0]
        if pos < 0:
            pos = 0
        if n_ev < 0:
            n_ev = 0
        cap_tr = triggers.shape[0]
        cap_at = tr_at.shape[0]
        started = state[S_STARTED]
        if started == 0:
            # Words before the first TIME_HIGH cannot be timed: drop them.
            while pos < n and (words[np.uint64(pos)] >> 12) != 0x8:
                pos += 1
            if pos < n:
                started = 1
                state[S3_LOOP] = 0
                state[S3_HIGH] = np.int64(words[np.uint64(pos)]) & 0xFFF
                state[S3_LOW] = 0
                pos += 1
        t = (state[S3_LOOP] << 24) | (state[S3_HIGH] << 12) | state[S3_LOW]
        y = state[S3_Y]
        row_ok = state[S3_ROW_OK]
        base_x = state[S3_BASE_X]
        base_p = state[S3_BASE_P]
        has_base = state[S3_HAS_BASE]
        stop = events.shape[0] - 32
        if limit < stop:
            stop = limit
        status = STATUS_DONE
        while pos < n:
            if n_ev >= stop:
                status = STATUS_FULL
                break
            w = np.int64(words[np.uint64(pos)])
            typ = w >> 12
            # Dispatch by bit tests, not one switch: a switch compiles to a jump table, whose
            # single indirect branch mispredicts on the irregular TIME_HIGH runs of sparse
            # streams; a tree of conditional branches gives the predictor each type's history.
            if typ & 0x8:
                if typ == 0x8:  # EVT_TIME_HIGH
                    # A fall of 2048 or more is a 24-bit wrap; a new value resets TIME_LOW to 0
                    # until the next TIME_LOW word (OpenEB's rule).
                    w12 = w & 0xFFF
                    high = (t >> 12) & 0xFFF
                    if w12 != high:
                        loop = (t >> 24) + np.int64(high >= 2048 + w12)
                        t = (loop << 24) | (w12 << 12)
                elif typ == 0xA:  # EXT_TRIGGER: value bit 0, channel bits 11..8
                    if n_tr >= cap_tr:
                        status = STATUS_FULL
                        break
                    tr = triggers[np.uint64(n_tr)]
                    tr.t = t
                    tr.rising = (w & 1) == 1
                    tr.id = (w >> 8) & 0xF
                    if n_tr < cap_at:
                        tr_at[np.uint64(n_tr)] = n_ev
                    n_tr += 1
                elif skip_repeated_high and typ == 0xE:
                    # OTHERS + CONTINUED_12 + CONTINUED_12 + CONTINUED_4 groups (sensor
                    # monitoring) carry nothing: step over them in one loop.
                    q = pos
                    while q + 3 < n:
                        c0 = np.int64(words[np.uint64(q)]) >> 12
                        c1 = np.int64(words[np.uint64(q + 1)]) >> 12
                        c2 = np.int64(words[np.uint64(q + 2)]) >> 12
                        c3 = np.int64(words[np.uint64(q + 3)]) >> 12
                        if ((c0 ^ 0xE) | (c1 ^ 0xF) | (c2 ^ 0xF) | (c3 ^ 0x7)) != 0:
                            break
                        q += 4
                    if q > pos:
                        pos = q
                        continue
                # IMU (0xD), OTHERS (0xE), CONTINUED_12 (0xF) and the unused types 0x9, 0xB,
                # 0xC carry nothing for CD events or triggers.
            elif typ & 0x4:
                if typ == 0x6:  # EVT_TIME_LOW
                    t = (t & ~np.int64(0xFFF)) | (w & 0xFFF)
                    # A sparse stream times each event alone: TIME_LOW, EVT_ADDR_Y (CD),
                    # EVT_ADDR_X. Take the three words in one step; an event outside the
                    # sensor goes word by word below, which reports it.
                    if pos + 2 < n:
                        wy = np.int64(words[np.uint64(pos + 1)])
                        wx = np.int64(words[np.uint64(pos + 2)])
                        if ((wy >> 12) | ((wx >> 12) ^ 0x2)) == 0:
                            y = wy & 0x7FF
                            row_ok = 1
                            x = wx & 0x7FF
                            if x < width and y < height:
                                rec = events[np.uint64(n_ev)]
                                rec.x = x
                                rec.y = y
                                rec.p = ((wx >> 10) & 2) - 1
                                rec.t = t
                                n_ev += 1
                                pos += 3
                                if skip_repeated_high:
                                    # A TIME_HIGH word that repeats the time high changes
                                    # nothing: step over one without a branch (words[n - 1],
                                    # read at the end, is this EVT_ADDR_X: no match).
                                    nxt = np.int64(words[np.uint64(min(pos, n - 1))])
                                    pos += np.int64(nxt == (0x8000 | ((t >> 12) & 0xFFF)))
                                continue
                elif typ != 0x7:  # VECT_12 / VECT_8: bit i -> column base_x + i
                    # (CONTINUED_4, 0x7, carries nothing for CD events or triggers.)
                    if has_base < 0:
                        status = STATUS_NEED_BASE
                        break
                    size = 12 if typ == 0x4 else 8
                    if row_ok == 1:
                        mask = w & (0xFFF if typ == 0x4 else 0xFF)
                        if has_base == 1 and mask != 0:
                            if y >= height:
                                state[S_ERR_X] = base_x + _first_bit_at_or_above(mask, 0)
                                state[S_ERR_Y] = y
                                status = STATUS_BAD_Y
                                break
                            if base_x + size > width:
                                first_bad = _first_bit_at_or_above(mask, max(width - base_x, 0))
                                if first_bad >= 0:
                                    state[S_ERR_X] = base_x + first_bad
                                    state[S_ERR_Y] = y
                                    status = STATUS_BAD_X
                                    break
                            cnt = np.int64(_POP12[np.uint64(mask)])
                            for k in range(cnt):
                                rec = events[np.uint64(n_ev)]
                                rec.x = base_x + np.int64(_BITS12[np.uint64(mask * 12 + k)])
                                rec.y = y
                                rec.p = base_p
                                rec.t = t
                                n_ev += 1
                        base_x += size
            elif typ & 0x2:
                if typ == 0x2:  # EVT_ADDR_X: x bits 10..0, polarity bit 11
                    if row_ok == 1:
                        x = w & 0x7FF
                        if x >= width or y >= height:
                            state[S_ERR_X] = x
                            state[S_ERR_Y] = y
                            status = STATUS_BAD_X if x >= width else STATUS_BAD_Y
                            break
                        rec = events[np.uint64(n_ev)]
                        rec.x = x
                        rec.y = y
                        rec.p = ((w >> 10) & 2) - 1  # bit 11: 1 -> +1, 0 -> -1
                        rec.t = t
                        n_ev += 1
                else:  # VECT_BASE_X: base column bits 10..0, polarity bit 11
                    if (
                        row_ok == 1
                        and pos + 3 < n
                        and (words[np.uint64(pos + 1)] >> 12) == 0x4
                        and (words[np.uint64(pos + 2)] >> 12) == 0x4
                        and (words[np.uint64(pos + 3)] >> 12) == 0x5
                    ):
                        # VECT_BASE_X + VECT_12 + VECT_12 + VECT_8, the sensor's 32-column
                        # group, in one step. A group that reaches outside the sensor goes word
                        # by word below, which reports the exact pixel.
                        m0 = np.int64(words[np.uint64(pos + 1)]) & 0xFFF
                        m1 = np.int64(words[np.uint64(pos + 2)]) & 0xFFF
                        m2 = np.int64(words[np.uint64(pos + 3)]) & 0xFF
                        gx = w & 0x7FF
                        if (m0 | m1 | m2) == 0 or (y < height and gx + 32 <= width):
                            base_x = gx + 32
                            base_p = ((w >> 10) & 2) - 1
                            has_base = 1
                            for part in range(3):
                                mask = m0 if part == 0 else (m1 if part == 1 else m2)
                                cnt = np.int64(_POP12[np.uint64(mask)])
                                for k in range(cnt):
                                    rec = events[np.uint64(n_ev)]
                                    rec.x = (
                                        gx + 12 * part + np.int64(_BITS12[np.uint64(mask * 12 + k)])
                                    )
                                    rec.y = y
                                    rec.p = base_p
                                    rec.t = t
                                    n_ev += 1
                            pos += 4
                            continue
                    base_x = w & 0x7FF
                    base_p = ((w >> 10) & 2) - 1
                    has_base = 1
            elif typ == 0x0:  # EVT_ADDR_Y: bit 11 is the system type, not part of y
                y = w & 0x7FF
                row_ok = 1
            else:  # 0x1, EVT_ADDR_Y of a non-CD row: its events are not CD events
                row_ok = 0
            pos += 1
        state[S_STARTED] = started
        state[S3_LOOP] = t >> 24
        state[S3_HIGH] = (t >> 12) & 0xFFF
        state[S3_LOW] = t & 0xFFF
        state[S3_Y] = y
        state[S3_ROW_OK] = row_ok
        state[S3_BASE_X] = base_x
        state[S3_BASE_P] = base_p
        state[S3_HAS_BASE] = has_base
        return status, pos, n_ev, n_tr

    return decode_evt3


decode_evt3 = _evt3_decoder(False)
decode_evt3_sparse = _evt3_decoder(True)
"""EVT 3.0 decoder for streams that time each event alone, repeat their TIME_HIGH word
between events and interleave sensor monitoring groups (sparse scenes): after a lone
event (TIME_LOW, EVT_ADDR_Y, EVT_ADDR_X), a TIME_HIGH word that repeats the time high
is stepped over without a branch, and OTHERS + CONTINUED_12 + CONTINUED_12 +
CONTINUED_4 groups are stepped over in one loop. Same results as :func:`decode_evt3`.
Measured on a sparse recording (one word in five a repeated TIME_HIGH, one in seven in
a monitoring group): 13 % less time. Compiled into the one decoder, the first step alone
made two dense recordings 5-7 % slower (the compiled loop's layout changes), hence two
variants, picked by :func:`evt3_sparse`."""


@njit(cache=True, nogil=True, boundscheck=False)
def evt3_sparse(words, pos):
    """Whether the EVT 3.0 words from ``pos`` look sparse: at least one in 16 of the
    next 1,024 is a TIME_HIGH word (about one in five in a sparse recording, one in a
    hundred and fifty or fewer in dense ones)."""
    n = words.shape[0]
    stop = min(n, pos + 1024)
    count = 0
    for i in range(max(pos, 0), stop):
        count += (words[i] >> 12) == 0x8
    return 16 * count >= stop - max(pos, 0) and count > 0


@njit(cache=True, nogil=True, boundscheck=False)
def evt3_state_at(words, s, state0, out, base_scan):
    """EVT 3.0 decoder state before word ``s`` of a block that starts in ``state0``, into ``out``.

    Equal to the state :func:`decode_evt3` holds after decoding ``words[:s]``
    from ``state0``, except the wrap count: ``out[S3_LOOP]`` is the count at the
    block start (``state0``'s, or 0 when the block starts before the first
    TIME_HIGH); the caller adds the wraps of ``words[:s]``, which only the
    words themselves can tell (2**24 µs each).

    Found by scanning backwards from ``s - 1`` to the last EVT_ADDR_Y (row),
    the last EVT_ADDR_Y or non-CD row word (row kind), the last VECT_BASE_X (plus
    12 / 8 columns per vector word after it on a CD row), the last TIME_HIGH and
    the last TIME_LOW (kept only when no TIME_HIGH after it changed the value,
    OpenEB's rule); what the scan does not find before the block start comes
    from ``state0``. When ``base_scan >= 0`` and no VECT_BASE_X lies within
    ``base_scan`` words before ``s``, the vector base is marked unknown
    (``out[S3_HAS_BASE] = -1``): :func:`decode_evt3` then stops with
    ``STATUS_NEED_BASE`` at the first vector word that needs it.
    """
    for i in range(EVT3_STATE_SIZE):
        out[i] = state0[i]
    lo = 0
    if state0[S_STARTED] == 0:
        # Words before the first TIME_HIGH are dropped: the block's decoding starts there.
        f = 0
        while f < s and (words[f] >> 12) != 0x8:
            f += 1
        if f >= s:
            return
        out[S_STARTED] = 1
        out[S3_LOOP] = 0
        out[S3_HIGH] = np.int64(words[f]) & 0xFFF
        out[S3_LOW] = 0
        lo = f + 1
    # out holds the state at word lo; scan words s-1 down to lo.
    y = out[S3_Y]
    row_ok = out[S3_ROW_OK]
    base_x = out[S3_BASE_X]
    base_p = out[S3_BASE_P]
    has_base = out[S3_HAS_BASE]
    need_y = True
    need_row = True
    need_base = True  # no VECT_BASE_X found yet
    need_base_row = False  # found, but vector words after it wait for their row kind
    base_unknown = False
    # Vector columns after the VECT_BASE_X: on a CD row (cols_ok), or before any row
    # word seen so far, so on the row kind in force further back (cols_wait).
    cols_ok = 0
    cols_wait = 0
    found_high = False
    low_done = False
    pending = False
    pending_low = 0
    high_s = 0
    low_s = 0
    i = s - 1
    while i >= lo:
        if need_base and base_scan >= 0 and s - i > base_scan:
            need_base = False
            base_unknown = True
        if not (
            need_y or need_row or need_base or need_base_row or not found_high or not low_done
        ):
            break
        w = int(words[i])
        typ = w >> 12
        if typ == 0x0 or typ == 0x1:
            if typ == 0x0 and need_y:
                y = w & 0x7FF
                need_y = False
            if need_row:
                row_ok = 1 if typ == 0x0 else 0
                need_row = False
            if typ == 0x0:
                cols_ok += cols_wait
            cols_wait = 0
            if need_base_row:
                base_x += cols_ok
                need_base_row = False
        elif typ == 0x3:
            if need_base:
                base_x = w & 0x7FF
                base_p = ((w >> 10) & 2) - 1
                has_base = 1
                need_base = False
                need_base_row = True
        elif typ == 0x4 or typ == 0x5:
            if need_base:
                cols_wait += 12 if typ == 0x4 else 8
        elif typ == 0x6:
            if not low_done and not pending:
                if found_high:
                    # TIME_HIGH words follow: the low survives if none changed the value.
                    pending = True
                    pending_low = w & 0xFFF
                else:
                    low_s = w & 0xFFF
                    low_done = True
        elif typ == 0x8:
            v = w & 0xFFF
            if not found_high:
                found_high = True
                high_s = v
            elif not low_done:
                # Every TIME_HIGH after this one has the value high_s.
                if pending:
                    low_s = pending_low if v == high_s else 0
                    low_done = True
                elif v != high_s:
                    low_s = 0  # reset by the next TIME_HIGH, no TIME_LOW after it
                    low_done = True
        i -= 1
    # What the scan did not find comes from the state at lo.
    if need_base or need_base_row:
        if out[S3_ROW_OK] == 1:
            cols_ok += cols_wait
        base_x += cols_ok
    high_lo = out[S3_HIGH]
    if not found_high:
        high_s = high_lo
        if not low_done:
            low_s = out[S3_LOW]
    elif not low_done:
        if pending:
            low_s = pending_low if high_lo == high_s else 0
        else:
            low_s = out[S3_LOW] if high_lo == high_s else 0
    out[S3_HIGH] = high_s
    out[S3_LOW] = low_s
    out[S3_Y] = y
    out[S3_ROW_OK] = row_ok
    if base_unknown:
        out[S3_BASE_X] = 0
        out[S3_BASE_P] = 1
        out[S3_HAS_BASE] = -1
    else:
        out[S3_BASE_X] = base_x
        out[S3_BASE_P] = base_p
        out[S3_HAS_BASE] = has_base


@njit(cache=True, nogil=True, boundscheck=False)
def decode_evt2(words, pos, state, width, height, events, n_ev, limit, triggers, n_tr):
    """Decode EVT 2.0 32-bit words from ``pos``; see the module docstring for the contract.

    Time is ``t = (TIME_HIGH << 6) + ts6`` µs (34 bits), plus ``2**34`` µs per wrap:
    a TIME_HIGH whose time falls by at least ``(2**28 - 1) * 2**6 - 10000`` µs counts
    a wrap (OpenEB's rule).
    """
    n = words.shape[0]
    cap_tr = triggers.shape[0]
    started = state[S_STARTED]
    base = state[S2_BASE]
    shift = state[S2_SHIFT]
    stop = events.shape[0] - 1
    if limit < stop:
        stop = limit
    status = STATUS_DONE
    while pos < n:
        if n_ev >= stop:
            status = STATUS_FULL
            break
        w = np.int64(words[pos])
        typ = w >> 28
        if started == 0:
            if typ == 0x8:
                started = 1
                base = (w & 0xFFFFFFF) << 6
                shift = 0
            pos += 1
            continue
        if typ == 0x0 or typ == 0x1:  # CD_OFF / CD_ON
            x = (w >> 11) & 0x7FF
            y = w & 0x7FF
            if x >= width or y >= height:
                state[S_ERR_X] = x
                state[S_ERR_Y] = y
                status = STATUS_BAD_X if x >= width else STATUS_BAD_Y
                break
            rec = events[n_ev]
            rec.x = x
            rec.y = y
            rec.p = 1 if typ == 0x1 else -1
            rec.t = base + ((w >> 22) & 0x3F)
            n_ev += 1
        elif typ == 0x8:  # EVT_TIME_HIGH
            new_base = ((w & 0xFFFFFFF) << 6) + shift
            if new_base < base and base - new_base >= _EVT2_MAX_TIMESTAMP - _EVT2_LOOP_THRESHOLD:
                shift += _EVT2_TIME_LOOP
                new_base += _EVT2_TIME_LOOP
            base = new_base
        elif typ == 0xA:  # EXT_TRIGGER: value bit 0, channel bits 12..8, ts6 bits 27..22
            if n_tr >= cap_tr:
                status = STATUS_FULL
                break
            tr = triggers[n_tr]
            tr.t = base + ((w >> 22) & 0x3F)
            tr.rising = (w & 1) == 1
            tr.id = (w >> 8) & 0x1F
            n_tr += 1
        # IMU (0xD), OTHERS (0xE), CONTINUED (0xF) and reserved types: ignored.
        pos += 1
    state[S_STARTED] = started
    state[S2_BASE] = base
    state[S2_SHIFT] = shift
    return status, pos, n_ev, n_tr


@njit(cache=True, nogil=True, boundscheck=False)
def decode_evt21(halves, legacy, pos, state, width, height, events, n_ev, limit, triggers, n_tr):
    """Decode EVT 2.1 64-bit words given as pairs of 32-bit halves; ``pos`` counts 64-bit words.

    Standard layout (``legacy == 0``): the word is one little-endian 64-bit integer,
    ``valid`` mask in bits 31..0, y in 42..32, x in 53..43, ts6 in 59..54, type in
    63..60. Legacy layout (``legacy == 1``, IMX636 and older Prophesee systems): the
    two 32-bit halves are stored the other way round. Event ``i`` of a vector word
    is at column ``x + i`` for each set bit ``i`` of ``valid``.
    """
    n = halves.shape[0] // 2
    cap_tr = triggers.shape[0]
    started = state[S_STARTED]
    last = state[S21_LAST]
    stop = events.shape[0] - 32
    if limit < stop:
        stop = limit
    status = STATUS_DONE
    while pos < n:
        if n_ev >= stop:
            status = STATUS_FULL
            break
        if legacy == 1:
            hi = np.int64(halves[2 * pos])
            lo = np.int64(halves[2 * pos + 1])
        else:
            lo = np.int64(halves[2 * pos])
            hi = np.int64(halves[2 * pos + 1])
        typ = hi >> 28
        if started == 0:
            if typ == 0x8:
                started = 1
                last = (hi & 0xFFFFFFF) << 6
            pos += 1
            continue
        if typ == 0x0 or typ == 0x1:  # EVT_NEG / EVT_POS, 32-pixel vector
            last = (last & ~np.int64(0x3F)) + ((hi >> 22) & 0x3F)
            if lo != 0:
                x0 = (hi >> 11) & 0x7FF
                y = hi & 0x7FF
                if y >= height:
                    state[S_ERR_X] = x0 + _first_bit_at_or_above(lo, 0)
                    state[S_ERR_Y] = y
                    status = STATUS_BAD_Y
                    break
                if x0 + 32 > width:
                    first_bad = _first_bit_at_or_above(lo, max(width - x0, 0))
                    if first_bad >= 0:
                        state[S_ERR_X] = x0 + first_bad
                        state[S_ERR_Y] = y
                        status = STATUS_BAD_X
                        break
                p = 1 if typ == 0x1 else -1
                for part in range(3):  # bits 0..11, 12..23, 24..31
                    mask = (lo >> (12 * part)) & 0xFFF
                    cnt = np.int64(_POP12[mask])
                    for k in range(cnt):
                        rec = events[n_ev]
                        rec.x = x0 + 12 * part + np.int64(_BITS12[mask * 12 + k])
                        rec.y = y
                        rec.p = p
                        rec.t = last
                        n_ev += 1
        elif typ == 0x8:  # EVT_TIME_HIGH: bits 33..6 of the time
            t_high = (hi & 0xFFFFFFF) << 6
            last_high = last & _EVT21_HIGH_MASK
            n_loop = last >> 34
            if t_high < last_high and last_high - t_high >= _EVT21_HIGH_MASK:
                n_loop += 1
            if t_high != last_high:
                last = t_high | (n_loop << 34)
        elif typ == 0xA:  # EXT_TRIGGER
            if n_tr >= cap_tr:
                status = STATUS_FULL
                break
            last = (last & ~np.int64(0x3F)) + ((hi >> 22) & 0x3F)
            tr = triggers[n_tr]
            tr.t = last
            tr.rising = (hi & 1) == 1
            tr.id = (hi >> 8) & 0x1F
            n_tr += 1
        # OTHERS (0xE), CONTINUED (0xF) and reserved types: ignored.
        pos += 1
    state[S_STARTED] = started
    state[S21_LAST] = last
    return status, pos, n_ev, n_tr


# EVT 3.0 encoder state.
E_STARTED = 0
E_HIGH = 1  # full time-high (t >> 12) of the last TIME_HIGH written
E_LOW = 2  # TIME_LOW the decoder holds
E_Y = 3  # row the decoder holds, -1 for none
ENCODER_STATE_SIZE = 4

# TIME_HIGH values the writer steps through between two words: every value, as a
# sensor emits them. OpenEB counts a wrap on any fall of 2048 or more, but other
# decoders (faery 0.7.1) only follow single steps, so the writer never skips one.
_HIGH_STEP = 1
# Below this the first TIME_HIGH value is written directly; beyond it the stream
# starts at 0 and steps up.
_FIRST_HIGH_DIRECT = 4094
# Shortest run of same-time, same-row, same-polarity events written as a vector.
_MIN_VECTOR_RUN = 5


@njit(cache=True, nogil=True, boundscheck=False)
def encode_evt3(events, triggers, i, j, state, width, out):
    """Encode time-sorted events and triggers, interleaved by time, into EVT 3.0 words.

    Resumable: returns ``(status, i, j, n_words)`` where ``i`` and ``j`` are the
    next event and trigger to write; ``STATUS_FULL`` means ``out`` needs emptying.
    Triggers come before events of the same time. Time-high words step through
    every value between two items (one word per 4096 µs of gap), as a sensor
    writes them, so that every EVT 3.0 decoder follows the wraps. Runs of at least
    five events with the same time, row and polarity and increasing columns inside
    one 32-column group become VECT_BASE_X + VECT_12 + VECT_12 + VECT_8; other
    events become EVT_ADDR_X words. ``STATUS_BAD_TIME`` means time went back.
    """
    ne = events.shape[0]
    nt = triggers.shape[0]
    cap = out.shape[0]
    n = 0
    started = state[E_STARTED]
    cur_high = state[E_HIGH]
    low = state[E_LOW]
    cur_y = state[E_Y]
    status = STATUS_DONE
    while i < ne or j < nt:
        if n + 16 > cap:
            status = STATUS_FULL
            break
        take_trigger = False
        if j < nt:
            if i >= ne or triggers[j].t <= events[i].t:
                take_trigger = True
        t = triggers[j].t if take_trigger else events[i].t
        high = t >> 12
        if started == 1 and high < cur_high:
            status = STATUS_BAD_TIME
            break
        if started == 0 or high != cur_high:
            if started == 0:
                cur_high = high if high < _FIRST_HIGH_DIRECT else 0
                started = 1
            else:
                cur_high += _HIGH_STEP
            out[n] = np.uint16(0x8000 | (cur_high & 0xFFF))
            n += 1
            low = -1  # a TIME_LOW follows every TIME_HIGH before the next item, as sensors write
            continue  # re-check capacity; more steps may follow
        lo = t & 0xFFF
        if lo != low:
            out[n] = np.uint16(0x6000 | lo)
            n += 1
            low = lo
        if take_trigger:
            tr = triggers[j]
            out[n] = np.uint16(0xA000 | ((np.int64(tr.id) & 0xF) << 8) | (1 if tr.rising else 0))
            n += 1
            j += 1
            continue
        ev = events[i]
        y = np.int64(ev.y)
        x = np.int64(ev.x)
        pol = 1 if ev.p > 0 else 0
        if y != cur_y:
            out[n] = np.uint16(y & 0x7FF)
            n += 1
            cur_y = y
        # Look for a vector run starting at event i.
        base = x & ~np.int64(31)
        k = 1
        if base + 32 <= width:
            last_x = x
            while i + k < ne and k < 32:
                e2 = events[i + k]
                x2 = np.int64(e2.x)
                if (
                    e2.t != t
                    or np.int64(e2.y) != y
                    or (1 if e2.p > 0 else 0) != pol
                    or x2 <= last_x
                    or x2 >= base + 32
                ):
                    break
                last_x = x2
                k += 1
        if k >= _MIN_VECTOR_RUN:
            mask = np.int64(0)
            for m in range(k):
                mask |= np.int64(1) << (np.int64(events[i + m].x) - base)
            out[n] = np.uint16(0x3000 | (pol << 11) | base)
            out[n + 1] = np.uint16(0x4000 | (mask & 0xFFF))
            out[n + 2] = np.uint16(0x4000 | ((mask >> 12) & 0xFFF))
            out[n + 3] = np.uint16(0x5000 | ((mask >> 24) & 0xFF))
            n += 4
            i += k
        else:
            out[n] = np.uint16(0x2000 | (pol << 11) | x)
            n += 1
            i += 1
    state[E_STARTED] = started
    state[E_HIGH] = cur_high
    state[E_LOW] = low
    state[E_Y] = cur_y
    return status, i, j, n


# EVT 2.0 encoder state.
E2_STARTED = 0
E2_HIGH = 1  # time >> 6 of the last TIME_HIGH written
ENCODER2_STATE_SIZE = 2


@njit(cache=True, nogil=True, boundscheck=False)
def encode_evt2(events, triggers, i, j, state, out):
    """Encode time-sorted events and triggers, interleaved by time, into EVT 2.0 words.

    Resumable like :func:`encode_evt3`: returns ``(status, i, j, n_words)``. A TIME_HIGH
    word (bits 33..6 of the time; times must lie in ``[0, 2**34)`` µs) precedes the first
    item and every change of those bits. CD words
    carry type 0x1 (ON) or 0x0 (OFF), ts6 in bits 27..22, x in 21..11, y in 10..0;
    EXT_TRIGGER words type 0xA, ts6 in 27..22, channel in 12..8, the edge's value in
    bit 0. Triggers come before events of the same time. ``STATUS_BAD_TIME``: time went
    back.
    """
    ne = events.shape[0]
    nt = triggers.shape[0]
    cap = out.shape[0]
    n = 0
    started = state[E2_STARTED]
    cur_high = state[E2_HIGH]
    status = STATUS_DONE
    while i < ne or j < nt:
        if n + 2 > cap:
            status = STATUS_FULL
            break
        take_trigger = False
        if j < nt:
            if i >= ne or triggers[j].t <= events[i].t:
                take_trigger = True
        t = triggers[j].t if take_trigger else events[i].t
        high = t >> 6
        if started == 1 and high < cur_high:
            status = STATUS_BAD_TIME
            break
        if started == 0 or high != cur_high:
            cur_high = high
            started = 1
            out[n] = np.uint32(0x80000000 | (cur_high & 0xFFFFFFF))
            n += 1
            continue
        ts6 = (t & 0x3F) << 22
        if take_trigger:
            tr = triggers[j]
            out[n] = np.uint32(0xA0000000 | ts6 | ((np.int64(tr.id) & 0x1F) << 8)
                               | (1 if tr.rising else 0))
            j += 1
        else:
            ev = events[i]
            typ = 0x10000000 if ev.p > 0 else 0
            out[n] = np.uint32(typ | ts6 | (np.int64(ev.x) << 11) | np.int64(ev.y))
            i += 1
        n += 1
    state[E2_STARTED] = started
    state[E2_HIGH] = cur_high
    return status, i, j, n
