"""The ridge solve (Eq. 13) on ill-conditioned features, in float64 as the field does it,
against a float64 least-squares solve of the augmented system (stable, QR-based), and what
float32 would lose: the error bounds are written in the test."""

from __future__ import annotations

import numpy as np

from sync4d.phase3.field import fit_ridge


def test_the_ridge_is_accurate_in_float64_on_nearly_collinear_features():
    rng = np.random.default_rng(0)
    n, p, d, lam = 200, 29, 16, 0.01
    base = rng.normal(size=(n, 1))
    # 28 features that are the same signal up to 1e-6 (an object's speed, its EMA, its
    # relative speed ...), and the bias column of ones
    x = np.hstack([base + 1e-6 * rng.normal(size=(n, p - 1)), np.ones((n, 1))])
    y = rng.normal(size=(n, d))
    cond = np.linalg.cond(x.T @ x + lam * np.eye(p))
    assert cond > 1e5  # ill-conditioned: lam keeps it finite
    w = fit_ridge(x, y, lam)
    # the same minimiser from the augmented least-squares system [x; sqrt(lam) I] w = [y; 0]
    aug = np.vstack([x, np.sqrt(lam) * np.eye(p)])
    ref = np.linalg.lstsq(aug, np.vstack([y, np.zeros((p, d))]), rcond=None)[0]
    rel = np.linalg.norm(w - ref) / np.linalg.norm(ref)
    assert rel <= cond * 1e-15  # float64: within cond x 4.5 eps
    # the predictions, what the field uses, agree to 1e-9
    assert np.abs(x @ w - x @ ref).max() <= 1e-9 * np.abs(x @ ref).max()
    # float32 normal equations lose about cond x 6e-8 of that: why the field solves in float64
    x32, y32 = x.astype(np.float32), y.astype(np.float32)
    w32 = np.linalg.solve(x32.T @ x32 + np.float32(lam) * np.eye(p, dtype=np.float32),
                          x32.T @ y32)  # fmt: skip
    rel32 = np.linalg.norm(w32 - ref) / np.linalg.norm(ref)
    assert rel32 > 100 * rel
