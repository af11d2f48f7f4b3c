"""The optimal-step NICP linear system (Amberg et al. 2007) and its sparse Cholesky solve.

Unknowns: one 3×4 affine transform per template vertex, stacked as ``X`` (4n × 3); the
deformed vertex i is ``v̂_iᵀ X_i`` with ``v̂_i = ((v_i - c) / s, 1)`` (the template centred
and scaled to unit RMS radius, so that the translation weight ``gamma`` is unit-free).

Energy (all point terms share one form, so they add up per vertex)::

    E(X) = alpha² Σ_edges ||(X_i - X_j)ᵀ G||²  +  Σ_i w_i ||v̂_iᵀ X_i - u_i||²  +  eps ||X - X0||²

with ``G = diag(1, 1, 1, gamma)``, ``w_i`` the summed weights of the cloud, landmark, ear and
edge targets of vertex i and ``u_i`` their weighted mean target. The normal equations

    (alpha² (MᵀM ⊗ G²) + Dᵀ W D + eps I) X = Dᵀ W U + eps X0

have a fixed sparsity pattern (the vertex graph Laplacian ⊗ diag plus 4×4 diagonal blocks),
so the symbolic Cholesky analysis is done once per fit and only the numeric factorisation
is redone when the weights change; the three coordinates are solved at once (3 right-hand
sides). CHOLMOD's supernodal factorisation (from cvxopt's self-contained wheel) takes ~1 s
for the 53k-vertex template (213k unknowns) on one core; scipy's SuperLU, the fallback,
~7 s.
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

# Imported where used: cvxopt (CHOLMOD) is optional: without it the solves fall back to scipy.

__all__ = ["NicpSystem", "edges_of", "have_cholmod"]


def edges_of(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2) of a triangle mesh, smaller id first, in lexicographic
    order (read-only: the fold checks ask for the template's edges many times a fit, so they
    are worked out once per mesh)."""
    f = np.ascontiguousarray(faces, np.int64)
    return _edges_of(f.tobytes(), len(f))


@functools.lru_cache(maxsize=4)
def _edges_of(faces_bytes: bytes, n_faces: int) -> np.ndarray:
    f = np.frombuffer(faces_bytes, np.int64).reshape(n_faces, 3)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e.sort(axis=1)
    if len(e):
        # One integer key per edge: np.unique over rows is six times slower.
        n = int(e.max()) + 1
        keys = np.unique(e[:, 0] * n + e[:, 1])
        e = np.column_stack([keys // n, keys % n])
    e.flags.writeable = False
    return e


def have_cholmod() -> bool:
    try:
        import cvxopt.cholmod  # noqa: F401
    except ImportError:
        return False
    return True


class NicpSystem:
    """The NICP normal equations of one template, ready for repeated weighted solves.

    ``solve(alpha, weights, targets)`` returns the deformed vertices (mm); ``weights`` (n,)
    and ``targets`` (n, 3) are the per-vertex summed weight and weighted-mean target. The
    factorisation is kept and reused while ``alpha`` and ``weights`` stay the same.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, gamma: float = 1.0,
                 solver: str = "auto", damping: float = 1e-6):
        v = np.asarray(vertices, float)
        self.n = n = len(v)
        self.centre = v.mean(0)
        self.scale = float(np.sqrt(np.mean(np.sum((v - self.centre) ** 2, axis=1)))) or 1.0
        self.vh = np.c_[(v - self.centre) / self.scale, np.ones(n)]  # (n, 4)
        self.gamma = float(gamma)
        self.damping = float(damping)
        if solver == "auto":
            solver = "cholmod" if have_cholmod() else "scipy"
        if solver == "cholmod" and not have_cholmod():
            raise ImportError("solver 'cholmod' needs cvxopt (pip install cvxopt)")
        self.solver = solver
        edges = edges_of(faces)
        # Graph Laplacian MᵀM of the node-arc incidence matrix M.
        deg = np.bincount(edges.ravel(), minlength=n).astype(float)
        # Lower-triangular pattern of the 4n × 4n matrix: Laplacian off-diagonals ⊗ diag(4),
        # plus the full lower 4×4 block on each vertex.
        i4 = np.arange(4)
        lo, hi = edges[:, 1], edges[:, 0]  # row > column in the lower triangle
        off_r = (4 * lo[:, None] + i4).ravel()
        off_c = (4 * hi[:, None] + i4).ravel()
        br, bc = np.tril_indices(4)
        blk_r = (4 * np.arange(n)[:, None] + br).ravel()
        blk_c = (4 * np.arange(n)[:, None] + bc).ravel()
        rows = np.r_[off_r, blk_r]
        cols = np.r_[off_c, blk_c]
        # CSC order (column-major, rows sorted within a column), remembered as a permutation.
        order = np.lexsort((rows, cols))
        self._rows, self._cols = rows[order].astype(np.int64), cols[order].astype(np.int64)
        self._n_off = len(off_r)
        inv = np.empty_like(order)
        inv[order] = np.arange(len(order))
        self._pos_off = inv[: self._n_off]
        self._pos_blk = inv[self._n_off:]
        g2 = np.array([1.0, 1.0, 1.0, self.gamma ** 2])
        self._stiff_off = -np.repeat(g2[None, :], len(edges), axis=0).ravel()  # × alpha²
        diag_stiff = (deg[:, None] * g2[None, :])  # (n, 4)
        # stiffness on the 4×4 blocks (diagonal entries only), in tril order
        is_diag = br == bc
        self._stiff_blk = np.zeros((n, len(br)))
        self._stiff_blk[:, is_diag] = diag_stiff[:, br[is_diag]]
        self._outer = self.vh[:, br] * self.vh[:, bc]  # (n, 10): v̂ v̂ᵀ in tril order
        self._is_diag_blk = np.tile(is_diag, n)
        self._symbolic = None
        self._factor = None
        self._key = None
        self.factorizations = 0
        self.X = np.tile(np.vstack([np.eye(3), np.zeros((1, 3))]), (n, 1))  # identity

    # -- matrix --------------------------------------------------------------------------

    def _values(self, alpha: float, weights: np.ndarray) -> np.ndarray:
        vals = np.empty(len(self._rows))
        vals[self._pos_off] = alpha ** 2 * self._stiff_off
        blk = alpha ** 2 * self._stiff_blk + weights[:, None] * self._outer
        blk = blk.ravel()
        blk[self._is_diag_blk] += self.damping
        vals[self._pos_blk] = blk
        return vals

    def matrix(self, alpha: float, weights: np.ndarray) -> sp.csc_matrix:
        """The full symmetric 4n × 4n normal-equation matrix (for tests and inspection)."""
        lower = sp.csc_matrix((self._values(alpha, weights), (self._rows, self._cols)),
                              shape=(4 * self.n, 4 * self.n))
        return (lower + sp.tril(lower, -1).T).tocsc()

    def _factorize(self, alpha: float, weights: np.ndarray):
        vals = self._values(alpha, weights)
        self.factorizations += 1
        if self.solver == "cholmod":
            import cvxopt
            import cvxopt.cholmod as cholmod

            cholmod.options["supernodal"] = 2
            cholmod.options["postorder"] = True
            A = cvxopt.spmatrix(vals, self._rows, self._cols, (4 * self.n, 4 * self.n))
            if self._symbolic is None:
                self._symbolic = cholmod.symbolic(A, uplo="L")
            cholmod.numeric(A, self._symbolic)
            self._factor = ("cholmod", self._symbolic)
        else:
            A = self.matrix(alpha, weights)
            lu = splu(A, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
            self._factor = ("splu", lu)

    def _solve(self, rhs: np.ndarray) -> np.ndarray:
        kind, F = self._factor
        if kind == "cholmod":
            import cvxopt
            import cvxopt.cholmod as cholmod

            B = cvxopt.matrix(np.asfortranarray(rhs))
            cholmod.solve(F, B, sys=0)
            return np.array(B)
        return F.solve(rhs)

    # -- solve ---------------------------------------------------------------------------

    def normalise(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, float) - self.centre) / self.scale

    def deformed(self, X: np.ndarray | None = None) -> np.ndarray:
        """Deformed vertices (mm) of the affine stack ``X`` (default: the current one)."""
        X = self.X if X is None else X
        p = np.einsum("nk,nkc->nc", self.vh, X.reshape(self.n, 4, 3))
        return p * self.scale + self.centre

    def solve(self, alpha: float, weights: np.ndarray, targets: np.ndarray,
              refactor: bool | None = None) -> np.ndarray:
        """One optimal step: minimise E for stiffness ``alpha`` and the given targets (mm).

        The factorisation is redone when ``alpha`` or ``weights`` changed (or ``refactor``).
        """
        w = np.asarray(weights, float)
        u = self.normalise(targets)
        u = np.where(w[:, None] > 0, u, 0.0)
        key = (float(alpha), w.tobytes())
        if refactor or (refactor is None and key != self._key) or self._factor is None:
            self._factorize(alpha, w)
            self._key = key
        rhs = (self.vh[:, :, None] * (w[:, None] * u)[:, None, :]).reshape(4 * self.n, 3)
        rhs = rhs + self.damping * self.X
        X = self._solve(rhs)
        self.X = X
        return self.deformed(X)
