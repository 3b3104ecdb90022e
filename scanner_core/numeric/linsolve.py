"""A tiny dense solver for numba kernels: the normal equations of small least-squares fits.

np.linalg.solve would go through BLAS/LAPACK; for 4x4 and 5x5 systems inside per-column
and per-blob loops plain elimination is faster and never wakes OpenBLAS threads (docs/design.md).
"""
from numba import njit

#: A pivot this small means the system is singular (the fit is degenerate).
SINGULAR_PIVOT = 1e-12


@njit(nogil=True, cache=True)
def solve_in_place(m, v):
    """Solve ``m x = v`` by Gaussian elimination with partial pivoting, in place.

    Parameters
    ----------
    m : (n, n) float64
        Overwritten.
    v : (n,) float64
        Overwritten with the solution.

    Returns
    -------
    bool
        False when the system is singular (``v`` then holds garbage).
    """
    n = m.shape[0]
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(m[i, k]) > abs(m[p, k]):
                p = i
        if abs(m[p, k]) < SINGULAR_PIVOT:
            return False
        if p != k:
            for j in range(n):
                t = m[k, j]
                m[k, j] = m[p, j]
                m[p, j] = t
            t = v[k]
            v[k] = v[p]
            v[p] = t
        for i in range(k + 1, n):
            f = m[i, k] / m[k, k]
            for j in range(k, n):
                m[i, j] -= f * m[k, j]
            v[i] -= f * v[k]
    for k in range(n - 1, -1, -1):
        s = v[k]
        for j in range(k + 1, n):
            s -= m[k, j] * v[j]
        v[k] = s / m[k, k]
    return True
