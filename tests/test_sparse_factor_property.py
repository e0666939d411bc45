"""Property: the sparse factor's symbolic analysis (``kamino.warp_backend.linear_solve_pattern.symbolic``:
minimum-degree
order, fill pattern, update lists) factorises what a dense Cholesky factorises, on random systems of redundant planar
loops.

A system is ``D~ = P J M^-1 J^T P + sigma I`` of random bodies joined by hinges about world y (a random tree plus
random loop-closing hinges): 5 rows per hinge, three of each loop's rows redundant in 3-D, so the proximal shift
``sigma = eta + rho_free`` (1.01e-4 at the defaults) is all that keeps the system positive definite. The factor is
computed entry by entry through the update lists, as the device kernel ``factor_fixed_rows`` does:

- in float64 it equals the dense Cholesky factor of the permuted matrix to rounding (a missing fill entry or update
  would show here);
- in float32 its solve is as accurate as a dense float32 Cholesky solve of the same matrix (both against a float64
  solve), within a factor of 10, or within ``10 cond eps`` where the dense one is luckier.

``L_f^-1`` on its pattern (``inverse_pattern``: a column's path up the elimination tree), computed in the device
kernel's order (``solver_lanes.invert_func``): in float64 it is the dense inverse with nothing outside the pattern,
and in float32 the solve by its products is as accurate as the dense float32 Cholesky solve, by the same measure.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

from kamino.warp_backend.linear_solve_pattern import inverse_pattern, symbolic

SIGMA = 1e-5 + 1e-4  # SolverConfig's eta + rho_free


def _skew(r: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])


def _hinge_rows(com: np.ndarray, parent: int, child: int, anchor: np.ndarray, nb: int) -> np.ndarray:
    """The 5 rows of a hinge about world y at ``anchor``: the anchor's relative velocity (3) and the relative angular
    velocity about x and z (2), over the bodies' twists ``(v, w)`` at their CoMs (``-1``: the world)."""
    J = np.zeros((5, 6 * nb))
    for b, sign in ((child, 1.0), (parent, -1.0)):
        if b < 0:
            continue
        J[:3, 6 * b:6 * b + 3] = sign * np.eye(3)
        J[:3, 6 * b + 3:6 * b + 6] = -sign * _skew(anchor - com[b])
        J[3, 6 * b + 3] = sign
        J[4, 6 * b + 5] = sign
    return J


@st.composite
def planar_loops(draw):
    """``(D~, bodies)``: a random planar mechanism's scaled Delassus matrix with the proximal shift, and each row's
    moving bodies ``[n, 2]``."""
    nb = draw(st.integers(3, 14))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    com = np.zeros((nb, 3))
    com[:, [0, 2]] = rng.uniform(-0.5, 0.5, (nb, 2))
    joints = [(draw(st.integers(-1, b - 1)), b) for b in range(nb)]  # a tree (the first body on the world)
    n_loops = draw(st.integers(1, max(1, nb // 2)))
    for _ in range(n_loops):
        a, b = sorted(rng.choice(np.arange(-1, nb), 2, replace=False))
        joints.append((int(a), int(b)))
    rows, bodies = [], []
    for parent, child in joints:
        anchor = np.zeros(3)
        anchor[[0, 2]] = rng.uniform(-0.5, 0.5, 2)
        rows.append(_hinge_rows(com, parent, child, anchor, nb))
        bodies += [[parent, child]] * 5
    J = np.concatenate(rows)
    mass = 10.0 ** rng.uniform(-1.5, 1.0, nb)  # light links and heavy bodies: a mass ratio up to ~300
    inertia = mass[:, None] * 10.0 ** rng.uniform(-3.0, -1.0, (nb, 3))
    inv_m = np.concatenate([np.concatenate([np.full(3, 1.0 / m), 1.0 / i]) for m, i in zip(mass, inertia, strict=True)])
    D = (J * inv_m) @ J.T
    P = 1.0 / np.sqrt(np.diag(D))
    return P[:, None] * D * P[None, :] + SIGMA * np.eye(len(D)), np.asarray(bodies, np.int64)


def _factor(A: np.ndarray, sym, dtype) -> np.ndarray:
    """The sparse factor of ``A`` (rows permuted to positions) entry by entry through ``sym``'s update lists, in
    ``dtype`` (the device kernel's order of operations)."""
    Ap = A[np.ix_(sym.perm, sym.perm)].astype(dtype)
    val = Ap[sym.row, sym.col].copy()
    for k in range(sym.nnz):
        s = val[k]
        for u in range(sym.upd_ptr[k], sym.upd_ptr[k + 1]):
            s = s - val[sym.upd_a[u]] * val[sym.upd_b[u]]
        val[k] = np.sqrt(s) if sym.div[k] == k else s / val[sym.div[k]]
    L = np.zeros(A.shape, dtype)
    L[sym.row, sym.col] = val
    return L


def _solve32(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    y = scipy.linalg.solve_triangular(L, b.astype(np.float32), lower=True)
    return scipy.linalg.solve_triangular(L.T, y, lower=False).astype(np.float64)


@settings(max_examples=25, deadline=None)
@given(planar_loops())
def test_sparse_factor_solves_what_the_dense_factor_solves(system):
    A, bodies = system
    sym = symbolic(bodies)
    assert sorted(sym.perm) == list(range(len(A)))
    # float64: the factor through the update lists is the dense Cholesky factor of the permuted matrix
    L64 = _factor(A, sym, np.float64)
    exact = np.linalg.cholesky(A[np.ix_(sym.perm, sym.perm)])
    np.testing.assert_allclose(L64, exact, atol=1e-9 * np.abs(exact).max())
    # float32: as accurate as the dense float32 factor of the same matrix
    b = np.random.default_rng(len(A)).standard_normal(len(A))
    x = np.linalg.solve(A, b)
    xs = np.empty_like(x)
    xs[sym.perm] = _solve32(_factor(A, sym, np.float32), b[sym.perm])
    xd = _solve32(np.linalg.cholesky(A.astype(np.float32)), b)
    err = lambda y: np.linalg.norm(y - x) / np.linalg.norm(x)  # noqa: E731
    ev = np.linalg.eigvalsh(A)
    floor = 10.0 * (ev[-1] / ev[0]) * np.finfo(np.float32).eps
    assert err(xs) <= max(10.0 * err(xd), floor), (err(xs), err(xd), floor)


def _inverse(L: np.ndarray, sym, dtype) -> np.ndarray:
    """``L^-1`` through ``inverse_pattern(sym)`` in ``dtype``, position by position as ``solver_lanes.invert_func``:
    the columns of the subtree of ``q`` divide their entry ``q`` by ``L_qq``, then column ``q`` of ``L`` updates the
    entries above it on their paths (slot ``+ cup``)."""
    ip = inverse_pattern(sym)
    n = len(L)
    inv = np.zeros(ip.nnz, dtype)
    inv[ip.icol_ptr[:-1]] = 1.0
    one = dtype(1.0)
    for q in range(n):
        for k in range(ip.irow_ptr[q], ip.irow_ptr[q + 1]):
            slot = ip.irow_slot[k]
            inv[slot] = inv[slot] * (one / L[q, q])
            for j in range(sym.cptr[q], sym.cptr[q + 1]):
                e = sym.cent[j]
                inv[slot + ip.cup[j]] -= L[sym.row[e], q] * inv[slot]
    pos = np.empty(n, np.int64)
    pos[sym.perm] = np.arange(n)
    out = np.zeros((n, n), dtype)
    out[pos[ip.ipath_row], np.repeat(np.arange(n), np.diff(ip.icol_ptr))] = inv
    return out


@settings(max_examples=25, deadline=None)
@given(planar_loops())
def test_the_inverse_factor_solves_what_the_dense_factor_solves(system):
    A, bodies = system
    sym = symbolic(bodies)
    L64 = _factor(A, sym, np.float64)
    exact = np.linalg.inv(L64)
    np.testing.assert_allclose(_inverse(L64, sym, np.float64), exact, atol=1e-9 * np.abs(exact).max())
    b = np.random.default_rng(len(A)).standard_normal(len(A))
    x = np.linalg.solve(A, b)
    Li = _inverse(_factor(A, sym, np.float32), sym, np.float32)
    xs = np.empty_like(x)
    xs[sym.perm] = Li.T @ (Li @ b[sym.perm].astype(np.float32))
    xd = _solve32(np.linalg.cholesky(A.astype(np.float32)), b)
    err = lambda y: np.linalg.norm(y - x) / np.linalg.norm(x)  # noqa: E731
    ev = np.linalg.eigvalsh(A)
    floor = 10.0 * (ev[-1] / ev[0]) * np.finfo(np.float32).eps
    assert err(xs) <= max(10.0 * err(xd), floor), (err(xs), err(xd), floor)
