"""Compiled inner loops of the reduced camera system: eliminating the points, pair by pair of observations.

Eliminating the points of a bundle adjustment (Schur complement) leaves, for every pair of images that see
a common point ``p``, the 6 x 6 block ``- W_a Hpp_p^-1 W_b^T`` (``W_m = Ji_m^T Jx_m``, observation ``a`` in
the first image, ``b`` in the second), summed over the points. The 800-image conte-city block (382k
observations, 123k points) has 878k such pairs (unordered, each observation with itself included).
numpy formed them as batched 6 x 3 by 3 x 6 products, slow on such small shapes, with gathers and a sort of
the pair keys every iteration. This is the loop of Ceres' ``SchurEliminator``, here
compiled by numba: one pass over the points, each unordered pair once (the mirrored block is its
transpose), written in place into a block layout found once per block (:func:`image_pair_layout`) by a
binary search of the pair's row; the per-observation sums (each image's own ``J^T J`` and ``J^T r``, the
points' gradients and inverse blocks) in the same pass. The measurements that justified it are in
``benchmarks/history/engine_measurements.md``; the comparison with pycolmap's bundle adjustment on the same
problem is ``benchmarks/colmap_ba_bench.py``. The agreement with the general sparse products is checked in
``tests/test_adjust_core.py``.

The points are visited in an order that keeps the blocks being written few (:func:`point_visit_rank`):
visited by their index, the points of a simulated or matched block jump across it, and every pair writes
to rows far from the last, out of the cache; visited along a reverse Cuthill-McKee order of the images, the
pairs write to few blocks at a time.

Conventions: observations are rows of the block's observation tables; ``order`` lists them grouped by point,
the points in the visiting order ``visit`` (``pstart[q]:pstart[q + 1]`` are point ``visit[q]``'s); image blocks
are 6 x 6 in the (w, C) order of :class:`aerocal.adjust.solver.Layout`.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee


@dataclass(frozen=True)
class PairLayout:
    """The block-sparse (6 x 6 blocks, CSR by image) layout of the image-image part of the reduced camera
    system and the observations grouped by point; fixed for a block's observations, so formed once."""

    indptr: np.ndarray  # (N + 1,) int64: image i's blocks are indices[indptr[i]:indptr[i + 1]]
    indices: np.ndarray  # (B,) int64 column image of each block, sorted within a row
    diagonal: np.ndarray  # (N,) int64 position of block (i, i)
    order: np.ndarray  # (M,) int64 observations grouped by point, points in ``visit`` order (stable)
    pstart: np.ndarray  # (P + 1,) int64 first entry in ``order`` of the point visited q-th
    visit: np.ndarray  # (P,) int64 the point visited q-th

    @property
    def n_blocks(self) -> int:
        return len(self.indices)


@numba.njit(cache=True, nogil=True)
def _counting_order(keys, starts, out):  # pragma: no cover - compiled
    pos = starts.copy()
    for m in range(len(keys)):
        k = keys[m]
        out[pos[k]] = m
        pos[k] += 1


def stable_order(keys: np.ndarray, n_keys: int) -> np.ndarray:
    """``np.argsort(keys, kind="stable")`` for integer ``keys`` in ``[0, n_keys)``, by counting (one pass, no
    comparison sort), several times faster than numpy's stable argsort on an adjustment's keys
    (``benchmarks/history/engine_measurements.md``)."""
    keys = np.ascontiguousarray(keys, dtype=np.int64)
    starts = np.zeros(n_keys + 1, dtype=np.int64)
    np.cumsum(np.bincount(keys, minlength=n_keys), out=starts[1:])
    out = np.empty(len(keys), dtype=np.int64)
    _counting_order(keys, starts, out)
    return out


def image_graph(image: np.ndarray, point: np.ndarray, n_images: int, n_points: int) -> sp.csr_matrix:
    """Which images share a point, each image with itself included: the pattern of ``A A^T`` for the
    image-by-point incidence matrix ``A`` (scipy's sparse product: one pass over the ``sum_p L_p^2`` pairs in
    C++, no per-pair array kept), CSR with sorted indices."""
    A = sp.csr_matrix((np.ones(len(image), dtype=np.float32), (image, point)), shape=(n_images, n_points))
    G = (A @ A.T + sp.identity(n_images, dtype=np.float32, format="csr")).tocsr()
    G.sort_indices()
    return G


def point_visit_rank(graph: sp.csr_matrix, image: np.ndarray, point: np.ndarray, n_points: int) -> np.ndarray:
    """(P,) int64: when each point is visited by the compiled passes. The images are put in a reverse
    Cuthill-McKee order of ``graph`` (neighbours near each other, whatever order the images came in), and the
    points follow their first image in it; a point seen by no image comes last."""
    n_images = graph.shape[0]
    pos = np.empty(n_images, dtype=np.int64)
    pos[np.asarray(reverse_cuthill_mckee(graph, symmetric_mode=True))] = np.arange(n_images)
    key = np.full(n_points, n_images, dtype=np.int64)
    np.minimum.at(key, point, pos[image])
    rank = np.empty(n_points, dtype=np.int64)
    rank[stable_order(key, n_images + 1)] = np.arange(n_points)
    return rank


def image_pair_layout(image: np.ndarray, point: np.ndarray, n_images: int, n_points: int,
                      graph: sp.csr_matrix | None = None, rank: np.ndarray | None = None) -> PairLayout:
    """The layout of every pair of images that share a point, and every image's own block; the points visited
    in ``rank`` order (default :func:`point_visit_rank`). ``graph``: :func:`image_graph` of the observations,
    when already formed."""
    G = image_graph(image, point, n_images, n_points) if graph is None else graph
    if rank is None:
        rank = point_visit_rank(G, image, point, n_points)
    indptr = G.indptr.astype(np.int64)
    indices = G.indices.astype(np.int64)
    rows = np.repeat(np.arange(n_images), np.diff(indptr))
    diagonal = np.flatnonzero(rows == indices)
    order = stable_order(rank[point], n_points)
    visit = np.empty(n_points, dtype=np.int64)
    visit[rank] = np.arange(n_points)
    pstart = np.zeros(n_points + 1, dtype=np.int64)
    np.cumsum(np.bincount(point, minlength=n_points)[visit], out=pstart[1:])
    return PairLayout(indptr, indices, diagonal, order, pstart, visit)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _find(indptr, indices, row, col):  # pragma: no cover - compiled
    """Position of block (row, col) in a sorted CSR layout (binary search of the row)."""
    lo, hi = indptr[row], indptr[row + 1] - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if indices[mid] < col:
            lo = mid + 1
        else:
            hi = mid
    return lo


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _inverse3(A, out):  # pragma: no cover - compiled
    """``out = A^-1`` for a symmetric 3 x 3 block by cofactors; a (nearly) singular block (a point seen along
    one ray) gets its diagonal loaded by 1e-9 of its mean, so that the point simply does not move."""
    load = 0.0
    for _ in range(2):
        a00, a01, a02 = A[0, 0] + load, A[0, 1], A[0, 2]
        a11, a12, a22 = A[1, 1] + load, A[1, 2], A[2, 2] + load
        c00 = a11 * a22 - a12 * a12
        c01 = a02 * a12 - a01 * a22
        c02 = a01 * a12 - a02 * a11
        det = a00 * c00 + a01 * c01 + a02 * c02
        scale = abs(a00) + abs(a11) + abs(a22)
        if abs(det) > 1e-14 * scale * scale * scale and det != 0.0:
            break
        load = 1e-9 * max(scale / 3.0, 1e-12)
    inv = 1.0 / det
    out[0, 0] = c00 * inv
    out[0, 1] = out[1, 0] = c01 * inv
    out[0, 2] = out[2, 0] = c02 * inv
    out[1, 1] = (a00 * a22 - a02 * a02) * inv
    out[1, 2] = out[2, 1] = (a01 * a02 - a00 * a12) * inv
    out[2, 2] = (a00 * a11 - a01 * a01) * inv


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _reduce(p0, p1, order, pstart, visit, image, Ji, Jx, r, Hpp, damp, point_grad, indptr, indices,
            data, Hii, gi, back, Hpp_inv, gpp):  # pragma: no cover - compiled
    """One pass over the points visited ``p0:p1``-th and their observations (see :func:`reduce_points`)."""
    T = np.empty((6, 3))
    B = np.empty((6, 6))
    Hd = np.empty((3, 3))
    longest = 0
    for q in range(p0, p1):
        longest = max(longest, pstart[q + 1] - pstart[q])
    Wp = np.empty((longest, 6, 3))  # the point's W blocks, contiguous
    for q in range(p0, p1):
        p = visit[q]
        s, e = pstart[q], pstart[q + 1]
        # the point's damped block, its inverse and its gradient J^T r (+ a control point's own rows)
        for u in range(3):
            for v in range(3):
                Hd[u, v] = Hpp[p, u, v]
            Hd[u, u] *= damp
        _inverse3(Hd, Hpp_inv[p])
        H = Hpp_inv[p]
        g0, g1, g2 = point_grad[p, 0], point_grad[p, 1], point_grad[p, 2]
        # per observation: W = Ji^T Jx, the image's own J^T J and gradient
        for a in range(s, e):
            m = order[a]
            i = image[m]
            r0, r1 = r[m, 0], r[m, 1]
            g0 += Jx[m, 0, 0] * r0 + Jx[m, 1, 0] * r1
            g1 += Jx[m, 0, 1] * r0 + Jx[m, 1, 1] * r1
            g2 += Jx[m, 0, 2] * r0 + Jx[m, 1, 2] * r1
            for u in range(6):
                ju0, ju1 = Ji[m, 0, u], Ji[m, 1, u]
                gi[i, u] += ju0 * r0 + ju1 * r1
                for v in range(3):
                    Wp[a - s, u, v] = ju0 * Jx[m, 0, v] + ju1 * Jx[m, 1, v]
                for v in range(6):
                    Hii[i, u, v] += ju0 * Ji[m, 0, v] + ju1 * Ji[m, 1, v]
        gpp[p, 0], gpp[p, 1], gpp[p, 2] = g0, g1, g2
        # every pair of the point's observations: -W_a H W_b^T into block (image a, image b), the mirrored
        # block its transpose; the images' part of Hcp Hpp^-1 gp
        for a in range(s, e):
            ma = order[a]
            ia = image[ma]
            for u in range(6):
                w0, w1, w2 = Wp[a - s, u, 0], Wp[a - s, u, 1], Wp[a - s, u, 2]
                for v in range(3):
                    T[u, v] = w0 * H[0, v] + w1 * H[1, v] + w2 * H[2, v]
                back[ia, u] += T[u, 0] * g0 + T[u, 1] * g1 + T[u, 2] * g2
            for bb in range(a, e):
                mb = order[bb]
                ib = image[mb]
                for u in range(6):
                    t0, t1, t2 = T[u, 0], T[u, 1], T[u, 2]
                    for v in range(6):
                        B[u, v] = t0 * Wp[bb - s, v, 0] + t1 * Wp[bb - s, v, 1] + t2 * Wp[bb - s, v, 2]
                k = _find(indptr, indices, ia, ib)
                for u in range(6):
                    for v in range(6):
                        data[k, u, v] -= B[u, v]
                if bb != a:
                    k2 = _find(indptr, indices, ib, ia)
                    for u in range(6):
                        for v in range(6):
                            data[k2, u, v] -= B[v, u]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def scale_observation_blocks(m, p, k, Ji, Jx, Hpp):  # pragma: no cover - compiled
    """Observation ``m`` of :func:`jacobian_blocks`: its rows scaled by ``k``, ``-Jx`` into the last 3 columns
    of ``Ji``, its share of point ``p``'s J^T J added to ``Hpp``. Also called from the projection's loop
    (:func:`aerocal.adjust.projection.project_observations` with ``scale``)."""
    for u in range(2):
        for v in range(3):
            Ji[m, u, v] *= k
            Jx[m, u, v] *= k
            Ji[m, u, v + 3] = -Jx[m, u, v]
    for u in range(3):
        for v in range(3):
            Hpp[p, u, v] += Jx[m, 0, u] * Jx[m, 0, v] + Jx[m, 1, u] * Jx[m, 1, v]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _jacobian_blocks(point, scale, Ji, Jx, Hpp):  # pragma: no cover - compiled
    for m in range(len(point)):
        scale_observation_blocks(m, point[m], scale[m], Ji, Jx, Hpp)


def jacobian_blocks(point: np.ndarray, Ji: np.ndarray, Jx: np.ndarray, scale: np.ndarray,
                    n_points: int) -> np.ndarray:
    """The observations' rows of the Jacobian scaled by ``scale`` (M,) (sqrt of the robust weight over the
    a-priori sigma), in place, and the points' 3 x 3 blocks of J^T J (P, 3, 3), returned, in one pass.

    On entry ``Ji`` (M, 2, 6) holds d(uv)/dw in its first 3 columns and ``Jx`` (M, 2, 3) d(uv)/dX (both as
    :func:`aerocal.adjust.projection.project_observations` writes them with ``d_rot_out=Ji``,
    ``d_point_out=Jx``); on return ``Ji`` is the image's block in its (w, C) columns (``d(uv)/dC = -d(uv)/dX``)
    and ``Jx`` the point's, both scaled. One compiled pass instead of numpy's strided products and batched
    (3 x 2) by (2 x 3) ones with a sparse sum. Written in place of the projection's own arrays: no (M, 2, 3)
    array more per iteration, and the same arrays serve every iteration
    (:meth:`aerocal.adjust.solver.BundleProblem.residuals`).

    Raises:
        ValueError: ``Ji`` or ``Jx`` is not a C-contiguous float64 array.
    """
    f8 = np.float64
    if not (Ji.dtype == f8 and Jx.dtype == f8 and Ji.flags.c_contiguous and Jx.flags.c_contiguous):
        raise ValueError("Ji and Jx must be C-contiguous float64 arrays")
    Hpp = np.zeros((n_points, 3, 3))
    _jacobian_blocks(np.ascontiguousarray(point, dtype=np.int64), np.ascontiguousarray(scale, dtype=f8), Ji, Jx, Hpp)
    return Hpp


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _points_from_images(order, pstart, visit, image, Ji, Jx, dc, out):  # pragma: no cover - compiled
    for q in range(len(pstart) - 1):
        p = visit[q]
        for a in range(pstart[q], pstart[q + 1]):
            m = order[a]
            i = image[m]
            # W_m^T dc_i = Jx_m^T (Ji_m dc_i)
            e0 = (Ji[m, 0, 0] * dc[i, 0] + Ji[m, 0, 1] * dc[i, 1] + Ji[m, 0, 2] * dc[i, 2]
                  + Ji[m, 0, 3] * dc[i, 3] + Ji[m, 0, 4] * dc[i, 4] + Ji[m, 0, 5] * dc[i, 5])
            e1 = (Ji[m, 1, 0] * dc[i, 0] + Ji[m, 1, 1] * dc[i, 1] + Ji[m, 1, 2] * dc[i, 2]
                  + Ji[m, 1, 3] * dc[i, 3] + Ji[m, 1, 4] * dc[i, 4] + Ji[m, 1, 5] * dc[i, 5])
            for v in range(3):
                out[p, v] += Jx[m, 0, v] * e0 + Jx[m, 1, v] * e1


def points_from_images(layout: PairLayout, image: np.ndarray, Ji: np.ndarray, Jx: np.ndarray,
                       dc_images: np.ndarray) -> np.ndarray:
    """``Hcp^T dc`` of the image columns (P, 3): per point, the sum over its observations of ``W_m^T dc_i``
    with ``W_m = Ji_m^T Jx_m`` (``dc_images`` (N, 6)): the back-substitution's product, in the points' order
    (one compiled pass instead of numpy's gathered products and per-point bincounts). ``W`` is formed here from
    the Jacobian blocks, not kept from the elimination: an (M, 6, 3) array would be allocated afresh every
    step."""
    out = np.zeros((len(layout.pstart) - 1, 3))
    f8 = np.float64
    _points_from_images(layout.order, layout.pstart, layout.visit, np.ascontiguousarray(image, dtype=np.int64),
                        np.ascontiguousarray(Ji, dtype=f8), np.ascontiguousarray(Jx, dtype=f8),
                        np.ascontiguousarray(dc_images, dtype=f8), out)
    return out


@dataclass
class Reduction:
    """What one pass over the observations gives (:func:`reduce_points`)."""

    data: np.ndarray  # (B, 6, 6) blocks of -Hcp Hpp^-1 Hcp^T in the layout (images' own J^T J not added)
    Hii: np.ndarray  # (N, 6, 6) each image's own J^T J from its observations
    grad: np.ndarray  # (N, 6) images' J^T r from their observations (priors not added)
    back: np.ndarray  # (N, 6) images' part of Hcp Hpp^-1 gp
    Hpp_inv: np.ndarray  # (P, 3, 3) inverses of the damped point blocks
    gpp: np.ndarray  # (P, 3) the points' J^T r, the control rows' included


#: Threads that share :func:`reduce_points` (the compiled pass releases the GIL): each sums its own points'
#: pairs into a copy of the blocks, added up after (``benchmarks/history/engine_measurements.md``).
REDUCE_THREADS = min(4, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


def reduce_points(layout: PairLayout, image: np.ndarray, Ji: np.ndarray, Jx: np.ndarray, r: np.ndarray,
                  Hpp: np.ndarray, lam: float, point_grad: np.ndarray, n_images: int,
                  threads: int | None = None) -> Reduction:
    """Eliminate the points: the image-image part of the reduced camera system and its right-hand side.

    ``Ji`` (M, 2, 6), ``Jx`` (M, 2, 3), ``r`` (M, 2): the observations' Jacobian blocks and residuals (rows
    scaled); ``Hpp`` (P, 3, 3) the points' blocks of J^T J (control rows included), damped here by
    ``1 + lam`` on the diagonal; ``point_grad`` (P, 3) the control rows' J^T r. ``threads``: how many share
    the pass (default :data:`REDUCE_THREADS`), the points cut where the pairs' work is halved."""
    P = len(Hpp)
    f8 = np.float64
    args = (layout.order, layout.pstart, layout.visit, np.ascontiguousarray(image, dtype=np.int64),
            np.ascontiguousarray(Ji, dtype=f8), np.ascontiguousarray(Jx, dtype=f8), np.ascontiguousarray(r, dtype=f8),
            np.ascontiguousarray(Hpp, dtype=f8), 1.0 + lam, np.ascontiguousarray(point_grad, dtype=f8),
            layout.indptr, layout.indices)
    n = max(1, min(threads or REDUCE_THREADS, P // 256 + 1))
    # shared by the threads, so touched here first: page faults of fresh memory in two threads at once wait on
    # each other, and two threads on untouched outputs were slower than one
    new = np.empty if n == 1 else lambda shape: np.full(shape, 0.0)
    Hpp_inv, gpp = new((P, 3, 3)), new((P, 3))
    work = np.cumsum(np.diff(layout.pstart) ** 2)
    cuts = np.concatenate([[0], np.searchsorted(work, work[-1] * np.arange(1, n) / n) if P else [], [P]]).astype(int)

    def part(k: int) -> tuple:
        out = (np.zeros((layout.n_blocks, 6, 6)), np.zeros((n_images, 6, 6)), np.zeros((n_images, 6)),
               np.zeros((n_images, 6)))
        _reduce(cuts[k], cuts[k + 1], *args, *out, Hpp_inv, gpp)
        return out

    if n == 1:
        parts = [part(0)]
    else:
        with ThreadPoolExecutor(n) as pool:
            parts = list(pool.map(part, range(n)))
    sums = parts[0]
    for other in parts[1:]:
        for acc, x in zip(sums, other, strict=True):
            acc += x
    return Reduction(*sums, Hpp_inv, gpp)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _global_blocks(image, point, Jg, Ji, Jx, Hgi, Hcp_g):  # pragma: no cover - compiled
    ng = Jg.shape[2]
    for m in range(len(image)):
        i, p = image[m], point[m]
        for g in range(ng):
            a0, a1 = Jg[m, 0, g], Jg[m, 1, g]
            for k in range(6):
                Hgi[i, g, k] += a0 * Ji[m, 0, k] + a1 * Ji[m, 1, k]
            for k in range(3):
                Hcp_g[p, g, k] += a0 * Jx[m, 0, k] + a1 * Jx[m, 1, k]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _global_image_coupling(image, point, Tg, Ji, Jx, out):  # pragma: no cover - compiled
    ng = Tg.shape[1]
    for m in range(len(image)):
        i, p = image[m], point[m]
        for g in range(ng):
            # Tg[p, g] W_m^T = (Jx_m Tg[p, g]) . Ji_m
            t0, t1, t2 = Tg[p, g, 0], Tg[p, g, 1], Tg[p, g, 2]
            e0 = Jx[m, 0, 0] * t0 + Jx[m, 0, 1] * t1 + Jx[m, 0, 2] * t2
            e1 = Jx[m, 1, 0] * t0 + Jx[m, 1, 1] * t1 + Jx[m, 1, 2] * t2
            for k in range(6):
                out[i, g, k] += e0 * Ji[m, 0, k] + e1 * Ji[m, 1, k]


def global_blocks(image: np.ndarray, point: np.ndarray, Jg: np.ndarray, Ji: np.ndarray, Jx: np.ndarray,
                  n_images: int, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """``(Hgi, Hcp_g)``: the global columns' (IO, thermal slopes; ``Jg`` (M, 2, ng)) blocks of ``J^T J``
    against each image's (w, C) columns, (N, ng, 6), and against each point's, (P, ng, 3), in one pass over
    the observations (numpy's batched (ng x 2) by (2 x 6) products and per-image sums: most of a
    self-calibration's iteration, see :func:`global_image_coupling`)."""
    ng = Jg.shape[2]
    Hgi, Hcp_g = np.zeros((n_images, ng, 6)), np.zeros((n_points, ng, 3))
    f8 = np.float64
    _global_blocks(np.ascontiguousarray(image, dtype=np.int64), np.ascontiguousarray(point, dtype=np.int64),
                   np.ascontiguousarray(Jg, dtype=f8), np.ascontiguousarray(Ji, dtype=f8),
                   np.ascontiguousarray(Jx, dtype=f8), Hgi, Hcp_g)
    return Hgi, Hcp_g


def global_image_coupling(image: np.ndarray, point: np.ndarray, Tg: np.ndarray, Ji: np.ndarray, Jx: np.ndarray,
                          n_images: int) -> np.ndarray:
    """(N, ng, 6): per image, the sum over its observations of ``Tg[point] W_m^T`` (``Tg`` (P, ng, 3), the
    points' ``Hcp_g Hpp^-1``; ``W_m = Ji_m^T Jx_m`` formed from the Jacobian blocks), the global-image part of
    ``Hcp Hpp^-1 Hcp^T``. It replaced
    numpy einsums over (M, ng, 6) and their per-image sums (with :func:`global_blocks` and the compiled IO
    Jacobians it more than halved a self-calibration's time: ``benchmarks/history/engine_measurements.md``)."""
    out = np.zeros((n_images, Tg.shape[1], 6))
    _global_image_coupling(np.ascontiguousarray(image, dtype=np.int64), np.ascontiguousarray(point, dtype=np.int64),
                           np.ascontiguousarray(Tg, dtype=np.float64), np.ascontiguousarray(Ji, dtype=np.float64),
                           np.ascontiguousarray(Jx, dtype=np.float64), out)
    return out
