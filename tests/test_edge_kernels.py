"""The line extractor's compiled loops (omni_sfm/lines/_edges.c) against the numpy code they
replaced in omni_sfm/lines/extract.py (kept here as the reference): the same bits, except the
corner test's window sums (summed in another order than numpy's BLAS), whose decisions must
still agree."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from linetest_utils import Room, hyperboloid_camera, render

from omni_sfm.lines import edge_kernels
from omni_sfm.lines.extract import LineExtractor, _oriented_components

# ---- the numpy reference implementations (extract.py before the kernels) ---------------------


def _corner_numpy(dxy_img, pix, flat, win_flat, win_w, ratio, origin):
    dxy = dxy_img.ravel()
    wxy = np.take(dxy, flat[:, None] + win_flat)
    wx, wy = wxy.real, wxy.imag
    a = (wx * wx) @ win_w
    b = (wy * wy) @ win_w
    c = (wx * wy) @ win_w
    half_tr = 0.5 * (a + b)
    disc = np.sqrt(np.maximum(0.25 * (a - b) ** 2 + c * c, 0.0))
    lmax, lmin = half_tr + disc, np.maximum(half_tr - disc, 0.0)
    keep = lmax >= ratio**2 * lmin
    pix, flat = np.compress(keep, pix, axis=0), flat[keep]
    g = np.take(dxy, flat)
    theta = np.mod(np.arctan2(g.imag, g.real), np.pi).astype(np.float64)
    return pix + np.array(origin, np.int32), g, theta


def _components_numpy(p, shape, theta, max_angle):
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(p)
    w = int(shape[1])
    img = np.full(int(shape[0]) * w, -1, np.int32)
    flat = p[:, 1].astype(np.int64) * w + p[:, 0]
    img[flat] = np.arange(n, dtype=np.int32)
    nb = np.take(img, flat[:, None] + np.array([1, w - 1, w, w + 1], np.int64)).ravel()
    m = np.flatnonzero(nb >= 0)
    r, c = m >> 2, nb[m].astype(np.int64)
    d = np.abs(theta[r] - theta[c])
    d = np.minimum(d, np.pi - d)
    ok = d < max_angle
    r, c = r[ok], c[ok]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=n))])
    g = csr_matrix((np.ones(len(r), np.int8), c, indptr), shape=(n, n))
    ncomp, lab = connected_components(g, directed=False)
    return int(ncomp), lab.astype(np.int64)


def _magnitude(g):
    gx, gy = g.real, g.imag
    return np.sqrt(gx * gx + gy * gy)


def _bilinear_magnitude(dxy, x, y):
    h, w = dxy.shape
    x = np.clip(x, 0, w - 1.001)
    y = np.clip(y, 0, h - 1.001)
    x0 = x.astype(np.int64)
    y0 = y.astype(np.int64)
    fx, fy = x - x0, y - y0
    i = y0 * w + x0
    f = _magnitude(np.take(dxy.ravel(), i[:, None] + np.array([0, 1, w, w + 1])))
    top = f[:, 0] * (1 - fx) + f[:, 1] * fx
    bot = f[:, 2] * (1 - fx) + f[:, 3] * fx
    return np.asarray(top * (1 - fy) + bot * fy, dtype=np.float32)


def _subpixel_numpy(dxy, pix_all, grad, sel, origin):
    pix, g = np.take(pix_all, sel, axis=0), grad[sel]
    gx, gy = g.real, g.imag
    xl, yl = pix[:, 0] - origin[0], pix[:, 1] - origin[1]
    m0 = _magnitude(g)
    gn = np.where(m0 > 0, m0, 1.0)
    ux, uy = gx / gn, gy / gn
    xs, ys = pix[:, 0], pix[:, 1]
    mp = _bilinear_magnitude(dxy, xl + ux, yl + uy)
    mm = _bilinear_magnitude(dxy, xl - ux, yl - uy)
    den = mp - 2.0 * m0 + mm
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(den < 0, 0.5 * (mm - mp) / den, 0.0)
    off = np.clip(off, -0.5, 0.5)
    return np.stack([xs + off * ux, ys + off * uy], 1).astype(np.float64)


def _msac_numpy(r32, hyp_k, seg, start, t2):
    d = r32[0][:, None] * hyp_k[0][seg]
    for k in (1, 2):
        d += r32[k][:, None] * hyp_k[k][seg]
    t2 = t2[:, None]
    cost = np.minimum(d * d, t2) / t2
    return cost, np.add.reduceat(cost, start, axis=0)


# ---- data ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def frame():
    """A rendered hyperboloid frame (and a noisy copy: texture-like edges everywhere), its
    extractor and the inputs of the corner test, as LineExtractor._edge_points makes them."""
    cam = hyperboloid_camera()
    img = render(cam, Room(), np.eye(3), np.array([0.3, 0.2, 0.1]))
    noisy = np.clip(img + np.random.default_rng(0).normal(0, 12, img.shape), 0, 255)
    ex = LineExtractor(cam)
    return ex, [_corner_inputs(ex, img), _corner_inputs(ex, noisy.astype(np.uint8))]


def _corner_inputs(ex, gray):
    o = ex.options
    roi = ex._roi
    g = gray[roi]
    img = cv2.GaussianBlur(g.astype(np.float32), (5, 5), o.blur_sigma)
    dx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    dy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    dx16 = (dx * 8.0).astype(np.int16)
    dy16 = (dy * 8.0).astype(np.int16)
    edges = cv2.Canny(dx16, dy16, 8.0 * o.canny_low, 8.0 * o.canny_high, L2gradient=True)
    edges = cv2.bitwise_and(edges, ex.search_mask[roi])
    pix = cv2.findNonZero(edges).reshape(-1, 2)
    flat = pix[:, 1].astype(np.int64) * g.shape[1] + pix[:, 0]
    dxy = cv2.merge([dx, dy]).view(np.complex64)[..., 0]
    return dxy, pix, flat, (roi[1].start, roi[0].start)


# ---- corner test ----------------------------------------------------------------------------


def test_corner_test_keeps_the_points_numpy_kept(frame):
    ex, inputs = frame
    for dxy, pix, flat, origin in inputs:
        for ratio in (2.0, 1.3):
            ref_pix, ref_g, ref_theta = _corner_numpy(dxy, pix, flat, ex._win_flat, ex._win_w,
                                                      ratio, origin)
            out_pix, out_g = edge_kernels.corner_test(dxy, pix, flat, ex._win_flat, ex._win_w,
                                                      ratio**2, origin)
            assert 100 < len(out_pix) < len(pix)
            np.testing.assert_array_equal(out_pix, ref_pix)
            np.testing.assert_array_equal(out_g.view(np.uint64), ref_g.view(np.uint64))
            theta = edge_kernels.mod_pi(np.arctan2(out_g.imag, out_g.real))
            np.testing.assert_array_equal(theta, ref_theta)


def test_corner_test_no_point_one_point_and_bounds(frame):
    ex, inputs = frame
    dxy, pix, flat, _ = inputs[0]
    p, g = edge_kernels.corner_test(dxy, pix[:0], flat[:0], ex._win_flat, ex._win_w, 4.0)
    assert p.shape == (0, 2) and g.shape == (0,)
    p, g = edge_kernels.corner_test(dxy, pix[:1], flat[:1], ex._win_flat, ex._win_w, 1.0)
    np.testing.assert_array_equal(p, pix[:1])  # ratio 1 keeps everything
    assert g[0] == dxy.ravel()[flat[0]]
    with pytest.raises(IndexError):
        edge_kernels.corner_test(dxy, pix[:1], np.array([dxy.size - 1]), ex._win_flat,
                                 ex._win_w, 4.0)


def test_mod_pi_is_numpys_float32_remainder():
    rng = np.random.default_rng(3)
    p = np.float32(np.pi)
    a = np.concatenate([rng.uniform(-np.pi, np.pi, 5000), rng.uniform(-20, 20, 500),
                        [0.0, -0.0, p, -p, np.nextafter(p, 0), -np.nextafter(p, 0), 2 * p,
                         -2 * p, 1e-30, -1e-30, np.nan]]).astype(np.float32)
    ref = np.mod(a, np.pi).astype(np.float64)
    out = edge_kernels.mod_pi(a)
    np.testing.assert_array_equal(out.view(np.uint64)[:-1], ref.view(np.uint64)[:-1])
    assert np.isnan(out[-1])
    assert edge_kernels.mod_pi(np.zeros(0, np.float32)).shape == (0,)


# ---- components -----------------------------------------------------------------------------


def test_components_match_scipys_labels_on_random_points():
    rng = np.random.default_rng(0)
    h, w = 60, 80
    for density in (0.05, 0.3, 0.8):
        m = rng.random((h, w)) < density
        m[0], m[-1], m[:, 0], m[:, -1] = False, False, False, False
        ys, xs = np.nonzero(m)
        order = rng.permutation(len(xs))  # the points in any order
        p = np.stack([xs, ys], 1)[order].astype(np.int64)
        theta = rng.uniform(0, np.pi, len(p))
        for max_angle in (np.radians(15), np.radians(60), 4.0):
            ref = _components_numpy(p, (h, w), theta, max_angle)
            out = edge_kernels.oriented_components(p, (h, w), theta, max_angle)
            assert out[0] == ref[0]
            np.testing.assert_array_equal(out[1], ref[1])


def test_components_on_a_frame_and_edge_cases(frame):
    ex, inputs = frame
    dxy, pix, flat, origin = inputs[1]
    p, g = edge_kernels.corner_test(dxy, pix, flat, ex._win_flat, ex._win_w, 4.0, origin)
    theta = edge_kernels.mod_pi(np.arctan2(g.imag, g.real))
    q = p.astype(np.int64) - (p.min(0) - 1)
    shape = (int(q[:, 1].max()) + 2, int(q[:, 0].max()) + 2)
    ref = _components_numpy(q, shape, theta, np.radians(15))
    out = _oriented_components(q, shape, theta, np.radians(15))
    assert out[0] == ref[0] > 100
    np.testing.assert_array_equal(out[1], ref[1])
    n, lab = edge_kernels.oriented_components(np.zeros((0, 2), np.int64), (3, 3), np.zeros(0),
                                              0.3)
    assert n == 0 and lab.shape == (0,)
    n, lab = edge_kernels.oriented_components(np.array([[1, 1]]), (3, 3), np.zeros(1), 0.3)
    assert n == 1 and lab.tolist() == [0]
    with pytest.raises(IndexError):
        edge_kernels.oriented_components(np.array([[3, 1]]), (3, 3), np.zeros(1), 0.3)


# ---- sub-pixel positions --------------------------------------------------------------------


def test_subpixel_matches_numpy(frame):
    ex, inputs = frame
    for dxy, pix, flat, origin in inputs:
        p, g = edge_kernels.corner_test(dxy, pix, flat, ex._win_flat, ex._win_w, 4.0, origin)
        sel = np.flatnonzero(np.random.default_rng(1).random(len(p)) < 0.5)
        for s in (sel, np.arange(len(p)), sel[:1], sel[:0]):
            ref = _subpixel_numpy(dxy, p, g, s, origin)
            out = edge_kernels.subpixel(dxy, p, g, s, origin)
            assert out.shape == (len(s), 2)
            np.testing.assert_array_equal(out, ref)
    # random gradients (zero ones included) at points near the border of a small image
    rng = np.random.default_rng(2)
    dxy = (rng.normal(size=(7, 9)) + 1j * rng.normal(size=(7, 9))).astype(np.complex64)
    pix = np.stack([rng.integers(0, 9, 300), rng.integers(0, 7, 300)], 1).astype(np.int32) + 5
    g = (rng.normal(size=300) + 1j * rng.normal(size=300)).astype(np.complex64)
    g[:10] = 0
    s = np.arange(300)
    np.testing.assert_array_equal(edge_kernels.subpixel(dxy, pix, g, s, (5, 5)),
                                  _subpixel_numpy(dxy, pix, g, s, (5, 5)))


# ---- MSAC scores ----------------------------------------------------------------------------


def test_msac_costs_match_numpy():
    rng = np.random.default_rng(4)
    cnt = np.array([3, 8, 9, 40, 128, 129, 300, 1000, 1])  # both sides of numpy's sum blocks
    n, nh = int(cnt.sum()), 16
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    seg = np.repeat(np.arange(len(cnt)), cnt)
    rays = rng.normal(size=(n, 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    hyp = rng.normal(size=(len(cnt), nh, 3))
    hyp = (hyp / np.linalg.norm(hyp, axis=2, keepdims=True)).astype(np.float32)
    tol = rng.uniform(1e-3, 5e-2, n)
    r32 = np.ascontiguousarray(rays.T, dtype=np.float32)
    hyp_k = np.ascontiguousarray(hyp.transpose(2, 0, 1))
    t2 = (tol * tol).astype(np.float32)
    ref_cost, ref_sum = _msac_numpy(r32, hyp_k, seg, start, t2)
    cost, seg_cost = edge_kernels.msac_costs(r32, hyp_k, seg, start, t2)
    np.testing.assert_array_equal(cost, ref_cost)
    np.testing.assert_array_equal(seg_cost, ref_sum)
    # one point, and no point
    c1, s1 = edge_kernels.msac_costs(r32[:, :1], hyp_k[:, :1], seg[:1], start[:1], t2[:1])
    np.testing.assert_array_equal(s1, _msac_numpy(r32[:, :1], hyp_k[:, :1], seg[:1],
                                                  start[:1], t2[:1])[1])
    c0, s0 = edge_kernels.msac_costs(r32[:, :0], hyp_k[:, :0], seg[:0], start[:0], t2[:0])
    assert c0.shape == (0, nh) and s0.shape == (0, nh)
    with pytest.raises(IndexError):
        edge_kernels.msac_costs(r32, hyp_k, seg + 1, start, t2)
