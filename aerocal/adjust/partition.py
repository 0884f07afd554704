"""Partitioned bundle adjustment: sub-blocks reduce themselves onto the cameras they share, in parallel.

The block's images are cut into spatially compact sub-blocks (recursive median bisection of the projection
centres); every tie point (and control GCP) goes to the sub-block holding most of its observations, with all
its observations. An image observed in several sub-blocks is a *boundary* image; the others are *interior*.
Each Levenberg-Marquardt iteration then runs as in :func:`aerocal.adjust.solver.solve`, but split:

1. every sub-block forms its own reduced camera system (its points eliminated,
   :func:`~aerocal.adjust.solver.schur_complement`) and eliminates its interior images too, leaving a dense
   system on its boundary images and the global unknowns (IO, thermal slopes);
2. those systems are summed (a boundary image's normal-equation blocks are the sums of its sub-blocks'
   shares, each GNSS / attitude prior counted once, by the image's own sub-block) and solved;
3. every sub-block back-substitutes its interior images and its points, tries the step and returns its share
   of the cost.

This is the single adjustment's normal equations solved by nested elimination, not a consensus between
separately adjusted sub-blocks: the steps, the damping and the stopping rule are the same, so the result is
the single adjustment's to rounding (``tests/test_adjust_partition.py``). What changes is where the work and
the memory are: the per-observation blocks (the bulk, ~1.5 kB per observation) live in the sub-blocks, on
the Dask workers when a client is given (one :class:`SubBlock` actor each), and only the boundary system is
formed on the caller's side. The covariances reported (IO, check points) come from the same factorisations,
column by column (:class:`PartitionedInverse`), never as a dense inverse.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp

from aerocal.adjust.problem import AdjustConfig, AdjustmentError, Block
from aerocal.adjust.solver import (
    MIN_DEPTH_FRACTION,
    Problem,
    Solution,
    SparseInverse,
    State,
    factorise,
    schur_complement,
    solve,
)


def partition_images(xy: np.ndarray, n_parts: int) -> np.ndarray:
    """(N,) sub-block label of each image: recursive median bisection of ``xy`` (N, 2; metres) along the longer
    side of each part, so the parts are compact and hold ``N / n_parts`` images each to one image."""
    xy = np.asarray(xy, dtype=float)
    labels = np.zeros(len(xy), dtype=np.int64)

    def split(idx: np.ndarray, k: int, first: int) -> None:
        if k == 1 or len(idx) < 2:
            labels[idx] = first
            return
        k1 = k // 2
        axis = int(np.argmax(np.ptp(xy[idx], axis=0)))
        order = idx[np.argsort(xy[idx, axis], kind="stable")]
        cut = int(round(len(idx) * k1 / k))
        split(order[:cut], k1, first)
        split(order[cut:], k - k1, first + k1)

    split(np.arange(len(xy)), max(1, int(n_parts)), 0)
    return labels


@dataclasses.dataclass
class Plan:
    """How a block is cut: per sub-block its images, points and observations (indices into the whole block),
    and the boundary images every sub-block shares with another."""

    images: list[np.ndarray]  # per sub-block: whole-block image indices (its local image order)
    points: list[np.ndarray]  # per sub-block: whole-block point indices (its tie points, then its GCPs)
    observations: list[np.ndarray]  # per sub-block: whole-block observation indices
    owned: list[np.ndarray]  # per sub-block: (n_images_k,) 1 where the image's priors count here
    boundary: np.ndarray  # whole-block indices of the boundary images (sorted)

    @property
    def n_parts(self) -> int:
        return len(self.images)


def plan_partition(block: Block, xy: np.ndarray, n_parts: int) -> Plan:
    """Cut ``block`` into ``n_parts`` sub-blocks by its images' positions ``xy`` (N, 2 metres)."""
    label = partition_images(xy, n_parts)
    K = int(label.max()) + 1
    P = block.n_points
    # each point goes to the sub-block that owns most of the images observing it (ties: the lower label)
    votes = np.bincount(block.obs_point * K + label[block.obs_image], minlength=P * K).reshape(P, K)
    point_label = np.argmax(votes, axis=1)
    point_label[votes.sum(axis=1) == 0] = 0
    obs_label = point_label[block.obs_point]
    images, points, observations, owned = [], [], [], []
    member = np.zeros((K, block.n_images), dtype=bool)
    for k in range(K):
        obs = np.flatnonzero(obs_label == k)
        imgs = np.union1d(block.obs_image[obs], np.flatnonzero(label == k))
        member[k, imgs] = True
        pts = np.flatnonzero(point_label == k)  # tie points (< n_tie) sort before control GCPs
        images.append(imgs)
        points.append(pts)
        observations.append(obs)
        owned.append((label[imgs] == k).astype(float))
    boundary = np.flatnonzero(member.sum(axis=0) > 1)
    return Plan(images, points, observations, owned, boundary)


def sub_block(block: Block, plan: Plan, k: int) -> Block:
    """The arrays of sub-block ``k`` of ``plan``, indices local (check points stay with the whole block)."""
    imgs, pts, obs = plan.images[k], plan.points[k], plan.observations[k]
    img_local = np.full(block.n_images, -1, dtype=np.int64)
    img_local[imgs] = np.arange(len(imgs))
    pt_local = np.full(block.n_points, -1, dtype=np.int64)
    pt_local[pts] = np.arange(len(pts))
    tie = pts[pts < block.n_tie]
    ctrl = pts[pts >= block.n_tie] - block.n_tie
    is_tie = block.obs_is_tie[obs]
    return Block(
        crs=block.crs, origin=block.origin, image_ids=block.image_ids[imgs], R_rec=block.R_rec[imgs],
        gnss=block.gnss[imgs], temperature=block.temperature[imgs],
        obs_image=img_local[block.obs_image[obs]], obs_point=pt_local[block.obs_point[obs]],
        obs_uv=block.obs_uv[obs], obs_sigma=block.obs_sigma[obs], obs_is_tie=is_tie, obs_row=block.obs_row[obs],
        n_tie=len(tie), track_ids=block.track_ids[tie], control_ids=[block.control_ids[g] for g in ctrl],
        control_xyz=block.control_xyz[ctrl].reshape(-1, 3), control_sigma=block.control_sigma[ctrl].reshape(-1, 3),
        check_ids=[], check_xyz=np.zeros((0, 3)), check_sigma=np.zeros((0, 3)),
        check_image=np.zeros(0, np.int64), check_point=np.zeros(0, np.int64), check_uv=np.zeros((0, 2)),
        check_sigma_px=np.zeros(0), n_tie_obs=int(is_tie.sum()),
    )


class _Factor:
    """Sparse LU (:func:`~aerocal.adjust.solver.factorise`) solving for vectors and matrices; dense least
    squares where the matrix is exactly singular."""

    def __init__(self, A) -> None:
        self.A = sp.csc_matrix(A)
        self.lu, self.d = factorise(self.A)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        rhs = np.asarray(rhs, dtype=float)
        d = self.d if rhs.ndim == 1 else self.d[:, None]
        if self.lu is None:
            As = self.A.toarray() / self.d[:, None] / self.d[None, :]
            return np.linalg.lstsq(As, rhs / d, rcond=None)[0] / d
        return self.lu.solve(rhs / d) / d


class SubBlock:
    """One sub-block of a partitioned adjustment: its observations, its linearisation and its factorisations.

    Stateful (a Dask actor when the adjustment runs on a cluster): it keeps its current and candidate state
    and its last Jacobian between the calls of :func:`solve_partitioned`. Camera-side vectors handed in and
    out are in the sub-block's local layout restricted to the boundary: ``[globals | 6 per boundary image]``
    in the order of ``boundary_local``.
    """

    def __init__(self, block: Block, config: AdjustConfig, t0: float, owned: np.ndarray,
                 boundary_local: np.ndarray, start: State) -> None:
        self.problem = Problem(block, config, t0, check_datum=False)
        self.problem.prior_weight = np.asarray(owned, dtype=float)
        lay = self.problem.layout
        ng, N = lay.n_global, block.n_images
        boundary_local = np.asarray(boundary_local, dtype=np.int64)
        interior = np.setdiff1d(np.arange(N), boundary_local)
        self.b_cols = np.concatenate([np.arange(ng), lay.image_cols(boundary_local).ravel()]).astype(np.int64)
        self.a_cols = lay.image_cols(interior).ravel().astype(np.int64)
        self.interior = interior
        self.state = start
        self.candidate: State | None = None
        self.lin: tuple | None = None
        self.step_parts: tuple | None = None
        self.final: tuple | None = None

    # -- set-up
    def tie_depths(self) -> np.ndarray:
        """Depths (metres, > 0) of the tie observations at the start state: the whole block's median sets the
        floor below which a point is held (:meth:`Problem.hold_close_points`)."""
        b, st = self.problem.b, self.state
        i, j = b.obs_image[b.obs_is_tie], b.obs_point[b.obs_is_tie]
        z = np.einsum("mk,mk->m", st.R[i][:, 2], st.X[j] - st.C[i])
        return z[z > 0]

    def set_depth_floor(self, floor: float) -> None:
        self.problem.depth_floor = float(floor)

    def linearise(self) -> float:
        """Jacobian at the current state; returns this sub-block's share of the cost."""
        cost, _, _, _, _, _, Hpp = self.problem.residuals(self.state, jac=True, sparse=False)
        self.lin = (Hpp,)
        return cost

    # -- one iteration
    def _reduce(self, lam: float) -> tuple[np.ndarray, np.ndarray]:
        (Hpp,) = self.lin
        S, rhs, Hpp_inv, Hcp, gp = schur_complement(None, None, Hpp, None, lam, self.problem.blocks)
        S = sp.csc_matrix(S)
        a, b = self.a_cols, self.b_cols
        Sb = S[b]
        C = Sb[:, b].toarray()
        r_b = rhs[b].copy()
        fac, B = None, None
        if len(a):
            fac = _Factor(S[a][:, a])
            B = sp.csc_matrix(S[a][:, b])
            AinvB = fac.solve(B.toarray())
            C -= B.T @ AinvB
            del AinvB
            r_b -= B.T @ fac.solve(rhs[a])
        self.step_parts = (rhs, Hpp_inv, Hcp, gp, fac, B)
        return 0.5 * (C + C.T), r_b

    def reduce(self, lam: float) -> tuple[np.ndarray, np.ndarray]:
        """This sub-block's reduced system on its boundary, ``(S_b, rhs_b)``, with damping ``lam``."""
        return self._reduce(lam)

    def _back_substitute(self, dc_b: np.ndarray) -> np.ndarray:
        rhs, Hpp_inv, Hcp, gp, fac, B = self.step_parts
        dc = np.zeros(self.problem.layout.n_camera)
        dc[self.b_cols] = dc_b
        if fac is not None:
            dc[self.a_cols] = fac.solve(rhs[self.a_cols] - B @ dc_b)
        return dc

    def try_step(self, dc_b: np.ndarray) -> tuple[float, float]:
        """Back-substitute the boundary step, form the candidate state and return ``(cost, dc . rhs)``: its
        share of the candidate's cost and of the step's metric."""
        rhs, Hpp_inv, Hcp, gp, _, _ = self.step_parts
        dc = self._back_substitute(dc_b)
        dp = -np.einsum("pij,pj->pi", Hpp_inv, (gp + Hcp.T @ dc).reshape(-1, 3)).ravel()
        metric = float(dc @ rhs)
        self.step_parts = None  # the per-observation operator goes before the next residuals
        cand = self.problem.apply(self.state, dc, dp)
        self.problem.hold_close_points(self.state, cand)
        self.candidate = cand
        return self.problem.residuals(cand, jac=False)[0], metric

    def accept(self) -> float:
        """Move to the candidate and linearise there; returns the cost share."""
        self.state, self.candidate = self.candidate, None
        return self.linearise()

    def reject(self) -> None:
        self.candidate = None

    # -- the end
    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        """The undamped reduced boundary system at the solution; its interior factor is kept for
        :meth:`covariance_reduce` / :meth:`covariance_back`."""
        S_b, r_b = self._reduce(0.0)
        _, _, _, _, fac, B = self.step_parts
        self.final = (fac, B)
        self.step_parts = None
        self.lin = None
        self.problem.blocks = None
        return S_b, r_b

    def covariance_reduce(self, E_a: np.ndarray) -> np.ndarray:
        """``-B^T A^-1 E_a``: the boundary right-hand side of unit columns ``E_a`` on the interior."""
        fac, B = self.final
        if fac is None:  # every image of this sub-block is a boundary image
            return np.zeros((len(self.b_cols), E_a.shape[1]))
        return -(B.T @ fac.solve(E_a))

    def covariance_back(self, E_a: np.ndarray, X_b: np.ndarray) -> np.ndarray:
        """``A^-1 (E_a - B X_b)``: the interior rows of the inverse's columns."""
        fac, B = self.final
        return E_a if fac is None else fac.solve(E_a - B @ X_b)

    def result(self) -> tuple[State, np.ndarray, np.ndarray, float]:
        """``(state, res_px, w, cost)`` at the solution: the local state, the observations' residuals (pixels)
        and robust weights in the sub-block's observation order, and its share of the cost."""
        cost, res_px, w = self.problem.residuals(self.state, jac=False)
        return self.state, res_px, w, cost


def _gather(calls: list) -> list:
    """The values of calls made on sub-blocks: Dask actor futures are waited for, plain values pass."""
    return [c.result() if hasattr(c, "result") else c for c in calls]


class PartitionedInverse(SparseInverse):
    """Columns of the inverse of the whole block's reduced camera system, by the partitioned elimination:
    for unit columns ``E``, each sub-block reduces its interior rows onto the boundary, the boundary system is
    solved with its factor, and each sub-block back-substitutes its interior rows."""

    def __init__(self, n: int, boundary_factor: _Factor | None, boundary_cols: np.ndarray, parts: list,
                 part_b_pos: list[np.ndarray], part_a_cols: list[np.ndarray]) -> None:
        self.n = n
        self._dense = None
        self._cols = {}
        self.fb, self.bcols = boundary_factor, boundary_cols
        self.parts, self.part_b_pos, self.part_a_cols = parts, part_b_pos, part_a_cols
        self.d = np.ones(n)

    def columns(self, cols: np.ndarray) -> np.ndarray:
        cols = np.asarray(cols, dtype=np.int64)
        missing = [int(c) for c in cols if int(c) not in self._cols]
        if missing:
            miss = np.asarray(missing)
            c = len(miss)
            nb = len(self.bcols)
            bpos = np.full(self.n, -1)
            bpos[self.bcols] = np.arange(nb)
            E_b = np.zeros((nb, c))
            on_b = bpos[miss] >= 0
            E_b[bpos[miss[on_b]], np.flatnonzero(on_b)] = 1.0
            E_as = []
            for a_cols in self.part_a_cols:
                E_a = np.zeros((len(a_cols), c))
                hit = np.isin(miss, a_cols)
                if hit.any():
                    E_a[np.searchsorted(a_cols, miss[hit]), np.flatnonzero(hit)] = 1.0
                E_as.append(E_a)
            reduced = _gather([p.covariance_reduce(E) for p, E in zip(self.parts, E_as, strict=True)])
            rhs = E_b
            for pos, y in zip(self.part_b_pos, reduced, strict=True):
                np.add.at(rhs, pos, y)
            X_b = self.fb.solve(rhs) if nb else rhs
            backs = _gather([p.covariance_back(E, X_b[pos]) for p, E, pos in
                             zip(self.parts, E_as, self.part_b_pos, strict=True)])
            X = np.zeros((self.n, c))
            X[self.bcols] = X_b
            for a_cols, x in zip(self.part_a_cols, backs, strict=True):
                X[a_cols] = x
            for k, col in enumerate(missing):
                self._cols[col] = X[:, k]
        return np.column_stack([self._cols[int(c)] for c in cols]) if len(cols) else np.zeros((self.n, 0))


def solve_partitioned(problem: Problem, start: State, n_parts: int, client: object | None = None) -> Solution:
    """:func:`aerocal.adjust.solver.solve` with the block cut into ``n_parts`` sub-blocks (see the module),
    on ``client``'s Dask workers (one actor per sub-block) or, without a client, in this process.

    The returned :class:`Solution` is the single adjustment's: same state, sigma0, dof, iterations and
    covariances (:class:`PartitionedInverse`, which keeps the sub-blocks until it is dropped)."""
    cfg, block, lay = problem.cfg, problem.b, problem.layout
    ng = lay.n_global
    plan = plan_partition(block, start.C[:, :2], n_parts)
    K = plan.n_parts
    # the boundary vector: globals, then 6 per boundary image; and each sub-block's place in it
    bcols = np.concatenate([np.arange(ng), lay.image_cols(plan.boundary).ravel()]).astype(np.int64)
    b_index = np.full(block.n_images, -1, dtype=np.int64)
    b_index[plan.boundary] = np.arange(len(plan.boundary))
    part_b_pos, part_a_cols, parts = [], [], []
    for k in range(K):
        imgs = plan.images[k]
        is_b = b_index[imgs] >= 0
        local_b = np.flatnonzero(is_b)
        local_b = local_b[np.argsort(b_index[imgs[local_b]], kind="stable")]
        part_b_pos.append(np.concatenate([np.arange(ng), (ng + 6 * b_index[imgs[local_b]][:, None]
                                                          + np.arange(6)).ravel()]).astype(np.int64))
        part_a_cols.append(lay.image_cols(imgs[~is_b]).ravel().astype(np.int64))
        sub = sub_block(block, plan, k)
        st = State(start.io.copy(), start.slopes.copy(), start.R[imgs], start.C[imgs], start.X[plan.points[k]])
        args = (sub, cfg, problem.t0, plan.owned[k], local_b, st)
        parts.append(client.submit(SubBlock, *args, actor=True).result() if client is not None  # type: ignore[attr-defined]
                     else SubBlock(*args))
    depths = np.concatenate(_gather([p.tie_depths() for p in parts]))
    floor = MIN_DEPTH_FRACTION * float(np.median(depths)) if len(depths) else 0.0
    _gather([p.set_depth_floor(floor) for p in parts])
    nb = len(bcols)

    def boundary_system(lam: float | None) -> tuple[sp.csc_matrix, np.ndarray]:
        out = _gather([p.reduce(lam) if lam is not None else p.finish() for p in parts])
        rows, cols, vals = [], [], []
        r = np.zeros(nb)
        for pos, (S_k, r_k) in zip(part_b_pos, out, strict=True):
            rows.append(np.repeat(pos, len(pos)))
            cols.append(np.tile(pos, len(pos)))
            vals.append(S_k.ravel())
            np.add.at(r, pos, r_k)
        S = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(nb, nb))
        return S, r

    cost = sum(_gather([p.linearise() for p in parts]))
    lam = 1e-4
    history = [cost]
    converged = False
    it = 0
    for _ in range(cfg.max_iterations):
        it += 1
        S_b, r_b = boundary_system(lam)
        dc_b = _Factor(S_b).solve(r_b) if nb else np.zeros(0)
        del S_b
        out = _gather([p.try_step(dc_b[pos]) for p, pos in zip(parts, part_b_pos, strict=True)])
        new_cost = sum(c for c, _ in out)
        step_metric = sum(m for _, m in out)
        if np.isfinite(new_cost) and new_cost <= cost:
            rel = (cost - new_cost) / max(cost, 1e-300)
            history.append(new_cost)
            lam = max(lam / 10.0, 1e-12)
            cost = sum(_gather([p.accept() for p in parts]))
            if rel < cfg.tolerance or abs(step_metric) < cfg.step_tolerance**2:
                converged = True
                break
        else:
            _gather([p.reject() for p in parts])
            lam *= 10.0
            if lam > 1e8:
                converged = True
                break
    S_b, _ = boundary_system(None)
    fb = _Factor(S_b) if nb else None
    results = _gather([p.result() for p in parts])
    st = start.copy()
    M = len(block.obs_image)
    res_px, w = np.full((M, 2), np.nan), np.ones(M)
    cost = 0.0
    for k, (st_k, res_k, w_k, cost_k) in enumerate(results):
        st.io, st.slopes = st_k.io, st_k.slopes
        st.R[plan.images[k]], st.C[plan.images[k]] = st_k.R, st_k.C
        st.X[plan.points[k]] = st_k.X
        res_px[plan.observations[k]], w[plan.observations[k]] = res_k, w_k
        cost += cost_k
    n_res = 2 * M + (3 * block.n_images if problem.gnss_sigma is not None else 0) \
        + (3 * block.n_images if problem.att_sigma is not None else 0) + 3 * len(block.control_ids)
    n_unk = lay.n_camera + 3 * lay.n_points
    dof = n_res - n_unk
    if dof <= 0:
        raise AdjustmentError(f"the adjustment has {n_res} observations for {n_unk} unknowns: no redundancy")
    cov = PartitionedInverse(lay.n_camera, fb, bcols, parts, part_b_pos, part_a_cols)
    return Solution(state=st, layout=lay, cov_camera=cov, sigma0=float(np.sqrt(2.0 * cost / dof)), dof=dof,
                    cost=cost, iterations=it, converged=converged, obs_residual_px=res_px, obs_weight=w,
                    t0=problem.t0, history=history)



@dataclasses.dataclass
class PartitionedSolver:
    """A ``solver`` for :func:`aerocal.adjust.bundle.adjust`: blocks of at least ``min_images`` images are solved
    by :func:`solve_partitioned` in ``max(n_workers, ceil(N / max_images))`` sub-blocks (each holds at most
    about ``max_images`` images, bounding a worker's memory), smaller ones by the single solve. ``client``:
    a Dask client whose workers hold the sub-blocks (``None``: in this process). ``runs`` records, per solve,
    the images, sub-blocks and boundary images, for the step's summary."""

    min_images: int
    max_images: int
    n_workers: int = 2
    client: object | None = None
    runs: list[dict] = dataclasses.field(default_factory=list)

    def n_parts(self, n_images: int) -> int:
        if self.min_images <= 0 or n_images < self.min_images:
            return 1
        return max(2, self.n_workers, -(-n_images // max(1, self.max_images)))

    def __call__(self, problem: Problem, start: State) -> Solution:
        K = self.n_parts(problem.b.n_images)
        if K < 2:
            return solve(problem, start)
        sol = solve_partitioned(problem, start, K, self.client)
        cov = sol.cov_camera
        self.runs.append({"images": problem.b.n_images, "sub_blocks": K,
                          "boundary_images": (len(cov.bcols) - problem.layout.n_global) // 6,
                          "iterations": sol.iterations})
        return sol
