"""The light across a frame (``illumination_kernel.fit_light``, ``light_gradient``) against NumPy.

The reference does what the kernel's docstring says with array operations: the plateaus that count
(level > 0, semi-minor axis >= MIN_PLATEAU_PX, not clipped, their window usable), those within
FAR_FROM_MEDIAN of the median, then PASSES + 1 ridge least-squares fits of ``ln(level)`` on the
quadratic's terms (``np.linalg.solve`` of the normal equations), each after dropping the plateaus
farther than TRIM robust sigmas from the residuals' median of the fit before. And on plateaus of a
known light, with the junk a real frame holds, the gradient is the light's.
"""

from __future__ import annotations

import numpy as np
import pytest

from service.core._kernels import illumination_kernel as L
from service.core._kernels.detect_kernel import CLIPPED_PX

W, H = 1300, 1030


def _terms(u, v):
    s = 2.0 / max(W, H)
    x, y = (u - W / 2) * s, (v - H / 2) * s
    return np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])


def _reference(u, v, level, b, n_sat, usable):
    use = usable & (level > 0) & (b >= L.MIN_PLATEAU_PX) & (n_sat <= CLIPPED_PX) & np.isfinite(u) & np.isfinite(v)
    if use.sum() < L.MIN_DISKS:
        return np.zeros(L.N_COEF)
    y = np.log(np.where(use, level, 1.0))
    use &= np.abs(y - np.median(y[use])) <= L.FAR_FROM_MEDIAN
    T = _terms(u, v)
    for k in range(L.PASSES + 1):
        if use.sum() < L.MIN_DISKS:
            return np.zeros(L.N_COEF)
        A = T[use]
        G = A.T @ A + np.diag([0.0] + [L.RIDGE * use.sum()] * (L.N_COEF - 1))
        coef = np.linalg.solve(G, A.T @ y[use])
        if k == L.PASSES:
            break
        e = y - T @ coef
        mid = np.median(e[use])
        limit = max(L.TRIM * 1.4826 * np.median(np.abs(e[use] - mid)), L.MIN_TRIM)
        use &= np.abs(e - mid) <= limit
    coef[0] = 0.0
    return coef


def _plateaus(rng, n, falloff):
    """``n`` disks over the frame under a ring light darkening the corners by ``falloff``, with
    shot noise, some small and some clipped disks, and a tenth of them junk (grey print, a
    sticker's edge: a tenth of the level, or half)."""
    u, v = rng.uniform(20, W - 20, n), rng.uniform(20, H - 20, n)
    r2 = ((u - W / 2) ** 2 + (v - H / 2) ** 2) / ((W / 2) ** 2 + (H / 2) ** 2)
    light = 1.0 - falloff * r2
    level = 200.0 * light * rng.normal(1.0, 0.02, n)
    junk = rng.random(n) < 0.1
    level[junk] *= rng.choice([0.1, 0.5], junk.sum())
    b = rng.uniform(2.5, 9.0, n)
    n_sat = np.where(rng.random(n) < 0.05, 10, 0)
    usable = rng.random(n) < 0.95
    return u, v, level, b, n_sat.astype(np.intp), usable, light


@pytest.mark.parametrize("falloff", [0.0, 0.3, 0.6])
def test_the_light_is_the_numpy_fit_and_its_gradient_the_lights(rng, falloff):
    u, v, level, b, n_sat, usable, light = _plateaus(rng, 250, falloff)
    coef = L.fit_light(u, v, level, b, n_sat, usable, W, H, CLIPPED_PX)
    np.testing.assert_allclose(coef, _reference(u, v, level, b, n_sat, usable), rtol=1e-9, atol=1e-12)
    got = np.array([L.light_gradient(coef, uu, vv, W, H) for uu, vv in zip(u, v, strict=True)])
    # the light's own: d ln(1 - f r2) / du
    D = (W / 2) ** 2 + (H / 2) ** 2
    true = -falloff * 2 * np.column_stack([u - W / 2, v - H / 2]) / D / light[:, None]
    inner = np.hypot(u - W / 2, v - H / 2) < 0.6 * np.sqrt(D)  # a quadratic bends less than ln(1 - f r2) outside
    assert np.max(np.abs(got - true)[inner]) < 1.5e-4 + 0.12 * np.max(np.abs(true)), falloff


def test_too_few_plateaus_an_even_light_and_the_clamp(rng):
    u, v, level, b, n_sat, usable, _ = _plateaus(rng, 250, 0.3)
    small = np.full(u.size, L.MIN_PLATEAU_PX - 0.1)  # no core on its plateau: no fit
    assert not L.fit_light(u, v, level, small, n_sat, usable, W, H, CLIPPED_PX).any()
    few = slice(0, L.MIN_DISKS - 1)
    big = np.full(u.size, 6.0)
    assert not L.fit_light(u[few], v[few], level[few], big[few], n_sat[few], usable[few], W, H, CLIPPED_PX).any()
    even = L.fit_light(u, v, np.full(u.size, 150.0), big, n_sat, usable, W, H, CLIPPED_PX)
    assert np.max(np.abs(even)) < 1e-12
    steep = np.zeros(L.N_COEF)
    steep[1] = 100.0  # ln L rising by 100 across half the frame: no light
    assert L.light_gradient(steep, 650.0, 500.0, W, H) == (L.MAX_GRADIENT, 0.0)
