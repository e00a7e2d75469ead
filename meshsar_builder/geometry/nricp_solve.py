"""The sparse linear algebra of the NRICP fit (nricp.py): its system's operator, the conjugate
gradients that solve it, their sparse Cholesky preconditioner and the fill-reducing order of its unknowns.
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.sparse as sp
from cvxopt import cholmod, spmatrix
from cvxopt import matrix as cvx_matrix
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


def pcg(matrix, rhs: np.ndarray, start: np.ndarray, precondition, rtol: float, max_iterations: int) -> np.ndarray:
    """Preconditioned conjugate gradients for a symmetric positive definite system, columns at once.

    The residual is tested before each preconditioning, so no solve is spent once it is small
    (a warm start from the previous iteration is often there after one step).
    """
    x = start.copy()
    residual = rhs - matrix @ x
    goal = rtol * np.linalg.norm(rhs, axis=0)
    direction, rz = np.zeros_like(x), np.zeros(x.shape[1])
    for _ in range(max_iterations):
        if np.all(np.linalg.norm(residual, axis=0) <= goal):
            break
        z = precondition(residual)
        rz_new = np.sum(residual * z, axis=0)
        direction = z + np.divide(rz_new, rz, out=np.zeros_like(rz), where=rz > 0) * direction
        rz = rz_new
        k_dir = matrix @ direction
        curvature = np.sum(direction * k_dir, axis=0)
        step = np.divide(rz, curvature, out=np.zeros_like(rz), where=curvature > 0)
        x += step * direction
        residual -= step * k_dir
    return x


def preconditioner(matrix: sp.csr_matrix, order: np.ndarray):
    """r -> A^-1 r for the sparse part A of K = A + beta R^T R: its Cholesky factor (unknowns in `order`, a
    fill-reducing order), from CHOLMOD's supernodal factorisation (through cvxopt).

    The landmark part, rank k but dense over each structure's vertices, is left to the conjugate gradients
    (Woodbury's identity cost k more solves per factorisation than it saved: fits 10-12 % faster without it, at
    1,500 and 6,000 vertices, the same distances to 4 digits). On a demo frame fit's first matrix (19,316
    unknowns, one core) CHOLMOD factorises in 0.20-0.23 s (0.05 s more for its symbolic analysis and the
    conversion) where SuperLU's single-precision LU took 0.80 s: its supernodes are dense blocks for BLAS, and a
    Cholesky factor is half an LU. Its solves (21-28 ms for 3 right-hand sides) are no slower, and in double
    precision they leave a sixth of the LU's residual. A is semi-definite: transforms that move no vertex cost
    nothing (a small fit's matrix has eigenvalues within 1e-12 of zero), and CHOLMOD met a non-positive pivot in
    the last columns of that demo matrix. A diagonal shift of 1e-9 of the largest entry (larger ones where that
    is not enough) keeps the factorisation going: the factor only preconditions the conjugate gradients, which
    still solve K itself.
    """
    n = matrix.shape[0]
    rank = np.empty_like(order)
    rank[order] = np.arange(n)
    entries = matrix.tocoo()
    rows, cols = rank[entries.row], rank[entries.col]
    lower = rows >= cols
    rows, cols, values = rows[lower].astype(np.int64), cols[lower].astype(np.int64), entries.data[lower]
    diagonal = np.where(rows == cols, np.abs(values).max(), 0.0)
    cholmod.options["supernodal"] = 2  # always: CHOLMOD's automatic choice may go simplicial on small systems
    factor = None
    for shift in (1e-9, 1e-6, 1e-3):
        lower_part = spmatrix(cvx_matrix(values + shift * diagonal), cvx_matrix(rows), cvx_matrix(cols), (n, n))
        if factor is None:  # the pattern is the same for every shift; the unknowns are already in order
            factor = cholmod.symbolic(lower_part, p=cvx_matrix(np.arange(n, dtype=np.int64)), uplo="L")
        try:
            cholmod.numeric(lower_part, factor)
            break
        except ArithmeticError:
            continue
    else:
        raise ArithmeticError(f"NRICP preconditioner: the system ({n} unknowns) is not positive definite")

    def solve(residual: np.ndarray) -> np.ndarray:
        ordered = cvx_matrix(np.asfortranarray(residual[order], dtype=np.float64))
        cholmod.solve(factor, ordered)
        solved = np.empty_like(residual)
        solved[order] = np.asarray(ordered).reshape(residual.shape)
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
