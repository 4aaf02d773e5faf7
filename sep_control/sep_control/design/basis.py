"""An orthonormal basis of field snapshots, built while the snapshots stream in (POD without
storing them).

Field responses of the identification experiments arrive block by block (each a few dozen
vectors of n_f numbers). `IncrementalBasis.add(D)` returns their coefficients on the current
orthonormal basis Phi (n_f x r) and extends Phi by the part of D it does not yet span:

    C = D Phi,   E = D - C Phi'   (twice: re-orthogonalization keeps Phi orthonormal to round-off)
    E = U S V',  new directions V_k for S_i > tol * scale,  V_k - Phi Phi' V_k = V R (QR: the
    smallest kept directions carry round-off of relative size eps |D| / S_i),
    Phi <- [Phi, V],  C <- [C, U_k S_k R']

`scale` is the largest snapshot norm seen so far, so what is dropped is below `tol` relative to
the data. Memory: n_f r for Phi instead of every snapshot; cost per block n_f r b flops.
`merge(phi, coefficients)` adds snapshots given on another orthonormal basis (a chunk's) the
same way, streaming their coefficients instead of the n_f-long vectors.
`truncate(coefficients)` then compresses the basis to the span the coefficients actually use
(an SVD of the r x m coefficient matrix, not of the n_f x m data).

`method` "gram" (the default; experiment plan 0.9) finds a block's new directions from its
b x b Gram matrix instead of an SVD of the b x n_f residual (LAPACK's SVD and QR of a wide block
are bandwidth-bound: 0.77 s for 64 x 65,536 on one core, against 0.02 s for E E'):

    C = D Phi,  E = D - C Phi'  (once: the directions found in E are projected off Phi again,
    and E's coefficients are taken on them, so E's round-off along Phi changes nothing)
    E E' = U Lambda U',  W = E' U_k Lambda_k^{-1/2}  (eigenvalues above GRAM_RESOLVE lambda_1 and
    (tol * scale)^2: nearly orthonormal),  W -= Phi Phi' W,  W = Q R (CholeskyQR2),
    another round on E - (E Q) Q' where lambda_1 spans more than GRAM_RESOLVE resolves,
    E Q = U_2 S_2 W_2' (b x K) keeps S_2 > tol * scale:  Phi <- [Phi, Q W_2],  C <- [C, U_2 S_2]

It keeps what the SVD keeps up to directions at the tolerance's edge. `merge` finds the
directions of a chunk's snapshots outside Phi the same way, without a QR, from the range of the
residual snapshots as a whole (A U_c S_c, `_merge_gram`) rather than of every direction of the
chunk's basis: an identification's field responses then agree with "svd"'s to 2.4e-9 at a
tolerance of 1e-8 with 1-4 fewer directions (`bench/bench_field_basis.py`, docs/benchmarks.md).
"svd" is 0.8.0's arithmetic (experiment plan 0.8).

`xp`: the array module Phi lives in. On a device (`sep_plant.device`) the snapshots arrive
there and Phi stays there: the n_f-long work (the projections, the Gram matrices and
CholeskyQR2, or "svd"'s SVD of the residual block through a QR and the QR of the new
directions) runs on the device, and only the small matrices (b x b, b x K, k x k) and the
coefficients (b x r) come to the host. With numpy and "svd" the operations are those of 0.8.0,
bit for bit.
Pure numpy (or a numpy-compatible module): no ROS import.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.linalg.blas

from sep_plant.plants.backend import to_host

from sep_control.compute.budget import default_budget
from sep_control.design.svd import svd

#: how a block's new directions are found (module docstring): "svd" is 0.8.0's arithmetic
METHODS = ("gram", "svd")
#: eigenvalues of a Gram matrix below this fraction of its largest give no direction in one round:
#: their eigenvectors carry errors of eps lambda_1 / lambda_i (here <= 2e-5; CholeskyQR2 needs
#: the directions W well conditioned)
GRAM_RESOLVE = 1e-11
#: rounds of `_gram_range` (each resolves sqrt(GRAM_RESOLVE) ~ 3e-6 of what the last one left)
GRAM_ROUNDS = 4
#: a projection's round-off, in sqrt(b) eps |D|_F: `_gram_range` takes no direction below it
GRAM_NOISE = 64.0
#: the most bytes a basis reserves for its columns ahead (`IncrementalBasis` `reserve`)
RESERVE_BYTES = 4 * 2 ** 30
#: the largest condition number CholeskyQR2 is trusted with (Q'Q - I ~ (eps cond^2)^2 after the
#: second pass; beyond ~eps^{-1/2} = 6.7e7 the first Cholesky loses the small directions)
CHOLQR_COND = 1e6


class IncrementalBasis:
    """Orthonormal basis of the snapshots added so far (columns of `phi`)."""

    def __init__(self, n: int, tol: float = 1e-12, max_rank: int | None = None, xp=np, method: str = "gram",
                 reserve: int = 0):
        """`reserve`: the most columns the basis is expected to reach (e.g. the number of snapshots
        to come). Host "gram" allocates that many at once, up to RESERVE_BYTES and the memory
        budget (`sep_control.compute.budget`): address space only, its pages mapped as columns are
        written, and no growth copies (a growth faulted in and copied the whole basis: 0.4 s of a
        plate 256^2 identification's merges)."""
        if method not in METHODS:
            raise ValueError(f"field basis method must be one of {', '.join(METHODS)}, got {method!r}")
        self.n, self.tol = int(n), float(tol)
        self.max_rank = max_rank
        self.xp, self.method = xp, method
        # "gram" keeps Phi's columns contiguous (column-major): a new direction is written, and a
        # growth copied, in one piece, and a growth touches only the pages it fills (a row-major
        # buffer is touched whole, O(n cap), at every doubling: 0.1 s at 16,384 x 512 here);
        # "svd" keeps 0.8.0's row-major buffer, so that its products stay 0.8.0's bit for bit
        self._order = "F" if method == "gram" else "C"
        self._phi = xp.zeros((self.n, 0), order=self._order)
        self._cols = 0
        self._reserve = min(int(reserve), self.n, min(RESERVE_BYTES, default_budget()) // (8 * max(self.n, 1))) \
            if method == "gram" and xp is np and reserve > 0 else 0
        self.scale = 0.0

    @property
    def rank(self) -> int:
        return self._cols

    @property
    def phi(self) -> np.ndarray:
        """(n, r) orthonormal columns."""
        return self._phi[:, :self._cols]

    def result(self) -> np.ndarray:
        """Phi to keep once the streaming is done: in host memory "gram"'s column-major view itself
        (contiguous; the buffer's columns past r were never touched, so their pages were never
        mapped: a copy cost 0.2 s per chunk at 65,536 x 330), else a compact copy (a device's
        buffer is allocated whole; "svd"'s row-major buffer is 0.8.0's)."""
        return self.phi if self._order == "F" and self.xp is np else self.phi.copy()

    def add(self, D: np.ndarray, scale: float | None = None, overwrite: bool = False) -> np.ndarray:
        """Coefficients (b, r) of the snapshots D (b, n) on the basis after adding them.

        `scale`: the size the tolerance is relative to, when it is not the largest norm in D
        (default), e.g. the largest snapshot of a whole set that arrives in parts. `overwrite`:
        D is scratch ("gram" may leave its residual there instead of in a new block)."""
        xp = self.xp
        D = xp.atleast_2d(D)
        if D.shape[1] != self.n:
            raise ValueError(f"snapshots of length {D.shape[1]}, basis of length {self.n}")
        sq = xp.einsum("ij,ij->i", D, D)                  # squared snapshot norms
        if scale is None:
            norms = xp.sqrt(sq)
            scale = float(norms.max(initial=0.0)) if xp is np else (float(norms.max()) if D.shape[0] else 0.0)
        self.scale = max(self.scale, float(scale))
        if self.method == "gram":
            return self._add_gram(D, float(np.sqrt(float(sq.sum()))), overwrite)
        phi = self.phi
        if xp is not np and self._cols == 0:     # no products with an empty basis on a device
            C, E = xp.zeros((D.shape[0], 0)), D.copy()
        else:
            C = D @ phi
            E = D - C @ phi.T
            C2 = E @ phi                 # re-orthogonalize (classical Gram-Schmidt, twice)
            E -= C2 @ phi.T
            C += C2
        if self._inside(E):
            # every singular value of E is at most its Frobenius norm: nothing to add, and no SVD
            # (most blocks once the basis holds the responses: 3/4 of them at the reference)
            return C
        U, S, Vt = svd(E) if xp is np else _svd_wide(xp, E)
        S_host = S if xp is np else S.get()
        # the kept directions are a leading run: S is sorted, and so are the caps on their number
        k = min(int(np.count_nonzero(S_host > self.tol * self.scale)), self._room())
        if k == 0:
            return C
        # the smallest kept directions (S near tol * scale) carry the projection's round-off at
        # a relative size of eps |D| / S: orthogonalize them once more and among themselves
        # (V_old = V R + round-off, so E's coefficients on V are U S R')
        V = Vt[:k].copy().T
        if xp is np or self._cols:
            V -= phi @ (phi.T @ V)
        V, R = np.linalg.qr(V) if xp is np else _qr(xp, V)
        self._grow(V)
        return xp.hstack([C, (U[:, :k] * S[:k]) @ R.T])

    def _inside(self, E) -> bool:
        """Whether a residual block E is within the tolerance (its Frobenius norm bounds every
        singular value)."""
        return self.scale == 0.0 or float(self.xp.linalg.norm(E)) <= self.tol * self.scale

    def _room(self) -> int:
        """How many directions the basis may still take (n, and `max_rank`)."""
        room = self.n - self._cols
        return room if self.max_rank is None else min(room, max(0, self.max_rank - self._cols))

    def _add_gram(self, D, size: float, overwrite: bool = False):
        """`add` with "gram": C = D Phi and E = D - C Phi' in one pass (the directions found in E
        are projected off Phi again, and E's coefficients are taken on them, so E's round-off
        along Phi changes nothing), then E's directions above tol * scale (`_gram_range`, and
        the SVD of the small E Q) join Phi; returns (b, r) coefficients. `overwrite`: E is
        formed in D's memory. `size`: |D|_F."""
        xp, phi, theta = self.xp, self.phi, self.tol * self.scale
        if self._cols:
            C = D @ phi
            E = _residual(xp, D, C, phi, overwrite)
        else:                                    # no products with an empty basis (a device's rule)
            C, E = xp.zeros((D.shape[0], 0)), D
        if self._room() == 0:
            return C
        # a residual within the tolerance (|E|_F <= tol * scale) gives no direction: the Gram
        # matrix's trace says so (no separate pass over E for its norm)
        Q, EQ = _gram_range(xp, E, theta, phi, size)
        if Q.shape[1] == 0:
            return C
        U2, S2, W2t = svd(to_host(EQ))                      # E on the found directions (b, K)
        k = min(int(np.count_nonzero(S2 > theta)), self._room())
        if k == 0:
            return C
        if k == Q.shape[1]:                                   # every direction kept: no rotation
            self._grow(Q)
            return xp.hstack([C, EQ])
        self._grow((xp.asarray(W2t[:k]) @ Q.T).T)             # Q W_2, orthonormal: Q and W_2 both are
        return xp.hstack([C, xp.asarray(U2[:, :k] * S2[:k])])

    def merge(self, phi: np.ndarray, coefficients: np.ndarray, block: int = 64) -> np.ndarray | None:
        """Add the snapshots phi @ coefficients (phi (n, r_c) orthonormal, coefficients (r_c, m)),
        as `add` would one block of `block` snapshots at a time, but without forming them: their
        part outside the basis is Q Z (Q (n, r_c) orthonormal, Z = R coefficients from the QR of
        phi's residual) and the streaming runs on the columns of Z, in r_c numbers each. How
        chunk bases (`sep_control.design.tvera`) become one: the same tolerance as within a chunk,
        against `scale` (set it beforehand to the largest snapshot of all chunks, so that the
        order of the chunks does not decide what is dropped) or the largest snapshot so far.

        Returns, for "gram", Phi' phi (r, r_c) on the host (r: the rank after the merge), from
        the products the merge makes anyway; None for "svd" (0.8.0's merge: the caller projects
        phi itself)."""
        if phi.ndim != 2 or phi.shape[0] != self.n or coefficients.ndim != 2 or coefficients.shape[0] != phi.shape[1]:
            raise ValueError(f"merge: basis {phi.shape} and coefficients {np.shape(coefficients)} do not "
                             f"fit a basis of length {self.n}")
        if phi.shape[1] == 0 or coefficients.size == 0:
            return None
        xp = self.xp
        self.scale = max(self.scale, float(np.sqrt(np.einsum("ij,ij->j", coefficients, coefficients)).max()))
        if self.method == "gram":
            return self._merge_gram(phi, coefficients, block)
        own = self.phi
        if xp is not np and self._cols == 0:         # no products with an empty basis on a device
            A = phi.copy()
        else:
            A = phi - own @ (own.T @ phi)
            A -= own @ (own.T @ A)                  # re-orthogonalize
        Q, R = np.linalg.qr(A) if xp is np else _qr(xp, A)
        Z = (R if xp is np else R.get()) @ coefficients     # (r_c, m): the residual snapshots on Q
        room = None if self.max_rank is None else max(0, self.max_rank - self._cols)
        sub = self._streamed(Z, room, block)
        if sub.rank:
            V = Q @ (sub.phi if xp is np else xp.asarray(sub.phi))
            if xp is np or self._cols:
                V -= own @ (own.T @ V)             # orthogonal to the basis to round-off
            self._grow(np.linalg.qr(V)[0] if xp is np else _qr(xp, V)[0])
        return None

    def _merge_gram(self, phi, coefficients: np.ndarray, block: int) -> np.ndarray:
        """`merge` with "gram": the residual snapshots A c, A = (I - Phi Phi') phi, hold directions
        above tol * scale only within the range of Y = A U_c S_c (c = U_c S_c V_c': the same
        singular values as A c, in r_c columns); `_gram_range` on Y' finds them, Q, and the
        streaming runs on the columns of Z = (A' Q)' c. Into an empty basis phi itself serves,
        Q = phi and Z = c, and where the streaming keeps every direction, phi joins as it is.
        (A's own directions down to a floor would be r_c of them, most of them carrying nothing
        of the snapshots.) The transfer T stacks M = Phi' phi and
        phi_sub' (A' Q)' (Q' phi = Q' A: Q is orthogonal to Phi), or phi_sub' into an empty basis."""
        xp, own = self.xp, self.phi
        if self._cols == 0:
            if self._room() == 0:
                return np.zeros((0, phi.shape[1]))
            Q, Z, M, QtA = phi, coefficients, np.zeros((0, phi.shape[1])), None
        else:
            M = own.T @ phi
            if self._room() == 0:
                return to_host(M)
            # one projection: the directions found in Y are projected off Phi again. The n-long
            # products are formed as their transposes, (r_c, n) rows: an n x r_c row-major
            # product runs at 2/3 of the speed (one core)
            A = phi - (M.T @ own.T).T                                      # column-major (n, r_c)
            M = to_host(M)
            Uc, Sc, _ = svd(coefficients)
            Yt = xp.asarray((Uc[:, :Sc.size] * Sc).T) @ A.T                # Y' (min(r_c, m), n)
            Q, _ = _gram_range(xp, Yt, self.tol * self.scale, own, float(np.sqrt(np.sum(Sc * Sc))))
            if Q.shape[1] == 0:
                return M
            QtA = to_host(A.T @ Q).T                  # (K, r_c)
            Z = QtA @ coefficients                    # (K, m): the residual snapshots on Q
        sub = self._streamed(Z, self._room(), block)
        if not sub.rank:
            return M
        if QtA is None and sub.rank == phi.shape[1]:
            # every direction of phi kept: phi itself is a basis of their span (Phi' phi = I),
            # without the n r_c^2 rotation into phi_sub's
            self._grow(phi)
            return np.eye(sub.rank)
        self._grow((xp.asarray(sub.phi.T) @ Q.T).T)    # Q phi_sub: orthonormal, and orthogonal to the basis
        return np.vstack([M, sub.phi.T if QtA is None else sub.phi.T @ QtA])

    def _streamed(self, Z: np.ndarray, max_rank: int | None, block: int) -> "IncrementalBasis":
        """A host basis of the columns of Z (residual snapshots in a merge's coordinates), added
        `block` at a time with the tolerance against this basis' scale."""
        sub = IncrementalBasis(Z.shape[0], self.tol, max_rank=max_rank, method=self.method)
        for i in range(0, Z.shape[1], block):
            sub.add(Z[:, i:i + block].T, scale=self.scale)
        return sub

    def _grow(self, V: np.ndarray) -> None:
        need = self._cols + V.shape[1]
        if need > self._phi.shape[1]:     # amortized growth of the column buffer
            cap = max(need, 2 * self._phi.shape[1], 16, self._reserve)
            buf = _zeros(self.xp, (self.n, cap), self._order)
            buf[:, :self._cols] = self._phi[:, :self._cols]
            self._phi = buf
        self._phi[:, self._cols:need] = V
        self._cols = need


def _residual(xp, D, C, phi, overwrite: bool):
    """E = D - C Phi' (D (b, n), C (b, r), Phi (n, r)); with `overwrite` in host memory in D's own
    (one BLAS call, E' = D' - Phi C' on D's transpose: no n x b temporary, whose pages a new
    allocation faults in again every block)."""
    if overwrite and xp is np and D.flags.c_contiguous and D.dtype == np.float64 and phi.dtype == np.float64:
        E = scipy.linalg.blas.dgemm(-1.0, phi, C, beta=1.0, c=D.T, trans_b=True, overwrite_c=True)
        if np.shares_memory(E, D):
            return E.T
        return np.ascontiguousarray(E.T)
    return D - C @ phi.T


def _gram_range(xp, E, floor: float, against, size: float):
    """Orthonormal directions Q (n, K), orthogonal to `against` (n, r), that hold every direction
    of the rows of E (b, n) with a singular value above `floor` (the singular values of
    E - (E Q) Q' are all below it, up to what a Gram matrix resolves in GRAM_ROUNDS rounds), and
    E Q (b, K). One round on R (what the rounds before left of E): the eigenpairs
    (lambda_i, u_i) of R R' above max(GRAM_RESOLVE lambda_1, floor^2) give the directions
    R' u_i / sqrt(lambda_i), projected off `against` and the rounds before and made orthonormal
    (`_orthonormal`), Q_i; another round runs on R - (R Q_i) Q_i' only where GRAM_RESOLVE
    lambda_1 was above floor^2 (directions between the two may be left) and |R|_F^2 - |R Q_i|_F^2
    may exceed floor^2. `floor` is raised to the round-off the projection that made E left in it,
    GRAM_NOISE sqrt(b) eps `size` (size = |D|_F, the block before the projection): below it a
    residual holds no direction, only round-off, mostly along `against`, which one projection
    would not remove from a direction made of little else.
    Cost per round: n b^2 (R R'), 4 n b K (the directions, R Q_i), 4 n r K (the projection),
    4 n K^2 (the QR)."""
    b, found, R = E.shape[0], [], E
    eps = np.finfo(float).eps
    floor = max(floor, GRAM_NOISE * np.sqrt(b) * eps * size)
    for _ in range(GRAM_ROUNDS):
        G = to_host(R @ R.T)
        total = float(np.trace(G))
        if total <= floor ** 2:
            break
        lam, U = np.linalg.eigh(G)
        lam, U = lam[::-1], U[:, ::-1]
        cut = max(GRAM_RESOLVE * lam[0], floor ** 2)
        k = int(np.count_nonzero(lam > cut))
        if k == 0:
            break
        # (n, k), orthonormal to ~eps lambda_1/lambda_k; formed as (k, n) rows, i.e. column-major:
        # products with the n-long W then run at 22 GFLOP/s (k = 12, one core), 8.6 row-major
        W = (xp.asarray((U[:, :k] / np.sqrt(lam[:k])).T) @ R).T
        Q = _orthonormal(xp, W, [against] + [Q for Q, _ in found])
        if Q.shape[1] == 0:
            break
        RQ = R @ Q
        found.append((Q, RQ))
        left = total - float(xp.sum(RQ * RQ))                 # |R - R Q Q'|_F^2, to ~b eps |R|^2
        if GRAM_RESOLVE * lam[0] <= floor ** 2 or left + 8 * b * eps * total <= floor ** 2:
            break
        R = R - RQ @ Q.T
    if not found:
        return xp.zeros((E.shape[1], 0)), xp.zeros((b, 0))
    if len(found) == 1:
        return found[0]
    return xp.hstack([Q for Q, _ in found]), xp.hstack([RQ for _, RQ in found])


def _orthonormal(xp, W, against: list):
    """W (n, k) projected off the orthonormal blocks `against` and made orthonormal: CholeskyQR2
    (W is nearly orthonormal by construction); where it fails (W'W not positive definite or W
    worse conditioned than CholeskyQR2 handles), the leading left singular vectors of W (those
    above sqrt(eps) of the largest: a rank-revealing fallback, on the host), projected again."""
    def project(V):
        # V' -= (V' B) B' on the transpose: (k, n) products, where B (B' V) writes an n x k
        # row-major product (2.6 times slower at k = 12); column-major V's transpose is contiguous
        Vt = V.T
        for B in against:
            if B.shape[1]:
                Vt -= (Vt @ B) @ B.T
        return V

    W = project(W)
    Q = _cholqr2(xp, W)
    if Q is not None:
        return Q
    U, s, _ = np.linalg.svd(to_host(W), full_matrices=False)
    keep = s > np.sqrt(np.finfo(float).eps) * s[0] if s.size and s[0] > 0 else np.zeros(s.shape, bool)
    V = project(xp.asarray(U[:, keep]))
    Q = _cholqr2(xp, V)
    return Q if Q is not None else xp.asarray(np.linalg.qr(to_host(V))[0])


def _cholqr2(xp, W):
    """The Q of a well-conditioned tall W (n, k) by CholeskyQR2 (W'W = L L', W <- W L'^{-1},
    twice: orthonormal to round-off for cond(W) << eps^{-1/2}; gemm-bound, where a Householder
    QR of a tall block is bandwidth-bound); None where W'W is not positive definite or W's
    condition number exceeds CHOLQR_COND."""
    k = W.shape[1]
    for i in range(2):
        try:
            L = np.linalg.cholesky(to_host(W.T @ W))
        except np.linalg.LinAlgError:
            return None
        if i == 0 and np.linalg.cond(L) > CHOLQR_COND:
            return None
        # W L'^{-1} formed as (L^{-1} W')': column-major, as Phi's buffer keeps its columns
        W = (xp.asarray(scipy.linalg.solve_triangular(L, np.eye(k), lower=True)) @ W.T).T
    return W


def _zeros(xp, shape: tuple[int, int], order: str):
    """A zeroed buffer for Phi. In host memory without transparent huge pages: numpy asks the
    kernel for them on arrays of 4 MB or more, and a buffer whose columns are written a few at a
    time then takes a huge-page fault (with compaction) every 2 MB; at plate 256^2 (one TV-ERA
    identification, one core) the basis' growths and writes took 2.6 s with them, 0.76 s with huge
    pages off for the whole process, 0.65 s with this buffer alone without them and its new columns
    formed column-major."""
    toggle = getattr(getattr(getattr(np, "_core", None), "multiarray", None), "_set_madvise_hugepage", None) \
        if xp is np else None                  # numpy's switch (1.20 on); without it, numpy's default
    if toggle is None:
        return xp.zeros(shape, order=order)
    before = toggle(False)
    try:
        return np.zeros(shape, order=order)
    finally:
        toggle(before)


#: what the device's own QR failed with, once (then the host's QR serves: a slower, working design)
QR_FALLBACK: list[str] = []


def _qr(xp, A):
    """The thin QR of a tall device array: the device's (cuSOLVER), or the host's if the device
    module's fails to run (no cuSOLVER in the installation, say), said once on stderr."""
    if not QR_FALLBACK:
        try:
            return xp.linalg.qr(A)
        except (ImportError, RuntimeError, AttributeError) as exc:
            import sys
            QR_FALLBACK.append(f"{type(exc).__name__}: {exc}")
            print(f"sep: the device's QR failed ({QR_FALLBACK[0]}); the field basis uses the host's QR",
                  file=sys.stderr, flush=True)
    Q, R = np.linalg.qr(A.get())
    return xp.asarray(Q), xp.asarray(R)


def _svd_wide(xp, E):
    """The thin SVD U S V' of a wide device block E (b x n_f, b << n_f) through its QR: E' = Q R
    on the device (cuSOLVER's geqrf/orgqr: n_f b^2 flops, streamed once), the b x b SVD of R' on
    the host, V = Q V_r. The same factorization as an SVD of E to round-off (QR is backward
    stable), without a bidiagonalization of the n_f-long block on the device."""
    Q, R = _qr(xp, E.T)
    Ur, S, Vrt = np.linalg.svd(R.T.get())
    return xp.asarray(Ur), xp.asarray(S), (Q @ xp.asarray(Vrt.T)).T


def truncate(phi: np.ndarray, coefficients: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Compress a basis to the span its coefficients use: coefficients (r, m) on phi (n, r) ->
    (phi' (n, r'), coefficients' (r', m)) with phi' coefficients' = phi coefficients up to
    singular values below tol * sigma_1 (phi' orthonormal, r' <= r)."""
    if coefficients.size == 0 or phi.shape[1] == 0:
        return phi[:, :0], coefficients[:0]
    U, S, _ = svd(coefficients)
    r = int(np.count_nonzero(S > tol * S[0])) if S[0] > 0 else 0
    return phi @ U[:, :r], U[:, :r].T @ coefficients
