"""Depth uncertainty arithmetic: eq. 11 and 13 against finite differences, eq. 14 against the closed form
and by Monte Carlo, calibration gain, heuristic models, metrics."""
import numpy as np
import pytest

from services.depth.uncertainty import (EXPECTED_WITHIN, calibration_gain, depth_metrics, disparity_to_depth, fuse,
                                       gain_from_ratios, heuristic_sigma, logdepth_to_depth)


def test_eq11_depth_and_sigma_match_linearisation():
    f, b = 312.0, 0.11
    u = np.array([[2.0, 10.0, 50.0]])
    su = np.array([[0.5, 0.3, 1.0]])
    d, s = disparity_to_depth(u, su, f, b)
    np.testing.assert_allclose(d, f * b / u, rtol=1e-6)
    h = 1e-4  # finite-difference derivative of f b / u times sigma_u
    deriv = np.abs((f * b / (u + h) - f * b / (u - h)) / (2 * h))
    np.testing.assert_allclose(s, deriv * su, rtol=1e-4)


def test_eq11_invalid_disparities_become_nan():
    d, s = disparity_to_depth(np.array([0.0, -1.0, np.nan, 0.2, 4.0]), np.array([1.0, 1.0, 1.0, 1.0, np.inf]), 300, 0.1)
    assert np.isnan(d).all() and np.isnan(s).all()


def test_eq13_log_depth_sigma_matches_derivative():
    ld = np.array([-1.0, 0.0, 2.0])
    sl = np.array([0.1, 0.05, 0.2])
    d, s = logdepth_to_depth(ld, sl)
    np.testing.assert_allclose(d, np.exp(ld), rtol=1e-6)
    h = 1e-5
    np.testing.assert_allclose(s, (np.exp(ld + h) - np.exp(ld - h)) / (2 * h) * sl, rtol=1e-4)


def test_fusion_closed_form_and_variance_reduction():
    d1, s1 = np.array([2.0, 3.0]), np.array([0.1, 0.3])
    d2, s2 = np.array([2.2, 2.0]), np.array([0.2, 0.1])
    d, s = fuse(d1, s1, d2, s2)
    w1, w2 = 1 / s1 ** 2, 1 / s2 ** 2
    np.testing.assert_allclose(d, (w1 * d1 + w2 * d2) / (w1 + w2), rtol=1e-6)
    np.testing.assert_allclose(s, 1 / np.sqrt(w1 + w2), rtol=1e-6)
    assert (s < np.minimum(s1, s2)).all()


def test_fusion_of_unbiased_estimates_has_predicted_error():
    rng = np.random.default_rng(0)
    n = 200_000
    truth = rng.uniform(1, 5, n)
    s1, s2 = rng.uniform(0.05, 0.5, n), rng.uniform(0.05, 0.5, n)
    d, s = fuse(truth + s1 * rng.standard_normal(n), s1, truth + s2 * rng.standard_normal(n), s2)
    z = (d - truth) / s
    assert abs(z.std() - 1.0) < 0.01
    err1 = np.mean((truth + s1 * rng.standard_normal(n) - truth) ** 2)
    assert np.mean((d - truth) ** 2) < 0.6 * err1


def test_fusion_handles_missing_sources():
    d, s = fuse(np.array([1.0, np.nan, 2.0, np.nan, 3.0]), np.array([0.1, 0.1, np.inf, 0.1, 0.0]),
                np.array([np.nan, 2.0, 4.0, np.nan, 5.0]), np.array([0.1, 0.2, 0.4, 0.1, 0.5]))
    np.testing.assert_allclose(d[:3], [1.0, 2.0, 4.0], rtol=1e-6)
    np.testing.assert_allclose(s[:3], [0.1, 0.2, 0.4], rtol=1e-6)
    assert np.isnan(d[3]) and np.isnan(s[3])
    np.testing.assert_allclose([d[4], s[4]], [5.0, 0.5], rtol=1e-6)  # sigma 0 is invalid, not infinitely sure


def test_calibration_gain_makes_mean_mahalanobis_one():
    rng = np.random.default_rng(1)
    gt = rng.uniform(1, 6, 50_000)
    b = 0.02 * gt ** 2
    est = gt + rng.laplace(0, b)
    sigma = b * 0.3  # over-confident by a factor 3.3
    k = calibration_gain(est, sigma, gt)
    assert k == pytest.approx(1 / 0.3, rel=0.03)
    assert depth_metrics(est, sigma * k, gt)["mahalanobis"] == pytest.approx(1.0, abs=1e-9)
    m = depth_metrics(est, sigma * k, gt)  # a well-calibrated Laplacian hits the expected coverage
    for got, want in zip((m["within_1s"], m["within_2s"], m["within_3s"]), EXPECTED_WITHIN["laplace"]):
        assert got == pytest.approx(want, abs=0.01)


def test_heuristic_models():
    d = np.array([1.0, 2.0, 4.0])
    np.testing.assert_allclose(heuristic_sigma(d, "quadratic", 0.01), [0.01, 0.04, 0.16], rtol=1e-6)
    np.testing.assert_allclose(heuristic_sigma(d, "linear", 0.02), [0.02, 0.04, 0.08], rtol=1e-6)
    with pytest.raises(ValueError):
        heuristic_sigma(d, "cubic", 1.0)


def test_metrics_by_hand():
    m = depth_metrics(np.array([1.1, 2.0, np.nan]), np.array([0.1, 0.5, 1.0]), np.array([1.0, 2.5, 1.0]))
    assert m["n"] == 2
    assert m["absrel"] == pytest.approx((0.1 / 1.0 + 0.5 / 2.5) / 2)
    assert m["rmse"] == pytest.approx(np.sqrt((0.01 + 0.25) / 2))
    assert m["mahalanobis"] == pytest.approx(1.0)
    assert m["delta1"] == 0.5  # 2.5 / 2.0 = 1.25 is not < 1.25
    assert m["nll_laplace"] == pytest.approx(np.mean([1 + np.log(0.2), 1 + np.log(1.0)]))


def test_median_gain_rule_resists_a_tail_of_gross_errors():
    """Laplacian errors of scale b with 15 % gross outliers: the 'median' rule moves by the
    outliers' share of the quantile only (1.28x), the mean rule is pulled far up by the tail; both agree on clean data; an unknown rule is refused."""
    rng = np.random.default_rng(2)
    n = 200_000
    gt = rng.uniform(1, 6, n)
    b = 0.01 * gt
    clean = gt + rng.laplace(0, b)
    sigma = 0.5 * b  # over-confident by 2
    assert calibration_gain(clean, sigma, gt, "median") == pytest.approx(2.0, rel=0.02)
    assert calibration_gain(clean, sigma, gt, "mean") == pytest.approx(2.0, rel=0.02)
    gross = rng.random(n) < 0.15
    dirty = np.where(gross, gt + rng.uniform(-2, 2, n), clean)
    # the overall median is the clean errors' 0.5 / 0.85 quantile: -ln(1 - 0.5 / 0.85) b instead of ln 2 b
    bulk = -np.log(1 - 0.5 / 0.85) / np.log(2)
    assert calibration_gain(dirty, sigma, gt, "median") == pytest.approx(2.0 * bulk, rel=0.03)
    assert calibration_gain(dirty, sigma, gt, "mean") > 5 * 2.0
    with pytest.raises(ValueError, match="unknown gain rule"):
        gain_from_ratios(np.ones(3), "mode")
    with pytest.raises(ValueError, match="no valid pixels"):
        gain_from_ratios(np.array([np.nan]))


def test_fusion_with_correlated_errors_predicts_its_error():
    """Errors with correlation rho: fusing with that rho gives a sigma that matches the error and no larger error
    than either source; assuming independence (eq. 14) makes the sigma too small."""
    rng = np.random.default_rng(1)
    n, rho = 200_000, 0.6
    truth = rng.uniform(1, 5, n)
    s1, s2 = rng.uniform(0.05, 0.5, n), rng.uniform(0.05, 0.5, n)
    g1 = rng.standard_normal(n)
    g2 = rho * g1 + np.sqrt(1 - rho ** 2) * rng.standard_normal(n)
    d1, d2 = truth + s1 * g1, truth + s2 * g2
    d, s = fuse(d1, s1, d2, s2, rho)
    assert abs(((d - truth) / s).std() - 1.0) < 0.01
    mse = np.mean((d - truth) ** 2)
    assert mse <= min(np.mean((d1 - truth) ** 2), np.mean((d2 - truth) ** 2))
    _, s_indep = fuse(d1, s1, d2, s2)
    assert ((d - truth) / s_indep).std() > 1.1
    # a much worse, strongly correlated source gets weight 0, not a negative one: the better source is kept
    d, s = fuse(np.array([2.0]), np.array([0.1]), np.array([3.0]), np.array([1.0]), 0.5)
    assert d[0] == pytest.approx(2.0) and s[0] == pytest.approx(0.1)
    with pytest.raises(ValueError):
        fuse(d1, s1, d2, s2, 1.0)
