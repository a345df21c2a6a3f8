"""The line extractor's compiled loops (omni_sfm/lines/_edges.c) against the numpy code they
replaced in omni_sfm/lines/extract.py (kept here as the reference): the same bits, except the
corner test's window sums (summed in another order than numpy's BLAS), whose decisions must
still agree. The great-circle fits' kernels are checked on the calls the extractor makes on
rendered frames and on synthetic pieces of great circles."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from linetest_utils import Room, hyperboloid_camera, render

from omni_sfm.geometry import completion_towards, unsigned_angle
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


# ---- Canny's inputs, the edge points, the long chains ------------------------------------------


def _gradients_numpy(dx, dy):
    dx16 = np.empty(dx.shape, np.int16)
    dy16 = np.empty(dy.shape, np.int16)
    with np.errstate(invalid="ignore"):
        np.multiply(dx, 8.0, out=dx16, casting="unsafe")
        np.multiply(dy, 8.0, out=dy16, casting="unsafe")
    return dx16, dy16, cv2.merge([dx, dy]).view(np.complex64)[..., 0]


def _edge_points_numpy(edges, mask):
    nz = cv2.findNonZero(cv2.bitwise_and(edges, mask))
    pix = np.zeros((0, 2), np.int32) if nz is None else nz.reshape(-1, 2)
    return pix, pix[:, 1].astype(np.int64) * edges.shape[1] + pix[:, 0]


def _long_chains_numpy(edges_masked, flat, min_points):
    ncomp, comp_img = cv2.connectedComponents(edges_masked, connectivity=8, ltype=cv2.CV_32S)
    comp = np.take(comp_img.ravel(), flat)
    return np.bincount(comp, minlength=ncomp)[comp] >= min_points


def test_gradients_are_numpys_int16_cast_and_cv2_merge():
    rng = np.random.default_rng(5)
    dx = rng.normal(0, 300, (37, 53)).astype(np.float32)
    dy = rng.normal(0, 300, (37, 53)).astype(np.float32)
    # values past int16 and int32 after the scaling, halves, negative zeros, NaN, infinities
    special = np.array([4095.9, -4095.9, 4096.0, 1e5, -1e5, 3e9, -3e9, 0.0625, -0.0625,
                        0.124, -0.124, -0.0, np.inf, -np.inf, np.nan, 1020.0, -1020.0],
                       np.float32)
    dx.ravel()[: len(special)] = special
    dy.ravel()[-len(special):] = special[::-1]
    out = edge_kernels.gradients(dx[:0], dy[:0])
    assert [x.shape for x in out] == [(0, 53)] * 3
    for a, b in ((dx, dy), (dx[3:4, 5:12], dy[3:4, 5:12]), (dx[::2, 1::3], dy[::2, 1::3])):
        ref = _gradients_numpy(a, b)
        out = edge_kernels.gradients(a, b)
        np.testing.assert_array_equal(out[0], ref[0])
        np.testing.assert_array_equal(out[1], ref[1])
        assert out[2].dtype == np.complex64 and out[2].shape == a.shape
        np.testing.assert_array_equal(out[2].view(np.uint64), ref[2].view(np.uint64))
    with pytest.raises(ValueError):
        edge_kernels.gradients(dx, dy[:, 1:])


def _sobel_gradients_numpy(img):
    """cv2.Sobel's order of operations where its loops are 8 floats wide (see
    ``_edges.c``: sobel_gradients), then :func:`_gradients_numpy`."""
    h, w = img.shape
    p = np.pad(img, 1, mode="reflect")  # OpenCV's reflect-101
    two = np.float32(2)
    t = p[:, 2:] - p[:, :-2]
    dx = (t[:-2] + t[2:]) + two * t[1:-1]
    s = (p[:, :-2] + p[:, 2:]) + two * p[:, 1:-1]
    xs = w - w % 8
    dx[:, xs:] = ((t[:-2] + two * t[1:-1]) + t[2:])[:, xs:]
    s_tail = (p[:, :-2] + two * p[:, 1:-1]) + p[:, 2:]
    tail = np.zeros(w, bool)
    tail[xs:] = True
    if (w - xs) % 2:  # the scalar loops' pairs leave the last column to the vector formula
        tail[w - 1] = False
    s[:, tail] = s_tail[:, tail]
    dy = s[2:] - s[:-2]
    return _gradients_numpy(dx, dy)


def test_sobel_gradients_are_cv2_sobels_gradients(frame):
    """The fused kernel: the reference's bits on every size; cv2.Sobel's up to round-off
    anywhere, and its bits on widths that OpenCV's vector loops cover whole (multiples of 16,
    so 8- and 16-wide loops alike) where the processor has AVX2 (the tails' scalar order,
    which the reference repeats, is OpenCV's 8-wide build's)."""
    rng = np.random.default_rng(15)
    avx2 = cv2.checkHardwareSupport(getattr(cv2, "CPU_AVX2", 11))  # cv::CPU_AVX2
    sizes = [(h, w) for w in (2, 3, 7, 8, 9, 10, 15, 16, 17, 26, 32, 587) for h in (2, 3, 8, 41)]
    for h, w in sizes:
        img = rng.normal(0, 300, (h, w)).astype(np.float32)
        out = edge_kernels.sobel_gradients(img)
        ref = _sobel_gradients_numpy(img)
        for a, b in zip(out, ref, strict=True):
            np.testing.assert_array_equal(a.view(np.uint8), b.view(np.uint8))
        dx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
        dy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
        np.testing.assert_allclose(out[2].real, dx, rtol=1e-5, atol=1e-3)
        np.testing.assert_allclose(out[2].imag, dy, rtol=1e-5, atol=1e-3)
        if avx2 and w % 16 == 0:
            np.testing.assert_array_equal(out[2].view(np.uint64),
                                          edge_kernels.gradients(dx, dy)[2].view(np.uint64))
    # a blurred frame's region, as the extractor calls it
    ex, _ = frame
    g = render(hyperboloid_camera(), Room(), np.eye(3), np.zeros(3))
    img = cv2.GaussianBlur(g[ex._roi].astype(np.float32), (5, 5), 1.0)
    out = edge_kernels.sobel_gradients(img)
    for a, b in zip(out, _sobel_gradients_numpy(img), strict=True):
        np.testing.assert_array_equal(a.view(np.uint8), b.view(np.uint8))
    with pytest.raises(ValueError):
        edge_kernels.sobel_gradients(np.zeros((1, 5), np.float32))


def test_histogram_is_calchist_with_the_mask():
    rng = np.random.default_rng(16)
    for h, w in ((600, 800), (7, 9), (1, 1), (30, 17)):
        g = rng.integers(0, 256, (h, w), dtype=np.uint8)
        masks = [(rng.random((h, w)) > 0.3).astype(np.uint8) * 255,
                 np.full((h, w), 255, np.uint8), rng.integers(0, 3, (h, w)).astype(np.uint8)]
        for m in masks:
            for roi in ((slice(0, h), slice(0, w)), (slice(h // 3, h), slice(w // 4, w - 1))):
                ref = cv2.calcHist([g[roi]], [0], m[roi], [256], [0, 256]).ravel()
                out = edge_kernels.histogram(g, m, roi)
                assert out.dtype == ref.dtype
                np.testing.assert_array_equal(out, ref)
    with pytest.raises(ValueError):
        edge_kernels.histogram(g, m, (slice(0, h + 1), slice(0, w)))


def test_smallest_eigenvector3_is_eighs_to_round_off():
    """Scatter matrices of rays on arcs from 0.06 to 180 deg with noise: the plane's normal as
    np.linalg.eigh finds it, within round-off over the gap of the two smallest eigenvalues."""
    rng = np.random.default_rng(17)
    k = 400
    n = rng.normal(size=(k, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    e1 = np.cross(n, rng.normal(size=(k, 3)))
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(n, e1)
    arc = 10 ** rng.uniform(-3, np.log10(np.pi), k)
    t = (rng.random((k, 60)) - 0.5) * arc[:, None]
    r = np.cos(t)[..., None] * e1[:, None] + np.sin(t)[..., None] * e2[:, None]
    r += rng.normal(0, 1e-4, r.shape) * rng.random((k, 1, 1))
    S = np.einsum("kni,knj->kij", r, r)
    out = edge_kernels.smallest_eigenvector3(S)
    ref = np.linalg.eigh(S)[1][..., 0]
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-14)
    w = np.linalg.eigvalsh(S)
    angle = unsigned_angle(out, ref)
    assert np.all(angle <= 1e-14 * w[:, 2] / (w[:, 1] - w[:, 0]))
    # diagonal, equal eigenvalues, zero, NaN and no matrix at all
    S = np.array([np.diag([1.0, 2.0, 3.0]), np.diag([3.0, 1.0, 2.0]), 5 * np.eye(3),
                  np.zeros((3, 3)), np.diag([1.0, np.nan, 1.0])])
    out = edge_kernels.smallest_eigenvector3(S)
    np.testing.assert_array_equal(np.abs(out[:2]), [[1, 0, 0], [0, 1, 0]])
    np.testing.assert_allclose(np.linalg.norm(out[2:4], axis=1), 1.0)
    assert np.isnan(out[4]).all()
    assert edge_kernels.smallest_eigenvector3(np.zeros((0, 3, 3))).shape == (0, 3)
    with pytest.raises(ValueError):
        edge_kernels.smallest_eigenvector3(np.zeros((2, 3)))


def test_edge_points_are_findnonzero_of_the_masked_edges(frame):
    ex, inputs = frame
    rng = np.random.default_rng(6)
    for dxy, pix, flat, origin in inputs:
        dx16, dy16, _ = _gradients_numpy(dxy.real.copy(), dxy.imag.copy())
        o = ex.options
        edges = cv2.Canny(dx16, dy16, 8.0 * o.canny_low, 8.0 * o.canny_high, L2gradient=True)
        # the mask read in place at the region's corner
        p, f = edge_kernels.edge_points(edges, ex.search_mask, origin)
        np.testing.assert_array_equal(p, pix)
        np.testing.assert_array_equal(f, flat)
        assert p.dtype == np.int32 and f.dtype == np.int64
    # odd widths (the eight-pixel words' tails), masks of any bytes, a cap just large enough
    p, f = edge_kernels.edge_points(np.zeros((0, 4), np.uint8), np.zeros((1, 4), np.uint8))
    assert p.shape == (0, 2) and f.shape == (0,)
    for h, w in ((13, 29), (5, 8), (1, 3), (9, 1)):
        for density in (0.02, 0.5, 1.0):
            e = np.where(rng.random((h, w)) < density, rng.integers(1, 256, (h, w)), 0)
            m = rng.integers(0, 256, (h + 3, w + 5)).astype(np.uint8)
            e = e.astype(np.uint8)
            ref_p, ref_f = _edge_points_numpy(e, np.ascontiguousarray(m[2 : 2 + h, 4 : 4 + w]))
            p, f = edge_kernels.edge_points(e, m, (4, 2), cap=len(ref_p))
            np.testing.assert_array_equal(p, ref_p)
            np.testing.assert_array_equal(f, ref_f)
            if len(ref_p):
                with pytest.raises(ValueError):
                    edge_kernels.edge_points(e, m, (4, 2), cap=len(ref_p) - 1)
    e = np.full((4, 6), 255, np.uint8)
    with pytest.raises(ValueError):
        edge_kernels.edge_points(e, np.full((4, 6), 255, np.uint8), (1, 0))  # leaves the mask


def test_long_chains_are_connected_components_sizes(frame):
    ex, inputs = frame
    rng = np.random.default_rng(7)
    cases = []
    for dxy, pix, _, _ in inputs:  # the rendered frame's and the noisy frame's edge points
        img = np.zeros(dxy.shape, np.uint8)
        img[pix[:, 1], pix[:, 0]] = 255
        cases.append((img, ex.options.min_points))
    for h, w in ((40, 70), (7, 9), (1, 12), (12, 1), (3, 3)):
        for density in (0.05, 0.3, 0.6, 1.0):  # random points: chains of every shape
            cases.append(((rng.random((h, w)) < density).astype(np.uint8) * 255, 4))
    for img, min_points in cases:
        pix, flat = _edge_points_numpy(img, img)
        for mp in (min_points, 1, 2, 30):
            ref = _long_chains_numpy(img, flat, mp)
            keep, p, f = edge_kernels.long_chains(pix, flat, img.shape, mp)
            assert keep.dtype == bool
            np.testing.assert_array_equal(keep, ref)
            np.testing.assert_array_equal(p, pix[ref])
            np.testing.assert_array_equal(f, flat[ref])
    keep, p, f = edge_kernels.long_chains(np.zeros((0, 2), np.int32), np.zeros(0, np.int64),
                                          (5, 5), 3)
    assert keep.shape == (0,) and p.shape == (0, 2) and f.shape == (0,)
    pix = np.array([[1, 1], [0, 2]], np.int32)
    with pytest.raises(ValueError):  # not in row-major order
        edge_kernels.long_chains(pix[::-1], np.array([10, 6]), (5, 5), 2)
    with pytest.raises(ValueError):  # flat indices not y w + x
        edge_kernels.long_chains(pix, np.array([6, 11]), (5, 5), 2)
    with pytest.raises(ValueError):  # outside the image
        edge_kernels.long_chains(pix, np.array([6, 10]), (2, 5), 2)


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


# ---- great-circle fits: the numpy code of extract.py before its kernels -----------------------


def _scatter_numpy(rays, weight, seg, nseg):
    weight = np.ones(len(rays)) if weight is None else weight
    out = np.empty((nseg, 3, 3))
    x, y, z = rays[:, 0] * weight, rays[:, 1] * weight, rays[:, 2] * weight
    for (i, j), v in (((0, 0), x * rays[:, 0]), ((0, 1), x * rays[:, 1]),
                      ((0, 2), x * rays[:, 2]), ((1, 1), y * rays[:, 1]),
                      ((1, 2), y * rays[:, 2]), ((2, 2), z * rays[:, 2])):
        out[:, i, j] = out[:, j, i] = np.bincount(seg, weights=v, minlength=nseg)
    return out


def _arc_parameter_numpy(r, n, group, ngroup):
    mean = np.zeros((ngroup, 3))
    for k in range(3):
        mean[:, k] = np.bincount(group, weights=r[:, k], minlength=ngroup)
    e1, e2 = completion_towards(n, mean)
    return np.arctan2(np.einsum("nk,nk->n", r, np.take(e2, group, axis=0)),
                      np.einsum("nk,nk->n", r, np.take(e1, group, axis=0)))


def _gap_pieces_numpy(seg, t, s, nseg, max_gap, min_points):
    order = np.lexsort((t, seg))
    seg, t, s = seg[order], t[order], s[order]
    cut = (np.diff(seg) != 0) | (np.diff(t) > max_gap * s[1:])
    piece = np.concatenate([[0], np.cumsum(cut)]).astype(np.int64)
    keep = np.bincount(piece)[piece] >= min_points
    pos, seg, piece = order[keep], seg[keep], piece[keep]
    _, piece = np.unique(piece, return_inverse=True)
    piece_seg = np.zeros(piece.max() + 1 if len(piece) else 0, np.int64)
    piece_seg[piece] = seg
    return pos, piece, piece_seg


def _trim_ends_numpy(lab, t, s, nl, trim, min_points):
    lo, hi = np.full(nl, np.inf), np.full(nl, -np.inf)
    with np.errstate(invalid="ignore"):
        np.minimum.at(lo, lab, t)
        np.maximum.at(hi, lab, t)
    lim = trim * s
    keep = (t - lo[lab] > lim) & (hi[lab] - t > lim)
    pos, lab = np.flatnonzero(keep), lab[keep]
    keep = (np.bincount(lab, minlength=nl) >= min_points)[lab]
    _, lab = np.unique(lab[keep], return_inverse=True)
    return pos[keep], lab


def _package_numpy(r, normals, lab, t, s, noise):
    nl = len(normals)
    # a strided view, as the normals were when this was the extractor's code (a column of
    # np.linalg.eigh's output): it sets einsum's order of summation, which the kernel keeps
    strided = np.empty((nl, 3, 2))
    strided[..., 0] = normals
    normals = strided[..., 0]
    sizes = np.bincount(lab, minlength=nl)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    first, last = offsets[:-1], offsets[1:] - 1
    ends = np.stack([r[first], r[last]], 1)
    ends -= np.einsum("lek,lk->le", ends, normals)[..., None] * normals[:, None, :]
    ends /= np.linalg.norm(ends, axis=2, keepdims=True)
    px = np.abs(np.einsum("nk,nk->n", r, np.take(normals, lab, axis=0))) / s
    resid = np.sqrt(np.bincount(lab, weights=px * px, minlength=nl) / sizes)
    mean_scale = np.bincount(lab, weights=s, minlength=nl) / sizes
    m, tdir = completion_towards(normals, ends[:, 0] + ends[:, 1])
    w = 1.0 / (noise * s) ** 2
    info = np.stack([np.bincount(lab, weights=w * np.einsum(
        "nk,nk->n", r, np.take(v, lab, axis=0)) ** 2, minlength=nl) for v in (m, tdir)], axis=1)
    sigma = 1.0 / np.sqrt(np.maximum(info, 1e-300))
    return sizes, ends, resid, t[last] - t[first], mean_scale, sigma


def _inliers_numpy(rays, n, seg, tol):
    inl = np.abs(np.einsum("nk,nk->n", rays, np.take(n, seg, axis=0))) < tol
    return inl, np.bincount(seg, weights=inl, minlength=len(n))


def _hypotheses_numpy(rays, ia, ib):
    hyp = np.cross(rays[ia], rays[ib])
    hn = np.linalg.norm(hyp, axis=2, keepdims=True)
    degenerate = hn[..., 0] < 1e-9
    hyp = (hyp / np.where(hn > 0, hn, 1.0)).astype(np.float32)
    return np.ascontiguousarray(hyp.transpose(2, 0, 1)), degenerate


def _merge_numpy(rays, idx, lab, normals, cand, max_gap):
    nl = len(normals)
    in_order = idx[np.argsort(lab, kind="stable")]
    size = np.bincount(lab, minlength=nl)
    first = np.concatenate([[0], np.cumsum(size)[:-1]])
    gaps = []
    e1 = e2 = np.zeros((0, 3))
    for side in (0, 1):
        piece = cand[:, side]
        n = size[piece]
        starts = np.concatenate([[0], np.cumsum(n)[:-1]])
        pair = np.repeat(np.arange(len(cand)), n)
        r = np.take(rays, in_order[np.arange(int(n.sum())) - starts[pair]
                                   + first[piece][pair]], axis=0)
        if side == 0:
            mean = np.add.reduceat(r, starts, axis=0) / n[:, None]
            e1, e2 = completion_towards(normals[piece], mean)
        t = np.arctan2(np.einsum("nk,nk->n", r, np.take(e2, pair, axis=0)),
                       np.einsum("nk,nk->n", r, np.take(e1, pair, axis=0)))
        gaps.append((np.minimum.reduceat(t, starts), np.maximum.reduceat(t, starts)))
    (lo_i, hi_i), (lo_j, hi_j) = gaps
    gap = np.maximum(lo_j - hi_i, lo_i - hi_j)
    join = (gap >= 0) & (gap <= max_gap)
    parent = np.arange(nl)

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return int(i)

    for i, j in cand[join]:
        parent[find(int(i))] = find(int(j))
    roots = np.array([find(i) for i in range(nl)])
    return np.unique(roots, return_inverse=True)[1]


_FIT_KERNELS = {
    "scatter": _scatter_numpy, "arc_parameter": _arc_parameter_numpy,
    "order_by": lambda key, t, nkey: np.lexsort((t, key)),
    "gap_pieces": _gap_pieces_numpy, "trim_ends": _trim_ends_numpy,
    "package": _package_numpy, "inliers": _inliers_numpy, "hypotheses": _hypotheses_numpy,
    "merge_labels": _merge_numpy,
}


def _same(a, b):
    a, b = (a,) if not isinstance(a, tuple) else a, (b,) if not isinstance(b, tuple) else b
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        x, y = np.asarray(x), np.asarray(y)
        assert x.shape == y.shape
        assert np.ascontiguousarray(x).tobytes() == np.ascontiguousarray(y).tobytes()


@pytest.fixture(scope="module")
def fit_calls():
    """Every call of the fitting kernels while the extractor runs on a rendered frame and its
    noisy copy (the arguments as the extractor passed them, the kernel's results)."""
    cam = hyperboloid_camera()
    img = render(cam, Room(), np.eye(3), np.array([0.3, 0.2, 0.1]))
    noisy = np.clip(img + np.random.default_rng(1).normal(0, 6, img.shape), 0, 255)
    calls: list[tuple[str, tuple, object]] = []
    saved = {name: getattr(edge_kernels, name) for name in _FIT_KERNELS}

    def recorder(name, f):
        def g(*args):
            out = f(*args)
            calls.append((name, args, out))
            return out
        return g

    mp = pytest.MonkeyPatch()
    for name, f in saved.items():
        mp.setattr(edge_kernels, name, recorder(name, f))
    try:
        ex = LineExtractor(cam)
        lines = [ex.extract(img), ex.extract(noisy.astype(np.uint8))]
    finally:
        mp.undo()
    assert all(ln.num_lines > 5 for ln in lines)
    return calls


def test_fit_kernels_match_numpy_on_frames(fit_calls):
    seen = set()
    for name, args, out in fit_calls:
        _same(out, _FIT_KERNELS[name](*args))
        seen.add(name)
    assert seen >= set(_FIT_KERNELS) - {"order_by", "merge_labels"}


def _great_circle_pieces(rng, sizes, spread=0.3):
    """Rays near a few great circles (pieces with the sizes given, some on one circle with
    gaps between them), their piece labels (shuffled order) and normals."""
    base = rng.normal(size=(3, 3))
    base /= np.linalg.norm(base, axis=1, keepdims=True)
    rays, lab, normals = [], [], []
    for p, n in enumerate(sizes):
        nv = base[p % 3]
        e1 = np.cross(nv, [0.3, 0.5, 0.8])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(nv, e1)
        a = (p // 3) * (spread + 0.05) + np.sort(rng.uniform(0, spread, n))
        r = np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2 + rng.normal(0, 1e-4, (n, 3))
        rays.append(r / np.linalg.norm(r, axis=1, keepdims=True))
        lab.append(np.full(n, p))
        normals.append(nv + rng.normal(0, 1e-5, 3))
    perm = rng.permutation(sum(sizes))
    return (np.concatenate(rays)[perm], np.concatenate(lab)[perm],
            np.array(normals) / np.linalg.norm(normals, axis=1, keepdims=True))


def test_fit_kernels_match_numpy_on_synthetic_pieces():
    rng = np.random.default_rng(7)
    sizes = [3, 8, 9, 40, 128, 129, 300, 1, 60, 61, 250, 45]  # both sides of the sum blocks
    rays, lab, normals = _great_circle_pieces(rng, sizes)
    nl = len(sizes)
    w = rng.integers(0, 2, len(rays)).astype(np.float64)
    for weight in (None, w):
        _same(edge_kernels.scatter(rays, weight, lab, nl), _scatter_numpy(rays, weight, lab, nl))
    # eigh's normals (a non-contiguous view), as the extractor passes them
    nrm = np.linalg.eigh(_scatter_numpy(rays, None, lab, nl))[1][..., 0]
    t = edge_kernels.arc_parameter(rays, nrm, lab, nl)
    _same(t, _arc_parameter_numpy(rays, nrm, lab, nl))
    s = rng.uniform(1e-3, 3e-3, len(rays))
    _same(edge_kernels.order_by(lab, t, nl), np.lexsort((t, lab)))
    for max_gap, min_points in ((4.0, 40), (0.5, 5), (1e9, 1)):
        _same(edge_kernels.gap_pieces(lab, t, s, nl, max_gap, min_points),
              _gap_pieces_numpy(lab, t, s, nl, max_gap, min_points))
    for trim, min_points in ((5.0, 40), (0.0, 1), (50.0, 3)):
        _same(edge_kernels.trim_ends(lab, t, s, nl, trim, min_points),
              _trim_ends_numpy(lab, t, s, nl, trim, min_points))
    order = np.lexsort((t, lab))
    args = (rays[order], nrm, lab[order], t[order], s[order], 0.5)
    _same(edge_kernels.package(*args), _package_numpy(*args))
    tol = rng.uniform(0, 3e-4, len(rays))
    _same(edge_kernels.inliers(rays, normals, lab, tol), _inliers_numpy(rays, normals, lab, tol))
    ia, ib = rng.integers(0, len(rays), (2, nl, 16))
    ib[0, :3] = ia[0, :3]  # degenerate pairs
    _same(edge_kernels.hypotheses(rays, ia, ib), _hypotheses_numpy(rays, ia, ib))


def test_merge_labels_match_numpy():
    rng = np.random.default_rng(3)
    # pieces 0, 3, 6, 9 on one circle, 1, 4, 7, 10 on another, ... with gaps between them
    sizes = [50, 41, 60, 130, 45, 9, 70, 200, 40, 55, 48, 44]
    rays, lab, normals = _great_circle_pieces(rng, sizes, spread=0.2)
    idx = rng.permutation(len(rays) + 20)[: len(rays)]  # points of a larger ray array
    big = np.zeros((len(rays) + 20, 3))
    big[idx] = rays
    big[np.setdiff1d(np.arange(len(big)), idx)] = [1.0, 0.0, 0.0]
    cosang = np.abs(normals @ normals.T)
    cand = np.argwhere(np.triu(cosang > np.cos(np.radians(0.3)), 1))
    assert len(cand) >= 6
    for max_gap in (np.radians(20.0), np.radians(2.0), 0.0):
        new = edge_kernels.merge_labels(big, idx, lab, normals, cand, max_gap)
        _same(new, _merge_numpy(big, idx, lab, normals, cand, max_gap))
    assert edge_kernels.merge_labels(big, idx, lab, normals, cand, np.radians(20.0)).max() < 6
    # the reverse order of the pairs and pairs not on one circle
    cand2 = np.concatenate([cand[::-1], [[0, 1], [2, 5]]])
    _same(edge_kernels.merge_labels(big, idx, lab, normals, cand2, 1.0),
          _merge_numpy(big, idx, lab, normals, cand2, 1.0))


def test_fit_kernels_edge_cases_and_bounds():
    rays = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    seg = np.array([0, 1, 1])
    z = np.zeros(0, np.int64)
    assert edge_kernels.scatter(rays[:0], None, z, 2).shape == (2, 3, 3)
    _same(edge_kernels.scatter(rays[:0], None, z, 2), np.zeros((2, 3, 3)))
    assert edge_kernels.order_by(z, np.zeros(0), 0).shape == (0,)
    t = np.array([np.nan, 0.5, -0.0, 0.0, np.nan, -1.0])
    key = np.array([1, 1, 0, 0, 1, 1])
    _same(edge_kernels.order_by(key, t, 2), np.lexsort((t, key)))  # NaN last, ties by index
    pos, piece, piece_seg = edge_kernels.gap_pieces(z, np.zeros(0), np.zeros(0), 0, 4.0, 3)
    assert len(pos) == len(piece) == len(piece_seg) == 0
    t3 = np.array([0.0, np.nan, 0.3])
    _same(edge_kernels.trim_ends(seg, t3, np.ones(3), 2, 0.01, 1),
          _trim_ends_numpy(seg, t3, np.ones(3), 2, 0.01, 1))
    for bad in (seg + 1, seg - 1):
        with pytest.raises(IndexError):
            edge_kernels.scatter(rays, None, bad, 2)
        with pytest.raises(IndexError):
            edge_kernels.arc_parameter(rays, rays[:2], bad, 2)
        with pytest.raises(IndexError):
            edge_kernels.order_by(bad, np.zeros(3), 2)
        with pytest.raises(IndexError):
            edge_kernels.gap_pieces(bad, np.zeros(3), np.ones(3), 2, 1.0, 1)
        with pytest.raises(IndexError):
            edge_kernels.trim_ends(bad, np.zeros(3), np.ones(3), 2, 1.0, 1)
        with pytest.raises(IndexError):
            edge_kernels.inliers(rays, rays[:2], bad, np.ones(3))
    with pytest.raises(ValueError):  # labels not sorted or not dense
        edge_kernels.package(rays, rays[:2], np.array([1, 0, 0]), np.zeros(3), np.ones(3), 0.5)
    with pytest.raises(ValueError):
        edge_kernels.package(rays, rays[:3], np.array([0, 0, 2]), np.zeros(3), np.ones(3), 0.5)
    with pytest.raises(ValueError):
        edge_kernels.scatter(rays, np.ones(2), seg, 2)
    with pytest.raises(IndexError):
        edge_kernels.hypotheses(rays, np.array([[0, 3]]), np.array([[1, 2]]))
    with pytest.raises(IndexError):
        edge_kernels.merge_labels(rays, np.array([0, 1, 2]), seg, rays[:2], np.array([[0, 2]]),
                                  1.0)


# ---- tracking: the nearest edge point ---------------------------------------------------------


def test_snap_finds_the_kd_trees_neighbours():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(5)
    pts = rng.uniform(0, 300, (3000, 2))
    pts[100:110] = pts[0]  # equal points: the lowest index
    q = np.concatenate([pts[rng.integers(0, len(pts), 500)] + rng.normal(0, 2, (500, 2)),
                        [[-50.0, -50.0], [1e5, 3.0], [np.nan, 1.0]]])
    got = edge_kernels.snap(pts, q, 3.0)
    dist, ref = cKDTree(pts).query(np.nan_to_num(q, nan=-1e9), distance_upper_bound=3.0)
    ref = np.where(np.isfinite(dist), ref, -1)
    assert got is not None and (got >= 0).sum() > 300
    np.testing.assert_array_equal(got, ref)
    assert edge_kernels.snap(pts[:0], q, 3.0).tolist() == [-1] * len(q)
    # points too sparse for a grid: None (the caller's tree)
    assert edge_kernels.snap(np.array([[0.0, 0.0], [1e6, 1e6]]), q, 3.0) is None


def _line_samples_numpy(offsets, points_uv, spacing, max_samples):
    """LineTracker._samples as numpy computed it."""
    n = np.diff(offsets)
    step = np.maximum(spacing, n / max(1, max_samples))
    k = np.maximum(1, np.floor(n / step)).astype(np.int64)
    line = np.repeat(np.arange(len(n)), k)
    within = np.arange(len(line)) - np.repeat(np.cumsum(k) - k, k)
    pos = offsets[line] + ((within + 0.5) * n[line] / k[line]).astype(np.int64)
    lo = np.maximum(pos - 2, offsets[line])
    hi = np.minimum(pos + 2, offsets[line + 1] - 1)
    tangent = points_uv[hi] - points_uv[lo]
    tn = np.linalg.norm(tangent, axis=1, keepdims=True)
    tangent = np.where(tn > 0, tangent / np.where(tn > 0, tn, 1.0), 0.0)
    return points_uv[pos], tangent, line, k


def test_line_samples_are_the_trackers_numpy_samples(frame):
    ex, _ = frame
    img = render(hyperboloid_camera(), Room(), np.eye(3), np.array([0.3, 0.2, 0.1]))
    lines = ex.extract(img)
    rng = np.random.default_rng(18)
    sizes = rng.integers(1, 300, 40)
    cases = [(lines.offsets, lines.points_uv),
             (np.concatenate([[0], np.cumsum(sizes)]), rng.normal(0, 100, (sizes.sum(), 2)))]
    pts = rng.normal(0, 1, (12, 2))
    pts[5:9] = pts[5]  # a line whose points coincide: zero tangents
    cases.append((np.array([0, 1, 2, 5, 9, 12]), pts))
    for offsets, uv in cases:
        for spacing, most in ((8.0, 8), (8.0, 16), (3.5, 1), (20.0, 0)):
            out = edge_kernels.line_samples(offsets, uv, spacing, most)
            ref = _line_samples_numpy(offsets, uv, spacing, most)
            for a, b in zip(out, ref, strict=True):
                assert a.dtype == b.dtype and a.shape == b.shape
                assert a.tobytes() == b.tobytes()
    out = edge_kernels.line_samples(np.zeros(1, np.int64), np.zeros((0, 2)), 8.0, 8)
    assert [len(a) for a in out] == [0, 0, 0, 0]
    with pytest.raises(ValueError):
        edge_kernels.line_samples(np.array([0, 3, 3]), np.zeros((3, 2)), 8.0, 8)  # empty line
    with pytest.raises(ValueError):
        edge_kernels.line_samples(np.array([0, 5]), np.zeros((3, 2)), 8.0, 8)  # past the points


def test_canny_is_cv2_canny_on_gradients(frame):
    """The compiled Canny against cv2.Canny(dx, dy, low, high, L2gradient=True): the same
    edge map on a rendered frame and its noisy copy at several thresholds, and on random
    gradients of odd sizes (ties between neighbours included)."""
    _, inputs = frame
    rng = np.random.default_rng(19)
    for dxy, _, _, _ in inputs:
        dx16, dy16, _ = _gradients_numpy(dxy.real.copy(), dxy.imag.copy())
        for low, high in ((160.0, 320.0), (40.0, 80.0), (400.0, 1200.0), (0.0, 8.0),
                          (320.0, 160.0), (163.7, 330.2)):
            ref = cv2.Canny(dx16, dy16, low, high, L2gradient=True)
            np.testing.assert_array_equal(edge_kernels.canny(dx16, dy16, low, high), ref)
    for t in range(60):
        h, w = (int(v) for v in rng.integers(1, 30, 2))
        dx = rng.integers(-3000, 3000, (h, w)).astype(np.int16)
        dy = rng.integers(-3000, 3000, (h, w)).astype(np.int16)
        if t % 3 == 0:
            dx[:, ::2] = 0  # equal magnitudes side by side
        if t % 4 == 0:
            dy[::2] = dx[::2]  # diagonals
        ref = cv2.Canny(dx, dy, 100.0, 250.0, L2gradient=True)
        np.testing.assert_array_equal(edge_kernels.canny(dx, dy, 100.0, 250.0), ref)
    with pytest.raises(ValueError):
        edge_kernels.canny(dx, dy[:, 1:], 100.0, 250.0)


def test_extraction_is_the_same_with_either_canny():
    """Which Canny runs follows the previous frame's edge density: the lines are the same."""
    cam = hyperboloid_camera()
    img = render(cam, Room(), np.eye(3), np.array([0.3, 0.2, 0.1]))
    noisy = np.clip(img + np.random.default_rng(2).normal(0, 20, img.shape), 0, 255)
    for image in (img, noisy.astype(np.uint8)):
        runs = []
        for dense in (False, True):
            ex = LineExtractor(cam)
            ex._dense_edges = dense
            runs.append(ex.extract(image))
        a, b = runs
        assert a.num_lines > 5
        for name in ("normals", "offsets", "points_uv", "num_support", "normal_sigma"):
            assert getattr(a, name).tobytes() == getattr(b, name).tobytes()
    # the noisy frame's edges are dense, the clean one's are not: each picks its Canny next
    ex = LineExtractor(cam)
    ex.extract(noisy.astype(np.uint8))
    assert ex._dense_edges
    ex.extract(img)
    assert not ex._dense_edges
