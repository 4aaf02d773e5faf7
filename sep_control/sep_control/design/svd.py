"""The design's SVD: numpy's (LAPACK gesdd), and where it does not converge, LAPACK gesvd.

gesdd (divide and conquer) can fail on a finite matrix: measured on a 140 x 201 residual block
of the field basis of a 201-node reaction-diffusion plant with noise on every node (its singular
values spread from 0.76 down to 1e-21), where gesvd (QR iteration, slower) converges. Where
gesdd converges the result is numpy's, bit for bit.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg


def svd(a: np.ndarray, full_matrices: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """U, S, Vt of a (as `np.linalg.svd`), with gesvd where gesdd does not converge."""
    try:
        return np.linalg.svd(a, full_matrices=full_matrices)
    except np.linalg.LinAlgError:
        if not np.isfinite(a).all():
            raise
        return scipy.linalg.svd(a, full_matrices=full_matrices, lapack_driver="gesvd", check_finite=False)
