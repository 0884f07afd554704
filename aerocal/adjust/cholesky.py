"""Sparse Cholesky factor of a symmetric positive definite system: Intel MKL PARDISO through ctypes.

The reduced camera system of a block is symmetric positive definite once GNSS/attitude priors or ground
control fix the datum. SuperLU (scipy), which the adjustment used alone before, is an LU factorisation: it
stores ``L`` and ``U`` and does twice a Cholesky's work, and it runs in one thread. PARDISO (mtype 2, real
symmetric positive definite) factorises the upper triangle as ``L L^T`` with supernodes on every core, in
its own METIS nested-dissection order: several times faster than SuperLU in aerocal's METIS order
(:func:`aerocal.adjust.solver.camera_ordering`) on city-scale systems, with the same solutions to rounding
(``benchmarks/history/engine_measurements.md``).

The library comes from the ``mkl`` wheel (x86-64; ``AEROCAL_MKL_RT`` names another ``libmkl_rt`` to load
first). Where it is missing, :func:`available` is False and the adjustment keeps SuperLU; a system PARDISO
finds not positive definite (:class:`NotPositiveDefinite`) goes to SuperLU too, which tells an exactly
singular system apart.
"""

from __future__ import annotations

import ctypes
import glob
import os
import sys
from functools import cache

import numpy as np
import scipy.sparse as sp

#: PARDISO's matrix type for real symmetric positive definite systems
_SPD = 2
#: PARDISO phases: analysis + numerical factorisation; numerical factorisation alone (the analysis of the
#: same pattern kept); solve with iterative refinement; release memory
_ANALYSE_FACTOR, _FACTOR, _SOLVE, _RELEASE = 12, 22, 33, -1
#: PARDISO's error codes (its documentation), for the messages
_ERRORS = {-1: "input inconsistent", -2: "not enough memory", -3: "reordering problem",
           -4: "zero pivot (the matrix is not positive definite)", -5: "unclassified internal error",
           -6: "preordering failed", -7: "diagonal matrix is singular", -8: "32-bit integer overflow",
           -10: "error opening out-of-core files", -11: "read/write error with out-of-core files",
           -12: "pardiso_64 called from 32-bit library", -13: "interrupted by the mkl_progress function"}


class PardisoError(RuntimeError):
    """PARDISO failed for a reason other than the matrix (memory, library)."""


class NotPositiveDefinite(PardisoError):
    """PARDISO met a zero or negative pivot: the matrix is singular or indefinite."""


@cache
def _library():
    """The ``pardiso`` entry point of MKL's single dynamic library, or None where MKL is not installed."""
    names = [os.environ.get("AEROCAL_MKL_RT", "")]
    for root in (sys.prefix, sys.base_prefix):
        names += sorted(glob.glob(os.path.join(root, "lib", "libmkl_rt.so*")), key=len)
    for name in filter(None, names):
        try:
            lib = ctypes.CDLL(name)
        except OSError:
            continue
        fn = lib.pardiso
        i32 = ctypes.POINTER(ctypes.c_int32)
        fn.argtypes = [ctypes.POINTER(ctypes.c_int64), i32, i32, i32, i32, i32, ctypes.c_void_p, i32, i32, i32,
                       i32, i32, i32, ctypes.c_void_p, ctypes.c_void_p, i32]
        fn.restype = None
        return fn
    return None


def available() -> bool:
    """Whether MKL PARDISO can be loaded in this environment."""
    return _library() is not None


def _upper_triangle(A, pattern: tuple | None = None) -> tuple:
    """``(indptr, indices, data, pattern)``: the upper triangle of the symmetric ``A`` as zero-based CSR arrays
    (int32 indices, sorted within rows) as PARDISO reads it. ``pattern`` (what an earlier call returned) is
    returned as it is, with the indices it holds, when ``A`` has the same one: only ``data`` is new.

    A symmetric CSC matrix's arrays are its CSR arrays too, so the triangle is a mask over its entries
    instead of scipy's ``triu`` through COO, whose conversion back to CSR copies the whole matrix."""
    A = A if sp.issparse(A) and A.format in ("csr", "csc") else sp.csr_matrix(A)
    if not A.has_canonical_format:
        A = A.copy()
        A.sum_duplicates()
    n = A.shape[0]
    if pattern is not None and np.array_equal(pattern[0], A.indptr) and np.array_equal(pattern[1], A.indices):
        return pattern[2], pattern[3], A.data[pattern[4]], pattern
    rows = np.repeat(np.arange(n, dtype=A.indices.dtype), np.diff(A.indptr))  # the row of each entry (CSR view)
    keep = np.flatnonzero(A.indices >= rows)
    indptr = np.zeros(n + 1, dtype=np.int32)
    np.cumsum(np.bincount(rows[keep], minlength=n), out=indptr[1:])
    indices = A.indices[keep].astype(np.int32)
    pattern = (A.indptr.copy(), A.indices.copy(), indptr, indices, keep)
    return indptr, indices, np.ascontiguousarray(A.data[keep], dtype=np.float64), pattern


class PardisoCholesky:
    """``L L^T`` of a sparse symmetric positive definite matrix ``A`` (n, n); :meth:`solve` gives ``A^-1 b``.

    Raises :class:`NotPositiveDefinite` when PARDISO meets a non-positive pivot, :class:`PardisoError` on
    other failures. The factor lives in MKL's memory until the object is deleted."""

    def __init__(self, A) -> None:
        fn = _library()
        if fn is None:
            raise PardisoError("MKL PARDISO is not installed (the 'mkl' package)")
        self._fn = fn
        indptr, indices, data, self._pattern = _upper_triangle(A)
        self.n = len(indptr) - 1
        self._indptr, self._indices, self._data = indptr, indices, data
        self._pt = np.zeros(64, dtype=np.int64)  # PARDISO's internal handle, zeroed before the first call
        self._iparm = np.zeros(64, dtype=np.int32)
        self._iparm[0] = 1  # the values below, not PARDISO's defaults
        self._iparm[1] = 2  # METIS nested-dissection ordering
        self._iparm[7] = 0  # iterative refinement only where pivots were perturbed (never, for SPD)
        self._iparm[9] = 13  # pivot perturbation threshold 1e-13 (unused for SPD)
        self._iparm[17] = -1  # report the factor's entries
        self._iparm[34] = 1  # zero-based indices
        self._call(_ANALYSE_FACTOR, np.zeros((self.n, 1), order="F"))

    def refactor(self, A) -> bool:
        """Factorise ``A`` in place of the factor held, keeping the analysis (ordering and symbolic factor)
        when ``A`` has the held matrix's pattern (the reduced camera systems of one block, step after step):
        PARDISO's numerical phase alone (the analysis is a large share of a factorisation). Returns False, the
        held factor unchanged, when the pattern differs."""
        indptr, indices, data, pattern = _upper_triangle(A, self._pattern)
        if pattern is not self._pattern:
            return False
        self._data = data
        self._call(_FACTOR, np.zeros((self.n, 1), order="F"))
        return True

    @property
    def factor_entries(self) -> int:
        """Entries of ``L`` (PARDISO's count, supernodal storage)."""
        return int(self._iparm[17])

    def _call(self, phase: int, b: np.ndarray) -> np.ndarray:
        i32 = ctypes.c_int32
        x = np.zeros_like(b)
        err = i32(0)
        p = ctypes.POINTER(i32)
        self._fn(self._pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)), ctypes.byref(i32(1)), ctypes.byref(i32(1)),
                 ctypes.byref(i32(_SPD)), ctypes.byref(i32(phase)), ctypes.byref(i32(self.n)),
                 self._data.ctypes.data, self._indptr.ctypes.data_as(p), self._indices.ctypes.data_as(p),
                 None, ctypes.byref(i32(b.shape[1] if b.ndim == 2 else 1)), self._iparm.ctypes.data_as(p),
                 ctypes.byref(i32(0)), b.ctypes.data, x.ctypes.data, ctypes.byref(err))
        if err.value != 0:
            msg = f"MKL PARDISO phase {phase}: error {err.value} ({_ERRORS.get(err.value, 'unknown')})"
            raise (NotPositiveDefinite if err.value in (-4, -7) else PardisoError)(msg)
        return x

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``A^-1 b`` for ``b`` of shape (n,) or (n, k).

        Raises:
            ValueError: ``b`` has another number of rows than the factor (``n``).
        """
        b = np.asarray(b, dtype=np.float64)
        if b.shape[0] != self.n:
            raise ValueError(f"right-hand side has {b.shape[0]} rows, the factor {self.n}")
        if b.size == 0:  # no columns (a block without check points): PARDISO calls nrhs = 0 inconsistent
            return np.zeros(b.shape)
        x = self._call(_SOLVE, np.asfortranarray(b.reshape(self.n, -1)))
        return np.ascontiguousarray(x).reshape(b.shape)

    def __del__(self) -> None:
        if getattr(self, "_pt", None) is not None and self._pt.any():  # PARDISO holds memory for this handle
            try:
                self._call(_RELEASE, np.zeros((self.n, 1), order="F"))
            except (PardisoError, ImportError):  # nothing to do about a failed release at teardown (an
                pass  # ImportError: the interpreter is shutting down and ctypes can no longer be imported)
