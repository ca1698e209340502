"""The ILLumiSense record tokenizer: one compiled pass over many payloads (docs/protocols-illumisense.md).

A record is ASCII text: fields separated by TAB. Converting ~300 decimal fields per record with Python's
``float`` (or numpy's string conversion, which calls it) costs ≈ 0.2 µs a field, most of the decoder's time.
:func:`scan` does it in one numba pass over a buffer holding many payloads, without copying them:

- it strips each payload's line ending (CR LF, LF, CR or none) and one trailing TAB, and reports the offset of
  any NUL, CR or LF left inside (a payload is one line of printable text);
- it splits the rest at TAB and classifies every token (:data:`INT`, :data:`DEC`, :data:`SLOW`, :data:`TEXT`,
  :data:`EMPTY`);
- it converts numbers on the exact fast path (Clinger's): a mantissa of at most 15 significant digits and a
  decimal exponent of magnitude at most 22 are exact in float64, so one multiplication or division by an exact
  power of ten is correctly rounded — bit-identical to Python's ``float``. Anything else made of number
  characters is :data:`SLOW` and left to ``float`` by the caller; text tokens (the labels) get a 52-bit hash in
  place of a value, so labels can be compared as numbers in batch;
- it reads the date (``YYYY-MM-DD`` or ``YYYY/MM/DD``) and time (``HH:MM:SS`` with or without a fraction)
  fields as UTC epoch seconds (NaN when they are not a time; :data:`TIME_SLOW` when the fraction is too long
  for the fast path).

:func:`parse_layout` is the stream's common case in one pass: records of a layout already known are read
straight into the token values and the Frame arrays (:func:`channels`), each field checked against what its
place in the layout requires, without the tokenizer's arrays; what it does not read goes through :func:`scan`.

The framing passes live here too, so that no byte of a hostile input costs a Python step: :func:`spans` (the
records of a stream in sync), :func:`hunt` (the next possible record after an error) and :func:`lines` (the
lines of a text log).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["DEC", "EMPTY", "INT", "ROLE_ANY", "ROLE_FIXED", "ROLE_INT", "ROLE_LABEL", "ROLE_NUMBER", "SLOW", "TEXT",
           "TIME_SLOW", "channels", "hunt", "lines", "match_layout", "parse_layout", "scan", "spans"]

INT = 0  #: optional sign and 1–15 digits: value exact
DEC = 1  #: decimal number on the exact fast path
SLOW = 2  #: only number characters, but not on the fast path (nan, inf, 16+ digits, 1e99, "1.", …)
TEXT = 3  #: any other byte: a label (or garbage); value holds a hash of the bytes
EMPTY = 4  #: nothing between two TABs
TIME_SLOW = -1.0  #: marker in the time output: the fields look like a time, let Python read them

# what :func:`parse_layout` expects of each token of a known layout
ROLE_ANY = 0  #: any text without NUL, CR or LF (the date and time)
ROLE_INT = 1  #: an INT
ROLE_FIXED = 2  #: an INT of a given value
ROLE_NUMBER = 3  #: an INT or a DEC
ROLE_LABEL = 4  #: a TEXT of a given hash

_POW10 = np.array([10.0**k for k in range(23)])


# bytes a number field may hold: digits . + - e E and the letters of nan / inf / infinity (any case)
_NUMCHAR = np.zeros(256, np.bool_)
_NUMCHAR[np.frombuffer(b"0123456789.+-eEnNaAiIfFtTyY", np.uint8)] = True


@njit(cache=True)
def _other(buf, a, b):
    """Kind and value of a token that left the fast grammar: SLOW if made of number bytes, else TEXT + hash."""
    for i in range(a, b):
        if not _NUMCHAR[buf[i]]:
            h = np.uint64(1469598103934665603)
            for j in range(a, b):
                h = (h ^ np.uint64(buf[j])) * np.uint64(1099511628211)
            return TEXT, float(h >> np.uint64(12))
    return SLOW, 0.0


@njit(cache=True)
def _token(buf, a, b, pow10):
    """(kind, value) of buf[a:b], in one pass on the fast path."""
    if a >= b:
        return EMPTY, 0.0
    i = a
    neg = False
    c = buf[i]
    if c == 45 or c == 43:
        neg = c == 45
        i += 1
    mant = 0
    sig = 0  # significant digits taken (leading zeros skipped)
    n_int = 0
    n_frac = 0
    exp10 = 0
    while i < b:
        c = buf[i]
        if c < 48 or c > 57:
            break
        if sig > 0 or c != 48:
            sig += 1
            mant = mant * 10 + (c - 48)
        n_int += 1
        i += 1
    if i == b:
        if n_int == 0 or sig > 15:
            return _other(buf, a, b)
        v = float(mant)
        return INT, -v if neg else v
    if c != 46 or n_int == 0:
        return _other(buf, a, b)
    i += 1
    while i < b:
        c = buf[i]
        if c < 48 or c > 57:
            break
        if sig > 0 or c != 48:
            sig += 1
            mant = mant * 10 + (c - 48)
        n_frac += 1
        i += 1
    if n_frac == 0 or sig > 15:  # "5." parses in Python but never comes from a sender: leave it to Python
        return _other(buf, a, b)
    exp10 = -n_frac
    if i < b:
        if c != 101 and c != 69:
            return _other(buf, a, b)
        i += 1
        eneg = False
        if i < b and (buf[i] == 45 or buf[i] == 43):
            eneg = buf[i] == 45
            i += 1
        if i == b:
            return _other(buf, a, b)
        e = 0
        while i < b:
            c = buf[i]
            if c < 48 or c > 57 or e > 1000:
                return _other(buf, a, b)
            e = e * 10 + (c - 48)
            i += 1
        exp10 += -e if eneg else e
    if exp10 > 22 or exp10 < -22:
        if mant == 0:
            return DEC, -0.0 if neg else 0.0
        return SLOW, 0.0
    v = float(mant)
    if exp10 >= 0:
        v = v * pow10[exp10]
    else:
        v = v / pow10[-exp10]
    return DEC, -v if neg else v


@njit(cache=True)
def _digits(buf, a, n):
    v = 0
    for i in range(a, a + n):
        c = buf[i]
        if c < 48 or c > 57:
            return -1
        v = v * 10 + (c - 48)
    return v


@njit(cache=True)
def _days_from_civil(y, m, d):
    y -= m <= 2
    era = (y if y >= 0 else y - 399) // 400
    yoe = y - era * 400
    mp = m + 9 if m <= 2 else m - 3
    doy = (153 * mp + 2) // 5 + d - 1
    doe = yoe * 365 + yoe // 4 - yoe // 100 + doy
    return era * 146097 + doe - 719468


@njit(cache=True)
def _timestamp(buf, da, db, ta, tb, pow10):
    """Epoch seconds of date buf[da:db] and time buf[ta:tb]; NaN if not a time; TIME_SLOW for long fractions."""
    if db - da != 10 or tb - ta < 8:
        return np.nan
    sep = buf[da + 4]
    if (sep != 45 and sep != 47) or buf[da + 7] != sep:
        return np.nan
    y = _digits(buf, da, 4)
    mo = _digits(buf, da + 5, 2)
    d = _digits(buf, da + 8, 2)
    if y < 1 or mo < 1 or mo > 12 or d < 1:
        return np.nan
    leap = (y % 4 == 0 and y % 100 != 0) or y % 400 == 0
    dim = (31, 29 if leap else 28, 31, 30, 31, 30, 31, 31, 30, 31, 30, 31)
    if d > dim[mo - 1]:
        return np.nan
    if buf[ta + 2] != 58 or buf[ta + 5] != 58:
        return np.nan
    hh = _digits(buf, ta, 2)
    mm = _digits(buf, ta + 3, 2)
    s_int = _digits(buf, ta + 6, 2)
    if hh < 0 or mm < 0 or s_int < 0 or hh > 23 or mm > 59 or s_int > 60:
        return np.nan
    n = tb - ta - 8
    if n == 0:
        ss = float(s_int)
    else:
        if buf[ta + 8] != 46:
            return np.nan
        if n - 1 + 2 > 15:  # before reading the digits: 19 of them would overflow int64
            return TIME_SLOW
        f = _digits(buf, ta + 9, n - 1)
        if f < 0:
            return np.nan
        ss = float(s_int * _ipow10(n - 1) + f) / pow10[n - 1]
    day = float((_days_from_civil(y, mo, d)) * 86400)
    return day + float(hh * 3600 + mm * 60) + ss


@njit(cache=True)
def _ipow10(k):
    v = 1
    for _ in range(k):
        v *= 10
    return v


@njit(cache=True)
def _scan(buf, starts, ends, pow10):
    n = starts.size
    body_end = np.empty(n, np.int64)
    bad = np.full(n, -1, np.int64)
    counts = np.empty(n + 1, np.int64)
    counts[0] = 0
    for r in range(n):
        a, e = starts[r], ends[r]
        if e > a and buf[e - 1] == 10:
            e -= 1
        if e > a and buf[e - 1] == 13:
            e -= 1
        if e > a and buf[e - 1] == 9:
            e -= 1
        body_end[r] = e
        k = 1
        for i in range(a, e):
            c = buf[i]
            if c == 9:
                k += 1
            elif c == 0 or c == 10 or c == 13:
                if bad[r] < 0:
                    bad[r] = i - a
        counts[r + 1] = counts[r] + k
    m = counts[n]
    kind = np.empty(m, np.int8)
    value = np.empty(m, np.float64)
    tstart = np.empty(m, np.int64)
    tend = np.empty(m, np.int64)
    stamp = np.full(n, np.nan)
    for r in range(n):
        a, e = starts[r], body_end[r]
        t = counts[r]
        p = a
        while True:
            # the fast path in the same pass that finds the token's end: [sign] digits [. digits], at most 15
            # digits in all (exact in float64 whatever their significance); anything else goes to _token,
            # which decides it exactly as before
            i = p
            neg = False
            if i < e:
                c = buf[i]
                if c == 45:
                    neg = True
                    i += 1
                elif c == 43:
                    i += 1
            d0 = i
            mant = 0
            while i < e:
                d = np.int64(buf[i]) - 48
                if d < 0 or d > 9:
                    break
                mant = mant * 10 + d
                i += 1
            n_int = i - d0
            k = -1
            v = 0.0
            if i == e or buf[i] == 9:
                if 0 < n_int <= 15:
                    k = INT
                    v = float(mant)
            elif buf[i] == 46 and n_int > 0:
                i += 1
                f0 = i
                while i < e:
                    d = np.int64(buf[i]) - 48
                    if d < 0 or d > 9:
                        break
                    mant = mant * 10 + d
                    i += 1
                n_frac = i - f0
                if (i == e or buf[i] == 9) and n_frac > 0 and n_int + n_frac <= 15:
                    k = DEC
                    v = float(mant) / pow10[n_frac]
            if k < 0:
                while i < e and buf[i] != 9:
                    i += 1
                k, v = _token(buf, p, i, pow10)
            elif neg:
                v = -v
            tstart[t] = p
            tend[t] = i
            kind[t] = k
            value[t] = v
            t += 1
            if i >= e:
                break
            p = i + 1
        if counts[r + 1] - counts[r] >= 2:
            c0 = counts[r]
            stamp[r] = _timestamp(buf, tstart[c0], tend[c0], tstart[c0 + 1], tend[c0 + 1], pow10)
    return counts, kind, value, tstart, tend, stamp, bad, body_end


def scan(buf: np.ndarray, starts: np.ndarray, ends: np.ndarray):
    """Tokenize payloads ``buf[starts[i]:ends[i]]``.

    Parameters
    ----------
    buf : ndarray of uint8
        The bytes (e.g. ``np.frombuffer(data, np.uint8)``).
    starts, ends : ndarray of int64, shape (n,)
        Payload bounds in ``buf``.

    Returns
    -------
    counts : ndarray of int64 (n + 1,)
        Tokens of payload i are ``counts[i]:counts[i + 1]`` of the arrays below.
    kind : ndarray of int8 (m,)
        :data:`INT`, :data:`DEC`, :data:`SLOW`, :data:`TEXT` or :data:`EMPTY`.
    value : ndarray of float64 (m,)
        The number (INT, DEC), a hash (TEXT), 0 otherwise.
    tstart, tend : ndarray of int64 (m,)
        Token bounds in ``buf``.
    stamp : ndarray of float64 (n,)
        UTC epoch seconds from the first two tokens, NaN when they are not a date and time, :data:`TIME_SLOW`
        when Python must read them.
    bad : ndarray of int64 (n,)
        Offset (within the payload) of the first NUL, CR or LF before the line ending, or −1.
    body_end : ndarray of int64 (n,)
        End of each payload's fields in ``buf`` (line ending and trailing TAB stripped).
    """
    return _scan(buf, np.ascontiguousarray(starts, np.int64), np.ascontiguousarray(ends, np.int64), _POW10)


@njit(cache=True)
def _parse_layout(buf, starts, ends, role, want, pow10, wl, pw, status, n_cores, missing, channel_error, invalid):
    m = starts.size
    n = role.size
    lam, power, st, status4 = _channel_arrays(m, wl, n_cores)
    ok = np.zeros(m, np.bool_)
    V = np.empty((m, n))
    stamp = np.full(m, np.nan)
    dtb = np.zeros((m, 4), np.int64)
    for r in range(m):
        a, e = starts[r], ends[r]
        if e > a and buf[e - 1] == 10:
            e -= 1
        if e > a and buf[e - 1] == 13:
            e -= 1
        if e > a and buf[e - 1] == 9:
            e -= 1
        p = a
        good = True
        for j in range(n):
            rl = role[j]
            i = p
            if rl == ROLE_ANY or rl == ROLE_LABEL:
                h = np.uint64(1469598103934665603)  # the hash of _other, to compare labels as numbers
                text = False
                while i < e:
                    c = buf[i]
                    if c == 9:
                        break
                    if c == 0 or c == 10 or c == 13:
                        good = False
                    if not _NUMCHAR[c]:
                        text = True
                    h = (h ^ np.uint64(c)) * np.uint64(1099511628211)
                    i += 1
                if not good or (rl == ROLE_LABEL and not (text and float(h >> np.uint64(12)) == want[j])):
                    good = False
                    break
                if j < 2:
                    dtb[r, 2 * j] = p
                    dtb[r, 2 * j + 1] = i
                V[r, j] = 0.0
            else:
                # the tokenizer's exact fast path and nothing else: [sign] digits [. digits], ≤ 15 digits (written
                # out as in _scan, not shared: as a called function returning a tuple, inlined or not, numba made
                # this pass ~4× slower, 2.4 → 9.4 µs a 7 × 18 record)
                neg = False
                if i < e:
                    c = buf[i]
                    if c == 45:
                        neg = True
                        i += 1
                    elif c == 43:
                        i += 1
                d0 = i
                mant = 0
                while i < e:
                    d = np.int64(buf[i]) - 48
                    if d < 0 or d > 9:
                        break
                    mant = mant * 10 + d
                    i += 1
                n_int = i - d0
                if n_int == 0 or n_int > 15:
                    good = False
                    break
                if i == e or buf[i] == 9:
                    v = float(mant)
                    if rl == ROLE_FIXED and (-v if neg else v) != want[j]:
                        good = False
                        break
                elif buf[i] == 46 and rl == ROLE_NUMBER:
                    i += 1
                    f0 = i
                    while i < e:
                        d = np.int64(buf[i]) - 48
                        if d < 0 or d > 9:
                            break
                        mant = mant * 10 + d
                        i += 1
                    n_frac = i - f0
                    if not ((i == e or buf[i] == 9) and n_frac > 0 and n_int + n_frac <= 15):
                        good = False
                        break
                    v = float(mant) / pow10[n_frac]
                else:
                    good = False
                    break
                V[r, j] = -v if neg else v
            if j == n - 1:
                good = i == e  # else more tokens than the layout's
            elif i >= e:  # fewer tokens than the layout's
                good = False
                break
            p = i + 1
        if good:
            t = _timestamp(buf, dtb[r, 0], dtb[r, 1], dtb[r, 2], dtb[r, 3], pow10)
            if t == TIME_SLOW:
                good = False
            stamp[r] = t
        if good and n_cores:
            _channel_row(V, r, wl, pw, status, n_cores, missing, channel_error, invalid, lam, power, st, status4)
        ok[r] = good
    return ok, V, stamp, dtb, lam, power, st, status4


def parse_layout(buf: np.ndarray, starts: np.ndarray, ends: np.ndarray, role: np.ndarray, want: np.ndarray,
                 wl: np.ndarray, pw: np.ndarray, status: np.ndarray, n_cores: int, missing: int, channel_error: int,
                 invalid: int):
    """Payloads ``buf[starts[i]:ends[i]]`` read as records of one known layout, and their channel blocks turned
    into Frame arrays (:func:`channels`), in one compiled pass.

    The stream's common case: the layout is known, so each token's place says what it must be, and the
    payload is read straight into the values without the tokenizer's arrays. A payload is accepted only when
    :func:`scan` and :func:`match_layout` would accept it with the same values: the same line-ending
    stripping, exactly ``role.size`` tokens, every number on the tokenizer's inline fast path (``[sign]
    digits [. digits]``, at most 15 digits), no NUL, CR or LF, and a time that needs no Python. Anything else
    (a damaged record, another layout, a number the fast path leaves to ``float``) is left to the general
    path, which decides it exactly as before.

    Parameters
    ----------
    buf : ndarray of uint8
    starts, ends : ndarray of int64, shape (m,)
        Payload bounds in ``buf``.
    role : ndarray of int8, shape (n,)
        Per token: :data:`ROLE_ANY`, :data:`ROLE_INT`, :data:`ROLE_FIXED`, :data:`ROLE_NUMBER` or
        :data:`ROLE_LABEL`.
    want : ndarray of float64, shape (n,)
        The value of a FIXED token, the hash of a LABEL token (others ignored).
    wl, pw, status, n_cores, missing, channel_error, invalid
        As for :func:`channels`.

    Returns
    -------
    ok : ndarray of bool (m,)
        Payloads read.
    values : ndarray of float64 (m, n)
        Token values of the payloads read (as :func:`scan` gives them; 0 for ANY and LABEL tokens).
    stamp : ndarray of float64 (m,)
        UTC epoch seconds of the date and time tokens (NaN when they are not a time).
    dt_bounds : ndarray of int64 (m, 4)
        Start and end in ``buf`` of the date and of the time token.
    wavelengths, powers, status, status4
        As :func:`channels` returns them (rows of payloads not read hold garbage).
    """
    return _parse_layout(buf, np.ascontiguousarray(starts, np.int64), np.ascontiguousarray(ends, np.int64),
                         role, want, _POW10, wl, pw, status, int(n_cores), np.uint8(missing),
                         np.uint8(channel_error), np.uint8(invalid))


@njit(cache=True)
def _channel_row(V, r, wl, pw, status, n_cores, missing, channel_error, invalid, lam, power, st, status4):
    """Row r of the channel arrays from row r of the token values V (one record)."""
    c, g = wl.shape
    pad = V.shape[1]
    gg = c * g // n_cores
    nan = np.nan
    for k in range(c):
        err = np.uint8(0)
        for q in range(4):
            v = np.int64(V[r, status[k, q]])
            status4[r, k, q] = v
            if v != 0:
                err = channel_error
        for j in range(g):
            if gg == g:  # a channel per core
                core, row = k, j
            else:  # one channel holding every core, core-major
                f = k * g + j
                core = f // gg
                row = f - core * gg
            a = wl[k, j]
            if a == pad:
                x, y, s = nan, nan, missing
            else:
                x = V[r, a]
                y = V[r, pw[k, j]]
                s = np.uint8(0)
                if x == 0.0:
                    x, y, s = nan, nan, missing
                elif not (np.isfinite(x) and x > 0.0):
                    x, s = nan, invalid
            lam[r, row, core] = x
            power[r, row, core] = y
            st[r, row, core] = s | err


@njit(cache=True)
def _channel_arrays(m, wl, n_cores):
    c, g = wl.shape
    gg = c * g // n_cores if n_cores else 0
    return (np.empty((m, gg, n_cores)), np.empty((m, gg, n_cores)), np.empty((m, gg, n_cores), np.uint8),
            np.empty((m, c, 4), np.int64))


@njit(cache=True)
def _channels(V, wl, pw, status, n_cores, missing, channel_error, invalid):
    m = V.shape[0]
    lam, power, st, status4 = _channel_arrays(m, wl, n_cores)
    for r in range(m):
        _channel_row(V, r, wl, pw, status, n_cores, missing, channel_error, invalid, lam, power, st, status4)
    return lam, power, st, status4


def channels(V: np.ndarray, wl: np.ndarray, pw: np.ndarray, status: np.ndarray, n_cores: int, missing: int,
             channel_error: int, invalid: int):
    """The channel blocks of records of one layout as Frame arrays, in one compiled pass.

    Parameters
    ----------
    V : ndarray of float64, shape (m, n_tokens)
        Token values of m records.
    wl, pw : ndarray of int64, shape (c, g)
        Token index of each channel's wavelengths and powers; ``n_tokens`` marks the padding of a short
        channel (a MISSING peak).
    status : ndarray of int64, shape (c, 4)
        Token index of each channel's four status integers.
    n_cores : int
        Cores of the output: c, or for one channel holding every core (core-major) the number of cores.
    missing, channel_error, invalid : int
        The PeakStatus bits: MISSING for a padding or a zero wavelength (its power NaN too), CHANNEL_ERROR on
        every peak of a channel with a non-zero status, INVALID_VALUE for a negative or non-finite wavelength.

    Returns
    -------
    wavelengths, powers : ndarray of float64, shape (m, c·g / n_cores, n_cores)
        nm (NaN where missing or invalid), powers as sent (NaN where missing).
    status : ndarray of uint8, same shape
    status4 : ndarray of int64, shape (m, c, 4)
    """
    if wl.shape[0] == 0:  # no channel: no gratings, no cores
        m = V.shape[0]
        return (np.empty((m, 0, 0)), np.empty((m, 0, 0)), np.empty((m, 0, 0), np.uint8),
                np.empty((m, 0, 4), np.int64))
    return _channels(np.ascontiguousarray(V, np.float64), wl, pw, status, int(n_cores), np.uint8(missing),
                     np.uint8(channel_error), np.uint8(invalid))


@njit(cache=True)
def _spans(buf, p, min_payload, max_payload):
    n = buf.size
    starts = np.empty((n - p) // (4 + min_payload) + 1, np.int64)
    ends = np.empty_like(starts)
    k = 0
    while n - p >= 4:
        length = (np.int64(buf[p]) << 24) | (np.int64(buf[p + 1]) << 16) | (np.int64(buf[p + 2]) << 8) | \
            np.int64(buf[p + 3])
        if length < min_payload or length > max_payload:
            break
        end = p + 4 + length
        if end > n:
            break
        starts[k] = p
        ends[k] = end
        k += 1
        p = end
    return starts[:k], ends[:k]


def spans(buf: np.ndarray, p: int, min_payload: int, max_payload: int) -> tuple[np.ndarray, np.ndarray]:
    """The complete length-prefixed payloads from offset p on, while in sync.

    Parameters
    ----------
    buf : ndarray of uint8
    p : int
        Offset of a 4-byte big-endian length prefix.
    min_payload, max_payload : int
        Accepted payload lengths, bytes; the first prefix outside them ends the run (the caller decides).

    Returns
    -------
    prefix, end : ndarray of int64 (k,)
        Offset of each record's prefix and end of its payload; they stop at the first bad or incomplete one.
    """
    return _spans(buf, int(p), int(min_payload), int(max_payload))


@njit(cache=True)
def _lines(buf, pos):
    n = buf.size
    m = 0  # lines: every line end, and a last line without one
    i = pos
    while i < n:
        c = buf[i]
        if c == 10 or c == 13:
            m += 1
            if c == 13 and i + 1 < n and buf[i + 1] == 10:
                i += 1
        i += 1
    starts = np.empty(m + 1, np.int64)
    ends = np.empty(m + 1, np.int64)
    number = np.empty(m + 1, np.int64)
    k = 0
    line = 0
    a = pos
    filled = False
    i = pos
    while i <= n:
        c = buf[i] if i < n else 10
        if c == 10 or c == 13:
            if i == n and a == n:
                break  # the data ended with a line end
            line += 1
            if filled and i < n:  # a last line without its line end (i == n) was cut: left out
                starts[k] = a
                ends[k] = i
                number[k] = line
                k += 1
            if c == 13 and i + 1 < n and buf[i + 1] == 10:
                i += 1
            a = i + 1
            filled = False
        elif not (c == 32 or c == 9 or c == 11 or c == 12):
            filled = True
        i += 1
    return starts[:k], ends[:k], number[:k]


def lines(buf: np.ndarray, pos: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lines of a text log from offset ``pos`` on, in one compiled pass (no bytes object per line).

    Lines end in LF, CR LF or CR alone, in any mixture. Lines holding only white space are left out, and so is
    a last line without its line end (the writer was stopped mid-line: its last number may be cut short).

    Returns
    -------
    starts, ends : ndarray of int64 (k,)
        Each line's bounds in ``buf``, the line end excluded.
    number : ndarray of int64 (k,)
        Its 1-based line number (blank lines counted).
    """
    return _lines(buf, int(pos))


@njit(cache=True)
def _hunt(buf, p, min_payload, max_payload, checked):
    n = buf.size
    p0 = p
    while p < n:
        if buf[p] == 0:
            if n - p < 4:
                return p
            length = (np.int64(buf[p + 1]) << 16) | (np.int64(buf[p + 2]) << 8) | np.int64(buf[p + 3])
            if min_payload <= length <= max_payload:
                hi = min(p + 4 + length - 1, n)  # the last payload byte may be the LF
                i = p + 4 + (checked if p == p0 else 0)
                while i < hi and buf[i] != 0 and buf[i] != 10:
                    i += 1
                if i == hi:
                    return p
        p += 1
    return n


def hunt(buf: np.ndarray, p: int, min_payload: int, max_payload: int, checked: int = 0) -> int:
    """Where a resynchronising stream decoder looks next: the first offset from ``p`` on holding a NUL that could
    start a record — a 4-byte prefix in ``[min_payload, max_payload]`` whose payload bytes received so far hold no
    NUL and no LF before its last byte — or a NUL in the last 3 bytes (its prefix is not complete yet); ``buf.size``
    when there is none. Every offset skipped is one the decoder's own checks would reject one at a time (a flood of
    NUL bytes would cost a Python step each); the candidate returned is still decided by them.

    Parameters
    ----------
    buf : ndarray of uint8
    p : int
        Offset to start from.
    min_payload, max_payload : int
        Accepted payload lengths, bytes (``max_payload`` below 16 MiB: the prefix's first byte is NUL).
    checked : int
        Payload bytes of a candidate at ``p`` already found clean (a decoder waiting for the rest of one does not
        scan what it has scanned).
    """
    return int(_hunt(buf, int(p), int(min_payload), int(max_payload), int(checked)))


@njit(cache=True)
def _match_layout(K, V, ints, fixed, fixed_val, numbers, labels, label_hash):
    m = K.shape[0]
    ok = np.empty(m, np.bool_)
    for r in range(m):
        good = True
        for j in ints:
            if K[r, j] != INT:
                good = False
                break
        if good:
            for q in range(fixed.size):
                if V[r, fixed[q]] != fixed_val[q]:
                    good = False
                    break
        if good:
            for j in numbers:
                k = K[r, j]
                if k != INT and k != DEC:
                    good = False
                    break
        if good:
            for q in range(labels.size):
                j = labels[q]
                if K[r, j] != TEXT or V[r, j] != label_hash[q]:
                    good = False
                    break
        ok[r] = good
    return ok


def match_layout(K: np.ndarray, V: np.ndarray, ints: np.ndarray, fixed: np.ndarray, fixed_val: np.ndarray,
                 numbers: np.ndarray, labels: np.ndarray, label_hash: np.ndarray) -> np.ndarray:
    """Which rows of token kinds K and values V (m, n) are records of one layout, in one compiled pass.

    A row matches when the tokens at ``ints`` are INT, those at ``fixed`` hold ``fixed_val``, those at
    ``numbers`` are INT or DEC and those at ``labels`` are TEXT with the hashes ``label_hash`` (all index
    arrays int64, values float64). Returns a bool array (m,).
    """
    return _match_layout(K, V, ints, fixed, fixed_val, numbers, labels, label_hash)


@njit(cache=True)
def _format_fixed(values, decimals, out):
    scale = 10.0**decimals
    n = 0
    for k in range(values.size):
        x = values[k]
        if k:
            out[n] = 9
            n += 1
        if not np.isfinite(x):
            out[n] = 110
            out[n + 1] = 97
            out[n + 2] = 110
            n += 3
            continue
        q = np.rint(x * scale)
        neg = q < 0 or (q == 0 and x < 0)
        q = abs(q)
        ip = int(q // scale)
        fp = int(q - ip * scale)
        if neg:
            out[n] = 45
            n += 1
        # integer part
        digits = 1
        t = ip
        while t >= 10:
            t //= 10
            digits += 1
        for j in range(digits - 1, -1, -1):
            out[n + j] = 48 + ip % 10
            ip //= 10
        n += digits
        if decimals:
            out[n] = 46
            n += 1
            for j in range(decimals - 1, -1, -1):
                out[n + j] = 48 + fp % 10
                fp //= 10
            n += decimals
    return n


def format_fixed(values: np.ndarray, decimals: int) -> bytes:
    """TAB-separated fixed-point text of ``values`` (``nan`` where not finite), compiled.

    Each value is rounded to ``round(x·10^decimals)`` (half to even) before printing, which differs from
    Python's correctly rounded ``f"{x:.{decimals}f}"`` only when x·10^decimals lies within one rounding of a
    half: the printed value is then off by one unit of the last decimal at most. Used for the sensor blocks,
    whose readers tolerate their quantisation; wavelengths keep Python's formatting. |x| < 1e12 / 10^decimals.
    """
    a = np.ascontiguousarray(values, dtype=np.float64).ravel()
    if a.size and np.nanmax(np.abs(np.where(np.isfinite(a), a, 0.0))) * 10.0**decimals >= 1e15:
        raise ValueError("format_fixed: values too large for fixed-point text")
    out = np.empty(a.size * (18 + decimals) + 1, np.uint8)
    return out[: _format_fixed(a, int(decimals), out)].tobytes()
