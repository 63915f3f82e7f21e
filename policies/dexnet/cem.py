"""Gaussian mixtures for the cross-entropy method: a small vectorised EM (no scikit-learn in the stack)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class GaussianMixture:
    weights: np.ndarray  # (K,)
    means: np.ndarray  # (K, D)
    covariances: np.ndarray  # (K, D, D)

    def log_density(self, x: np.ndarray) -> np.ndarray:
        """(N, K) log of weight_k * N(x | mean_k, cov_k)."""
        d = x.shape[1]
        inv = np.linalg.inv(self.covariances)
        _, logdet = np.linalg.slogdet(self.covariances)
        diff = x[:, None, :] - self.means[None]
        maha = np.einsum("nki,kij,nkj->nk", diff, inv, diff)
        return np.log(np.maximum(self.weights, 1e-300))[None] - 0.5 * (maha + logdet[None] + d * np.log(2 * np.pi))

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        component = rng.choice(len(self.weights), size=n, p=self.weights / self.weights.sum())
        chol = np.linalg.cholesky(self.covariances)
        z = rng.standard_normal((n, self.means.shape[1]))
        return self.means[component] + np.einsum("nij,nj->ni", chol[component], z)


def fit_gmm(x: np.ndarray, num_components: int, rng: np.random.Generator, iterations: int = 10,
            reg_covar: float = 1e-4) -> GaussianMixture:
    """EM for a full-covariance mixture from a k-means++ start; ``reg_covar`` keeps every
    component at least that wide, so a component sitting on one elite still explores around it."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or len(x) == 0 or not np.all(np.isfinite(x)):
        raise ValueError(f"fit_gmm needs a non-empty finite (N, D) array, got shape {x.shape}")
    n, d = x.shape
    k = int(max(1, min(num_components, n)))
    eye = np.eye(d)
    resp = np.eye(k)[_nearest(x, _kmeans_pp_seeds(x, k, rng))]  # hard k-means++ start, as scikit-learn's default
    gmm = _m_step(x, resp, reg_covar * eye)
    for _ in range(iterations):
        log_p = gmm.log_density(x)
        log_p -= log_p.max(axis=1, keepdims=True)
        resp = np.exp(log_p)
        resp /= resp.sum(axis=1, keepdims=True)
        gmm = _m_step(x, resp, reg_covar * eye)
    return gmm


def _kmeans_pp_seeds(x: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding: each next seed drawn with probability proportional to squared distance."""
    seeds = [x[rng.integers(len(x))]]
    dist2 = np.sum((x - seeds[0]) ** 2, axis=1)
    for _ in range(1, k):
        total = dist2.sum()
        pick = rng.choice(len(x), p=dist2 / total) if total > 0 else rng.integers(len(x))
        seeds.append(x[pick])
        dist2 = np.minimum(dist2, np.sum((x - x[pick]) ** 2, axis=1))
    return np.asarray(seeds)


def _nearest(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    return np.argmin(np.sum((x[:, None, :] - centres[None]) ** 2, axis=-1), axis=1)


def _m_step(x: np.ndarray, resp: np.ndarray, reg: np.ndarray) -> GaussianMixture:
    nk = resp.sum(axis=0) + 1e-10
    means = resp.T @ x / nk[:, None]
    diff = x[:, None, :] - means[None]
    covs = np.einsum("nk,nki,nkj->kij", resp, diff, diff) / nk[:, None, None] + reg
    return GaussianMixture(weights=nk / nk.sum(), means=means, covariances=covs)
