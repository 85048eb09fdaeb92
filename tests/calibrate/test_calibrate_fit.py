"""The public per-pixel fit API (``hsiffc.calibrate``) and the model gradient it is built on."""

from __future__ import annotations

import numpy as np

from hsiffc.leakage import model
from hsiffc.calibrate import model_and_jacobian, predict


def _random_params(n, seed=0):
    rng = np.random.default_rng(seed)
    t = rng.uniform(0, 500, n)
    t[:10] = 0
    k = np.exp(rng.uniform(-8, 4, n))
    k[10:20] = 0
    b = np.exp(rng.uniform(np.log(1e-4), np.log(0.1), n))
    a = k * np.exp(-b * rng.uniform(0, 2000, n))
    a[20:30] = 0
    d = rng.uniform(0, 100, n)
    return t, k, a, b, d


def test_response_and_gradient_is_the_response_and_its_derivatives():
    t, k, a, b, d = _random_params(20000)
    y, *grad = model.response_and_gradient(t, k, a, b, d)
    assert np.max(np.abs(y - model.response(t, k, a, b, d))) < 1e-9
    eps = 1e-6
    moves = [lambda e: model.response(t, k * np.exp(e), a, b, d),
             lambda e: model.response(t, k, a * np.exp(e), b, d),
             lambda e: model.response(t, k, a, b * np.exp(e), d),
             lambda e: model.response(t, k, a, b, d + e)]
    for g, move in zip(grad, moves):
        numeric = (move(eps) - move(-eps)) / (2 * eps)
        assert np.max(np.abs(numeric - g) / np.maximum(1.0, np.abs(numeric))) < 1e-4


def test_model_and_jacobian_per_pixel_parameters():
    rng = np.random.default_rng(1)
    p, s = 50, 12
    theta = np.column_stack([np.log(rng.uniform(1, 10, p)), rng.uniform(-14, -8, p),
                             np.log(rng.uniform(0.005, 0.02, p)), rng.uniform(20, 40, p)])
    t = np.geomspace(1, 400, s)
    r = np.r_[np.ones(s - 2), 0.0, 0.0]
    dc = rng.uniform(0, 0.1, (p, 1))
    y, jac = model_and_jacobian(theta, t, r, dc)
    assert y.shape == (p, s) and jac.shape == (p, s, 4)
    assert np.allclose(y, predict(theta, t, r, dc), atol=1e-9)
    eps = 1e-6
    for i in range(4):
        step = np.zeros(4)
        step[i] = eps
        numeric = (predict(theta + step, t, r, dc) - predict(theta - step, t, r, dc)) / (2 * eps)
        assert np.allclose(jac[..., i], numeric, rtol=1e-4, atol=1e-5)
    assert np.all(jac[:, -2:, 0] == 0)  # dark samples do not depend on the responsivity
