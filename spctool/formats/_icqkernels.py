"""Numba kernels of the ICQ reader and writer (private; :mod:`spctool.formats.icq` calls them for large
shapes, and reads and writes small ones in plain Python with the same results).

Specification: ``spc-formats.md`` §0 (Fortran numbers: list-directed reading, ``D``/``E``/letterless
exponents) and §5 (ICQ: ``4F12.5`` / ``3F12.5`` rows, or exact exponent notation).  The kernels read
records of numbers with correctly rounded decimal → double conversion (128-bit products, ties to even),
falling back to Python for the rare tokens they cannot convert exactly (``slow``), and write fixed
``Fw.d`` fields and shortest-exact exponent fields digit for digit as the Python formatter would.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_TWO53 = 9007199254740992
_P10 = np.array([float(10**i) for i in range(23)])  # exact doubles
_P10I = np.array([10**i for i in range(19)], dtype=np.int64)
_P5 = np.array([5**i for i in range(28)], dtype=np.uint64)
_MAXSIG = 18  # significant digits kept in an int64 mantissa (10**18 < 2**60)


@njit(cache=True)
def _mul64(a, b):
    """Full 128-bit product (hi, lo) of two uint64."""
    m32 = np.uint64(0xFFFFFFFF)
    s32 = np.uint64(32)
    a0 = a & m32
    a1 = a >> s32
    b0 = b & m32
    b1 = b >> s32
    p00 = a0 * b0
    p01 = a0 * b1
    p10 = a1 * b0
    p11 = a1 * b1
    mid = (p00 >> s32) + (p01 & m32) + (p10 & m32)
    lo = (mid << s32) | (p00 & m32)
    hi = p11 + (p01 >> s32) + (p10 >> s32) + (mid >> s32)
    return hi, lo


@njit(cache=True)
def _shl128(hi, lo, n):
    """(hi, lo) << n for 0 ≤ n < 128 (the caller guarantees no overflow)."""
    if n == 0:
        return hi, lo
    if n >= 64:
        return lo << np.uint64(n - 64), np.uint64(0)
    return (hi << np.uint64(n)) | (lo >> np.uint64(64 - n)), lo << np.uint64(n)


@njit(cache=True)
def _cmp_mid(m, k, c, e):
    """Sign of m·10^−k − c·2^e, exactly (m < 2^60, c < 2^56, k ≤ 27); 2 if out of range."""
    a = -e - k  # compare m·2^a with c·5^k
    yh, yl = _mul64(np.uint64(c), _P5[k])
    if a >= 0:
        if a > 67:
            return 2
        xh, xl = _shl128(np.uint64(0), np.uint64(m), a)
    else:
        if -a > 9:
            return 2
        xh = np.uint64(0)
        xl = np.uint64(m)
        yh, yl = _shl128(yh, yl, -a)
    if xh > yh:
        return 1
    if xh < yh:
        return -1
    if xl > yl:
        return 1
    if xl < yl:
        return -1
    return 0


@njit(cache=True)
def _decimal_to_double(m, e10):
    """Correctly rounded m·10^e10 (m ≥ 0 int64 < 2^60); returns (value, ok)."""
    if m == 0:
        return 0.0, True
    if m <= _TWO53 and -22 <= e10 <= 22:  # Clinger: one exact operation, one rounding
        if e10 >= 0:
            return float(m) * _P10[e10], True
        return float(m) / _P10[-e10], True
    if e10 == 0:
        return float(m), True  # int64 → double rounds to nearest even
    if e10 > 0 or e10 < -27:
        return 0.0, False
    k = -e10
    if k <= 22:
        c = float(m) / _P10[k]
    else:
        c = float(m) / _P10[22] / _P10[k - 22]
    for _ in range(4):
        fr, ex = math.frexp(c)
        big = np.int64(fr * 9007199254740992.0)  # 53-bit significand
        e = ex - 53
        r = _cmp_mid(m, k, 2 * big + 1, e - 1)  # against the upper midpoint
        if r == 2:
            return 0.0, False
        if r > 0:
            c = np.nextafter(c, np.inf)
            continue
        if r == 0:
            if big & 1:
                c = np.nextafter(c, np.inf)
            return c, True
        if big == 4503599627370496:  # 2^52: the lower neighbour is half as far
            r2 = _cmp_mid(m, k, 4 * big - 1, e - 2)
        else:
            r2 = _cmp_mid(m, k, 2 * big - 1, e - 1)
        if r2 == 2:
            return 0.0, False
        if r2 < 0:
            c = np.nextafter(c, -np.inf)
            continue
        if r2 == 0 and (big & 1):
            c = np.nextafter(c, -np.inf)
        return c, True
    return 0.0, False


@njit(cache=True)
def _is_blank(c):
    return c == 32 or c == 9 or c == 44 or c == 13 or c == 11 or c == 12  # blank, tab, comma, CR, VT, FF


@njit(cache=True)
def parse_records(buf, pos, nrec, ncols, out, slow):
    """List-directed read of ``ncols`` reals from each of ``nrec`` lines starting at byte ``pos``.

    Extra values on a line are ignored (list-directed semantics).  Tokens whose
    value cannot be settled here are recorded in ``slow`` as (start, end, index).
    Returns (status, record, value, byte, end, nslow): status 0 ok, 1 bad token
    at ``byte``, 2 too few values on ``record``, 3 data end before ``record``,
    4 ``slow`` is full.
    """
    n = buf.shape[0]
    p = pos
    nslow = 0
    for r in range(nrec):
        if p >= n:
            return 3, r, 0, p, p, nslow
        for col in range(ncols):
            while p < n and _is_blank(buf[p]):
                p += 1
            if p >= n or buf[p] == 10:
                return 2, r, col, p, p, nslow
            start = p
            neg = False
            ch = buf[p]
            if ch == 43 or ch == 45:
                neg = ch == 45
                p += 1
            m = np.int64(0)
            nsig = 0
            ndig = 0
            e10 = 0
            lost = False
            while p < n and 48 <= buf[p] <= 57:
                d = buf[p] - 48
                ndig += 1
                if nsig < _MAXSIG:
                    if m != 0 or d != 0:
                        m = m * 10 + d
                        nsig += 1
                else:
                    e10 += 1
                    if d != 0:
                        lost = True
                p += 1
            if p < n and buf[p] == 46:
                p += 1
                while p < n and 48 <= buf[p] <= 57:
                    d = buf[p] - 48
                    ndig += 1
                    if nsig < _MAXSIG:
                        if m != 0 or d != 0:
                            m = m * 10 + d
                            nsig += 1
                        e10 -= 1
                    elif d != 0:
                        lost = True
                    p += 1
            if ndig == 0:
                return 1, r, col, start, p, nslow
            if p < n:
                ch = buf[p]
                has_exp = False
                esign = 1
                if ch == 69 or ch == 101 or ch == 68 or ch == 100 or ch == 81 or ch == 113:  # E e D d Q q
                    has_exp = True
                    p += 1
                    if p < n and (buf[p] == 43 or buf[p] == 45):
                        esign = -1 if buf[p] == 45 else 1
                        p += 1
                elif ch == 43 or ch == 45:  # letterless exponent 1.5-06
                    has_exp = True
                    esign = -1 if ch == 45 else 1
                    p += 1
                if has_exp:
                    edig = 0
                    ev = 0
                    while p < n and 48 <= buf[p] <= 57:
                        if ev < 100000:
                            ev = ev * 10 + (buf[p] - 48)
                        edig += 1
                        p += 1
                    if edig == 0:
                        return 1, r, col, start, p, nslow
                    e10 += esign * ev
            if p < n and not (_is_blank(buf[p]) or buf[p] == 10):
                return 1, r, col, start, p, nslow
            while m != 0 and m % 10 == 0:
                m //= 10
                e10 += 1
            idx = r * ncols + col
            ok = False
            if not lost:
                v, ok = _decimal_to_double(m, e10)
            if ok:
                out[idx] = -v if neg else v
            else:
                if nslow >= slow.shape[0]:
                    return 4, r, col, start, p, nslow
                slow[nslow, 0] = start
                slow[nslow, 1] = p
                slow[nslow, 2] = idx
                nslow += 1
        while p < n and buf[p] != 10:
            p += 1
        if p < n:
            p += 1
    return 0, nrec, 0, p, p, nslow


@njit(cache=True)
def _two_prod(a, b):
    """a·b = p + e exactly (Dekker/Veltkamp; no FMA needed)."""
    p = a * b
    t = 134217729.0 * a
    ah = t - (t - a)
    al = a - ah
    t = 134217729.0 * b
    bh = t - (t - b)
    bl = b - bh
    e = ((ah * bh - p) + ah * bl + al * bh) + al * bl
    return p, e


@njit(cache=True)
def _round_exact(p, e):
    """Nearest integer (ties to even) to the exact sum p + e (|e| ≤ ulp(p)/2), as int64."""
    r = np.rint(p)
    dd = p - r
    fe = np.floor(e)
    fre = e - fe
    if abs(p) >= 9007199254740992.0:
        n = np.int64(fe)
        if fre > 0.5:
            n += 1
        elif fre == 0.5 and (np.int64(r) + n) & 1:
            n += 1
        return np.int64(r) + n
    if dd == 0.5 and e > 0:
        return np.int64(r) + 1
    if dd == -0.5 and e < 0:
        return np.int64(r) - 1
    if dd == 0.0 and abs(e) == 0.5 and np.int64(r) & 1:
        return np.int64(r) + (1 if e > 0 else -1)
    return np.int64(r)


@njit(cache=True)
def format_fixed(vals, width, decimals, out):
    """Fortran ``Fw.d`` (as Python ``%w.df``: correctly rounded, ties to even) for every value.

    ``out`` is (rows, cols·width + 1) uint8; each line ends with a newline.
    Every field keeps at least one leading blank.  Returns (row, col) of the
    first value that does not fit (or is not finite), else (−1, −1).
    """
    rows, cols = vals.shape
    scale = _P10[decimals]
    pd = _P10I[decimals]
    for r in range(rows):
        for c in range(cols):
            x = vals[r, c]
            base = c * width
            if not (abs(x) < 1e9):  # also rejects NaN and infinities
                return r, c
            p, e = _two_prod(x, scale)
            k = _round_exact(p, e)
            neg = x < 0 or (x == 0.0 and math.copysign(1.0, x) < 0)
            kk = -k if k < 0 else k
            ip = kk // pd
            fr = kk - ip * pd
            nd = 1
            t = ip // 10
            while t > 0:
                nd += 1
                t //= 10
            length = nd + 1 + decimals + (1 if neg else 0)
            if length > width - 1:
                return r, c
            for t in range(width - length):
                out[r, base + t] = 32
            q = base + width - 1
            for _ in range(decimals):
                out[r, q] = 48 + fr % 10
                fr //= 10
                q -= 1
            out[r, q] = 46
            q -= 1
            for _ in range(nd):
                out[r, q] = 48 + ip % 10
                ip //= 10
                q -= 1
            if neg:
                out[r, q] = 45
        out[r, cols * width] = 10
    return -1, -1


EXACT_WIDTH = 24  # " " + "%23.16E": one blank, sign or blank, d.dddddddddddddddd, E±ee


@njit(cache=True)
def format_exact(vals, out, fallback):
    """17 significant digits, ``ES24.16``-like (identical to Python ``'%24.16E'``), lossless.

    Values outside 1e−6 ≤ |x| < 1e16 are flagged in ``fallback`` for Python formatting.
    """
    rows, cols = vals.shape
    w = 24
    for r in range(rows):
        for c in range(cols):
            x = vals[r, c]
            base = c * w
            for t in range(w):
                out[r, base + t] = 32
            neg = x < 0 or (x == 0.0 and math.copysign(1.0, x) < 0)
            ax = abs(x)
            m = np.int64(0)
            d = 0
            if ax != 0.0:
                if not (ax >= 1e-6 and ax < 1e16):
                    fallback[r, c] = True
                    continue
                d = int(math.floor(math.log10(ax)))
                good = False
                for _ in range(3):
                    j = 16 - d
                    if j < 0 or j > 22:
                        break
                    p, e = _two_prod(ax, _P10[j])
                    # the decade is decided on the exact product p + e, before rounding
                    if p < 1e16 or (p == 1e16 and e < 0):
                        d -= 1
                        continue
                    if p > 1e17 or (p == 1e17 and e >= 0):
                        d += 1
                        continue
                    m = _round_exact(p, e)
                    if m == 100000000000000000:  # 9.99…95 rounds up into the next decade
                        m = 10000000000000000
                        d += 1
                    good = True
                    break
                # p + e is x·10^j exactly and m its correct rounding: the correctly rounded
                # 17-digit decimal, which always reads back as x (no re-check needed).
                if not good:
                    fallback[r, c] = True
                    continue
            q = base + w - 1
            ed = -d if d < 0 else d
            out[r, q] = 48 + ed % 10
            out[r, q - 1] = 48 + (ed // 10) % 10
            out[r, q - 2] = 45 if d < 0 else 43
            out[r, q - 3] = 69
            q -= 4
            for _ in range(16):
                out[r, q] = 48 + m % 10
                m //= 10
                q -= 1
            out[r, q] = 46
            out[r, q - 1] = 48 + m % 10
            if neg:
                out[r, q - 2] = 45
        out[r, cols * w] = 10
