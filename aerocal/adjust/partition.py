"""Partitioned bundle adjustment: sub-blocks on the Dask workers, one reduced camera system.

The block's images are cut into spatially compact sub-blocks (recursive median bisection of the projection
centres); every tie point (and control GCP) goes to the sub-block holding most of its observations, with all
its observations, and each image's GNSS / attitude priors to the sub-block the image was cut into. An image
observed in several sub-blocks is a *boundary* image. Each Levenberg-Marquardt iteration then runs as in
:func:`aerocal.adjust.solver.solve`, split:

1. every sub-block linearises its observations and eliminates its points, giving its share of the reduced
   camera system (:func:`~aerocal.adjust.solver.schur_complement`; a boundary image's blocks are summed
   from its sub-blocks' shares);
2. the shares are summed into the whole block's sparse reduced camera system and solved (one sparse
   factorisation, as in the single adjustment);
3. every sub-block back-substitutes its points, tries the step and returns its share of the cost.

This is the single adjustment's normal equations, not a consensus between separately adjusted sub-blocks: the
steps, the damping and the stopping rule are the same, so the result is the single adjustment's to rounding
(``tests/test_adjust_partition.py``), covariances included. What changes is where the work and the memory
are: the per-observation blocks (the bulk: ~1.5 kB per observation) and the Schur sums over point tracks
(most of an iteration's time) live in the sub-blocks, on the Dask workers when a client is given (one
:class:`SubBlock` actor each, in parallel); the caller holds the reduced camera system (~36 numbers per pair
of images sharing points) and the block's arrays.

Summing the sub-blocks' sparse shares was measured against eliminating each sub-block's interior images too and
solving only the boundary images' dense system (the textbook nested dissection), whose dense interior-boundary
solves made it slower than the single adjustment (``benchmarks/partition_bench.py``; the figures:
``benchmarks/history/engine_measurements.md``).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import scipy.sparse as sp

from aerocal.adjust.problem import AdjustConfig, Block
from aerocal.adjust.solver import (
    MIN_DEPTH_FRACTION,
    BundleProblem,
    ReducedSolver,
    Solution,
    SparseInverse,
    State,
    levenberg_marquardt,
    redundancy,
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
        laser_range=None if block.laser_range is None else block.laser_range[imgs],
    )


class SubBlock:
    """One sub-block of a partitioned adjustment: its observations, its state and its last linearisation.

    Stateful (a Dask actor when the adjustment runs on a cluster): it keeps its current and candidate state
    and its last Jacobian between the calls of :func:`solve_partitioned`. Camera-side vectors handed in and
    out are in the sub-block's local layout (``[globals | 6 per local image]``).
    """

    def __init__(self, block: Block, config: AdjustConfig, t0: float, owned: np.ndarray, start: State) -> None:
        self.problem = BundleProblem(block, config, t0, check_datum=False)
        self.problem.prior_weight = np.asarray(owned, dtype=float)
        self.state = start
        self.candidate: State | None = None
        self.Hpp: np.ndarray | None = None
        self.candidate_Hpp: np.ndarray | None = None  # the candidate's linearisation (see :meth:`try_step`)
        self.candidate_cost = float("nan")
        self.step_parts: tuple | None = None

    def tie_depths(self) -> np.ndarray:
        """Depths (metres, > 0) of the tie observations at the start state: the whole block's median sets the
        floor below which a point is held (:meth:`BundleProblem.hold_close_points`)."""
        b, st = self.problem.b, self.state
        i, j = b.obs_image[b.obs_is_tie], b.obs_point[b.obs_is_tie]
        z = np.einsum("mk,mk->m", st.R[i][:, 2], st.X[j] - st.C[i])
        return z[z > 0]

    def set_depth_floor(self, floor: float) -> None:
        self.problem.depth_floor = float(floor)

    def linearise(self) -> float:
        """Jacobian at the current state; returns this sub-block's share of the cost."""
        cost, _, _, _, _, _, self.Hpp = self.problem.residuals(self.state, jac=True, sparse=False)
        return cost

    def reduce(self, lam: float) -> tuple[sp.coo_matrix, np.ndarray]:
        """This sub-block's share of the reduced camera system and its right-hand side (local layout), its
        points eliminated, with damping ``lam``."""
        S, rhs, Hpp_inv, Hcp, gp = schur_complement(None, None, self.Hpp, None, lam, self.problem.blocks)
        self.step_parts = (rhs, Hpp_inv, Hcp, gp)
        return sp.coo_matrix(S), rhs

    def try_step(self, dc: np.ndarray) -> tuple[float, float]:
        """Back-substitute the camera step ``dc`` (local layout) into the points, form the candidate state and
        return ``(cost, dc . rhs)``: its share of the candidate's cost and of the step's metric."""
        rhs, Hpp_inv, Hcp, gp = self.step_parts
        dp = -np.einsum("pij,pj->pi", Hpp_inv, (gp + Hcp.T @ dc).reshape(-1, 3)).ravel()
        metric = float(dc @ rhs)
        self.step_parts = None  # the per-observation operator goes before the next residuals
        cand = self.problem.apply(self.state, dc, dp)
        self.candidate = cand
        # linearised at the candidate at once, as :func:`aerocal.adjust.solver.solve` does: an accepted step
        # then needs no second projection; a rejected one re-linearises at the current state. Points brought
        # too close to a camera are found from that projection's depths, put back and linearised again
        self.candidate_cost, _, _, _, _, _, self.candidate_Hpp = self.problem.residuals(cand, jac=True, sparse=False)
        if self.problem.hold_close_points(self.state, cand, self.problem.last_depth):
            self.candidate_Hpp = None
            self.candidate_cost, _, _, _, _, _, self.candidate_Hpp = self.problem.residuals(cand, jac=True,
                                                                                            sparse=False)
        return self.candidate_cost, metric

    def accept(self) -> float:
        """Move to the candidate (linearised there already); returns the cost share."""
        self.state, self.Hpp = self.candidate, self.candidate_Hpp
        self.candidate, self.candidate_Hpp = None, None
        return self.candidate_cost

    def reject(self) -> None:
        self.candidate, self.candidate_Hpp = None, None
        self.linearise()

    def finish(self) -> tuple[sp.coo_matrix, np.ndarray]:
        """The undamped reduced system at the solution (for the covariances); frees the linearisation."""
        out = self.reduce(0.0)
        self.step_parts, self.Hpp = None, None
        self.problem.release()
        return out

    def result(self) -> tuple[State, np.ndarray, np.ndarray, float]:
        """``(state, res_px, w, cost)`` at the solution: the local state, the observations' residuals (pixels)
        and robust weights in the sub-block's observation order, and its share of the cost."""
        cost, res_px, w = self.problem.residuals(self.state, jac=False)
        return self.state, res_px, w, cost


def _gather(calls: list) -> list:
    """The values of calls made on sub-blocks: Dask actor futures are waited for, plain values pass."""
    return [c.result() if hasattr(c, "result") else c for c in calls]


def solve_partitioned(problem: BundleProblem, start: State, plan: Plan | int, client: object | None = None) -> Solution:
    """:func:`aerocal.adjust.solver.solve` with the block cut by ``plan`` (or into that many sub-blocks, see the
    module), on ``client``'s Dask workers (one actor per sub-block) or, without a client, in this process.

    The returned :class:`Solution` is the single adjustment's: same state, sigma0, dof, iterations and
    covariances."""
    cfg, block, lay = problem.cfg, problem.b, problem.layout
    ng = lay.n_global
    if not isinstance(plan, Plan):
        plan = plan_partition(block, start.C[:, :2], plan)
    # each sub-block's local camera columns in the whole block's layout
    cols = [np.concatenate([np.arange(ng), lay.image_cols(imgs).ravel()]).astype(np.int64) for imgs in plan.images]
    parts = []
    # sub-blocks dealt to the workers in turn: left to the scheduler, two actors can land on one worker
    workers = sorted(client.scheduler_info()["workers"]) if client is not None else []  # type: ignore[attr-defined]
    for k, imgs in enumerate(plan.images):
        st = State(start.io.copy(), start.slopes.copy(), start.R[imgs], start.C[imgs], start.X[plan.points[k]])
        sub = sub_block(block, plan, k)
        if client is None:
            parts.append(SubBlock(sub, cfg, problem.t0, plan.owned[k], st))
            continue
        # the arrays go to the worker as data, not inside the task graph (Dask warns past a few MB)
        where = [workers[k % len(workers)]]
        sub_f, st_f = client.scatter([sub, st], workers=where)  # type: ignore[attr-defined]
        parts.append(client.submit(SubBlock, sub_f, cfg, problem.t0, plan.owned[k], st_f, actor=True,  # type: ignore[attr-defined]
                                   workers=where, allow_other_workers=False))
        del sub_f, st_f
    parts = [p.result() if client is not None else p for p in parts]
    depths = np.concatenate(_gather([p.tie_depths() for p in parts]))
    floor = MIN_DEPTH_FRACTION * float(np.median(depths)) if len(depths) else 0.0
    _gather([p.set_depth_floor(floor) for p in parts])
    n = lay.n_camera

    def reduced_system(lam: float | None) -> tuple[sp.csc_matrix, np.ndarray]:
        """The whole block's reduced camera system: the sub-blocks' shares summed (``lam`` None: undamped, and
        the sub-blocks free their linearisation)."""
        out = _gather([p.reduce(lam) if lam is not None else p.finish() for p in parts])
        rows, cols_, vals = [], [], []
        r = np.zeros(n)
        for c, (S_k, r_k) in zip(cols, out, strict=True):
            rows.append(c[S_k.row])
            cols_.append(c[S_k.col])
            vals.append(S_k.data)
            r[c] += r_k  # a sub-block's columns are distinct
        S = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols_))), shape=(n, n))
        return S, r

    reduced = ReducedSolver(n_global=ng)

    def step(lam: float) -> tuple[float, float]:
        S, rhs = reduced_system(lam)
        dc = reduced.solve(S, rhs)
        del S
        out = _gather([p.try_step(dc[c]) for p, c in zip(parts, cols, strict=True)])
        return sum(c for c, _ in out), sum(m for _, m in out)

    _, it, converged, history = levenberg_marquardt(
        cfg, sum(_gather([p.linearise() for p in parts])), step,
        accept=lambda: sum(_gather([p.accept() for p in parts])), reject=lambda: _gather([p.reject() for p in parts]))
    S, _ = reduced_system(None)
    cov = SparseInverse(S, ng, earlier=reduced.spend())
    del S
    results = _gather([p.result() for p in parts])
    parts.clear()  # the actors are released with their last reference
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
    dof = redundancy(problem)
    return Solution(state=st, layout=lay, cov_camera=cov, sigma0=float(np.sqrt(2.0 * cost / dof)), dof=dof,
                    cost=cost, iterations=it, converged=converged, obs_residual_px=res_px, obs_weight=w,
                    t0=problem.t0, history=history)


@dataclasses.dataclass
class PartitionedSolver:
    """A ``solver`` for :func:`aerocal.adjust.bundle.adjust`: blocks of at least ``min_images`` images are solved
    by :func:`solve_partitioned` in ``max(2, n_workers, ceil(N / max_images))`` sub-blocks (each holds at most
    about ``max_images`` images, bounding a worker's memory), smaller ones by the single solve. ``client``:
    a Dask client whose workers hold the sub-blocks (``None``: in this process). A worker lost during a solve
    (killed, out of memory) takes its sub-blocks with it: the solve starts again from the same state on the
    workers left (in this process when none is), with the same answer; any other failure is raised. ``runs``
    records, per solve, the images, sub-blocks, boundary images and any restart, for the step's summary."""

    min_images: int
    max_images: int
    n_workers: int = 2
    client: object | None = None
    runs: list[dict] = dataclasses.field(default_factory=list)

    def n_parts(self, n_images: int) -> int:
        if self.min_images <= 0 or n_images < self.min_images:
            return 1
        return max(2, self.n_workers, -(-n_images // max(1, self.max_images)))

    def __call__(self, problem: BundleProblem, start: State) -> Solution:
        K = self.n_parts(problem.b.n_images)
        if K < 2:
            return solve(problem, start)
        plan = plan_partition(problem.b, start.C[:, :2], K)
        before = self._workers()
        restarted = None
        try:
            sol = solve_partitioned(problem, start, plan, self.client)
        except Exception as exc:
            left = self._workers_after_loss(before)
            if left is None:
                raise
            # a worker holding sub-blocks died (its actors and scattered data are gone): the same solve from the
            # same start on the workers left, or in this process when none is; the answer is the same
            where = f"on {len(left)} worker(s)" if left else "in the calling process (no worker left)"
            why = " ".join(str(exc).split())[:100]
            restarted = f"a worker was lost ({type(exc).__name__}: {why}); solved again {where}"
            sol = solve_partitioned(problem, start, plan, self.client if left else None)
        self.runs.append({"images": problem.b.n_images, "sub_blocks": K, "boundary_images": len(plan.boundary),
                          "iterations": sol.iterations, "restarted": restarted})
        return sol

    def _workers(self) -> set[str]:
        """The addresses of the client's workers (empty without a client)."""
        if self.client is None:
            return set()
        return set(self.client.scheduler_info()["workers"])  # type: ignore[attr-defined]

    def _workers_after_loss(self, before: set[str], wait_s: float = 10.0) -> set[str] | None:
        """After a failed solve on the cluster: the workers left when one of ``before`` is gone, ``None`` when all
        are still there (the failure is not the cluster's, and is raised). The scheduler drops a killed worker
        when its connection closes; up to ``wait_s`` seconds are given for that."""
        if self.client is None:
            return None
        deadline = time.monotonic() + wait_s
        while True:
            try:
                now = self._workers()
            except Exception:  # the scheduler itself is gone: nothing to retry on but this process
                return set()
            if before - now:
                return now
            if time.monotonic() > deadline:
                return None
            time.sleep(0.2)
