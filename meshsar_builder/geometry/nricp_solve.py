"""The sparse linear algebra of the NRICP fit (nricp.py): its system's operator, the conjugate
gradients that solve it, their sparse-LU preconditioner and the fill-reducing order of its unknowns.
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from meshsar_builder.geometry.measures import unique_edges


class Operator:
    """K = A + beta R^T R without forming R^T R (dense over a structure's vertices): K @ x."""

    def __init__(self, matrix: sp.csr_matrix, rows: sp.csr_matrix | None, beta: float):
        self.matrix, self.rows, self.beta = matrix, rows, beta

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        product = self.matrix @ x
        if self.rows is not None:
            product += self.beta * (self.rows.T @ (self.rows @ x))
        return product


def pcg(matrix, rhs: np.ndarray, start: np.ndarray, precondition, rtol: float,
        max_iterations: int) -> tuple[np.ndarray, bool]:
    """Preconditioned conjugate gradients for a symmetric positive definite system, columns at once.

    The residual is tested before each preconditioning, so no solve is spent once it is small
    (a warm start from the previous iteration is often there after one step).
    Returns the solution and whether every column reached rtol.
    """
    x = start.copy()
    residual = rhs - matrix @ x
    goal = rtol * np.linalg.norm(rhs, axis=0)
    direction, rz = np.zeros_like(x), np.zeros(x.shape[1])
    for _ in range(max_iterations):
        if np.all(np.linalg.norm(residual, axis=0) <= goal):
            return x, True
        z = precondition(residual)
        rz_new = np.sum(residual * z, axis=0)
        direction = z + np.divide(rz_new, rz, out=np.zeros_like(rz), where=rz > 0) * direction
        rz = rz_new
        k_dir = matrix @ direction
        curvature = np.sum(direction * k_dir, axis=0)
        step = np.divide(rz, curvature, out=np.zeros_like(rz), where=curvature > 0)
        x += step * direction
        residual -= step * k_dir
    return x, bool(np.all(np.linalg.norm(residual, axis=0) <= goal))


class CarriedSolver:
    """The conjugate gradients of one fit, with an LU preconditioner carried across its stiffness steps
    while that still pays.

    A factorisation is most of a fit's time (two of a frame fit's 2.2 s on the demo). Within a step the
    matches change the matrix, and the step's own factor still converges in 1-3 iterations. A factor carried
    to the next step (another stiffness) gets `carried_iterations`; a solve that needs more is done again
    from its start on its own matrix's factorisation, as without carrying, and the fit carries no factor
    after that. A frame fit's two soft steps start near the answer and share one factor; a registration's
    steps move the fit far, so its first carried solve fails and it stops carrying.
    factorise : csr matrix -> its preconditioner (r -> A^-1 r).
    """

    def __init__(self, factorise, carried_iterations: int, rtol: float, max_iterations: int):
        self.factorise, self.carried_iterations = factorise, carried_iterations
        self.rtol, self.max_iterations = rtol, max_iterations
        self.precondition, self.current, self.carrying, self.factorisations = None, False, carried_iterations > 0, 0

    def new_matrix(self, carry: bool) -> None:
        """The stiffness changed: the factor in hand is carried (carry, while carrying pays) or dropped."""
        self.current = False
        if not (carry and self.carrying):
            self.precondition = None

    def __call__(self, operator: Operator, rhs: np.ndarray, start: np.ndarray) -> np.ndarray:
        if self.precondition is not None and not self.current:
            x, done = pcg(operator, rhs, start, self.precondition, self.rtol, self.carried_iterations)
            if done:
                return x
            self.carrying = False  # and start again: a poor preconditioner's iterates drift where K is weak
        if not self.current:
            self.precondition, self.current = self.factorise(operator.matrix), True
            self.factorisations += 1
        return pcg(operator, rhs, start, self.precondition, self.rtol, self.max_iterations)[0]


def preconditioner(matrix: sp.csr_matrix, order: np.ndarray):
    """r -> A^-1 r for the sparse part A of K = A + beta R^T R: its LU (unknowns in `order`, a fill-reducing order).

    The landmark part, rank k but dense over each structure's vertices, is left to the conjugate gradients
    (Woodbury's identity cost k more solves per factorisation than it saved: fits 10-12 % faster without it, at
    1,500 and 6,000 vertices, the same distances to 4 digits). The LU is in single precision: it only
    preconditions the conjugate gradients, which run in double and stop at a relative residual of 3e-4, 3 orders
    above its rounding (two demo whole-heart fits: 15-19 % faster, the same figures). SuperLU's own supernode
    relaxation and panel size: relaxed to 80 columns in panels of 20, the factorisation was 10-15 % faster, but
    SuperLU then wrote past its buffers (glibc's checks abort within 25 factorisations of a small
    ellipsoid's fits; 30 and 40 columns as well), which crashed test processes at random.
    """
    factor = splu(matrix[order][:, order].tocsc().astype(np.float32), permc_spec="NATURAL", diag_pivot_thresh=0.0,
                  options={"SymmetricMode": True})

    def solve(residual: np.ndarray) -> np.ndarray:
        solved = np.empty_like(residual)
        solved[order] = factor.solve(residual[order].astype(np.float32))
        return solved

    return solve


@functools.lru_cache(maxsize=8)
def unknowns_order(n: int, faces: bytes) -> np.ndarray:
    """(4n,) the factorisation's order of the unknowns of a template with these faces ((m, 3) int64 as bytes).

    SuperLU's minimum degree order of the vertices, of a diagonally dominant matrix with the stiffness's
    pattern (vertices that share a ring: (I + adjacency)^2; only the order is used), each vertex's 4 unknowns
    kept together: it fills in a quarter less than ordering the 4n unknowns one by one, and factorises in
    half the time. It depends on the faces alone, so the fits of one process (every subject on one template,
    every frame of a subject) find it once: it was 2 % of a frame fit.
    """
    edges = unique_edges(np.frombuffer(faces, dtype=np.int64).reshape(-1, 3))
    ring = sp.csr_matrix((np.ones(2 * len(edges)), (edges.T.ravel(), edges[:, ::-1].T.ravel())), shape=(n, n))
    ring = ring + sp.eye(n)
    pattern = ring @ ring + n * sp.eye(n)
    vertices = np.argsort(splu(pattern.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                               options={"SymmetricMode": True}).perm_c)
    order = (4 * vertices[:, None] + np.arange(4)).ravel()
    order.flags.writeable = False  # shared by every system on these faces
    return order
