/* The line extractor's per-edge-point loops (omni_sfm.lines.extract), in C: the corner test
 * of the edge points, the orientation's value modulo pi, the orientation-linked connected
 * components of the edge points, their sub-pixel positions and the MSAC scores of the great
 * circle hypotheses.
 *
 * Why C: each of these was a dozen numpy calls on arrays of one row per edge point (tens of
 * thousands in a textured frame), and the calls' overhead and the temporary arrays were much
 * of the extraction's time. Every formula is the one numpy evaluated before, written out per
 * point in the same precision (float32 where numpy computed in float32) and the same order of
 * operations, so the results are the same bits (tests/test_edge_kernels.py), with one
 * exception: the corner test's 5x5 window sums add the window's terms one after the other,
 * where numpy's matrix-vector product (BLAS) added them in an order of its own; the sums
 * differ in the last bit, the kept points did not change on the rendered test sequences.
 *
 * Arrays come in through the buffer protocol, C-contiguous, of the dtypes the Python wrapper
 * (omni_sfm.lines.edge_kernels) makes them; outputs are written into arrays it allocates.
 * Compiled with -ffp-contract=off so that no fused multiply-add changes the rounding.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* ---- buffers ---------------------------------------------------------------------------- */

static int take(PyObject *o, Py_buffer *v, Py_ssize_t itemsize, Py_ssize_t n, int writable,
                const char *name)
{
    int flags = PyBUF_C_CONTIGUOUS | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(o, v, flags) < 0)
        return -1;
    if (v->itemsize != itemsize || v->len != n * itemsize) {
        PyErr_Format(PyExc_ValueError, "%s: expected %zd items of %zd bytes, got %zd bytes",
                     name, n, itemsize, v->len);
        PyBuffer_Release(v);
        return -1;
    }
    return 0;
}

static void release_all(int n, Py_buffer *b)
{
    for (int i = 0; i < n; i++)
        PyBuffer_Release(&b[i]);
}

/* One argument array: its name, bytes an item, items, whether it is written */
typedef struct {
    const char *name;
    Py_ssize_t itemsize, count;
    int writable;
} Spec;

/* All ``n`` buffers of ``o`` as ``spec`` says, or none (the error set, -1) */
static int take_all(int n, PyObject *const *o, const Spec *spec, Py_buffer *b)
{
    for (int i = 0; i < n; i++)
        if (take(o[i], &b[i], spec[i].itemsize, spec[i].count, spec[i].writable,
                 spec[i].name) < 0) {
            release_all(i, b);
            return -1;
        }
    return 0;
}

static int nonnegative(const char *what, Py_ssize_t n)
{
    if (n < 0) {
        PyErr_Format(PyExc_ValueError, "%s must not be negative, got %zd", what, n);
        return 0;
    }
    return 1;
}

/* ---- corner test ------------------------------------------------------------------------ */

/* For each edge point (flat index ``flat[i]`` into the gradient image ``dxy``, interleaved
 * float32 dx, dy): the second-moment matrix over the window (offsets ``win``, weights ``w``),
 * each entry summed over the window in order, sum_j (gx_j gx_j) w_j; its eigenvalues as
 * extract.py computes them in float32; the point is kept where lmax >= ratio2 lmin. The kept
 * points' pixels (plus x0, y0) and gradients are written in order; returns how many, -1 where
 * a window leaves the image (index reported in *bad). */
static Py_ssize_t corner_test(Py_ssize_t size, Py_ssize_t N, Py_ssize_t K, const float *dxy,
                              const int32_t *pix, const int64_t *flat, const int64_t *win,
                              const float *w, float ratio2, int32_t x0, int32_t y0,
                              int32_t *out_pix, float *out_g, Py_ssize_t *bad)
{
    int64_t lo = 0, hi = 0;
    for (Py_ssize_t j = 0; j < K; j++) {
        if (win[j] < lo)
            lo = win[j];
        if (win[j] > hi)
            hi = win[j];
    }
    Py_ssize_t n = 0;
    /* eight points at a time, their sums interleaved (each point's terms still added in window
     * order): independent additions instead of one chain of 3 K dependent ones per point */
    enum { B = 8 };
    for (Py_ssize_t i0 = 0; i0 < N; i0 += B) {
        Py_ssize_t nb = N - i0 < B ? N - i0 : B;
        const float *g0[B];
        for (Py_ssize_t q = 0; q < nb; q++) {
            int64_t f = flat[i0 + q];
            if (f + lo < 0 || f + hi >= size || f < 0 || f >= size) {
                *bad = i0 + q;
                return -1;
            }
            g0[q] = dxy + 2 * f;
        }
        for (Py_ssize_t q = nb; q < B; q++)
            g0[q] = g0[0]; /* padding, not written out */
        float a[B], b[B], c[B];
        for (int q = 0; q < B; q++) {
            const float *g = g0[q] + 2 * win[0];
            float gx = g[0], gy = g[1];
            a[q] = (gx * gx) * w[0];
            b[q] = (gy * gy) * w[0];
            c[q] = (gx * gy) * w[0];
        }
        for (Py_ssize_t j = 1; j < K; j++) {
            int64_t off = 2 * win[j];
            float wj = w[j], gx[B], gy[B];
            for (int q = 0; q < B; q++) { /* gathered, then the arithmetic in SIMD lanes */
                gx[q] = g0[q][off];
                gy[q] = g0[q][off + 1];
            }
            for (int q = 0; q < B; q++) {
                a[q] = a[q] + (gx[q] * gx[q]) * wj;
                b[q] = b[q] + (gy[q] * gy[q]) * wj;
                c[q] = c[q] + (gx[q] * gy[q]) * wj;
            }
        }
        for (Py_ssize_t q = 0; q < nb; q++) {
            float half_tr = 0.5f * (a[q] + b[q]);
            float amb = a[q] - b[q];
            float v = 0.25f * (amb * amb) + c[q] * c[q];
            float disc = sqrtf(v < 0.0f ? 0.0f : v);
            float lmax = half_tr + disc;
            float lmin = half_tr - disc;
            if (lmin < 0.0f)
                lmin = 0.0f;
            if (lmax >= ratio2 * lmin) {
                Py_ssize_t i = i0 + q;
                out_pix[2 * n] = pix[2 * i] + x0;
                out_pix[2 * n + 1] = pix[2 * i + 1] + y0;
                out_g[2 * n] = g0[q][0];
                out_g[2 * n + 1] = g0[q][1];
                n++;
            }
        }
    }
    return n;
}

static PyObject *py_corner_test(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t size, N, K;
    double ratio2;
    int x0, y0;
    PyObject *o[7];
    if (!PyArg_ParseTuple(args, "nnnOOOOOdiiOO", &size, &N, &K, &o[0], &o[1], &o[2], &o[3],
                          &o[4], &ratio2, &x0, &y0, &o[5], &o[6]))
        return NULL;
    if (!nonnegative("size", size) || !nonnegative("N", N) || !nonnegative("K", K))
        return NULL;
    Py_buffer b[7];
    const Spec spec[7] = {
        {"dxy", 4, 2 * size, 0},
        {"pix", 4, 2 * N, 0},
        {"flat", 8, N, 0},
        {"win", 8, K, 0},
        {"w", 4, K, 0},
        {"out_pix", 4, 2 * N, 1},
        {"out_g", 4, 2 * N, 1},
    };
    if (take_all(7, o, spec, b) < 0)
        return NULL;
    Py_ssize_t n, bad = -1;
    Py_BEGIN_ALLOW_THREADS
    n = corner_test(size, N, K, b[0].buf, b[1].buf, b[2].buf, b[3].buf, b[4].buf,
                    (float)ratio2, (int32_t)x0, (int32_t)y0, b[5].buf, b[6].buf, &bad);
    Py_END_ALLOW_THREADS
    release_all(7, b);
    if (n < 0) {
        PyErr_Format(PyExc_IndexError, "corner_test: the window of point %zd leaves the image",
                     bad);
        return NULL;
    }
    return PyLong_FromSsize_t(n);
}

/* ---- orientation modulo pi ---------------------------------------------------------------- */

/* numpy's float32 remainder np.mod(a, pi) (pi rounded to float32: fmod, then the sign of the
 * divisor), widened to float64 */
static void mod_pi(Py_ssize_t N, const float *a, double *out)
{
    const float p = (float)M_PI;
    for (Py_ssize_t i = 0; i < N; i++) {
        float x = a[i];
        float m = fabsf(x) < p ? x : fmodf(x, p);
        if (m != 0.0f) {
            if (m < 0.0f)
                m = m + p;
        } else {
            m = 0.0f;
        }
        out[i] = (double)m;
    }
}

static PyObject *py_mod_pi(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t N;
    PyObject *o[2];
    if (!PyArg_ParseTuple(args, "nOO", &N, &o[0], &o[1]))
        return NULL;
    if (!nonnegative("N", N))
        return NULL;
    Py_buffer b[2];
    const Spec spec[2] = {{"a", 4, N, 0}, {"out", 8, N, 1}};
    if (take_all(2, o, spec, b) < 0)
        return NULL;
    Py_BEGIN_ALLOW_THREADS
    mod_pi(N, b[0].buf, b[1].buf);
    Py_END_ALLOW_THREADS
    release_all(2, b);
    Py_RETURN_NONE;
}

/* ---- orientation-linked components -------------------------------------------------------- */

static int64_t find_root(int64_t *parent, int64_t i)
{
    while (parent[i] != i) {
        parent[i] = parent[parent[i]];
        i = parent[i];
    }
    return i;
}

/* Union-find over the points ``p`` (x, y in 0..w-1, 0..h-1), 8-neighbours joined where their
 * orientations (mod pi) differ by less than max_angle; labels numbered by each component's
 * lowest point index (as scipy's connected_components). Returns the number of components,
 * -1 where a point is outside the image (*bad), -2 where memory ran out. */
static Py_ssize_t components(Py_ssize_t N, Py_ssize_t h, Py_ssize_t w, const int64_t *p,
                             const double *theta, double max_angle, int64_t *lab,
                             Py_ssize_t *bad)
{
    for (Py_ssize_t i = 0; i < N; i++)
        if (p[2 * i] < 0 || p[2 * i] >= w || p[2 * i + 1] < 0 || p[2 * i + 1] >= h) {
            *bad = i;
            return -1;
        }
    int32_t *img = NULL;
    if (N > 0) {
        img = malloc((size_t)h * (size_t)w * sizeof(int32_t));
        if (img == NULL)
            return -2;
        memset(img, 0xff, (size_t)h * (size_t)w * sizeof(int32_t)); /* -1 */
    }
    int64_t *parent = malloc((size_t)(N > 0 ? N : 1) * sizeof(int64_t));
    if (parent == NULL) {
        free(img);
        return -2;
    }
    for (Py_ssize_t i = 0; i < N; i++) {
        img[p[2 * i + 1] * w + p[2 * i]] = (int32_t)i;
        parent[i] = i;
    }
    /* the neighbours right, below-left, below and below-right (each pair once) */
    const int dxs[4] = {1, -1, 0, 1}, dys[4] = {0, 1, 1, 1};
    for (Py_ssize_t i = 0; i < N; i++) {
        int64_t x = p[2 * i], y = p[2 * i + 1];
        for (int k = 0; k < 4; k++) {
            int64_t xn = x + dxs[k], yn = y + dys[k];
            if (xn < 0 || xn >= w || yn >= h)
                continue;
            int32_t j = img[yn * w + xn];
            if (j < 0)
                continue;
            double d = fabs(theta[i] - theta[j]);
            double d2 = M_PI - d;
            if (d2 < d)
                d = d2;
            if (!(d < max_angle))
                continue;
            int64_t ri = find_root(parent, i), rj = find_root(parent, j);
            if (ri != rj) {
                if (ri < rj)
                    parent[rj] = ri;
                else
                    parent[ri] = rj;
            }
        }
    }
    free(img);
    /* a root is its component's lowest index (a union keeps the smaller root): number the
     * roots in index order; a point's root comes before it, so its label is known already */
    Py_ssize_t ncomp = 0;
    for (Py_ssize_t i = 0; i < N; i++) {
        int64_t r = find_root(parent, i);
        lab[i] = r == i ? (int64_t)(ncomp++) : lab[r];
    }
    free(parent);
    return ncomp;
}

static PyObject *py_components(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t N, h, w;
    double max_angle;
    PyObject *o[3];
    if (!PyArg_ParseTuple(args, "nnnOOdO", &N, &h, &w, &o[0], &o[1], &max_angle, &o[2]))
        return NULL;
    if (!nonnegative("N", N) || !nonnegative("h", h) || !nonnegative("w", w))
        return NULL;
    Py_buffer b[3];
    const Spec spec[3] = {{"p", 8, 2 * N, 0}, {"theta", 8, N, 0}, {"labels", 8, N, 1}};
    if (take_all(3, o, spec, b) < 0)
        return NULL;
    Py_ssize_t n, bad = -1;
    Py_BEGIN_ALLOW_THREADS
    n = components(N, h, w, b[0].buf, b[1].buf, max_angle, b[2].buf, &bad);
    Py_END_ALLOW_THREADS
    release_all(3, b);
    if (n == -1) {
        PyErr_Format(PyExc_IndexError, "components: point %zd is outside the %zdx%zd image",
                     bad, w, h);
        return NULL;
    }
    if (n == -2)
        return PyErr_NoMemory();
    return PyLong_FromSsize_t(n);
}

/* ---- sub-pixel positions ------------------------------------------------------------------ */

/* float32 |g| as numpy: sqrt(dx * dx + dy * dy), each operation rounded */
static float magnitude(const float *g) { return sqrtf(g[0] * g[0] + g[1] * g[1]); }

static double clip(double x, double lo, double hi)
{
    x = x < lo ? lo : x;
    return x > hi ? hi : x;
}

/* extract._bilinear_magnitude at one point (float64 weights, the result rounded to float32) */
static float bilinear_magnitude(const float *dxy, Py_ssize_t h, Py_ssize_t w, double x,
                                double y)
{
    x = clip(x == x ? x : 0.0, 0.0, (double)w - 1.001); /* NaN (no gradient given): 0, to */
    y = clip(y == y ? y : 0.0, 0.0, (double)h - 1.001); /* stay inside the image */
    int64_t x0 = (int64_t)x, y0 = (int64_t)y;
    double fx = x - (double)x0, fy = y - (double)y0;
    const float *g = dxy + 2 * (y0 * w + x0);
    double f0 = magnitude(g), f1 = magnitude(g + 2), f2 = magnitude(g + 2 * w),
           f3 = magnitude(g + 2 * w + 2);
    double top = f0 * (1.0 - fx) + f1 * fx;
    double bot = f2 * (1.0 - fx) + f3 * fx;
    return (float)(top * (1.0 - fy) + bot * fy);
}

/* _EdgePoints.subpixel for the points ``sel``: the vertex of the parabola through the gradient
 * magnitude at the point and one pixel either way along its gradient. -1 where an index is
 * out of range (*bad). */
static int subpixel(Py_ssize_t N, Py_ssize_t M, Py_ssize_t h, Py_ssize_t w, const float *dxy,
                    const int32_t *pix, const float *grad, const int64_t *sel, int32_t ox,
                    int32_t oy, double *out, Py_ssize_t *bad)
{
    for (Py_ssize_t k = 0; k < M; k++) {
        int64_t i = sel[k];
        if (i < 0 || i >= N) {
            *bad = k;
            return -1;
        }
        float gx = grad[2 * i], gy = grad[2 * i + 1];
        float m0 = sqrtf(gx * gx + gy * gy);
        float gn = m0 > 0.0f ? m0 : 1.0f;
        float ux = gx / gn, uy = gy / gn;
        int32_t xs = pix[2 * i], ys = pix[2 * i + 1];
        int32_t xl = xs - ox, yl = ys - oy;
        float mp = bilinear_magnitude(dxy, h, w, (double)xl + (double)ux,
                                      (double)yl + (double)uy);
        float mm = bilinear_magnitude(dxy, h, w, (double)xl - (double)ux,
                                      (double)yl - (double)uy);
        float den = (mp - 2.0f * m0) + mm;
        float off = den < 0.0f ? (0.5f * (mm - mp)) / den : 0.0f;
        off = off < -0.5f ? -0.5f : off;
        off = off > 0.5f ? 0.5f : off;
        out[2 * k] = (double)xs + (double)(off * ux);
        out[2 * k + 1] = (double)ys + (double)(off * uy);
    }
    return 0;
}

static PyObject *py_subpixel(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t N, M, h, w;
    int ox, oy;
    PyObject *o[5];
    if (!PyArg_ParseTuple(args, "nnnnOOOOiiO", &N, &M, &h, &w, &o[0], &o[1], &o[2], &o[3], &ox,
                          &oy, &o[4]))
        return NULL;
    if (!nonnegative("N", N) || !nonnegative("M", M))
        return NULL;
    if (M > 0 && (h < 2 || w < 2)) {
        PyErr_Format(PyExc_ValueError, "subpixel: the gradient image is %zdx%zd px, need 2x2",
                     w, h);
        return NULL;
    }
    Py_buffer b[5];
    const Spec spec[5] = {
        {"dxy", 4, 2 * h * w, 0},
        {"pix", 4, 2 * N, 0},
        {"grad", 4, 2 * N, 0},
        {"sel", 8, M, 0},
        {"out", 8, 2 * M, 1},
    };
    if (take_all(5, o, spec, b) < 0)
        return NULL;
    int rc;
    Py_ssize_t bad = -1;
    Py_BEGIN_ALLOW_THREADS
    rc = subpixel(N, M, h, w, b[0].buf, b[1].buf, b[2].buf, b[3].buf, (int32_t)ox, (int32_t)oy,
                  b[4].buf, &bad);
    Py_END_ALLOW_THREADS
    release_all(5, b);
    if (rc < 0) {
        PyErr_Format(PyExc_IndexError, "subpixel: sel[%zd] out of range", bad);
        return NULL;
    }
    Py_RETURN_NONE;
}

/* ---- MSAC scores -------------------------------------------------------------------------- */

/* numpy's float32 pairwise sum of n values at stride ``s`` (its add reduction: eight partial
 * sums in blocks of up to 128 values, halves above) */
static float pairwise_sum(const float *a, Py_ssize_t n, Py_ssize_t s)
{
    if (n < 8) {
        float res = -0.0f;
        for (Py_ssize_t i = 0; i < n; i++)
            res = res + a[i * s];
        return res;
    }
    if (n <= 128) {
        float r[8];
        for (int j = 0; j < 8; j++)
            r[j] = a[j * s];
        Py_ssize_t i;
        for (i = 8; i < n - (n % 8); i += 8)
            for (int j = 0; j < 8; j++)
                r[j] = r[j] + a[(i + j) * s];
        float res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
        for (; i < n; i++)
            res = res + a[i * s];
        return res;
    }
    Py_ssize_t n2 = n / 2;
    n2 -= n2 % 8;
    return pairwise_sum(a, n2, s) + pairwise_sum(a + n2 * s, n - n2, s);
}

/* LineExtractor._ransac's scores: d = r . hyp[seg] (x, y, z in that order), cost = min(d^2,
 * t2) / t2 per point and hypothesis (``cost`` (N, H), float32) and its sums per segment as
 * np.add.reduceat(cost, start, axis=0) adds them (the first row, then numpy's pairwise sum of
 * the others). -1 where a segment index or start is out of range (*bad). */
static int msac(Py_ssize_t N, Py_ssize_t S, Py_ssize_t H, const float *r, const float *hyp,
                const int64_t *seg, const int64_t *start, const float *t2, float *cost,
                float *out, Py_ssize_t *bad)
{
    const float *r0 = r, *r1 = r + N, *r2 = r + 2 * N;
    const float *h0 = hyp, *h1 = hyp + S * H, *h2 = hyp + 2 * S * H;
    for (Py_ssize_t i = 0; i < N; i++) {
        int64_t s = seg[i];
        if (s < 0 || s >= S) {
            *bad = i;
            return -1;
        }
        float *c = cost + i * H;
        for (Py_ssize_t k = 0; k < H; k++) {
            float d = r0[i] * h0[s * H + k];
            d = d + r1[i] * h1[s * H + k];
            d = d + r2[i] * h2[s * H + k];
            float dd = d * d;
            float t = t2[i];
            c[k] = (dd <= t || dd != dd ? dd : t) / t; /* np.minimum: NaN propagates */
        }
    }
    for (Py_ssize_t s = 0; s < S; s++) {
        int64_t a = start[s], e = s + 1 < S ? start[s + 1] : N;
        if (a < 0 || a >= N || e > N) {
            *bad = N + s;
            return -1;
        }
        if (e <= a)
            e = a + 1; /* reduceat: the row at start alone */
        for (Py_ssize_t k = 0; k < H; k++)
            out[s * H + k] = cost[a * H + k] + pairwise_sum(cost + (a + 1) * H + k, e - a - 1, H);
    }
    return 0;
}

static PyObject *py_msac(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t N, S, H;
    PyObject *o[7];
    if (!PyArg_ParseTuple(args, "nnnOOOOOOO", &N, &S, &H, &o[0], &o[1], &o[2], &o[3], &o[4],
                          &o[5], &o[6]))
        return NULL;
    if (!nonnegative("N", N) || !nonnegative("S", S) || !nonnegative("H", H))
        return NULL;
    Py_buffer b[7];
    const Spec spec[7] = {
        {"rays", 4, 3 * N, 0},
        {"hyp", 4, 3 * S * H, 0},
        {"seg", 8, N, 0},
        {"start", 8, S, 0},
        {"t2", 4, N, 0},
        {"cost", 4, N * H, 1},
        {"seg_cost", 4, S * H, 1},
    };
    if (take_all(7, o, spec, b) < 0)
        return NULL;
    int rc;
    Py_ssize_t bad = -1;
    Py_BEGIN_ALLOW_THREADS
    rc = msac(N, S, H, b[0].buf, b[1].buf, b[2].buf, b[3].buf, b[4].buf, b[5].buf, b[6].buf,
              &bad);
    Py_END_ALLOW_THREADS
    release_all(7, b);
    if (rc < 0) {
        if (bad < N)
            PyErr_Format(PyExc_IndexError, "msac: seg[%zd] out of range", bad);
        else
            PyErr_Format(PyExc_IndexError, "msac: start[%zd] out of range", bad - N);
        return NULL;
    }
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"corner_test", py_corner_test, METH_VARARGS,
     "corner_test(size, N, K, dxy, pix, flat, win, w, ratio2, x0, y0, out_pix, out_g): the "
     "kept points' pixels and gradients written in order; returns how many"},
    {"mod_pi", py_mod_pi, METH_VARARGS,
     "mod_pi(N, a, out): out = float64(np.mod(a, pi)) of float32 a"},
    {"components", py_components, METH_VARARGS,
     "components(N, h, w, p, theta, max_angle, labels): orientation-linked 8-connected "
     "components, labels written; returns their number"},
    {"subpixel", py_subpixel, METH_VARARGS,
     "subpixel(N, M, h, w, dxy, pix, grad, sel, ox, oy, out): sub-pixel positions of the "
     "points sel written"},
    {"msac", py_msac, METH_VARARGS,
     "msac(N, S, H, rays, hyp, seg, start, t2, cost, seg_cost): MSAC costs and their sums "
     "per segment written"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_edges",
    "The line extractor's per-edge-point loops in C (omni_sfm.lines.edge_kernels).", -1,
    methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__edges(void) { return PyModule_Create(&module); }
