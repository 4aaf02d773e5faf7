"""Batched steps of controlgym's PDE envs, from each env's own operators (the fast path).

One ``env.step`` of a controlgym PDE steps one run and costs 5-200 ms (ETDRK4 substeps, its
coefficients recomputed every step, an n x n multivariate-normal draw). The design steps
hundreds of runs at once, so `FastStep` steps a batch (M, n) with the same scheme, reading the
env's own operators; `tests/test_controlgym_plant.py` checks it against ``env.step`` (noise
off) to 1e-10 on random states for every env it covers.

* Linear envs (convection_diffusion_reaction, wave, schrodinger): x' = A x + B2 u with the env's
  matrices ``env.A`` and ``env.B2``.
* The other seven, written in Fourier space as d v_hat/dt = L v_hat + N(v_hat) + B_hat u, with L
  the env's ``_compute_fourier_linear_op()``, B_hat = rfft(control support) and
  N(v_hat) = c(kappa) rfft(g(v)) computed 3/2-dealiased (v on 3n/2 points); per env:

      burgers, kuramoto_sivashinsky  c = -i kappa / 2,  g(v) = v^2
      korteweg_de_vries               c = 3 i kappa,     g(v) = v^2
      allen_cahn                      c = -p,            g(v) = v^3      (p: potential_constant)
      cahn_hilliard                   c = -D kappa^2,    g(v) = v^3      (D: diffusivity_constant)
      ginzburg_landau                 c = -1,            g(v) = v^3
      fisher                          c = r,             g(v) = v (1 - v) (r: reaction_constant)

  integrated, as the env does, by ETDRK4 (Cox-Matthews with the Kassam-Trefethen contour
  coefficients on 32 points, their real parts), floor(sample_time / integration_time) substeps
  of integration_time, the input held.
Numpy only.
"""
from __future__ import annotations

from typing import Any, Callable

import numpy as np

#: envs whose step is x' = A x + B2 u
LINEAR = ("convection_diffusion_reaction", "wave", "schrodinger")
#: envs stepped by ETDRK4 in Fourier space
SPECTRAL = ("burgers", "kuramoto_sivashinsky", "korteweg_de_vries", "allen_cahn", "cahn_hilliard",
            "ginzburg_landau", "fisher")
COVERED = LINEAR + SPECTRAL
#: contour points of the ETDRK4 coefficients
CONTOUR_POINTS = 32
#: runs stepped at once (keeps a block's work arrays in cache)
BLOCK = 256


def _nonlinear_term(env_id: str, env: Any) -> tuple[np.ndarray | complex, Callable[[np.ndarray], np.ndarray]]:
    """(c, g) of N(v_hat) = c rfft(g(v)) for a spectral env."""
    kappa = np.asarray(env.domain_wavenumbers)
    square: Callable[[np.ndarray], np.ndarray] = lambda v: v * v
    cube: Callable[[np.ndarray], np.ndarray] = lambda v: v * v * v
    table = {
        "burgers": (-0.5j * kappa, square),
        "kuramoto_sivashinsky": (-0.5j * kappa, square),
        "korteweg_de_vries": (3j * kappa, square),
        "allen_cahn": (-float(getattr(env, "potential_constant", 0.0)), cube),
        "cahn_hilliard": (-float(getattr(env, "diffusivity_constant", 0.0)) * kappa ** 2, cube),
        "ginzburg_landau": (-1.0, cube),
        "fisher": (float(getattr(env, "reaction_constant", 0.0)), lambda v: v * (1 - v)),
    }
    return table[env_id]


class FastStep:
    """x_{k+1} = F(x_k, u_k) of a controlgym PDE env for a batch of runs (noise-free).

    Parameters
    ----------
    env_id : str
        The env's name (one of `COVERED`).
    env : object
        The env instance whose operators are read.
    """

    def __init__(self, env_id: str, env: Any):
        if env_id not in COVERED:
            raise ValueError(f"no fast path for controlgym env {env_id!r} (covered: {', '.join(COVERED)})")
        self.env_id = env_id
        self.n = int(env.n_state)
        if env_id in LINEAR:
            self.A = np.asarray(env.A, dtype=float)
            self.B = np.asarray(env.B2, dtype=float)
            return
        self._spectral_setup(env)

    def _spectral_setup(self, env: Any) -> None:
        h = float(env.integration_time)
        self.substeps = int(env.sample_time // env.integration_time)
        L = np.asarray(env._compute_fourier_linear_op())
        self.E, self.E2 = np.exp(h * L), np.exp(h * L / 2)
        r = np.exp(1j * np.pi * (np.arange(1, CONTOUR_POINTS + 1) - 0.5) / CONTOUR_POINTS)
        LR = h * L[:, None] + r[None, :]
        eLR = np.exp(LR)
        self.Q = h * np.real(np.mean((np.exp(LR / 2) - 1) / LR, axis=1))
        self.f1 = h * np.real(np.mean((-4 - LR + eLR * (4 - 3 * LR + LR ** 2)) / LR ** 3, axis=1))
        self.f2 = h * np.real(np.mean((2 + LR + eLR * (-2 + LR)) / LR ** 3, axis=1))
        self.f3 = h * np.real(np.mean((-4 - 3 * LR - LR ** 2 + eLR * (4 - LR)) / LR ** 3, axis=1))
        self.Bhat = np.fft.rfft(np.asarray(env.control_sup, dtype=float), axis=0)   # (n/2+1, n_u)
        self.c, self.g = _nonlinear_term(self.env_id, env)
        self.n_aa = int(self.n * 1.5)

    def _N(self, vhat: np.ndarray, forcing: np.ndarray) -> np.ndarray:
        """N(v_hat) + B_hat u, 3/2-dealiased, for a batch (M, n/2+1)."""
        v = 1.5 * np.fft.irfft(vhat, n=self.n_aa, axis=-1)
        return self.c * (1 / 1.5) * np.fft.rfft(self.g(v), axis=-1)[:, : self.n // 2 + 1] + forcing

    def __call__(self, X: np.ndarray, U: np.ndarray) -> np.ndarray:
        """(M, n) next states of the runs X (M, n) under inputs U (M, n_u)."""
        if self.env_id in LINEAR:
            return X @ self.A.T + U @ self.B.T
        out = np.empty_like(X)
        for s in range(0, X.shape[0], BLOCK):
            out[s:s + BLOCK] = self._etdrk4(X[s:s + BLOCK], U[s:s + BLOCK])
        return out

    def _etdrk4(self, X: np.ndarray, U: np.ndarray) -> np.ndarray:
        forcing = U @ self.Bhat.T
        v = np.fft.rfft(X, axis=-1)
        E, E2, Q = self.E, self.E2, self.Q
        for _ in range(self.substeps):
            Nv = self._N(v, forcing)
            a = E2 * v + Q * Nv
            Na = self._N(a, forcing)
            b = E2 * v + Q * Na
            Nb = self._N(b, forcing)
            c = E2 * a + Q * (2 * Nb - Nv)
            Nc = self._N(c, forcing)
            v = E * v + Nv * self.f1 + 2 * (Na + Nb) * self.f2 + Nc * self.f3
        return np.fft.irfft(v, n=self.n, axis=-1)
