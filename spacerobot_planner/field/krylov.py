"""
The conjugate gradients' steps, the solve's clock and the coarsest level's dense factor, shared by the multigrid routes.

:mod:`.multigrid` (the aggregation levels, on the node graph or under the cells) and
:mod:`.geometric` (a 2-D band's geometric levels) run the same CG iteration with the same stop
rule (the largest residual), the same deadline (``time.perf_counter()``, read without the
interpreter where it can be) and the same dense Cholesky factor of their coarsest level.
"""
from __future__ import annotations

import math
import sys
import time

import numba as nb
import numpy as np

#: :func:`_cholesky`'s semidefinite pivot test: a pivot at most this fraction of its diagonal entry is null.
NULL_PIVOT = 1e-12


@nb.njit(cache=True, nogil=True)
def _cholesky(a, semidefinite=False):
    """
    Return the lower Cholesky factor of the symmetric positive definite ``a`` (m, m), float64 (m, m).

    The coarsest level's (the aggregation levels' at most :data:`.multigrid.DIRECT_NODES` rows, the
    geometric levels' at most :data:`.geometric.COARSEST_MOST`), in the kernel that builds it:
    LAPACK's through NumPy cost 30-80 us per band inside a plan (its code cold in the cache),
    against 4-6 us at 18-30 rows in a loop; this one 1-3 us at 15-30 rows, 25 us at 68.  Column by column:
    entry (i, j) from the products of rows i and j before column j, summed in four
    interleaved partial sums (a fixed order, so the same bits on any machine).  Reads the
    lower triangle of ``a``.  Raises ValueError where a pivot is not positive (or is NaN).
    ``semidefinite``: a pivot within :data:`NULL_PIVOT` times its diagonal entry of 0 (either
    side: rounding) instead gives a zero column, its unknown left at 0 by
    :func:`.geometric._coarsest` (a symmetric semidefinite generalized inverse, [A_KK⁻¹ 0; 0 0]),
    as a geometric coarsest level may need (an isolated fine unknown makes its four coarse
    parents' columns of the prolongation equal); a pivot below that, or NaN, still raises.
    """
    m = a.shape[0]
    low = np.zeros((m, m))
    for j in range(m):
        lj = low[j]
        for i in range(j, m):
            li = low[i]
            s0 = s1 = s2 = s3 = 0.0
            k = 0
            while k + 4 <= j:
                s0 += li[k] * lj[k]
                s1 += li[k + 1] * lj[k + 1]
                s2 += li[k + 2] * lj[k + 2]
                s3 += li[k + 3] * lj[k + 3]
                k += 4
            while k < j:
                s0 += li[k] * lj[k]
                k += 1
            t = a[i, j] - ((s0 + s1) + (s2 + s3))
            if i == j:
                if semidefinite and abs(t) <= NULL_PIVOT * a[j, j]:
                    break                      # a null column: low[:, j] stays 0
                if not t > 0.0:
                    raise ValueError("the coarsest level's matrix is not positive definite")
                low[j, j] = math.sqrt(t)
            else:
                low[i, j] = t / low[j, j]
    return low


#: The bits of float64's +inf (a |value|'s bits above it: NaN) and the mask of its sign bit.
_INF_BITS = 0x7FF0000000000000
_ABS_BITS = 0x7FFFFFFFFFFFFFFF


@nb.njit(cache=True, nogil=True)
def _subtract_max(r, q, c, n):
    """
    Compute r -= c q over the first n entries; return the largest |r| among them (NaN skipped).

    NaN skipped as before: a residual all NaN reads 0, so a caller keeps NaN out of CG's
    inputs (``solve_field`` checks its guess).

    The maximum is taken over the |r| bits as integers (the order of non-negative float64
    values is their bits' order, so it is the same value): an integer maximum is a vector
    reduction, a float one is a chain of dependent comparisons (25 000 entries: 17 -> 8 us).
    """
    bits = r.view(np.int64)
    m = 0
    for i in range(n):
        r[i] = r[i] - c * q[i]
        b = bits[i] & _ABS_BITS
        m = max(m, b if b <= _INF_BITS else 0)
    out = np.empty(1, np.int64)
    out[0] = m
    return out.view(np.float64)[0]


#: ``time.perf_counter``'s clock is CLOCK_MONOTONIC (Linux) and a ``struct timespec`` two int64
#: (a 64-bit build): the solve's deadline checks read it without the interpreter (:func:`_now`);
#: elsewhere they ask Python for it
_MONOTONIC_PERF_COUNTER = (getattr(time, "CLOCK_MONOTONIC", None) is not None and sys.maxsize > 2**32
                           and time.get_clock_info("perf_counter").implementation == "clock_gettime(CLOCK_MONOTONIC)")


#: the C library's ``clock_gettime(clock, struct timespec *)``, called by its symbol (numba caches the call)
_clock_gettime = nb.types.ExternalFunction("clock_gettime", nb.types.int32(nb.types.int32, nb.types.voidptr))
#: ``time.perf_counter``'s clock id (0 where it is not CLOCK_MONOTONIC: not read)
_CLOCK = int(time.CLOCK_MONOTONIC) if _MONOTONIC_PERF_COUNTER else 0


if _MONOTONIC_PERF_COUNTER:
    @nb.njit(cache=True, nogil=True)
    def _now():
        """Return ``time.perf_counter()``, s: the C library's monotonic clock, read without the GIL (40 ns)."""
        ts = np.empty(2, np.int64)          # struct timespec: seconds, nanoseconds (64-bit Linux)
        _clock_gettime(_CLOCK, ts.ctypes)
        return ts[0] + 1e-9 * ts[1]
else:
    @nb.njit(cache=True)
    def _now():
        """Return ``time.perf_counter()``, s (through the interpreter: 2 us and the GIL)."""
        with nb.objmode(t="float64"):
            t = time.perf_counter()
        return t


@nb.njit(cache=True, nogil=True, inline="always")
def _descend(r, q, u, p, rz, pq, tol, n, stop):
    """
    Take CG's step along p (q = A p, pq = p · q): alpha = rz / pq, r -= alpha q; return ``(alpha, largest |r|, done)``.

    done: the residual is below ``tol`` or the termination flag ``stop`` is set: u has then
    taken its step (u += alpha p), else it is left to :func:`_turn`.  Over the first n entries.
    """
    alpha = rz / pq
    res = _subtract_max(r, q, alpha, n)
    if res < tol or stop[0] != 0:
        _step(u, p, alpha, n)
        return alpha, res, True
    return alpha, res, False


@nb.njit(cache=True, nogil=True, inline="always")
def _step(u, p, alpha, n):
    """Add alpha p to u over the first n entries (CG's step along p)."""
    for i in range(n):
        u[i] += alpha * p[i]


@nb.njit(cache=True, nogil=True, inline="always")
def _turn(u, p, z, alpha, rz, rz_new, n):
    """
    Turn CG to its new direction from the preconditioned residual z: return rz_new.

    u's step along the old p (u += alpha p), then the new p = z + (rz_new / rz) p: one pass
    over p (first n entries).  rz_new: β's numerator, r · z (the flexible CG of
    :func:`.multigrid._spcg` passes its own).
    """
    beta = rz_new / rz
    for i in range(n):
        u[i] += alpha * p[i]
        p[i] = z[i] + beta * p[i]
    return rz_new


@nb.njit(cache=True, nogil=True, parallel=True)
def _subtract_max_chunks(r, q, c, n, chunk):
    """:func:`_subtract_max` over chunks of ``chunk`` entries in parallel: the same values, the same maximum."""
    count = (n + chunk - 1) // chunk
    part = np.zeros(count)
    for j in nb.prange(count):
        k0 = j * chunk
        k1 = min(n, k0 + chunk)
        part[j] = _subtract_max(r[k0:k1], q[k0:k1], c, k1 - k0)
    m = 0.0
    for j in range(count):
        m = max(m, part[j])
    return m


@nb.njit(cache=True, nogil=True, parallel=True)
def _step_chunks(u, p, alpha, n, chunk):
    """:func:`_step` over chunks of ``chunk`` entries in parallel: the same values."""
    for j in nb.prange((n + chunk - 1) // chunk):
        k0, k1 = j * chunk, min(n, (j + 1) * chunk)
        _step(u[k0:k1], p[k0:k1], alpha, k1 - k0)


@nb.njit(cache=True, nogil=True, parallel=True)
def _turn_chunks(u, p, z, alpha, rz, rz_new, n, chunk):
    """:func:`_turn` over chunks of ``chunk`` entries in parallel: the same values."""
    for j in nb.prange((n + chunk - 1) // chunk):
        k0, k1 = j * chunk, min(n, (j + 1) * chunk)
        _turn(u[k0:k1], p[k0:k1], z[k0:k1], alpha, rz, rz_new, k1 - k0)


@nb.njit(cache=True, nogil=True)
def _descend_in(r, q, u, p, rz, pq, tol, n, stop, chunk):
    """:func:`_descend`, over chunks of ``chunk`` entries on numba's threads where ``chunk`` > 0: the same values."""
    if chunk <= 0:
        return _descend(r, q, u, p, rz, pq, tol, n, stop)
    alpha = rz / pq
    worst = _subtract_max_chunks(r, q, alpha, n, chunk)
    done = worst < tol or stop[0] != 0
    if done:
        _step_chunks(u, p, alpha, n, chunk)
    return alpha, worst, done


@nb.njit(cache=True, nogil=True)
def _turn_in(u, p, z, alpha, rz, rz_new, n, chunk):
    """:func:`_turn`, over chunks of ``chunk`` entries on numba's threads where ``chunk`` > 0: the same values."""
    if chunk <= 0:
        _turn(u, p, z, alpha, rz, rz_new, n)
    else:
        _turn_chunks(u, p, z, alpha, rz, rz_new, n, chunk)
