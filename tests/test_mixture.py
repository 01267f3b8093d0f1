"""Tests of robot_change.mixture.model and its numba kernels (robot_change.mixture.em).

Every kernel is checked against a plain NumPy twin written here; EM at fixed K against
scikit-learn's GaussianMixture; split-EM on data drawn from known mixtures.
"""

from __future__ import annotations

import json
import math
import warnings
import zipfile

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment
from scipy.special import logsumexp

from robot_change.errors import ConvergenceWarning, InputError, MixtureFileError
from robot_change.mixture import em
from robot_change.mixture.model import (
    Mixture,
    criterion_value,
    fit_mixture,
    fit_over_background,
    gaussianity_deficiency,
    reg_covar_for_leaf,
)

# ----------------------------------------------------------------------------- helpers


def random_spd(rng, k, scale=0.05):
    a = rng.normal(size=(k, 3, 3)) * scale
    return a @ a.transpose(0, 2, 1) + 1e-3 * np.eye(3)


def random_params(rng, k, n=500):
    w = rng.uniform(0.5, 1.5, k)
    w /= w.sum()
    mu = rng.normal(size=(k, 3))
    cov = random_spd(rng, k, 0.3)
    x = rng.normal(size=(n, 3)) * 1.5
    return x, w, mu, cov


def draw(rng, weights, means, covs, n):
    counts = rng.multinomial(n, weights)
    parts = [rng.multivariate_normal(m, c, size=c_n)
             for m, c, c_n in zip(means, covs, counts, strict=True)]
    return np.vstack(parts)


# NumPy twins ------------------------------------------------------------------------


def np_prec_chol(covs):
    """Twin of em.precision_cholesky: inv(cholesky(C)).T and sum(log(diag))."""
    prec = np.stack([np.linalg.inv(np.linalg.cholesky(c)).T for c in covs])
    log_det = np.log(np.diagonal(prec, axis1=1, axis2=2)).sum(axis=1)
    return prec, log_det


def np_weighted_log_prob(x, w, mu, covs):
    """(N, K) log w_k + log N(x | mu_k, C_k), straight from the density formula."""
    out = np.empty((len(x), len(w)))
    for k in range(len(w)):
        d = x - mu[k]
        maha = np.einsum("ni,ij,nj->n", d, np.linalg.inv(covs[k]), d)
        _, logdet = np.linalg.slogdet(covs[k])
        out[:, k] = np.log(w[k]) - 0.5 * (3 * math.log(2 * math.pi) + logdet + maha)
    return out


def np_e_step(x, w, mu, covs):
    wlp = np_weighted_log_prob(x, w, mu, covs)
    lp = logsumexp(wlp, axis=1)
    return wlp - lp[:, None], lp


def np_m_step(x, resp, reg):
    nk = resp.sum(axis=0) + 10 * np.finfo(float).eps
    mu = resp.T @ x / nk[:, None]
    covs = np.empty((len(nk), 3, 3))
    for k in range(len(nk)):
        d = x - mu[k]
        covs[k] = (resp[:, k, None] * d).T @ d / nk[k] + reg * np.eye(3)
    return nk, mu, covs


# ----------------------------------------------------------------------------- kernel twins


def test_precision_cholesky_matches_numpy():
    rng = np.random.default_rng(1)
    covs = random_spd(rng, 6)
    prec, log_det, ok = em.precision_cholesky(covs)
    p2, l2 = np_prec_chol(covs)
    assert ok.all()
    np.testing.assert_allclose(prec, p2, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(log_det, l2, rtol=1e-12)
    np.testing.assert_allclose(-2 * log_det, np.linalg.slogdet(covs)[1], rtol=1e-12)
    assert np.all(np.tril(prec, -1) == 0)


def test_precision_cholesky_flags_non_pd():
    covs = np.stack([np.eye(3), np.diag([1.0, -1.0, 1.0]), np.zeros((3, 3))])
    _, _, ok = em.precision_cholesky(covs)
    assert ok.tolist() == [True, False, False]


def test_e_step_matches_numpy():
    rng = np.random.default_rng(2)
    x, w, mu, cov = random_params(rng, 5)
    prec, log_det, _ = em.precision_cholesky(cov)
    log_resp, log_prob = em.e_step(x, w, mu, prec, log_det)
    lr2, lp2 = np_e_step(x, w, mu, cov)
    np.testing.assert_allclose(log_prob, lp2, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(log_resp, lr2, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.exp(log_resp).sum(axis=1), 1.0, rtol=1e-12)


def test_log_prob_kernels_match_numpy():
    rng = np.random.default_rng(3)
    x, w, mu, cov = random_params(rng, 4)
    prec, log_det, _ = em.precision_cholesky(cov)
    lr2, lp2 = np_e_step(x, w, mu, cov)
    np.testing.assert_allclose(em.log_prob_samples(x, w, mu, prec, log_det), lp2, rtol=1e-10)
    lp, labels = em.log_prob_labels(x, w, mu, prec, log_det)
    np.testing.assert_allclose(lp, lp2, rtol=1e-10)
    np.testing.assert_array_equal(labels, lr2.argmax(axis=1))


def test_m_step_matches_numpy():
    rng = np.random.default_rng(4)
    x, w, mu, cov = random_params(rng, 3)
    resp = rng.dirichlet(np.ones(3), size=len(x))
    nk, mu_new, cov_new = em.m_step(x, resp, 1e-4)
    nk2, mu2, cov2 = np_m_step(x, resp, 1e-4)
    np.testing.assert_allclose(nk, nk2, rtol=1e-12)
    np.testing.assert_allclose(mu_new, mu2, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(cov_new, cov2, rtol=1e-10, atol=1e-12)


def test_fused_em_step_matches_e_then_m():
    rng = np.random.default_rng(5)
    x, w, mu, cov = random_params(rng, 4)
    x = x + 3.0  # offset from the origin: the one-pass scatter must not cancel
    mu = mu + 3.0
    prec, log_det, _ = em.precision_cholesky(cov)
    lp, nk, mu_new, cov_new = em.em_step(x, w, mu, prec, log_det, 1e-4)
    lr2, lp2 = np_e_step(x, w, mu, cov)
    nk2, mu2, cov2 = np_m_step(x, np.exp(lr2), 1e-4)
    assert lp == pytest.approx(lp2.mean(), rel=1e-12)
    np.testing.assert_allclose(nk, nk2, rtol=1e-10)
    np.testing.assert_allclose(mu_new, mu2, rtol=1e-10, atol=1e-11)
    np.testing.assert_allclose(cov_new, cov2, rtol=1e-8, atol=1e-11)


def test_em_loop_iterations_match_numpy_twin():
    rng = np.random.default_rng(6)
    x, w, mu, cov = random_params(rng, 3, n=400)
    w2, mu2, cov2, lp, n_iter, status, _ = em.em_loop(
        x, w, mu, cov, np.zeros(3, dtype=bool), False, 1e-4, 0.0, 4)
    assert (n_iter, status) == (4, em.STATUS_MAX_ITER)
    tw, tmu, tcov = w, mu, cov
    for _ in range(4):
        lr, lp_t = np_e_step(x, tw, tmu, tcov)
        nk, tmu, tcov = np_m_step(x, np.exp(lr), 1e-4)
        tw = nk / nk.sum()
    assert lp == pytest.approx(lp_t.mean(), rel=1e-10)
    np.testing.assert_allclose(w2, tw, rtol=1e-9)
    np.testing.assert_allclose(mu2, tmu, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(cov2, tcov, rtol=1e-8, atol=1e-10)


def np_background_e_step(x, log_bg, w, mu, covs):
    """Twin of the background kernels' E-step: log responsibilities (N, 1 + K), column 0 the
    background's, and log p (N,)."""
    wlp = np.column_stack([np.log(w[0]) + log_bg, np_weighted_log_prob(x, w[1:], mu, covs)])
    lp = logsumexp(wlp, axis=1)
    return wlp - lp[:, None], lp


def background_case(seed, k_bg=4, k=2, n=600):
    rng = np.random.default_rng(seed)
    x, wb, mb, cb = random_params(rng, k_bg, n)
    background = Mixture(wb, mb, cb)
    w = rng.uniform(0.1, 0.3, 1 + k)
    w[0] = 1.0
    w /= w.sum()
    return x, background, background.score_samples(x), w, rng.normal(size=(k, 3)), \
        random_spd(rng, k, 0.3)


def test_background_responsibilities_match_numpy():
    x, _, log_bg, w, mu, cov = background_case(30)
    prec, log_det, _ = em.precision_cholesky(cov)
    resp, lp = em.responsibilities_background(x, log_bg, w, mu, prec, log_det)
    lr2, lp2 = np_background_e_step(x, log_bg, w, mu, cov)
    np.testing.assert_allclose(lp, lp2, rtol=1e-10)
    np.testing.assert_allclose(resp, np.exp(lr2), rtol=1e-9, atol=1e-12)


def test_background_em_step_and_loop_match_numpy():
    x, _, log_bg, w, mu, cov = background_case(31)
    x, mu = x + 3.0, mu + 3.0  # the one-pass scatter must not cancel
    log_bg = log_bg + 0.0
    prec, log_det, _ = em.precision_cholesky(cov)
    lp, nk, mu_new, cov_new = em.em_step_background(x, log_bg, w, mu, prec, log_det, 1e-4)
    lr2, lp2 = np_background_e_step(x, log_bg, w, mu, cov)
    nk2, mu2, cov2 = np_m_step(x, np.exp(lr2), 1e-4)
    assert lp == pytest.approx(lp2.mean(), rel=1e-12)
    np.testing.assert_allclose(nk, nk2, rtol=1e-10)
    np.testing.assert_allclose(mu_new, mu2[1:], rtol=1e-10, atol=1e-11)
    np.testing.assert_allclose(cov_new, cov2[1:], rtol=1e-8, atol=1e-11)
    w3, mu3, cov3, lp3, n_iter, status, _ = em.em_loop_background(x, log_bg, w, mu, cov, 1e-4,
                                                                  0.0, 4)
    assert (n_iter, status) == (4, em.STATUS_MAX_ITER)
    tw, tmu, tcov = w, mu, cov
    for _ in range(4):
        lr, lp_t = np_background_e_step(x, log_bg, tw, tmu, tcov)
        nk_t, m_t, c_t = np_m_step(x, np.exp(lr), 1e-4)
        tw, tmu, tcov = nk_t / nk_t.sum(), m_t[1:], c_t[1:]
    assert lp3 == pytest.approx(lp_t.mean(), rel=1e-10)
    np.testing.assert_allclose(w3, tw, rtol=1e-9)
    np.testing.assert_allclose(mu3, tmu, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(cov3, tcov, rtol=1e-8, atol=1e-10)


def test_background_loop_with_fixed_background_weight_matches_numpy():
    # the partial EM of a split-and-merge move: the background keeps its total weight w_0,
    # the free components share 1 - w_0 in proportion to their responsibility mass
    x, _, log_bg, w, mu, cov = background_case(32, k=3)
    w2, mu2, cov2, lp, n_iter, status, _ = em.em_loop_background(x, log_bg, w, mu, cov, 1e-4,
                                                                 0.0, 5, True)
    assert (n_iter, status) == (5, em.STATUS_MAX_ITER)
    tw, tmu, tcov = w, mu, cov
    for _ in range(5):
        lr, lp_t = np_background_e_step(x, log_bg, tw, tmu, tcov)
        nk_t, m_t, c_t = np_m_step(x, np.exp(lr), 1e-4)
        tw = np.concatenate([w[:1], (1.0 - w[0]) * nk_t[1:] / nk_t[1:].sum()])
        tmu, tcov = m_t[1:], c_t[1:]
    assert w2[0] == w[0]
    assert lp == pytest.approx(lp_t.mean(), rel=1e-10)
    np.testing.assert_allclose(w2, tw, rtol=1e-9)
    np.testing.assert_allclose(mu2, tmu, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(cov2, tcov, rtol=1e-8, atol=1e-10)


def np_two_means(x, c0, c1, n_lloyd, reg):
    """Twin of em.two_means: Lloyd's two-means, then each half's mean and ML covariance."""
    cen = np.stack([c0, c1]).astype(np.float64)
    for it in range(n_lloyd + 1):
        side = np.linalg.norm(x - cen[1], axis=1) < np.linalg.norm(x - cen[0], axis=1)
        if min(side.sum(), (~side).sum()) < 2:
            return False, None, None, None
        new = np.stack([x[~side].mean(axis=0), x[side].mean(axis=0)])
        if it == n_lloyd or np.allclose(new, cen, rtol=0, atol=1e-15):
            break
        cen = new
    halves = (x[~side], x[side])
    counts = np.array([len(h) for h in halves], dtype=np.float64)
    covs = np.stack([np.cov(h, rowvar=False, bias=True) + reg * np.eye(3) for h in halves])
    return True, counts, new, covs


@pytest.mark.parametrize("seed", [50, 51, 52])
def test_two_means_matches_numpy(seed):
    rng = np.random.default_rng(seed)
    x = np.vstack([rng.normal(size=(300, 3)) * 0.2 + [3.0, 1.0, 2.0],
                   rng.normal(size=(200, 3)) * 0.3 + [3.8, 1.2, 2.1]])
    mean = x.mean(axis=0)
    c0, c1 = mean - [0.3, 0.0, 0.0], mean + [0.3, 0.0, 0.0]
    for n_lloyd in (0, 1, 5):
        ok, counts, means, covs = em.two_means(x, c0, c1, n_lloyd, 1e-4)
        ok2, counts2, means2, covs2 = np_two_means(x, c0, c1, n_lloyd, 1e-4)
        assert ok and ok2
        np.testing.assert_array_equal(counts, counts2)
        np.testing.assert_allclose(means, means2, rtol=1e-12, atol=1e-13)
        np.testing.assert_allclose(covs, covs2, rtol=1e-9, atol=1e-13)
    # a half with fewer than two points: not ok
    ok, *_ = em.two_means(x, mean, mean + [100.0, 0.0, 0.0], 5, 1e-4)
    assert not ok and not np_two_means(x, mean, mean + [100.0, 0.0, 0.0], 5, 1e-4)[0]


@pytest.mark.parametrize("seed", [40, 41, 42])
def test_fit_over_background_is_fit_mixture_with_fixed_weights(seed):
    """The same fit as fit_mixture with the background's components fixed, weights and all."""
    rng = np.random.default_rng(seed)
    w, mu, cov = (np.asarray(a, dtype=float) for a in KNOWN["blobs3"])
    background = Mixture(w[:2] / w[:2].sum(), mu[:2], cov[:2])
    x = draw(rng, w, mu, cov, 3000)  # a third blob appeared
    seed_mu = mu[2:] + rng.normal(0.0, 0.05, size=(1, 3))
    seed_cov = cov[2:] * 1.5
    start = np.array([0.8, 0.2])
    got = fit_over_background(x, background, background.score_samples(x), start, seed_mu,
                              seed_cov, reg_covar=1e-6, tol=1e-6)
    init = Mixture(np.concatenate([background.weights * start[0], start[1:]]),
                   np.vstack([background.means, seed_mu]),
                   np.concatenate([background.covariances, seed_cov]))
    want = fit_mixture(x, init=init, fixed=[0, 1], fix_weights=True, split=False,
                       reg_covar=1e-6, tol=1e-6)
    np.testing.assert_allclose(got.weights, want.weights, rtol=1e-9)
    np.testing.assert_allclose(got.means, want.means, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(got.covariances, want.covariances, rtol=1e-8, atol=1e-12)
    np.testing.assert_array_equal(got.means[:2], background.means)
    assert got.record.steps[0].n_iter == want.record.steps[0].n_iter
    # the last E-step's log-likelihood: within tol x N of the final parameters'
    assert abs(got.record.steps[0].log_likelihood - want.record.steps[0].log_likelihood) \
        <= 1e-6 * len(x)


def test_fit_over_background_drops_a_component_that_loses_its_points():
    rng = np.random.default_rng(43)
    w, mu, cov = (np.asarray(a, dtype=float) for a in KNOWN["blobs3"])
    background = Mixture(w / w.sum(), mu, cov)
    x = draw(rng, w, mu, cov, 2000)  # nothing new: a seed far away empties
    got = fit_over_background(x, background, background.score_samples(x), [0.9, 0.1],
                              [[50.0, 50.0, 50.0]], [np.eye(3) * 1e-4], reg_covar=1e-6)
    assert got.n_components == 3
    np.testing.assert_allclose(got.weights, background.weights, rtol=1e-9)
    assert got.record.steps[0].log_likelihood == pytest.approx(
        background.score_samples(x).sum(), rel=1e-12)
    with pytest.raises(InputError, match="must agree"):
        fit_over_background(x, background, background.score_samples(x)[:-1], [0.9, 0.1],
                            [[0.0, 0.0, 0.0]], [np.eye(3)])


# ----------------------------------------------------------------------------- vs scikit-learn


@pytest.mark.parametrize("tol,max_iter", [(0.0, 25), (1e-3, 200)])
def test_em_matches_sklearn_at_fixed_k(tol, max_iter):
    sk = pytest.importorskip("sklearn.mixture")
    rng = np.random.default_rng(7)
    true_cov = random_spd(rng, 3, 0.2)
    x = draw(rng, [0.5, 0.3, 0.2], rng.normal(size=(3, 3)) * 2, true_cov, 3000)
    w0 = np.array([0.4, 0.35, 0.25])
    mu0 = x[rng.choice(len(x), 3, replace=False)]
    cov0 = np.stack([np.eye(3) * 0.5] * 3)
    reg = 1e-6
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gm = sk.GaussianMixture(3, covariance_type="full", tol=tol, max_iter=max_iter,
                                reg_covar=reg, weights_init=w0, means_init=mu0,
                                precisions_init=np.linalg.inv(cov0)).fit(x)
        ours = fit_mixture(x, init=Mixture(w0, mu0, cov0), split=False, reg_covar=reg, tol=tol,
                           max_iter=max_iter)
    assert ours.n_components == 3
    assert ours.score(x) == pytest.approx(gm.score(x), rel=1e-6)
    assert ours.record.n_iter == gm.n_iter_
    np.testing.assert_allclose(ours.means, gm.means_, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(ours.weights, gm.weights_, rtol=1e-5)


# ----------------------------------------------------------------------------- known mixtures

KNOWN = {
    "blobs3": ([0.5, 0.3, 0.2],
               [[0.0, 0.0, 2.0], [1.0, 0.2, 2.5], [-0.6, -0.5, 3.0]],
               [np.diag([0.02, 0.01, 0.005]), np.diag([0.01, 0.03, 0.01]),
                np.array([[0.02, 0.01, 0.0], [0.01, 0.02, 0.0], [0.0, 0.0, 0.01]])]),
    "thin4": ([0.3, 0.3, 0.2, 0.2],
              [[0.0, 0.0, 3.0], [1.0, 0.0, 3.0], [0.0, 1.0, 3.0], [1.0, 1.0, 2.5]],
              [np.diag([0.02, 0.02, 0.0004]), np.diag([0.0004, 0.02, 0.02]),
               np.diag([0.02, 0.0004, 0.02]), np.diag([0.01, 0.01, 0.01])]),
}


@pytest.mark.parametrize("criterion", ["mdl", "bic"])
@pytest.mark.parametrize("name", sorted(KNOWN))
def test_known_mixture_recovered(name, criterion):
    """K exact; parameters within 5 standard errors of their estimators.

    With n_k = N w_k points in component k: weight SE sqrt(w(1-w)/N); mean SE
    sqrt(Sigma_ii / n_k); covariance entry SE sqrt((Sigma_ii Sigma_jj + Sigma_ij^2) / n_k)
    (Gaussian data).  5 SE over ~60 checked numbers keeps a false failure below 1e-4; the
    covariance floor (1e-6 here) is far below every SE.
    """
    w, mu, cov = (np.asarray(a, dtype=float) for a in KNOWN[name])
    n = 4000
    rng = np.random.default_rng(11)
    x = draw(rng, w, mu, cov, n)
    fit = fit_mixture(x, criterion, reg_covar=1e-6)
    assert fit.n_components == len(w), fit.record.steps
    row, col = linear_sum_assignment(((mu[:, None] - fit.means[None]) ** 2).sum(axis=2))
    for k, j in zip(row, col, strict=True):
        nk = n * w[k]
        assert abs(fit.weights[j] - w[k]) <= 5 * math.sqrt(w[k] * (1 - w[k]) / n)
        assert np.all(np.abs(fit.means[j] - mu[k]) <= 5 * np.sqrt(np.diag(cov[k]) / nk))
        d = np.diag(cov[k])
        se = np.sqrt((np.outer(d, d) + cov[k] ** 2) / nk)
        assert np.all(np.abs(fit.covariances[j] - cov[k]) <= 5 * se + 1e-6)


def test_criteria_order_on_known_mixture():
    """AIC never picks fewer components than BIC (its penalty is smaller for N > e^2)."""
    rng = np.random.default_rng(12)
    w, mu, cov = (np.asarray(a, dtype=float) for a in KNOWN["blobs3"])
    x = draw(rng, w, mu, cov, 2000)
    k = {c: fit_mixture(x, c, reg_covar=1e-6).n_components for c in ("aic", "bic")}
    assert k["aic"] >= k["bic"] == 3


def test_criterion_formulas():
    w = np.array([0.5, 0.3, 0.2])
    n, log_l = 1000, -1234.5
    p = 10 * 3 - 1
    assert criterion_value("aic", log_l, n, w) == pytest.approx(-2 * log_l + 2 * p)
    assert criterion_value("bic", log_l, n, w) == pytest.approx(-2 * log_l + p * math.log(n))
    mdl = (-log_l + 4.5 * np.log(n * w / 12).sum() + 1.5 * math.log(n / 12) + 3 * 10 / 2)
    assert criterion_value("mdl", log_l, n, w) == pytest.approx(mdl)
    # fixed components cost nothing but their weights
    fixed = np.array([True, True, False])
    assert criterion_value("aic", log_l, n, w, fixed) == pytest.approx(-2 * log_l + 2 * (9 + 2))
    with pytest.raises(InputError):
        criterion_value("hqc", log_l, n, w)


def test_gaussianity_deficiency_ranks_shapes():
    """~0 for a Gaussian sample, > 0 for a uniform square, largest for an L of two planes."""
    rng = np.random.default_rng(13)
    g = rng.multivariate_normal([0, 0, 0], np.diag([0.1, 0.05, 0.02]), 3000)
    a, b = np.meshgrid(np.arange(50) * 0.02, np.arange(50) * 0.02)
    square = np.column_stack([a.ravel(), b.ravel(), np.zeros(a.size)])
    square = square + rng.normal(0, 0.003, square.shape)
    ell = np.vstack([square, square[:, [0, 2, 1]]])
    j = [gaussianity_deficiency(p, 0.02, rng=np.random.default_rng(0)) for p in (g, square, ell)]
    assert abs(j[0]) < 0.08
    assert 0.1 < j[1] < 0.5  # uniform in 2 dims: 2 * 0.5 log(pi e / 6) = 0.35 before blurring
    assert j[2] > 1.0
    # unit-free: the same points in millimetres give the same J
    j_mm = gaussianity_deficiency(square * 1000, 20.0, rng=np.random.default_rng(0))
    assert j_mm == pytest.approx(j[1], abs=1e-9)


# ----------------------------------------------------------------------------- degenerate clouds


def assert_finite(m: Mixture):
    for a in (m.weights, m.means, m.covariances):
        assert np.isfinite(a).all()
    assert np.all(np.linalg.eigvalsh(m.covariances) > 0)


def test_one_point():
    m = fit_mixture(np.array([[1.0, 2.0, 3.0]]), leaf=0.02)
    assert m.n_components == 1
    np.testing.assert_array_equal(m.means[0], [1.0, 2.0, 3.0])
    np.testing.assert_allclose(m.covariances[0], reg_covar_for_leaf(0.02) * np.eye(3))
    assert_finite(m)


def test_fewer_points_than_parameters():
    x = np.random.default_rng(14).normal(size=(5, 3))
    m = fit_mixture(x, "aic")
    assert m.n_components == 1  # a split needs 2 * min_points points
    assert_finite(m)
    assert np.isfinite(m.score(x))


def test_duplicate_points():
    x = np.repeat(np.array([[0.0, 0.0, 1.0], [0.5, 0.0, 1.0]]), 200, axis=0)
    for crit in ("mdl", "bic", "aic"):
        m = fit_mixture(x, crit, leaf=0.01)
        assert_finite(m)
        assert m.n_components == 2
        np.testing.assert_allclose(np.sort(m.means[:, 0]), [0.0, 0.5], atol=1e-12)
        np.testing.assert_allclose(m.covariances, np.stack([np.eye(3) * 0.01**2 / 12] * 2),
                                   rtol=1e-9, atol=1e-15)
    same = fit_mixture(np.ones((100, 3)))
    assert same.n_components == 1
    assert_finite(same)


def test_plane_and_line():
    a, b = np.meshgrid(np.arange(40) * 0.02, np.arange(30) * 0.02)
    plane = np.column_stack([a.ravel(), b.ravel(), np.full(a.size, 2.0)])
    m = fit_mixture(plane, leaf=0.02)
    assert_finite(m)
    reg = reg_covar_for_leaf(0.02)
    assert np.linalg.eigvalsh(m.covariances).min() >= reg * (1 - 1e-9)
    line = np.column_stack([np.arange(300) * 0.01, np.zeros(300), np.ones(300)])
    m = fit_mixture(line, leaf=0.01)
    assert_finite(m)
    assert np.isfinite(m.score(line))


@pytest.mark.parametrize("bad", [
    np.array([[0.0, 0.0, 1.0], [np.nan, 0.0, 1.0]]),
    np.array([[0.0, np.inf, 1.0]]),
    np.zeros((0, 3)),
    np.zeros((10, 2)),
    np.zeros(3),
    [["a", "b", "c"]],
])
def test_bad_points_raise_input_error(bad):
    with pytest.raises(InputError):
        fit_mixture(bad)


@pytest.mark.parametrize("kwargs", [
    {"reg_covar": 0.0}, {"reg_covar": -1.0}, {"leaf": 0.0}, {"criterion": "hqc"},
    {"max_components": 0}, {"max_iter": 0}, {"tol": -1.0}, {"fixed": [0]},
])
def test_bad_options_raise_input_error(kwargs):
    x = np.random.default_rng(15).normal(size=(50, 3))
    with pytest.raises(InputError):
        fit_mixture(x, **kwargs)


def test_empty_component_removed_not_nan():
    rng = np.random.default_rng(16)
    x = rng.normal(size=(500, 3)) * 0.1
    init = Mixture([0.5, 0.5], [[0, 0, 0], [1e3, 1e3, 1e3]], np.stack([np.eye(3) * 0.01] * 2))
    m = fit_mixture(x, init=init, split=False, reg_covar=1e-6)
    assert m.n_components == 1
    assert_finite(m)


def test_max_iter_warns_not_raises():
    rng = np.random.default_rng(17)
    w, mu, cov = (np.asarray(a, dtype=float) for a in KNOWN["blobs3"])
    x = draw(rng, w, mu, cov, 1500)
    with pytest.warns(ConvergenceWarning, match="max_iter"):
        m = fit_mixture(x, max_iter=1, tol=0.0)
    assert_finite(m)


# ----------------------------------------------------------------------------- Mixture


def small_mixture():
    return Mixture([0.25, 0.75], [[0.0, 0.0, 1.0], [0.5, 0.1, 2.0]],
                   np.stack([np.eye(3) * 0.01, np.diag([0.02, 0.01, 0.005])]))


def test_mixture_is_immutable_and_validated():
    m = small_mixture()
    with pytest.raises(ValueError):
        m.weights[0] = 1.0
    with pytest.raises(AttributeError):
        m.weights = np.ones(2) / 2
    src = np.array([0.5, 0.5])
    m2 = Mixture(src, m.means, m.covariances)
    src[0] = 9.0  # a copy was taken
    assert m2.weights[0] == 0.5
    with pytest.raises(InputError, match="sum to 1"):
        Mixture([0.5, 0.6], m.means, m.covariances)
    with pytest.raises(InputError, match="positive definite"):
        Mixture([0.5, 0.5], m.means, np.stack([np.eye(3), -np.eye(3)]))
    with pytest.raises(InputError, match="symmetric"):
        Mixture([1.0], [[0, 0, 0]], [[[1, 0.5, 0], [0, 1, 0], [0, 0, 1]]])
    with pytest.raises(InputError, match="shape"):
        Mixture([1.0], [[0, 0]], [np.eye(3)])


def test_scores_and_responsibilities():
    m = small_mixture()
    x = np.random.default_rng(18).normal(size=(200, 3)) * 0.3 + 1.0
    lr, lp = np_e_step(x, np.array(m.weights), np.array(m.means), np.array(m.covariances))
    np.testing.assert_allclose(m.score_samples(x), lp, rtol=1e-10)
    assert m.score(x) == pytest.approx(lp.mean(), rel=1e-10)
    r = m.responsibilities(x)
    assert r.shape == (200, 2)
    np.testing.assert_allclose(r.sum(axis=1), 1.0)
    np.testing.assert_array_equal(m.predict(x), lr.argmax(axis=1))


def test_save_load_round_trip(tmp_path):
    m = fit_mixture(draw(np.random.default_rng(19), *KNOWN["blobs3"], 1000), "bic")
    path = tmp_path / "ref.npz"
    m.save(path)
    back = Mixture.load(path)
    for a, b in ((m.weights, back.weights), (m.means, back.means),
                 (m.covariances, back.covariances)):
        np.testing.assert_array_equal(a, b)
        assert not b.flags.writeable
    with np.load(path) as data:
        header = json.loads(str(data["header"][()]))
    assert header["criterion"] == "bic" and header["version"] == 2
    assert header["n_components"] == m.n_components
    assert [p.name for p in tmp_path.iterdir()] == ["ref.npz"]  # no temp file left


def _rewrite(path, header=None, resign=False, **arrays):
    """Change header fields or arrays of a saved file; ``resign``: with a valid checksum."""
    from robot_change.npzfile import checksum

    with np.load(path) as data:
        items = {k: data[k] for k in data.files}
    h = json.loads(str(items["header"][()]))
    h.update(header or {})
    items.update(arrays)
    if resign:
        h["sha256"] = checksum(h, {k: v for k, v in items.items() if k != "header"})
    items["header"] = np.array(json.dumps(h))
    np.savez(path, **items)


def test_a_version_1_file_still_loads(tmp_path):
    """Version 1 hashed the arrays alone; such files stay readable."""
    import hashlib

    m = small_mixture()
    h = hashlib.sha256()
    for a in (m.weights, m.means, m.covariances):
        h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
    header = {"format": "robot_change.mixture", "version": 1, "n_components": m.n_components,
              "criterion": None, "sha256": h.hexdigest()}
    path = tmp_path / "v1.npz"
    np.savez(path, header=np.array(json.dumps(header)), weights=m.weights, means=m.means,
             covariances=m.covariances)
    back = Mixture.load(path)
    np.testing.assert_array_equal(back.means, m.means)
    _rewrite(path, means=np.array(m.means) + 1e-9)
    with pytest.raises(MixtureFileError, match="checksum"):
        Mixture.load(path)


def test_load_refuses_newer_version_wrong_format_bad_checksum(tmp_path):
    m = small_mixture()
    for change, match in (({"version": 3}, "reads up to version 2"),
                          ({"format": "other"}, "format"), ({"n_components": 3}, "K = 3")):
        p = tmp_path / f"m{len(match)}.npz"
        m.save(p)
        _rewrite(p, header=change, resign=True)
        with pytest.raises(MixtureFileError, match=match):
            Mixture.load(p)
    p = tmp_path / "tampered.npz"
    m.save(p)
    _rewrite(p, means=np.array(m.means) + 1e-9)
    with pytest.raises(MixtureFileError, match="checksum"):
        Mixture.load(p)


def test_load_refuses_corrupt_and_truncated(tmp_path):
    m = small_mixture()
    p = tmp_path / "m.npz"
    m.save(p)
    raw = p.read_bytes()
    (tmp_path / "trunc.npz").write_bytes(raw[: len(raw) // 2])
    (tmp_path / "garbage.npz").write_bytes(b"not a zip at all")
    flipped = bytearray(raw)
    flipped[len(raw) // 3] ^= 0xFF
    (tmp_path / "flip.npz").write_bytes(bytes(flipped))
    for name in ("trunc.npz", "garbage.npz", "flip.npz"):
        with pytest.raises(MixtureFileError):
            Mixture.load(tmp_path / name)
    with zipfile.ZipFile(tmp_path / "nohdr.npz", "w") as z:
        z.writestr("weights.npy", b"")
    with pytest.raises(MixtureFileError):
        Mixture.load(tmp_path / "nohdr.npz")
    with pytest.raises(FileNotFoundError):
        Mixture.load(tmp_path / "absent.npz")


# ----------------------------------------------------------------------------- init and fixed


def test_init_from_existing_mixture():
    rng = np.random.default_rng(20)
    w, mu, cov = (np.asarray(a, dtype=float) for a in KNOWN["blobs3"])
    x = draw(rng, w, mu, cov, 2000)
    ref = fit_mixture(x, reg_covar=1e-6)
    x2 = draw(rng, w, mu, cov, 2000)
    again = fit_mixture(x2, init=ref, split=False, reg_covar=1e-6)
    assert again.n_components == ref.n_components
    assert again.score(x2) >= ref.score(x2) - 1e-9  # EM never lowers the likelihood
    assert again.record.steps[0].action == "start"
    assert again.record.n_iter <= 20  # started at the optimum's neighbourhood
    # from a 1-component start, splitting goes on where the criterion says so
    coarse = fit_mixture(x, reg_covar=1e-6, split=False)
    assert fit_mixture(x, init=coarse, reg_covar=1e-6).n_components == 3


def test_fixed_components_stay_exactly_fixed():
    rng = np.random.default_rng(21)
    w, mu, cov = (np.asarray(a, dtype=float) for a in KNOWN["blobs3"])
    ref = Mixture(w[:2] / w[:2].sum(), mu[:2], cov[:2])
    x = draw(rng, w, mu, cov, 3000)  # a third blob appeared
    novelty = ref.score_samples(x) < np.quantile(ref.score_samples(draw(rng, ref.weights,
                                                                         ref.means,
                                                                         ref.covariances,
                                                                         2000)), 0.01)
    fit = fit_mixture(x, init=ref, fixed="init", novelty=novelty, reg_covar=1e-6)
    np.testing.assert_array_equal(fit.means[:2], ref.means)
    np.testing.assert_array_equal(fit.covariances[:2], ref.covariances)
    assert fit.n_components >= 3
    new = fit.means[2:]
    assert np.min(np.linalg.norm(new - mu[2], axis=1)) < 0.05
    assert any(s.action == "seed" and s.accepted for s in fit.record.steps)
    # fix_weights: the fixed components keep their relative weights too
    fw = fit_mixture(x, init=ref, fixed=[0, 1], novelty=novelty, fix_weights=True,
                     reg_covar=1e-6)
    np.testing.assert_array_equal(fw.means[:2], ref.means)
    assert fw.weights[0] / fw.weights[1] == pytest.approx(ref.weights[0] / ref.weights[1],
                                                          rel=1e-12)


def test_fit_is_deterministic_and_recorded():
    x = draw(np.random.default_rng(22), *KNOWN["thin4"], 2000)
    a = fit_mixture(x, seed=3)
    b = fit_mixture(x, seed=3)
    np.testing.assert_array_equal(a.means, b.means)
    rec = a.record
    assert rec.criterion == "mdl" and rec.n_points == 2000
    assert rec.k_tried[0] == 1
    accepted = [s for s in rec.steps if s.accepted]
    assert accepted[-1].n_components == a.n_components
    crits = [s.criterion for s in accepted]
    assert crits == sorted(crits, reverse=True)  # every accepted split lowered the criterion
    assert rec.n_iter == sum(s.n_iter for s in rec.steps) and rec.seconds > 0


def test_max_components_bounds_k():
    x = draw(np.random.default_rng(23), *KNOWN["thin4"], 2000)
    m = fit_mixture(x, "aic", max_components=2)
    assert m.n_components == 2
    assert "max_components" in m.record.stop_reason


def test_search_subsample_polishes_on_all_points():
    x = draw(np.random.default_rng(24), *KNOWN["blobs3"], 6000)
    m = fit_mixture(x, search_points=1500, reg_covar=1e-6)
    assert m.n_components == 3
    assert m.record.steps[-1].action == "polish"
    full = fit_mixture(x, reg_covar=1e-6)
    assert m.score(x) == pytest.approx(full.score(x), abs=1e-3)


def test_polish_runs_coarse_to_fine_on_nested_subsets():
    # 40000 points, a 1000-point search, K > 16: EM on 4000, then 16000 points (at most half
    # the cloud; 64000 is not), then on all of them
    x = blob_cloud(40000)
    m = fit_mixture(x, max_components=24, search_points=1000)
    assert m.n_components > 16
    polish = [s for s in m.record.steps if s.action.startswith("polish")]
    assert [s.action for s in polish] == ["polish 4000", "polish 16000", "polish"]
    assert all(s.accepted and s.n_components == m.n_components for s in polish)
    # a mixture of up to 16 components is polished on all points at once
    small = fit_mixture(x, max_components=16, search_points=1000)
    assert [s.action for s in small.record.steps if s.action.startswith("polish")] == ["polish"]


def test_a_large_mixture_splits_several_components_per_round():
    x = blob_cloud(4000)
    m = fit_mixture(x, max_components=64, search_points=None, refine=0)
    steps = m.record.steps
    k_now = 1
    batches = []
    for s in steps:
        if s.action.startswith("split") and s.accepted:
            ks = [int(k) for k in s.action.split()[1].split(",")]
            # a round splits K // 8 components at once above K = 16, else one
            assert len(ks) in ({1, min(k_now // 8, 64 - k_now)} if k_now > 16 else {1})
            assert len(set(ks)) == len(ks) and max(ks) < k_now
            assert s.n_components <= k_now + len(ks)  # EM may empty a component
            batches.append(len(ks))
            k_now = s.n_components
    assert max(batches) >= 2
    assert k_now <= 64
    # up to 16 components the search is the single-split one: same fits as before batches
    small = fit_mixture(x, max_components=16, search_points=None, refine=0)
    assert all("," not in s.action for s in small.record.steps)

# ----------------------------------------------------------------------------- prune after polish


def blob_cloud(n, n_blobs=40, seed=0):
    """n points around n_blobs random centres (sd 8 cm) in a 3 m cube: a split search with a
    high bound and a small subsample overshoots on it."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(0.0, 3.0, (n_blobs, 3))
    return centres[rng.integers(0, n_blobs, n)] + rng.normal(0.0, 0.08, (n, 3))


def test_polish_leaves_no_free_component_below_min_points():
    # docs/algorithm.md, "How K behaves on our clouds": the search on an 800-point subsample
    # runs to K = 64, and the polish on all 4000 points left (before the prune) three
    # components with 4.8, 7.6 and 9.9 points of mass, below min_points = 10.
    x = blob_cloud(4000)
    m = fit_mixture(x, max_components=64, search_points=800)
    rec = m.record
    actions = [s.action for s in rec.steps]
    polish = actions.index("polish")
    assert rec.steps[polish].n_components == 64  # what the fit returned before the fix
    assert actions[polish + 1:] and set(actions[polish + 1:]) == {"prune"}
    assert all(s.accepted for s in rec.steps[polish:])
    assert rec.n_pruned == 64 - m.n_components > 0
    assert (len(x) * m.weights >= 10).all()
    assert_finite(m)
    # the pruned fit is a proper EM fit on all points: one more EM run from it barely moves
    # (EM stops at a gain below tol = 1e-3 per iteration; a re-run adds a few such steps)
    again = fit_mixture(x, init=m, split=False)
    assert again.n_components == m.n_components
    assert again.score(x) == pytest.approx(m.score(x), abs=2e-3)


def test_prune_never_drops_fixed_components():
    # a fixed component on 4 far points (mass ~4 < min_points) next to an overshooting search
    x_far = np.array([10.0, 10.0, 10.0]) + np.random.default_rng(1).normal(0, 0.05, (4, 3))
    x = np.vstack([blob_cloud(4000), x_far])
    blobs = x[:-4]
    init = Mixture([0.999, 0.001], [blobs.mean(axis=0), [10.0, 10.0, 10.0]],
                   np.stack([np.cov(blobs, rowvar=False), np.eye(3) * 0.0025]))
    m = fit_mixture(x, init=init, fixed=[1], max_components=64, search_points=800)
    assert m.record.n_pruned > 0  # free components were pruned ...
    kept = np.flatnonzero(np.all(m.means == init.means[1], axis=1))
    assert len(kept) == 1  # ... the fixed one, with less than min_points of mass, was not
    k = kept[0]
    np.testing.assert_array_equal(m.covariances[k], init.covariances[1])
    assert len(x) * m.weights[k] < 10
    others = np.arange(m.n_components) != k
    assert (len(x) * m.weights[others] >= 10).all()


# ----------------------------------------------------------------------------- refinement


def test_refine_keeps_k_and_never_raises_the_criterion():
    # split-and-merge moves at the K the search chose: K unchanged, every accepted move lowered
    # the criterion (on the refinement subset), the result at least as good as without them
    x = blob_cloud(6000, n_blobs=12, seed=3)
    plain = fit_mixture(x, max_components=8, refine=0)
    ref = fit_mixture(x, max_components=8, refine=12, refine_points=3000)
    assert ref.n_components == plain.n_components == 8
    steps = [s for s in ref.record.steps if s.action.startswith("refine ")]
    assert 0 < len(steps) <= 12
    base = next(s for s in ref.record.steps if s.action == "refine")
    crits = [base.criterion] + [s.criterion for s in steps if s.accepted]
    assert crits == sorted(crits, reverse=True)
    assert ref.score(x) >= plain.score(x) - 1e-9
    assert_finite(ref)
    again = fit_mixture(x, max_components=8, refine=12, refine_points=3000)
    np.testing.assert_array_equal(again.means, ref.means)
    # not run from a given mixture or without splitting
    fixed_k = fit_mixture(x, init=ref, split=False)
    assert not any(s.action.startswith("refine") for s in fixed_k.record.steps)


def test_split_gain_separates_two_parallel_sheets():
    # two 1 m x 1 m sheets 5 cm apart: the principal-axis two-means cuts across both; the
    # refinement's split also tries the thinnest axis and keeps the better, the two sheets
    from robot_change.mixture import refine

    rng = np.random.default_rng(60)
    sheets = [np.column_stack([rng.uniform(0, 1, 1500), rng.uniform(0, 1, 1500),
                               np.full(1500, z) + rng.normal(0, 0.002, 1500)])
              for z in (0.0, 0.05)]
    x = np.vstack(sheets)
    reg = reg_covar_for_leaf(0.01)
    mean, cov = x.mean(axis=0), np.cov(x, rowvar=False, bias=True) + reg * np.eye(3)
    gain, w, mu, cov2 = refine._split_gain(x, mean, cov, reg, 1e-4, 50)
    assert gain > 0.5 * len(x)  # nats: far more than a component costs
    assert w == pytest.approx([0.5, 0.5], abs=0.02)
    assert sorted(mu[:, 2]) == pytest.approx([0.0, 0.05], abs=0.003)
    np.testing.assert_allclose(mu[:, :2], 0.5, atol=0.03)
