"""The language field's maths (Sec. 3.5, Appendix B): static anchors, per-object
standardisation, the closed-form ridge map, predicted and synchronised embeddings, the query
score. Pure numpy, deterministic; every step is a function the tests check on its own.

Shapes: K objects, T frames, D embedding dimensions, F = 28 kinematic features.

Decisions the paper leaves open (each with its reason in docs/phase3.md):

* the blend weight beta = 0.65 goes on the kinematic prediction (Sec. 3.5 names the prediction
  first, and the prediction is the method's point) unless `beta_on = "observation"`;
* the temporal EMA (gamma = 0.15) is the weight of the neighbouring smoothed frame, run forward
  and then backward (zero phase: an activation interval is not delayed), renormalised;
* statistics of the standardisation and the ridge fit use the observed frames F_k only, and
  at unobserved frames the standardised features are clipped to their observed range (the
  ridge map is not extrapolated; `clip_unobserved`); an
  object observed in fewer than 2 frames gets W = 0 (its prediction is the static anchor);
* the W = 0 ablation (`Phase3Config.kinematics = False`, `query --scorer no-kinematics`): the
  same field with every W_k = 0, so e_hat = e_static at every frame while the observations are
  blended and smoothed as usual: what the kinematic conditioning alone adds
  (`unconditioned_sync`; docs/results/phase3.md).
"""

from __future__ import annotations

import numpy as np

from sync4d.phase3.encoders.encoder import normalise_rows

__all__ = [
    "blend",
    "fit_ridge",
    "predict_embeddings",
    "query_scores",
    "standardise",
    "static_embeddings",
    "temporal_ema",
    "unconditioned_sync",
]


def _unit(x: np.ndarray) -> np.ndarray:
    """`x` [..., D] scaled to unit rows along the last axis (float64)."""
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return x / np.maximum(n, 1e-12)


def static_embeddings(obs: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """e_static [K, D]: the normalised mean of each object's observed embeddings `obs`
    [K, T, D] over its observed frames `observed` [K, T] (zero for an object never seen)."""
    w = observed.astype(np.float64)[..., None]
    mean = (obs.astype(np.float64) * w).sum(1)
    return _unit(mean) * (observed.any(1)[:, None])


#: A feature that varies, over an object's observed frames, by less than this fraction of how
#: much it varies over the whole scene carries no signal for that object: it is standardised to
#: 0 rather than blown up from float noise (an object at rest: speeds and accelerations of float
#: noise would become unit-variance features, and its unobserved frames' noise any z-score).
#: In a scene where nothing moves at all the noise is the scene's whole spread and stays.
CONSTANT_FEATURE = 1e-3
#: The kinematic dims that are components of one vector (velocity 6-8, acceleration 9-11).
VECTOR_DIMS = ((6, 7, 8), (9, 10, 11))


def standardise(features: np.ndarray, observed: np.ndarray, clip_unobserved: bool = True
                ) -> np.ndarray:  # fmt: skip
    """f~ [K, T, F + 1]: per-object standardised `features` [K, T, F] (mean and standard
    deviation over the observed frames, sigma + 1e-8; a feature constant for the object, see
    `CONSTANT_FEATURE`, is 0) with a bias column of ones appended. `clip_unobserved`: at the
    object's unobserved frames each feature is clipped to the range it spans over the observed
    ones, so the ridge map is never extrapolated (an occluded object's visible fraction, dim 5,
    drops to 0, far outside what the map was fitted on: unclipped, that one dim decides e_hat
    there; docs/results/phase3.md, "The kinematic claim")."""
    k, t, nf = features.shape
    out = np.ones((k, t, nf + 1))
    seen = observed if observed.any() else np.ones_like(observed)
    scene_sd = features[seen].std(0)  # [F]: each feature's spread over the scene
    for group in VECTOR_DIMS:  # a vector's components: judged by the whole vector's spread
        if max(group) < nf:
            scene_sd[list(group)] = scene_sd[list(group)].max()
    for j in range(k):
        sel = observed[j] if observed[j].any() else np.ones(t, bool)
        mu = features[j, sel].mean(0)
        sd = features[j, sel].std(0)
        z = (features[j] - mu) / (sd + 1e-8)
        constant = sd <= CONSTANT_FEATURE * scene_sd + 1e-12
        z = np.where(constant[None], 0.0, z)
        if clip_unobserved and not sel.all():
            z[~sel] = np.clip(z[~sel], z[sel].min(0), z[sel].max(0))
        out[j, :, :nf] = z
    return out


def fit_ridge(x: np.ndarray, y: np.ndarray, lam: float = 0.01) -> np.ndarray:
    """Closed-form ridge W [P, D] = argmin ||x W - y||^2 + lam ||W||_F^2 of rows `x` [n, P]
    onto `y` [n, D] (the bias column regularised like the others, as Eq. 13 writes it)."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    p = x.shape[1]
    return np.linalg.solve(x.T @ x + lam * np.eye(p), x.T @ y)


def predict_embeddings(
    feats: np.ndarray, obs: np.ndarray, observed: np.ndarray, static: np.ndarray,
    lam: float = 0.01, kinematics: bool = True,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(e_hat [K, T, D], W [K, P, D]): per object the ridge map from standardised features
    `feats` [K, T, P] to residuals e_obs - e_static on the observed frames, and the predicted
    embeddings norm(e_static + f~ W) at every frame (Eq. 14). `kinematics` False: the W = 0
    ablation (every W_k = 0, e_hat = e_static)."""
    k, t, p = feats.shape
    d = obs.shape[-1]
    w_all = np.zeros((k, p, d))
    pred = np.zeros((k, t, d))
    for j in range(k):
        sel = observed[j]
        if kinematics and sel.sum() >= 2:
            w_all[j] = fit_ridge(feats[j, sel], obs[j, sel] - static[j], lam)
        pred[j] = _unit(static[j] + feats[j] @ w_all[j])
    return pred, w_all


def blend(
    pred: np.ndarray, obs: np.ndarray, observed: np.ndarray, beta: float = 0.65,
    beta_on: str = "prediction",
) -> np.ndarray:  # fmt: skip
    """Blended embeddings [K, T, D]: norm(beta e_hat + (1 - beta) e_obs) where observed
    (`beta_on = "observation"` swaps the weights), e_hat elsewhere."""
    wp = beta if beta_on == "prediction" else 1.0 - beta
    mixed = _unit(wp * pred + (1.0 - wp) * obs)
    return np.where(observed[..., None], mixed, pred)


def unconditioned_sync(
    static: np.ndarray, obs: np.ndarray, observed: np.ndarray, beta: float = 0.65,
    beta_on: str = "prediction", gamma: float = 0.15,
) -> np.ndarray:  # fmt: skip
    """e_sync [K, T, D] of the W = 0 ablation: e_hat = e_static [K, D] at every frame, blended
    with the observations `obs` [K, T, D] where `observed` [K, T] and smoothed as e_sync is;
    the observations are kept, the kinematic term is dropped."""
    pred = np.repeat(_unit(np.asarray(static, dtype=np.float64))[:, None], obs.shape[1], axis=1)
    return temporal_ema(blend(pred, np.asarray(obs, dtype=np.float64), observed, beta, beta_on),
                        gamma)  # fmt: skip


def temporal_ema(x: np.ndarray, gamma: float = 0.15) -> np.ndarray:
    """Zero-phase temporal EMA of unit embeddings `x` [K, T, D] along T: forward
    s(f) = norm((1 - gamma) x(f) + gamma s(f-1)), then the same backward over s."""
    def one_pass(a: np.ndarray) -> np.ndarray:
        out = a.copy()
        for f in range(1, a.shape[1]):
            out[:, f] = _unit((1.0 - gamma) * a[:, f] + gamma * out[:, f - 1])
        return out

    fwd = one_pass(np.asarray(x, dtype=np.float64))
    return one_pass(fwd[:, ::-1])[:, ::-1].copy()


def query_scores(
    static: np.ndarray, sync: np.ndarray, q: np.ndarray, w_static: float = 0.35,
    w_temporal: float = 0.65,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(S [K], sims [K, T]) for a query embedding `q` [D]: S(k) = w_s <e_static_k, q> +
    w_t max_f <e_sync_k,f, q> (Eq. 15) and the per-frame temporal similarities."""
    qn = normalise_rows(q[None])[0].astype(np.float64)
    sims = np.asarray(sync, dtype=np.float64) @ qn
    s = w_static * (np.asarray(static, dtype=np.float64) @ qn) + w_temporal * sims.max(1)
    return s, sims
