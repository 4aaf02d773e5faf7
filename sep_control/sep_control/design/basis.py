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

`xp`: the array module Phi lives in. On a device (`sep_plant.device`) the snapshots arrive
there and Phi stays there: the n_f-long work (the projections, the SVD of the residual block,
the QR of the new directions) runs on the device, and only the coefficients (b x r) and the
singular values come to the host. With numpy the operations are those of 0.8.0, bit for bit.
Pure numpy (or a numpy-compatible module): no ROS import.
"""
from __future__ import annotations

import numpy as np

from sep_control.design.svd import svd


class IncrementalBasis:
    """Orthonormal basis of the snapshots added so far (columns of `phi`)."""

    def __init__(self, n: int, tol: float = 1e-12, max_rank: int | None = None, xp=np):
        self.n, self.tol = int(n), float(tol)
        self.max_rank = max_rank
        self.xp = xp
        self._phi = xp.zeros((self.n, 0))
        self._cols = 0
        self.scale = 0.0

    @property
    def rank(self) -> int:
        return self._cols

    @property
    def phi(self) -> np.ndarray:
        """(n, r) orthonormal columns."""
        return self._phi[:, :self._cols]

    def add(self, D: np.ndarray, scale: float | None = None) -> np.ndarray:
        """Coefficients (b, r) of the snapshots D (b, n) on the basis after adding them.

        `scale`: the size the tolerance is relative to, when it is not the largest norm in D
        (default), e.g. the largest snapshot of a whole set that arrives in parts."""
        xp = self.xp
        D = xp.atleast_2d(D)
        if D.shape[1] != self.n:
            raise ValueError(f"snapshots of length {D.shape[1]}, basis of length {self.n}")
        if scale is None:
            norms = xp.sqrt(xp.einsum("ij,ij->i", D, D))
            scale = float(norms.max(initial=0.0)) if xp is np else (float(norms.max()) if D.shape[0] else 0.0)
        self.scale = max(self.scale, float(scale))
        phi = self.phi
        if xp is not np and self._cols == 0:     # no products with an empty basis on a device
            C, E = xp.zeros((D.shape[0], 0)), D.copy()
        else:
            C = D @ phi
            E = D - C @ phi.T
            C2 = E @ phi                 # re-orthogonalize (classical Gram-Schmidt, twice)
            E -= C2 @ phi.T
            C += C2
        if self.scale == 0.0 or float(xp.linalg.norm(E)) <= self.tol * self.scale:
            # every singular value of E is at most its Frobenius norm: nothing to add, and no SVD
            # (most blocks once the basis holds the responses: 3/4 of them at the reference)
            return C
        U, S, Vt = svd(E) if xp is np else _svd_wide(xp, E)
        S_host = S if xp is np else S.get()
        # the kept directions are a leading run: S is sorted, and so are the caps on their number
        k = int(np.count_nonzero(S_host > self.tol * self.scale))
        k = min(k, self.n - self._cols)                          # never more directions than n
        if self.max_rank is not None:
            k = min(k, max(0, self.max_rank - self._cols))
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

    def merge(self, phi: np.ndarray, coefficients: np.ndarray, block: int = 64) -> None:
        """Add the snapshots phi @ coefficients (phi (n, r_c) orthonormal, coefficients (r_c, m)),
        as `add` would one block of `block` snapshots at a time, but without forming them: their
        part outside the basis is Q Z (Q (n, r_c) orthonormal, Z = R coefficients from the QR of
        phi's residual) and the streaming runs on the columns of Z, in r_c numbers each. How
        chunk bases (`sep_control.design.tvera`) become one: the same tolerance as within a chunk,
        against `scale` (set it beforehand to the largest snapshot of all chunks, so that the
        order of the chunks does not decide what is dropped) or the largest snapshot so far."""
        if phi.ndim != 2 or phi.shape[0] != self.n or coefficients.ndim != 2 or coefficients.shape[0] != phi.shape[1]:
            raise ValueError(f"merge: basis {phi.shape} and coefficients {np.shape(coefficients)} do not "
                             f"fit a basis of length {self.n}")
        if phi.shape[1] == 0 or coefficients.size == 0:
            return
        xp = self.xp
        self.scale = max(self.scale, float(np.sqrt(np.einsum("ij,ij->j", coefficients, coefficients)).max()))
        own = self.phi
        if xp is not np and self._cols == 0:         # no products with an empty basis on a device
            A = phi.copy()
        else:
            A = phi - own @ (own.T @ phi)
            A -= own @ (own.T @ A)                  # re-orthogonalize
        Q, R = np.linalg.qr(A) if xp is np else _qr(xp, A)
        Z = (R if xp is np else R.get()) @ coefficients     # (r_c, m): the residual snapshots on Q
        room = None if self.max_rank is None else max(0, self.max_rank - self._cols)
        sub = IncrementalBasis(phi.shape[1], self.tol, max_rank=room)
        for i in range(0, Z.shape[1], block):
            sub.add(Z[:, i:i + block].T, scale=self.scale)      # the tolerance against our scale
        if sub.rank:
            V = Q @ (sub.phi if xp is np else xp.asarray(sub.phi))
            if xp is np or self._cols:
                V -= own @ (own.T @ V)             # orthogonal to the basis to round-off
            self._grow(np.linalg.qr(V)[0] if xp is np else _qr(xp, V)[0])

    def _grow(self, V: np.ndarray) -> None:
        need = self._cols + V.shape[1]
        if need > self._phi.shape[1]:     # amortized growth of the column buffer
            cap = max(need, 2 * self._phi.shape[1], 16)
            buf = self.xp.zeros((self.n, cap))
            buf[:, :self._cols] = self._phi[:, :self._cols]
            self._phi = buf
        self._phi[:, self._cols:need] = V
        self._cols = need


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
