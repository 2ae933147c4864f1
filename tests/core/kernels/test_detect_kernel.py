"""The per-window measurement and its assessment (``service.core._kernels.detect_kernel``) against NumPy.

The reference measures a window the way ``detect_windows`` describes it, on whole arrays: the
circle and its rim as boolean masks, the background plane by ``np.linalg.lstsq`` through the
rim's dark pixels, the moments of the plane-corrected pixels taken directly about the centroid
(the kernel takes raw moments and removes the plane's slopes analytically), the ellipse from
``np.linalg.eigh`` less the blur the plateau implies, and the fill model drawn over the window.
The assessment's noise terms are sums over the circle's pixels of the polynomials they
propagate (the kernel uses the window's moment sums) and moments of the uniform disk by
quadrature; the shot-noise coefficient is ``np.median``.

Windows are seeded blurred disks and ellipses on a sloping, noisy background, 8 and 16 bit:
clean ones, ones a neighbour crosses, saturated ones, windows at the image border, windows read
from the masked buffer, windows outside the image.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import roots_legendre

from service.core._kernels import detect_kernel as K
from service.core._kernels.detect_kernel import assess_kernel, measure_predicted_kernel, measure_windows_kernel
from service.core._kernels.edge_kernel import edge_centres_kernel
from service.core._kernels.illumination_kernel import fit_light, light_gradient
from service.core.targets.detect_types import DetectSettings
from service.core.targets.detect_windows import assess, assess_constants, measure_all


def _disk_moments(q, powers):
    """E[x^p] over a uniform disk whose marginal variance is q (radius 2 sqrt(q)), by quadrature:
    Gauss-Legendre in r, the trapezoid rule in theta; exact for these polynomials."""
    radius = 2 * np.sqrt(q)
    r, w = roots_legendre(12)
    r, w = 0.5 * radius * (r + 1), 0.5 * radius * w
    theta = np.linspace(0, 2 * np.pi, 32, endpoint=False)
    x = r[:, None] * np.cos(theta)[None]
    weight = (w * r)[:, None] * (2 * np.pi / 32) / (np.pi * radius**2)
    return [np.sum(weight * x**p) for p in powers]


def _measure_reference(P, img_win, h, seg, full):
    """The window's rows of measure_windows_kernel's output, (saturated, rim crossed)."""
    dv, du = np.mgrid[-h : h + 1, -h : h + 1].astype(np.float64)
    d2 = du**2 + dv**2
    circle, inner = d2 <= (h + 0.5) ** 2, d2 <= (h - 1.0) ** 2
    rim = circle & ~inner
    P = P.astype(np.float64)
    peak = float(img_win[circle].max())  # the window is the circle: its corners are not looked at
    n_sat = int(np.sum(img_win[circle] >= full)) if peak >= full else 0
    # the background plane through the rim's dark pixels
    rb, ru, rv = P[rim], du[rim], dv[rim]
    bright = rb > rb.mean() + seg
    used = np.ones(rb.size, bool)
    if bright.any():
        used = rb <= rb[~bright].mean() + seg
        assert used.sum() >= 6  # (the kernel's fallback for fewer is not exercised here)
    A = np.column_stack([np.ones(used.sum()), ru[used], rv[used]])
    (b0, b1, b2), *_ = np.linalg.lstsq(A, rb[used], rcond=None)
    rss = np.sum((rb[used] - A @ [b0, b1, b2]) ** 2)
    m_used = used.sum()
    ruu = 0.5 * np.sum(ru[used] ** 2 + rv[used] ** 2)
    sb2 = max(rss, 0) / max(m_used - 3, 1)
    # moments of the plane-corrected circle, about the centroid
    q = np.where(circle, P - (b0 + b1 * du + b2 * dv), 0.0)
    S = q.sum()
    uc, vc = np.sum(q * du) / S, np.sum(q * dv) / S
    x, y = du - uc, dv - vc

    def mom(i, j):
        return np.sum(q * x**i * y**j) / S

    M = np.array([[mom(2, 0), mom(1, 1)], [mom(1, 1), mom(0, 2)]])
    lam, vec = np.linalg.eigh(M)
    # the plateau: 3 x 3 pixels about the rounded centroid, in the circle, less the plane there
    ci, cj = (int(np.clip(np.rint(c), 1 - h, h - 1)) + h for c in (uc, vc))
    core = np.where(circle, P - b0, 0.0)[cj - 1 : cj + 2, ci - 1 : ci + 2]
    level = core.mean() - (b1 * uc + b2 * vc)
    core_var = np.var(core, ddof=1)
    # blur s: (l1 - s)(l2 - s) = (S / (4 pi level))^2, the smaller root, within [0, 0.9 l_min]
    root = np.roots([1.0, -(lam[0] + lam[1]), lam[0] * lam[1] - (S / (4 * np.pi * level)) ** 2]).real.min()
    s = max(min(root, 0.9 * lam[0]), 0.0)
    a, b = 2 * np.sqrt(lam[1] - s), 2 * np.sqrt(lam[0] - s)
    e = vec[:, 1]
    angle = np.arctan2(e[1], e[0])
    angle = (angle + np.pi / 2) % np.pi - np.pi / 2  # (-pi/2, pi/2]
    along = x * e[0] + y * e[1]
    var_major = np.sum(q * along**2) / S
    kurt = np.sum(q * along**4) / S / var_major**2
    m3sq = mom(3, 0) ** 2 + 3 * mom(2, 1) ** 2 + 3 * mom(1, 2) ** 2 + mom(0, 3) ** 2
    # a uniform disk's marginal (variance a^2 / 4) blurred by a Gaussian of variance s
    e2, e4 = _disk_moments(a * a / 4, (2, 4))
    kurt_model = (e4 + 6 * e2 * s + 3 * s * s) / (e2 + s) ** 2
    # the fill's model: clip(level / 2 + k (1 - rho^2), 0, level), rho = 1 on the blur-free ellipse
    if np.isfinite(uc) and S > 0 and level > 0 and b > 0:
        G = M - s * np.eye(2)
        rho2 = np.einsum("...i,ij,...j->...", np.stack([x, y], -1), np.linalg.inv(G), np.stack([x, y], -1)) / 4
        k = 0.5 * level * np.sqrt(a * b) / np.clip(np.sqrt(2 * np.pi * s), 0.5, 4.0)
        model = np.clip(level / 2 + k * (1 - rho2), 0, level)
        mismatch = np.sum(np.abs(model - np.where(circle, P - b0, 0.0))) / level
    else:
        mismatch = np.inf
    area = S / level
    a0, c2, c4, c22 = circle.sum(), np.sum(du[circle] ** 2), np.sum(du[circle] ** 4), np.sum((du * dv)[circle] ** 2)
    sums = [a0, c2, c4, c22, np.sum(du[circle] ** 6), np.sum((du**4 * dv**2)[circle]), np.sum(du[circle] ** 8)]
    row = np.zeros(K.NF)
    row[K.EDGE_UV : K.EDGE_SIGMA + 1] = np.nan  # the edge fit, not asked for (its own reference: test_edge_kernel)
    row[K.N_SAT] = n_sat
    row[0:5] = [uc, vc, a, b, angle]
    row[K.FLUX], row[K.LEVEL], row[K.PEAK] = S, level, peak
    row[K.BACKGROUND], row[K.SB2] = b0 + b1 * uc + b2 * vc, sb2
    row[K.K_SHOT] = max(core_var - sb2, 0) / level
    # the centroid's variance from background noise, per axis (detect_windows.measure_all), averaged
    row[K.VAR_BASE] = np.mean([sb2 * (c2**2 / ruu - c2 + c**2 * (a0**2 / m_used - a0)) / S**2 for c in (uc, vc)])
    row[K.VAR_PER_K], row[K.MISMATCH] = np.trace(M) / 2 / S, mismatch
    row[K.NOISE_BG] = np.sqrt(2 / np.pi * sb2) * max(a0 - area, 0) / level
    row[K.M3SQ], row[K.KURT], row[K.KURT_MODEL] = m3sq, kurt, kurt_model
    row[K.FLAT_TOP], row[K.VAR_MAJOR], row[K.BLUR] = 1 - s / lam[0], var_major, s
    row[K.SUMS : K.SUMS + 7] = sums
    return row, n_sat, m_used <= rb.size - 2


def _scene(rng, dtype, shape=(200, 260), n=24):
    """Blurred disks and ellipses on a plane with noise; their centres (n, 2) and radii (n,)."""
    full = 255 if dtype == np.uint8 else 4095
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    img = 0.12 * full + 0.0002 * full * (u - 2 * v) + rng.normal(0, 0.006 * full, shape)
    centres = np.column_stack([rng.uniform(20, shape[1] - 20, n), rng.uniform(20, shape[0] - 20, n)])
    radii = rng.uniform(2.5, 9.0, n)
    for (cu, cv), r in zip(centres, radii):
        ang, ratio, blur = rng.uniform(0, np.pi), rng.uniform(0.5, 1.0), rng.uniform(0.5, 1.2)
        x, y = u - cu, v - cv
        xr, yr = x * np.cos(ang) + y * np.sin(ang), (-x * np.sin(ang) + y * np.cos(ang)) / ratio
        edge = (np.hypot(xr, yr) - r) * np.minimum(1, ratio + 0.3)
        img += rng.uniform(0.3, 0.8) * full * 0.5 * (1 - np.tanh(edge / blur))
    return np.clip(np.rint(img), 0, full).astype(dtype), full, centres, radii


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_measured_windows_are_the_numpy_measurement(rng, dtype):
    img, full, centres, radii = _scene(rng, dtype)
    img[10:14, 250:254] = full  # a saturated patch ...
    centres[0], radii[0] = [251.5, 11.5], 2.0  # ... measured in a window at the image border
    n = len(centres)
    cu, cv = (np.ascontiguousarray(np.rint(centres[:, k] + rng.uniform(-1, 1, n)), dtype=np.intp) for k in (0, 1))
    half = np.ascontiguousarray(np.ceil(radii + 4 + rng.uniform(0, 4, n)), dtype=np.intp)
    cu[0], cv[0], half[0] = 251, 8, 8  # cv - half = 0: the window's first row is the image's
    cu[1], cv[1] = 5, img.shape[0] - 3  # a window reaching out of the image
    placed = (cu >= half) & (cu + half < img.shape[1]) & (cv >= half) & (cv + half < img.shape[0])
    assert placed[0] and not placed.all()  # one window at the border, some outside
    seg = np.full(n, 0.03 * full)
    # some windows read from the buffer (as mask_windows_kernel leaves them): the image's values
    # with a slight change, so a mistaken read of the image would show
    boff = np.full(n, -1, dtype=np.intp)
    parts, total = [], 0
    for i in np.flatnonzero(placed)[1::3]:
        s = 2 * half[i] + 1
        window = img[cv[i] - half[i] : cv[i] + half[i] + 1, cu[i] - half[i] : cu[i] + half[i] + 1]
        parts.append((window.astype(np.float32) * np.float32(0.97)).ravel())
        boff[i], total = total, total + s * s
    buf = np.concatenate(parts)
    out, n_sat, edge = measure_windows_kernel(img, cu, cv, half, placed, seg, float(full), buf, boff, False)
    assert out.shape == (K.NF, n)
    for i in range(n):
        if not placed[i]:  # zeros and a crossed rim
            assert np.all(out[: K.EDGE_UV, i] == 0) and n_sat[i] == 0 and edge[i]
            continue
        h = half[i]
        img_win = img[cv[i] - h : cv[i] + h + 1, cu[i] - h : cu[i] + h + 1]
        P = img_win if boff[i] < 0 else buf[boff[i] : boff[i] + (2 * h + 1) ** 2].reshape(2 * h + 1, -1)
        ref, sat_ref, crossed_ref = _measure_reference(P, img_win, h, seg[i], full)
        ref[0] += cu[i]
        ref[1] += cv[i]
        assert n_sat[i] == sat_ref and edge[i] == crossed_ref, i
        got = out[:, i]
        # the angle of a near-circular blob is ill-conditioned: compare it modulo pi, scaled by
        # the eccentricity (round-off of the moments ~1e-13 px^2 over l1 - l2)
        lam_gap = got[2] ** 2 - got[3] ** 2
        d_angle = (got[4] - ref[4] + np.pi / 2) % np.pi - np.pi / 2
        assert abs(d_angle) * lam_gap < 1e-9, i
        ref[4] = got[4]
        # sums over ~100-1000 pixels in another order (fastmath reassociation), raw moments less the
        # centroid's square against moments about the centroid, normal equations against lstsq:
        # measured up to 2.4e-13 relative on every row; the shot-noise coefficient (plateau variance
        # less sb2, ~1 DN/DN) cancels to 3e-9 relative, 1e-12 absolute
        np.testing.assert_allclose(got, ref, rtol=1e-11, atol=1e-9, err_msg=f"window {i}")
    assert n_sat[0] > 0 and edge.sum() > (~placed).sum()  # saturation and crossed rims were met
    # with the edge fit: the same measurement, and each placed window's edge centre is the edge
    # kernel's from its centroid and ellipse, on the image (not the masked buffer)
    with_fit = measure_windows_kernel(img, cu, cv, half, placed, seg, float(full), buf, boff, True)
    np.testing.assert_array_equal(with_fit[0][: K.EDGE_UV], out[: K.EDGE_UV])
    np.testing.assert_array_equal(with_fit[1], n_sat)
    np.testing.assert_array_equal(with_fit[2], edge)
    # the light the edges followed: fitted to the usable windows' plateaus, taken at each centroid
    h_img, w_img = img.shape
    o = with_fit[0]
    coef = fit_light(o[0], o[1], o[K.LEVEL], o[3], n_sat, placed & ~edge, w_img, h_img, K.CLIPPED_PX)
    for i in np.flatnonzero(placed):
        assert tuple(o[K.LIGHT : K.LIGHT + 2, i]) == light_gradient(coef, o[0, i], o[1, i], w_img, h_img)
    e = with_fit[0][:, placed]
    light = e[K.LIGHT : K.LIGHT + 2].T.copy()
    uv_ref, sigma_ref, ok = edge_centres_kernel(img, e[:2].T.copy(), e[:5].T.copy(), e[K.BACKGROUND].copy(), light)
    assert 0.5 * placed.sum() < ok.sum() < placed.sum()  # fits held, and some did not
    np.testing.assert_array_equal(e[K.EDGE_SIGMA], sigma_ref)
    np.testing.assert_array_equal(e[K.EDGE_UV : K.EDGE_UV + 2][:, ok], uv_ref[ok].T)
    assert np.all(np.isnan(e[K.EDGE_UV : K.EDGE_UV + 2][:, ~ok])) and np.all(
        np.isnan(with_fit[0][K.EDGE_UV : K.EDGE_SIGMA + 1, ~placed])
    )
    # no windows at all
    empty = measure_windows_kernel(
        img, *(np.zeros(0, np.intp),) * 3, np.zeros(0, bool), np.zeros(0), 255.0, buf, np.zeros(0, np.intp), True
    )
    assert empty[0].shape == (K.NF, 0) and empty[1].shape == empty[2].shape == (0,)


def _assess_reference(out, n_sat, edge, usable, contrast, limits, codes, h):
    """Reasons, sigma_px and fill, with the noise terms summed over each window's circle."""
    min_area, max_area, max_aspect, min_fill, max_sat, min_b, min_flat = limits[:7]
    sig0, sig1, floor0, floor1, ratio_flat, ratio_small = limits[7:13]
    a, b = out[2], out[3]
    S, level, sb2 = out[K.FLUX], out[K.LEVEL], out[K.SB2]
    with np.errstate(divide="ignore", invalid="ignore"):
        area = S / level
        levels = np.select(
            [
                n_sat > max_sat,
                ~((out[K.PEAK] - out[K.BACKGROUND] >= contrast) & (level > 0)),
                ~(area >= min_area),
                ~(area <= max_area),
            ],
            codes[:4],
            -1,
        )
        plateau = (levels < 0) & usable & ~edge & (b >= min_b) & (n_sat <= K.CLIPPED_PX)
        k = np.median(out[K.K_SHOT][plateau]) / 0.918 if plateau.any() else 0.0
        sigma = np.sqrt(out[K.VAR_BASE] + k * out[K.VAR_PER_K])
        tr = 2 * out[K.VAR_PER_K] * S
        mis = np.maximum(out[K.MISMATCH] - out[K.NOISE_BG] - np.sqrt(2 / np.pi * (sb2 + k * level)) * area / level, 0)
        fill = np.nan_to_num((area + np.pi * a * b - mis) / (area + np.pi * a * b + mis))
    reason = np.empty(len(S), dtype=int)
    for i in range(len(S)):
        dv, du = np.mgrid[-h[i] : h[i] + 1, -h[i] : h[i] + 1].astype(np.float64)
        circle = du**2 + dv**2 <= (h[i] + 0.5) ** 2
        du, dv = du[circle], dv[circle]
        m = tr[i] / 2
        # noise of |mu3| through the pixels: the third-order Hermite-like polynomials of each pixel
        bg3 = np.sum(2 * (du**3 - 3 * m * du) ** 2 + 6 * (du**2 * dv - m * dv) ** 2)
        asym_noise = np.sqrt(sb2[i] * bg3 + k * S[i] * (4 * m) ** 3 / 8) / S[i] / (2 * tr[i])
        m2, kap = out[K.VAR_MAJOR, i], out[K.KURT_MODEL, i]
        al, be = 2 * kap * m2, kap * m2**2
        bg4 = np.sum((du**4 - al * du**2 + be) ** 2)
        x2, x4, x6, x8 = _disk_moments(a[i] ** 2 / 4, (2, 4, 6, 8))
        shot4 = x8 - 2 * al * x6 + (al**2 + 2 * be) * x4 - 2 * al * be * x2 + be**2  # E[(x^4 - al x^2 + be)^2]
        kurt_noise = np.sqrt(sb2[i] * bg4 + k * S[i] * max(shot4, 0)) / (S[i] * m2**2)
        ratio_max = ratio_flat if b[i] >= min_b else ratio_small
        # the disk, or the disk smeared along its major axis: the ellipse's own variance qa - s and
        # the smear's s add, their fourth cumulants -(qa - s)^2 and -1.2 s^2 too; searched on a grid
        qa, qb = a[i] ** 2 / 4, b[i] ** 2 / 4
        s_grid = np.linspace(0.0, max(qa - qb, 0.0), 4001) if np.isfinite(qa - qb) else np.zeros(1)
        kurt_smeared = 3 - ((qa - s_grid) ** 2 + 1.2 * s_grid**2) / m2**2
        k_lo, k_hi = min(kurt_smeared.min(), kap), max(kurt_smeared.max(), kap)
        tol = sig1 * kurt_noise + floor1
        with np.errstate(invalid="ignore"):
            ok = (
                b[i] * max_aspect >= a[i]
                and fill[i] >= min_fill
                and out[K.FLAT_TOP, i] >= min_flat
                and area[i] <= ratio_max * np.pi * a[i] * b[i]
                and np.sqrt(out[K.M3SQ, i]) / (2 * tr[i]) <= sig0 * asym_noise + floor0
                and k_lo - tol <= out[K.KURT, i] <= k_hi + tol
                and np.isfinite(out[0, i])
                and np.isfinite(out[1, i])
            )
        reason[i] = levels[i] if levels[i] >= 0 else (-1 if ok else codes[4])
    return reason, sigma, fill


@pytest.mark.parametrize("max_saturated_px", [None, 2])  # clipped disks measured (the default), rejected
def test_assessment_is_the_numpy_decision(rng, max_saturated_px):
    img, full, centres, radii = _scene(rng, np.uint8, shape=(400, 500), n=90)
    img[rng.integers(0, 400, 300), rng.integers(0, 500, 300)] = 255  # hot pixels: saturated windows
    n = len(centres) + 10
    centres = np.concatenate([centres, rng.uniform(30, [470, 370], (10, 2))])  # 10 off any target
    radii = np.concatenate([radii, np.full(10, 4.0)])
    cu, cv = (np.ascontiguousarray(np.rint(centres[:, k]), dtype=np.intp) for k in (0, 1))
    half = np.ascontiguousarray(np.ceil(radii + 4 + rng.uniform(0, 3, n)), dtype=np.intp)
    placed = (cu >= half) & (cu + half < 500) & (cv >= half) & (cv + half < 400)
    seg = np.full(n, 0.03 * full)
    buf, boff = np.zeros(1, np.float32), np.full(n, -1, dtype=np.intp)
    out, n_sat, edge = measure_windows_kernel(img, cu, cv, half, placed, seg, float(full), buf, boff, False)
    limits, codes = assess_constants(DetectSettings(max_saturated_px=max_saturated_px))
    contrast = np.full(n, 0.08 * full)
    usable = placed & (rng.random(n) < 0.9)
    reason, sigma, fill = assess_kernel(out, n_sat, edge, usable, contrast, limits, codes)
    reason_r, sigma_r, fill_r = _assess_reference(
        out[:, placed], n_sat[placed], edge[placed], usable[placed], contrast[placed], limits, codes, half[placed]
    )
    np.testing.assert_array_equal(reason[placed], reason_r)
    # square roots and ratios of the same numbers: relative round-off
    np.testing.assert_allclose(sigma[placed], sigma_r, rtol=1e-12, atol=0, equal_nan=True)
    np.testing.assert_allclose(fill[placed], fill_r, rtol=1e-12, atol=1e-15)
    # accepted, and several reasons (saturated among them only when asked for)
    assert (reason_r == -1).sum() > 20 and len(set(reason_r) - {-1}) >= (2 if max_saturated_px is None else 3)
    # windows with hot pixels: rejected as saturated only when asked; measured (and flagged) else
    assert (codes[0] in reason_r) == (max_saturated_px is not None) and (n_sat[placed] > 2).any()
    # none on a plateau (no usable window): no shot noise, the background's alone
    reason0, sigma0, _ = assess_kernel(out, n_sat, edge, np.zeros(n, bool), contrast, limits, codes)
    np.testing.assert_allclose(sigma0[placed], np.sqrt(out[K.VAR_BASE][placed]), rtol=1e-12, equal_nan=True)
    empty = assess_kernel(
        np.zeros((K.NF, 0)), np.zeros(0, np.intp), np.zeros(0, bool), np.zeros(0, bool), np.zeros(0), limits, codes
    )
    assert all(x.shape == (0,) for x in empty)


@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("edge_fit", [False, True])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_predicted_windows_are_measured_and_assessed_as_the_numpy_path_does(rng, dtype, edge_fit, masked):
    """The one call of ROI tracking against measure_all + assess + the selection of accepted
    windows (what measure_windows did in numpy): the same disks, rows, sigma, fill and indices;
    with the edge fit, the centres and sigma are the edge fit's where it held; with own regions
    (a coded target's ring masked), every other window's neighbours masked as measure_all masks them."""
    img, full, centres, radii = _scene(rng, dtype)
    n = len(centres)
    uv = centres + rng.uniform(-1.5, 1.5, (n, 2))
    uv[0] = [np.nan, 40.0]  # no prediction
    uv[1] = [3.0, 3.0]  # a window reaching out of the image: made as large as it allows (3 px)
    half = np.ascontiguousarray(np.ceil(radii + 5), dtype=np.intp)
    half[2] = 2  # too small for its disk: refused
    seg, contrast = 0.03 * full, 0.08 * full
    limits, codes = assess_constants(DetectSettings())
    frozen = img.view()
    frozen.flags.writeable = False  # a replayed frame is read-only: the same measurement
    own = np.full((n, 5), np.nan)
    if masked:  # every other window: the disk and 1.5 px about the prediction
        r = (radii[::2] + 1.5) ** -2
        own[::2] = np.column_stack([uv[::2] - np.rint(uv[::2]), r, 0 * r, r])
        own[0] = np.nan
    table, sigma, fill, found = measure_predicted_kernel(
        frozen, uv, half, seg, contrast, float(full), limits, codes, edge_fit, own
    )
    if masked:  # some window had a neighbour to mask (the scene's crossed windows)
        plain = measure_predicted_kernel(
            frozen, uv, half, seg, contrast, float(full), limits, codes, edge_fit, np.full((n, 5), np.nan)
        )
        assert not np.array_equal(found, plain[3]) or not np.array_equal(table, plain[0])

    finite = np.isfinite(uv).all(axis=1)
    c = np.rint(np.where(finite[:, None], uv, -1e6)).astype(np.intp).T.copy()
    h_img, w_img = img.shape
    fits = np.minimum.reduce([half, c[0], w_img - 1 - c[0], c[1], h_img - 1 - c[1]])  # at the border: smaller
    meas, placed = measure_all(
        img, c[0], c[1], np.where(finite, np.maximum(fits, 0), 0), np.full(n, seg), full, own, edge_fit
    )
    reason, sigma_ref, fill_ref = assess(meas, placed, DetectSettings(), np.full(n, contrast))
    if edge_fit:  # the edge fit's centre and sigma where it held (blobs_from's choice)
        held = np.isfinite(meas.edge_sigma)
        assert held.sum() > n // 2
        meas.table[: K.UV + 2, held] = meas.edge_uv[held].T
        sigma_ref = np.where(held, meas.edge_sigma, sigma_ref)
    ok = ((reason < 0) & ~meas.edge & placed).nonzero()[0]
    assert 0 < ok.size < n - 3 and not placed[0] and placed[1] and found[1] == found[2] == -1  # refused ones
    np.testing.assert_array_equal(found[ok], np.arange(ok.size))
    assert np.all(np.delete(found, ok) == -1)
    np.testing.assert_array_equal(table, meas.table[:, ok])
    np.testing.assert_array_equal(sigma, sigma_ref[ok])
    np.testing.assert_array_equal(fill, fill_ref[ok])
