/* The line extractor's per-pixel and per-edge-point loops (omni_sfm.lines.extract), in C: the
 * grey-level histogram, Sobel, Canny (for frames with dense edges) and the glue around it (its
 * int16 gradients, the masked edge pixels, the long-chain test), the corner test of the edge
 * points, the orientation's value modulo pi, the orientation-linked connected components of
 * the edge points, their sub-pixel positions, the great circles' fits (MSAC scores, scatter
 * matrices, their smallest eigenvectors), the lines' bookkeeping, and the tracker's samples
 * and snapping. The eigenvectors (Jacobi rotations) are the one kernel that does not repeat
 * its predecessor's bits (np.linalg.eigh's LAPACK), only its accuracy.
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

/* take, release_all, Spec, take_all */
#include "../_buffers.h"

static int nonnegative(const char *what, Py_ssize_t n)
{
    if (n < 0) {
        PyErr_Format(PyExc_ValueError, "%s must not be negative, got %zd", what, n);
        return 0;
    }
    return 1;
}

/* ---- gradients for Canny, edge points, long chains ------------------------------------------ */

/* numpy's float32 -> int16 cast as this build makes it (the x86 one): truncated toward zero to
 * int32 (cvttss2si; NaN, infinities and values outside int32 give INT32_MIN), then its low 16
 * bits. Exact for |x| < 32768; written out so that C's undefined conversions never happen. */
static inline int16_t to_int16(float x)
{
    int32_t i = (x > -2147483648.0f && x < 2147483648.0f) ? (int32_t)x : INT32_MIN;
    return (int16_t)(uint16_t)((uint32_t)i & 0xffffu);
}

/* The Sobel images dx, dy (float32, n pixels): Canny's 16-bit gradients ``(int16)(8 dx)`` as
 * ``np.multiply(dx, 8.0, out=dx16, casting="unsafe")`` (the product by 8 is exact in float32)
 * and the interleaved image (dx, dy) as ``cv2.merge([dx, dy])``, in one pass. */
static void gradients(Py_ssize_t n, const float *dx, const float *dy, int16_t *dx16,
                      int16_t *dy16, float *dxy)
{
    for (Py_ssize_t i = 0; i < n; i++) {
        float gx = dx[i], gy = dy[i];
        dx16[i] = to_int16(gx * 8.0f);
        dy16[i] = to_int16(gy * 8.0f);
        dxy[2 * i] = gx;
        dxy[2 * i + 1] = gy;
    }
}

static PyObject *py_gradients(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t n;
    PyObject *o[5];
    if (!PyArg_ParseTuple(args, "nOOOOO", &n, &o[0], &o[1], &o[2], &o[3], &o[4]))
        return NULL;
    if (!nonnegative("n", n))
        return NULL;
    Py_buffer b[5];
    const Spec spec[5] = {
        {"dx", 4, n, 0}, {"dy", 4, n, 0}, {"dx16", 2, n, 1}, {"dy16", 2, n, 1},
        {"dxy", 4, 2 * n, 1},
    };
    if (take_all(5, o, spec, b) < 0)
        return NULL;
    Py_BEGIN_ALLOW_THREADS
    gradients(n, b[0].buf, b[1].buf, b[2].buf, b[3].buf, b[4].buf);
    Py_END_ALLOW_THREADS
    release_all(5, b);
    Py_RETURN_NONE;
}

/* Sobel's 3x3 derivatives of the float32 (h, w) image ``img`` (both at least 2), as
 * cv2.Sobel(img, cv2.CV_32F, 1, 0) and (0, 1) with OpenCV's border (reflect-101) and order of
 * operations, then what ``gradients`` writes, in one pass without the dx, dy images. OpenCV's
 * loops 8 floats wide (AVX2) compute dx = (t[y-1] + t[y+1]) + 2 t[y] across rows of
 * t = img[x+1] - img[x-1], and dy = s[y+1] - s[y-1] with s = (img[x-1] + img[x+1]) + 2 img[x];
 * the columns past the last multiple of 8 go through its scalar loops, which add in the order
 * (t[y-1] + 2 t[y]) + t[y+1] and (img[x-1] + 2 img[x]) + img[x+1] (but a last column left
 * alone by its pairs). Reproduced here: the same bits as cv2.Sobel where its loops are 8 wide
 * (tests/test_edge_kernels.py). */
static inline Py_ssize_t reflect101(Py_ssize_t i, Py_ssize_t n)
{
    return i < 0 ? -i : (i >= n ? 2 * n - 2 - i : i);
}

static inline void sobel_pixel(const float *a, const float *b, const float *c, Py_ssize_t l,
                               Py_ssize_t x, Py_ssize_t r, int scalar_x, int scalar_y,
                               int16_t *ox, int16_t *oy, float *o)
{
    float t0 = a[r] - a[l], t1 = b[r] - b[l], t2 = c[r] - c[l];
    float gx = scalar_x ? (t0 + 2.0f * t1) + t2 : (t0 + t2) + 2.0f * t1;
    float sa = scalar_y ? (a[l] + 2.0f * a[x]) + a[r] : (a[l] + a[r]) + 2.0f * a[x];
    float sc = scalar_y ? (c[l] + 2.0f * c[x]) + c[r] : (c[l] + c[r]) + 2.0f * c[x];
    float gy = sc - sa;
    ox[x] = to_int16(gx * 8.0f);
    oy[x] = to_int16(gy * 8.0f);
    o[2 * x] = gx;
    o[2 * x + 1] = gy;
}

WIDE_LOOPS static void sobel_gradients(Py_ssize_t h, Py_ssize_t w, const float *img,
                                       int16_t *dx16, int16_t *dy16, float *dxy)
{
    Py_ssize_t xs = w & ~(Py_ssize_t)7; /* where OpenCV's scalar loops start */
    Py_ssize_t end = xs < w - 1 ? xs : w - 1; /* the vector columns inside */
    for (Py_ssize_t y = 0; y < h; y++) {
        const float *a = img + reflect101(y - 1, h) * w, *b = img + y * w,
                    *c = img + reflect101(y + 1, h) * w;
        int16_t *ox = dx16 + y * w, *oy = dy16 + y * w;
        float *o = dxy + 2 * y * w;
        int s0 = xs == 0;
        sobel_pixel(a, b, c, 1, 0, 1, s0, s0, ox, oy, o);
        for (Py_ssize_t x = 1; x < end; x++) {
            float t0 = a[x + 1] - a[x - 1], t1 = b[x + 1] - b[x - 1], t2 = c[x + 1] - c[x - 1];
            float gx = (t0 + t2) + 2.0f * t1;
            float gy = ((c[x - 1] + c[x + 1]) + 2.0f * c[x]) - ((a[x - 1] + a[x + 1]) + 2.0f * a[x]);
            ox[x] = to_int16(gx * 8.0f);
            oy[x] = to_int16(gy * 8.0f);
            o[2 * x] = gx;
            o[2 * x + 1] = gy;
        }
        for (Py_ssize_t x = end > 1 ? end : 1; x < w - 1; x++)
            sobel_pixel(a, b, c, x - 1, x, x + 1, 1, 1, ox, oy, o);
        /* the last column: scalar where it is in the scalar loops' part and their pairs */
        int sl = w - 1 >= xs && (w - xs) % 2 == 0;
        sobel_pixel(a, b, c, w - 2, w - 1, w - 2, w - 1 >= xs, sl, ox, oy, o);
    }
}

static PyObject *py_sobel_gradients(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t h, w;
    PyObject *o[4];
    if (!PyArg_ParseTuple(args, "nnOOOO", &h, &w, &o[0], &o[1], &o[2], &o[3]))
        return NULL;
    if (h < 2 || w < 2) {
        PyErr_Format(PyExc_ValueError, "sobel_gradients: a %zdx%zd image (at least 2x2)", w, h);
        return NULL;
    }
    Py_buffer b[4];
    const Spec spec[4] = {
        {"img", 4, h * w, 0}, {"dx16", 2, h * w, 1}, {"dy16", 2, h * w, 1}, {"dxy", 4, 2 * h * w, 1},
    };
    if (take_all(4, o, spec, b) < 0)
        return NULL;
    Py_BEGIN_ALLOW_THREADS
    sobel_gradients(h, w, b[0].buf, b[1].buf, b[2].buf, b[3].buf);
    Py_END_ALLOW_THREADS
    release_all(4, b);
    Py_RETURN_NONE;
}

/* Canny's non-maximum suppression and hysteresis on given int16 gradients, L2 magnitude, as
 * cv2.Canny(dx, dy, low, high, L2gradient=True): magnitude m = dx^2 + dy^2 (int), thresholds
 * squared and floored; a pixel with m > low is a local maximum across its edge (the direction
 * quantised by tan 22.5 deg in 15-bit fixed point; left/up neighbours compared with >, the
 * others as OpenCV does); maxima above ``high`` seed the edges, which grow through the 8-connected
 * maxima above ``low``. Outside the image the magnitude is 0. ``edges`` (h, w) gets 255 on edge
 * pixels and 0 elsewhere. Returns -1 where memory ran out. */
/* One row of Canny's non-maximum suppression (see canny), without branches so that the
 * compiler can take several pixels at once: the map gets 2 (a maximum above high), 0 (a maximum
 * above low) or 1. ``mp``, ``mc``, ``mn``: the magnitudes of the rows above, here and below,
 * from one column left of the image. */
WIDE_LOOPS static void canny_row(Py_ssize_t w, const int16_t *rx, const int16_t *ry,
                                 const int *mp, const int *mc, const int *mn, int low, int high,
                                 uint8_t *row)
{
    enum { SHIFT = 15 };
    const int TG22 = (int)(0.4142135623730950488016887242097 * (1 << SHIFT) + 0.5);
    for (Py_ssize_t x = 0; x < w; x++) {
        int m = mc[x + 1], xs = rx[x], ys = ry[x];
        int ax = xs < 0 ? -xs : xs, ay = (ys < 0 ? -ys : ys) << SHIFT;
        int tg22x = ax * TG22, tg67x = tg22x + (ax << (SHIFT + 1));
        int across = ay < tg22x, along = !across && ay > tg67x, diag = !across && !along;
        int up = (xs ^ ys) >= 0; /* the diagonal through the upper left and lower right */
        int a = across ? mc[x] : along ? mp[x + 1] : up ? mp[x] : mp[x + 2];
        int b = across ? mc[x + 2] : along ? mn[x + 1] : up ? mn[x + 2] : mn[x];
        int keep = (m > low) & (m > a) & ((m > b) | ((m == b) & !diag));
        row[x] = (uint8_t)(keep ? (m > high ? 2 : 0) : 1);
    }
}

static int canny(Py_ssize_t h, Py_ssize_t w, const int16_t *dx, const int16_t *dy, int low,
                 int high, uint8_t *edges)
{
    Py_ssize_t W = w + 2;
    int *mag = calloc((size_t)(3 * W), sizeof(int));
    uint8_t *map = malloc((size_t)((h + 2) * W));
    /* each pixel is pushed at most once (marked 2 first), so the stack never outgrows the
     * image; the pages of its unused part are never touched */
    Py_ssize_t top = 0;
    uint8_t **stack = malloc((size_t)(h * w > 0 ? h * w : 1) * sizeof(uint8_t *));
    if (!mag || !map || !stack) {
        free(mag), free(map), free(stack);
        return -1;
    }
    memset(map, 1, (size_t)((h + 2) * W));
    int *mp = mag, *mc = mag + W, *mn = mag + 2 * W; /* rows y-1, y, y+1, one column of 0 a side */
    for (Py_ssize_t x = 0; x < w; x++)
        mn[x + 1] = (int)dx[x] * dx[x] + (int)dy[x] * dy[x];
    for (Py_ssize_t y = 0; y < h; y++) {
        int *t = mp;
        mp = mc, mc = mn, mn = t;
        if (y + 1 < h) {
            const int16_t *ax = dx + (y + 1) * w, *ay = dy + (y + 1) * w;
            for (Py_ssize_t x = 0; x < w; x++)
                mn[x + 1] = (int)ax[x] * ax[x] + (int)ay[x] * ay[x];
        } else {
            for (Py_ssize_t x = 0; x < W; x++)
                mn[x] = 0;
        }
        canny_row(w, dx + y * w, dy + y * w, mp, mc, mn, low, high, map + (y + 1) * W + 1);
        const uint8_t *row = map + (y + 1) * W + 1;
        for (Py_ssize_t x = 0; x < w; x++) {
            if (row[x] == 2)
                stack[top++] = (uint8_t *)row + x;
        }
    }
    const Py_ssize_t nb[8] = {-W - 1, -W, -W + 1, -1, 1, W - 1, W, W + 1};
    while (top > 0) {
        uint8_t *m = stack[--top];
        for (int k = 0; k < 8; k++)
            if (m[nb[k]] == 0) {
                m[nb[k]] = 2;
                stack[top++] = m + nb[k];
            }
    }
    for (Py_ssize_t y = 0; y < h; y++) {
        const uint8_t *row = map + (y + 1) * W + 1;
        uint8_t *out = edges + y * w;
        for (Py_ssize_t x = 0; x < w; x++)
            out[x] = row[x] == 2 ? 255 : 0;
    }
    free(mag), free(map), free(stack);
    return 0;
}

static PyObject *py_canny(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t h, w;
    int low, high;
    PyObject *o[3];
    if (!PyArg_ParseTuple(args, "nnOOiiO", &h, &w, &o[0], &o[1], &low, &high, &o[2]))
        return NULL;
    if (!nonnegative("h", h) || !nonnegative("w", w))
        return NULL;
    Py_buffer b[3];
    const Spec spec[3] = {{"dx", 2, h * w, 0}, {"dy", 2, h * w, 0}, {"edges", 1, h * w, 1}};
    if (take_all(3, o, spec, b) < 0)
        return NULL;
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = canny(h, w, b[0].buf, b[1].buf, low, high, b[2].buf);
    Py_END_ALLOW_THREADS
    release_all(3, b);
    if (rc < 0)
        return PyErr_NoMemory();
    Py_RETURN_NONE;
}

/* The 256-bin histogram of the pixels of an (h, w) uint8 image (rows ``gs`` bytes apart)
 * where the uint8 mask (rows ``ms`` apart) is not 0, as float32 counts (exact below 2^24):
 * cv2.calcHist([gray], [0], mask, [256], [0, 256]). Four partial histograms, so that runs of
 * one grey level do not wait on their own increments. */
static void histogram(Py_ssize_t h, Py_ssize_t w, const uint8_t *gray, Py_ssize_t gs,
                      const uint8_t *mask, Py_ssize_t ms, float *out)
{
    uint32_t c[4][256];
    memset(c, 0, sizeof(c));
    for (Py_ssize_t y = 0; y < h; y++) {
        const uint8_t *g = gray + y * gs, *m = mask + y * ms;
        Py_ssize_t x = 0;
        for (; x + 8 <= w; x += 8) {
            uint64_t mm;
            memcpy(&mm, m + x, 8);
            if (mm == 0)
                continue;
            if (mm == UINT64_MAX) { /* inside the mask: no test */
                c[0][g[x]]++;
                c[1][g[x + 1]]++;
                c[2][g[x + 2]]++;
                c[3][g[x + 3]]++;
                c[0][g[x + 4]]++;
                c[1][g[x + 5]]++;
                c[2][g[x + 6]]++;
                c[3][g[x + 7]]++;
                continue;
            }
            for (Py_ssize_t k = x; k < x + 8; k++)
                c[k & 3][g[k]] += m[k] != 0;
        }
        for (; x < w; x++)
            c[0][g[x]] += m[x] != 0;
    }
    for (int k = 0; k < 256; k++)
        out[k] = (float)((uint64_t)c[0][k] + c[1][k] + c[2][k] + c[3][k]);
}

static PyObject *py_histogram(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t h, w, gh, gw, mh, mw, x0, y0;
    PyObject *o[3];
    if (!PyArg_ParseTuple(args, "nnnnOnnOnnO", &h, &w, &gh, &gw, &o[0], &mh, &mw, &o[1], &x0,
                          &y0, &o[2]))
        return NULL;
    if (!nonnegative("h", h) || !nonnegative("w", w) || !nonnegative("x0", x0)
        || !nonnegative("y0", y0))
        return NULL;
    if (x0 + w > gw || y0 + h > gh || x0 + w > mw || y0 + h > mh) {
        PyErr_Format(PyExc_ValueError, "histogram: a %zdx%zd region at (%zd, %zd) leaves the "
                     "%zdx%zd image or the %zdx%zd mask", w, h, x0, y0, gw, gh, mw, mh);
        return NULL;
    }
    Py_buffer b[3];
    const Spec spec[3] = {{"gray", 1, gh * gw, 0}, {"mask", 1, mh * mw, 0}, {"out", 4, 256, 1}};
    if (take_all(3, o, spec, b) < 0)
        return NULL;
    Py_BEGIN_ALLOW_THREADS
    histogram(h, w, (const uint8_t *)b[0].buf + y0 * gw + x0, gw,
              (const uint8_t *)b[1].buf + y0 * mw + x0, mw, b[2].buf);
    Py_END_ALLOW_THREADS
    release_all(3, b);
    Py_RETURN_NONE;
}

/* The pixels of the (h, w) uint8 image ``edges`` where ``edges & mask`` is not 0, row by row
 * (cv2.findNonZero's order), ``mask`` the rows of ``ms`` bytes of a larger image that begin
 * at the edge image's top-left pixel: (x, y) into ``pix`` and y w + x into ``flat``, at most
 * ``cap`` of
 * them. Eight pixels are tested at a time (most words of a Canny image are 0); within a word
 * every pixel is written at the next free place, which advances only past the edge points
 * (no branch to mispredict on the pixels of a textured image). Returns how many, -1 where
 * there are more than ``cap``. */
static Py_ssize_t edge_points(Py_ssize_t h, Py_ssize_t w, const uint8_t *edges,
                              const uint8_t *mask, Py_ssize_t ms, Py_ssize_t cap, int32_t *pix,
                              int64_t *flat)
{
    Py_ssize_t n = 0;
    for (Py_ssize_t y = 0; y < h; y++) {
        const uint8_t *e = edges + y * w, *m = mask + y * ms;
        int64_t row = (int64_t)y * (int64_t)w;
        Py_ssize_t x = 0;
        for (; x + 8 <= w; x += 8) {
            uint64_t a, b;
            memcpy(&a, e + x, 8);
            memcpy(&b, m + x, 8);
            if ((a & b) == 0)
                continue;
            if (n + 8 > cap)
                break; /* near the end of the output: one pixel at a time, below */
            for (Py_ssize_t k = x; k < x + 8; k++) {
                pix[2 * n] = (int32_t)k;
                pix[2 * n + 1] = (int32_t)y;
                flat[n] = row + k;
                n += (e[k] & m[k]) != 0;
            }
        }
        for (; x < w; x++) {
            if ((e[x] & m[x]) == 0)
                continue;
            if (n >= cap)
                return -1;
            pix[2 * n] = (int32_t)x;
            pix[2 * n + 1] = (int32_t)y;
            flat[n] = row + x;
            n++;
        }
    }
    return n;
}

static PyObject *py_edge_points(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t h, w, mh, mw, mx, my, cap;
    PyObject *o[4];
    if (!PyArg_ParseTuple(args, "nnOnnOnnnOO", &h, &w, &o[0], &mh, &mw, &o[1], &mx, &my, &cap,
                          &o[2], &o[3]))
        return NULL;
    if (!nonnegative("h", h) || !nonnegative("w", w) || !nonnegative("mx", mx)
        || !nonnegative("my", my) || !nonnegative("cap", cap))
        return NULL;
    if (mx + w > mw || my + h > mh) {
        PyErr_Format(PyExc_ValueError, "edge_points: a %zdx%zd image at (%zd, %zd) leaves the "
                     "%zdx%zd mask", w, h, mx, my, mw, mh);
        return NULL;
    }
    Py_buffer b[4];
    const Spec spec[4] = {
        {"edges", 1, h * w, 0}, {"mask", 1, mh * mw, 0}, {"pix", 4, 2 * cap, 1},
        {"flat", 8, cap, 1},
    };
    if (take_all(4, o, spec, b) < 0)
        return NULL;
    Py_ssize_t n;
    Py_BEGIN_ALLOW_THREADS
    n = edge_points(h, w, b[0].buf, (const uint8_t *)b[1].buf + my * mw + mx, mw, cap,
                    b[2].buf, b[3].buf);
    Py_END_ALLOW_THREADS
    release_all(4, b);
    if (n < 0) {
        PyErr_Format(PyExc_ValueError, "edge_points: more than %zd edge points", cap);
        return NULL;
    }
    return PyLong_FromSsize_t(n);
}

static int32_t find_root32(int32_t *parent, int32_t i)
{
    while (parent[i] != i) {
        parent[i] = parent[parent[i]];
        i = parent[i];
    }
    return i;
}

/* The points of 8-connected chains of at least ``min_points`` points among the N points
 * ``pix`` (x, y) of an (h, w) image, row by row (edge_points' order; their flat indices
 * ``flat``, y w + x, are copied along): cv2.connectedComponents on the image of the points and
 * each point's component size, by a union-find over the points that looks up the neighbours
 * above and to the left in two rows of point indices (the previous and the current one; only
 * the entries set are cleared again). ``keep`` (0/1) is written, the kept points' pixels and
 * flat indices are copied in order into ``out_pix``, ``out_flat``. Returns how many are kept,
 * -1 where a point is outside the image, not after the one before or its flat index is not
 * y w + x (*bad), -2 where memory ran out. */
static Py_ssize_t long_chains(Py_ssize_t N, Py_ssize_t h, Py_ssize_t w, const int32_t *pix,
                              const int64_t *flat, Py_ssize_t min_points, uint8_t *keep,
                              int32_t *out_pix, int64_t *out_flat, Py_ssize_t *bad)
{
    for (Py_ssize_t i = 0; i < N; i++) {
        int64_t x = pix[2 * i], y = pix[2 * i + 1];
        if (x < 0 || x >= w || y < 0 || y >= h || flat[i] != y * (int64_t)w + x
            || (i > 0 && flat[i] <= flat[i - 1])) {
            *bad = i;
            return -1;
        }
    }
    if (N == 0)
        return 0;
    /* rows of w + 2 entries (a -1 either side: no test at the borders) */
    int32_t *rows = malloc((size_t)(2 * (w + 2)) * sizeof(int32_t));
    int32_t *parent = malloc((size_t)N * sizeof(int32_t));
    int32_t *size = calloc((size_t)N, sizeof(int32_t));
    if (rows == NULL || parent == NULL || size == NULL) {
        free(rows);
        free(parent);
        free(size);
        return -2;
    }
    for (Py_ssize_t k = 0; k < 2 * (w + 2); k++)
        rows[k] = -1;
    int32_t *prev = rows + 1, *cur = rows + (w + 2) + 1; /* prev[x], cur[x] for x in -1..w */
    int32_t cur_y = -2;                                     /* the row in cur */
    Py_ssize_t prev_start = 0, cur_start = 0;              /* the rows' first points */
    for (Py_ssize_t i = 0; i < N; i++) {
        int32_t x = pix[2 * i], y = pix[2 * i + 1];
        if (y != cur_y) {
            /* clear the previous row's entries; the current row becomes the previous one if
             * it is right above, else it is cleared as well */
            for (Py_ssize_t j = prev_start; j < cur_start; j++)
                prev[pix[2 * j]] = -1;
            int32_t *t = prev;
            prev = cur;
            cur = t;
            prev_start = cur_start;
            if (cur_y != y - 1) {
                for (Py_ssize_t j = prev_start; j < i; j++)
                    prev[pix[2 * j]] = -1;
                prev_start = i;
            }
            cur_y = y;
            cur_start = i;
        }
        /* the neighbours already seen: left, above-left, above, above-right. Those that
         * touch each other are joined already: the one above touches the three others, the
         * one to the left the one above-left; so at most two joins (as in Wu, Otoo and Suzuki's
         * decision tree for raster scans) */
        int32_t up = prev[x], a = -1, b = -1;
        if (up >= 0) {
            a = up;
        } else {
            a = cur[x - 1] >= 0 ? cur[x - 1] : prev[x - 1];
            b = prev[x + 1];
            if (a < 0) {
                a = b;
                b = -1;
            }
        }
        int32_t r = a < 0 ? (int32_t)i : find_root32(parent, a); /* r < i where joined */
        parent[i] = r;
        if (b >= 0) {
            int32_t s = find_root32(parent, b);
            if (s < r) { /* the smaller root stays */
                parent[r] = s;
                parent[i] = s;
            } else if (s > r) {
                parent[s] = r;
            }
        }
        cur[x] = parent[i]; /* i's root now (a shorter way to the root for its neighbours) */
    }
    free(rows);
    /* a root is its component's lowest index: roots come before their points */
    for (Py_ssize_t i = 0; i < N; i++) {
        int32_t r = parent[i] == (int32_t)i ? (int32_t)i : parent[parent[i]];
        parent[i] = r;
        size[r]++;
    }
    Py_ssize_t n = 0;
    for (Py_ssize_t i = 0; i < N; i++) {
        uint8_t k = size[parent[i]] >= min_points;
        keep[i] = k;
        out_pix[2 * n] = pix[2 * i];
        out_pix[2 * n + 1] = pix[2 * i + 1];
        out_flat[n] = flat[i];
        n += k;
    }
    free(parent);
    free(size);
    return n;
}

static PyObject *py_long_chains(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t N, h, w, min_points;
    PyObject *o[5];
    if (!PyArg_ParseTuple(args, "nnnOOnOOO", &N, &h, &w, &o[0], &o[1], &min_points, &o[2],
                          &o[3], &o[4]))
        return NULL;
    if (!nonnegative("N", N) || !nonnegative("h", h) || !nonnegative("w", w))
        return NULL;
    if (N > INT32_MAX) {
        PyErr_Format(PyExc_ValueError, "long_chains: %zd points, at most 2^31 - 1", N);
        return NULL;
    }
    Py_buffer b[5];
    const Spec spec[5] = {
        {"pix", 4, 2 * N, 0}, {"flat", 8, N, 0}, {"keep", 1, N, 1}, {"out_pix", 4, 2 * N, 1},
        {"out_flat", 8, N, 1},
    };
    if (take_all(5, o, spec, b) < 0)
        return NULL;
    Py_ssize_t n, bad = -1;
    Py_BEGIN_ALLOW_THREADS
    n = long_chains(N, h, w, b[0].buf, b[1].buf, min_points, b[2].buf, b[3].buf, b[4].buf,
                    &bad);
    Py_END_ALLOW_THREADS
    release_all(5, b);
    if (n == -1) {
        PyErr_Format(PyExc_ValueError, "long_chains: flat index %zd is outside the %zdx%zd "
                     "image or not above the one before", bad, w, h);
        return NULL;
    }
    if (n == -2)
        return PyErr_NoMemory();
    return PyLong_FromSsize_t(n);
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

/* numpy's pairwise sum of n values at stride ``s`` (its add reduction: eight partial sums in
 * blocks of up to 128 values, halves above), in float32 (pairwise_sum) and float64
 * (pairwise_sum_d) */
#define PAIRWISE_SUM(NAME, T)                                                                \
    static T NAME(const T *a, Py_ssize_t n, Py_ssize_t s)                                   \
    {                                                                                        \
        if (n < 8) {                                                                         \
            T res = (T)-0.0;                                                                 \
            for (Py_ssize_t i = 0; i < n; i++)                                               \
                res = res + a[i * s];                                                        \
            return res;                                                                      \
        }                                                                                    \
        if (n <= 128) {                                                                      \
            T r[8];                                                                          \
            for (int j = 0; j < 8; j++)                                                      \
                r[j] = a[j * s];                                                             \
            Py_ssize_t i;                                                                    \
            for (i = 8; i < n - (n % 8); i += 8)                                             \
                for (int j = 0; j < 8; j++)                                                  \
                    r[j] = r[j] + a[(i + j) * s];                                            \
            T res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));       \
            for (; i < n; i++)                                                               \
                res = res + a[i * s];                                                        \
            return res;                                                                      \
        }                                                                                    \
        Py_ssize_t n2 = n / 2;                                                               \
        n2 -= n2 % 8;                                                                        \
        return NAME(a, n2, s) + NAME(a + n2 * s, n - n2, s);                                 \
    }
PAIRWISE_SUM(pairwise_sum, float)
PAIRWISE_SUM(pairwise_sum_d, double)

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

/* ---- great-circle fits: scatter matrices, arc parameters, orderings, cuts, final fits ------ */

/* The 3-vector dot product np.einsum("nk,nk->n", a, b) computes on this numpy (its SIMD sum of
 * products: the products in lanes, the lanes summed x + z, then y, added to the output's zero),
 * which is not the sum in order */
static double dot3(const double *a, const double *b)
{
    double p0 = a[0] * b[0], p1 = a[1] * b[1], p2 = a[2] * b[2];
    return ((p0 + p2) + p1) + 0.0;
}

/* ... and the one it computes where an operand is not contiguous (the normals of
 * smallest_eigenvector, a view of eigh's output): the products summed in order */
static double dot3_seq(const double *a, const double *b)
{
    return ((a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]) + 0.0;
}

/* geometry.completion_towards for one normal: e1 = normalize(h - (h . n) n) (the sums of np.sum
 * and np.linalg.norm over 3 values: in order), e2 = n x e1 (geometry.cross3) */
static void completion(const double *n, const double *h, double *e1, double *e2)
{
    double d = ((h[0] * n[0] + h[1] * n[1]) + h[2] * n[2]) + 0.0;
    double v[3];
    for (int k = 0; k < 3; k++)
        v[k] = h[k] - d * n[k];
    double nrm = sqrt((v[0] * v[0] + v[1] * v[1]) + v[2] * v[2]);
    for (int k = 0; k < 3; k++)
        e1[k] = nrm > 0.0 ? v[k] / nrm : NAN;
    e2[0] = n[1] * e1[2] - n[2] * e1[1];
    e2[1] = n[2] * e1[0] - n[0] * e1[2];
    e2[2] = n[0] * e1[1] - n[1] * e1[0];
}

/* np.minimum / np.maximum of float64 (NaN propagates) */
static double nan_min(double a, double b) { return a != a || b != b ? NAN : (b < a ? b : a); }
static double nan_max(double a, double b) { return a != a || b != b ? NAN : (b > a ? b : a); }

/* extract._scatter: out (S, 3, 3) = sum over the points of each segment of w r r^T, each entry
 * summed in point order from zero as np.bincount(seg, weights=(r_i w) r_j) does (w NULL: 1).
 * -1 where a segment index is out of range (*bad). */
static int scatter(Py_ssize_t N, Py_ssize_t S, const double *r, const double *w,
                   const int64_t *seg, double *out, Py_ssize_t *bad)
{
    for (Py_ssize_t i = 0; i < 9 * S; i++)
        out[i] = 0.0;
    for (Py_ssize_t i = 0; i < N; i++) {
        int64_t s = seg[i];
        if (s < 0 || s >= S) {
            *bad = i;
            return -1;
        }
        const double *q = r + 3 * i;
        double wi = w ? w[i] : 1.0;
        double x = q[0] * wi, y = q[1] * wi, z = q[2] * wi;
        double *o = out + 9 * s;
        o[0] = o[0] + x * q[0];
        o[1] = o[1] + x * q[1];
        o[2] = o[2] + x * q[2];
        o[4] = o[4] + y * q[1];
        o[5] = o[5] + y * q[2];
        o[8] = o[8] + z * q[2];
    }
    for (Py_ssize_t s = 0; s < S; s++) {
        double *o = out + 9 * s;
        o[3] = o[1];
        o[6] = o[2];
        o[7] = o[5];
    }
    return 0;
}

/* The unit eigenvector of the smallest eigenvalue of each symmetric 3x3 matrix of ``S`` (K of
 * them, row-major), by cyclic Jacobi rotations (Numerical Recipes' ``jacobi``): accurate to
 * round-off relative to each eigenvalue, so a short line's plane, whose two smallest
 * eigenvalues are close, is found as precisely as by LAPACK, at a fraction of the cost of
 * np.linalg.eigh's per-call overhead on a few dozen matrices. NaN where an entry is not finite. */
static void smallest_eigvec3(Py_ssize_t K, const double *S, double *out)
{
    static const int P[3] = {0, 0, 1}, Q[3] = {1, 2, 2};
    for (Py_ssize_t k = 0; k < K; k++) {
        const double *m = S + 9 * k;
        double a[3][3], v[3][3] = {{1, 0, 0}, {0, 1, 0}, {0, 0, 1}};
        int finite = 1;
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++) {
                a[i][j] = 0.5 * (m[3 * i + j] + m[3 * j + i]);
                finite &= isfinite(m[3 * i + j]) != 0;
            }
        double *o = out + 3 * k;
        if (!finite) {
            o[0] = o[1] = o[2] = NAN;
            continue;
        }
        for (int sweep = 0; sweep < 50; sweep++) {
            if (a[0][1] == 0.0 && a[0][2] == 0.0 && a[1][2] == 0.0)
                break;
            for (int e = 0; e < 3; e++) {
                int p = P[e], q = Q[e], r = 3 - p - q;
                double apq = a[p][q];
                if (apq == 0.0)
                    continue;
                double g = 100.0 * fabs(apq);
                if (sweep > 3 && fabs(a[p][p]) + g == fabs(a[p][p])
                    && fabs(a[q][q]) + g == fabs(a[q][q])) {
                    a[p][q] = a[q][p] = 0.0;
                    continue;
                }
                double h = a[q][q] - a[p][p], t;
                if (fabs(h) + g == fabs(h)) {
                    t = apq / h;
                } else {
                    double theta = 0.5 * h / apq;
                    t = 1.0 / (fabs(theta) + sqrt(1.0 + theta * theta));
                    if (theta < 0.0)
                        t = -t;
                }
                double c = 1.0 / sqrt(1.0 + t * t), sn = t * c, tau = sn / (1.0 + c);
                a[p][p] -= t * apq;
                a[q][q] += t * apq;
                a[p][q] = a[q][p] = 0.0;
                double arp = a[r][p], arq = a[r][q];
                a[r][p] = a[p][r] = arp - sn * (arq + arp * tau);
                a[r][q] = a[q][r] = arq + sn * (arp - arq * tau);
                for (int i = 0; i < 3; i++) {
                    double vp = v[i][p], vq = v[i][q];
                    v[i][p] = vp - sn * (vq + vp * tau);
                    v[i][q] = vq + sn * (vp - vq * tau);
                }
            }
        }
        int j = 0;
        if (a[1][1] < a[j][j])
            j = 1;
        if (a[2][2] < a[j][j])
            j = 2;
        double n = sqrt(v[0][j] * v[0][j] + v[1][j] * v[1][j] + v[2][j] * v[2][j]);
        o[0] = v[0][j] / n;
        o[1] = v[1][j] / n;
        o[2] = v[2][j] / n;
    }
}

static PyObject *py_smallest_eigvec3(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t K;
    PyObject *o[2];
    if (!PyArg_ParseTuple(args, "nOO", &K, &o[0], &o[1]))
        return NULL;
    if (!nonnegative("K", K))
        return NULL;
    Py_buffer b[2];
    const Spec spec[2] = {{"S", 8, 9 * K, 0}, {"out", 8, 3 * K, 1}};
    if (take_all(2, o, spec, b) < 0)
        return NULL;
    Py_BEGIN_ALLOW_THREADS
    smallest_eigvec3(K, b[0].buf, b[1].buf);
    Py_END_ALLOW_THREADS
    release_all(2, b);
    Py_RETURN_NONE;
}

static PyObject *py_scatter(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t N, S;
    PyObject *o[4];
    if (!PyArg_ParseTuple(args, "nnOOOO", &N, &S, &o[0], &o[1], &o[2], &o[3]))
        return NULL;
    if (!nonnegative("N", N) || !nonnegative("S", S))
        return NULL;
    int weighted = o[1] != Py_None;
    PyObject *oo[4] = {o[0], weighted ? o[1] : o[0], o[2], o[3]};
    Py_buffer b[4];
    const Spec spec[4] = {
        {"rays", 8, 3 * N, 0},
        {"weight", 8, weighted ? N : 3 * N, 0},
        {"seg", 8, N, 0},
        {"out", 8, 9 * S, 1},
    };
    if (take_all(4, oo, spec, b) < 0)
        return NULL;
    int rc;
    Py_ssize_t bad = -1;
    Py_BEGIN_ALLOW_THREADS
    rc = scatter(N, S, b[0].buf, weighted ? b[1].buf : NULL, b[2].buf, b[3].buf, &bad);
    Py_END_ALLOW_THREADS
    release_all(4, b);
    if (rc < 0) {
        PyErr_Format(PyExc_IndexError, "scatter: seg[%zd] out of range", bad);
        return NULL;
    }
    Py_RETURN_NONE;
}

/* extract._arc_parameter up to its arctan2: per group the mean of its rays (np.bincount's sums),
 * the basis (e1, e2) of completion_towards(n, mean), and per point y = r . e2, x = r . e1
 * (einsum's sums). -1 where a group index is out of range (*bad), -2 out of memory. */
static int arc_xy(Py_ssize_t N, Py_ssize_t G, const double *r, const double *n,
                  const int64_t *group, double *y, double *x, Py_ssize_t *bad)
{
    double *mean = calloc((size_t)(G > 0 ? G : 1) * 9, sizeof(double));
    if (mean == NULL)
        return -2;
    double *e1 = mean + 3 * G, *e2 = mean + 6 * G;
    for (Py_ssize_t i = 0; i < N; i++) {
        int64_t g = group[i];
        if (g < 0 || g >= G) {
            free(mean);
            *bad = i;
            return -1;
        }
        for (int k = 0; k < 3; k++)
            mean[3 * g + k] = mean[3 * g + k] + r[3 * i + k];
    }
    for (Py_ssize_t g = 0; g < G; g++)
        completion(n + 3 * g, mean + 3 * g, e1 + 3 * g, e2 + 3 * g);
    for (Py_ssize_t i = 0; i < N; i++) {
        int64_t g = group[i];
        y[i] = dot3(r + 3 * i, e2 + 3 * g);
        x[i] = dot3(r + 3 * i, e1 + 3 * g);
    }
    free(mean);
    return 0;
}

static PyObject *py_arc_xy(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t N, G;
    PyObject *o[5];
    if (!PyArg_ParseTuple(args, "nnOOOOO", &N, &G, &o[0], &o[1], &o[2], &o[3], &o[4]))
        return NULL;
    if (!nonnegative("N", N) || !nonnegative("G", G))
        return NULL;
    Py_buffer b[5];
    const Spec spec[5] = {
        {"rays", 8, 3 * N, 0}, {"normals", 8, 3 * G, 0}, {"group", 8, N, 0},
        {"y", 8, N, 1},        {"x", 8, N, 1},
    };
    if (take_all(5, o, spec, b) < 0)
        return NULL;
    int rc;
    Py_ssize_t bad = -1;
    Py_BEGIN_ALLOW_THREADS
    rc = arc_xy(N, G, b[0].buf, b[1].buf, b[2].buf, b[3].buf, b[4].buf, &bad);
    Py_END_ALLOW_THREADS
    release_all(5, b);
    if (rc == -2)
        return PyErr_NoMemory();
    if (rc < 0) {
        PyErr_Format(PyExc_IndexError, "arc_xy: group[%zd] out of range", bad);
        return NULL;
    }
    Py_RETURN_NONE;
}

/* t[a] before t[b] in numpy's sort order (NaN last) */
static int t_less(const double *t, int64_t a, int64_t b)
{
    double x = t[a], y = t[b];
    return x < y || (x == x && y != y);
}

/* stable merge sort of the indices a[0..n) by t (tmp: n items) */
static void merge_sort(int64_t *a, int64_t *tmp, Py_ssize_t n, const double *t)
{
    if (n <= 16) {
        for (Py_ssize_t i = 1; i < n; i++) {
            int64_t v = a[i];
            Py_ssize_t j = i;
            while (j > 0 && t_less(t, v, a[j - 1])) {
                a[j] = a[j - 1];
                j--;
            }
            a[j] = v;
        }
        return;
    }
    Py_ssize_t h = n / 2;
    merge_sort(a, tmp, h, t);
    merge_sort(a + h, tmp, n - h, t);
    if (!t_less(t, a[h], a[h - 1]))
        return;
    memcpy(tmp, a, (size_t)h * sizeof(int64_t));
    Py_ssize_t i = 0, j = h, k = 0;
    while (i < h && j < n)
        a[k++] = t_less(t, a[j], tmp[i]) ? a[j++] : tmp[i++];
    while (i < h)
        a[k++] = tmp[i++];
}

/* extract._order_by: the order by key (0..K-1), then by t (NaN last), then by index: a
 * counting sort by key, then a stable sort by t within each key. -1 where a key is out of
 * range (*bad), -2 out of memory. */
static int order_by(Py_ssize_t N, Py_ssize_t K, const int64_t *key, const double *t,
                    int64_t *order, Py_ssize_t *bad)
{
    int64_t *start = calloc((size_t)K + 1, sizeof(int64_t));
    int64_t *tmp = malloc((size_t)(N > 0 ? N : 1) * sizeof(int64_t));
    if (start == NULL || tmp == NULL) {
        free(start);
        free(tmp);
        return -2;
    }
    for (Py_ssize_t i = 0; i < N; i++) {
        if (key[i] < 0 || key[i] >= K) {
            free(start);
            free(tmp);
            *bad = i;
            return -1;
        }
        start[key[i] + 1]++;
    }
    for (Py_ssize_t k = 0; k < K; k++)
        start[k + 1] += start[k];
    for (Py_ssize_t i = 0; i < N; i++)
        tmp[start[key[i]]++] = i; /* start[k] becomes the end of key k */
    memcpy(order, tmp, (size_t)N * sizeof(int64_t));
    for (Py_ssize_t k = 0, a = 0; k < K; k++) {
        merge_sort(order + a, tmp, start[k] - a, t);
        a = start[k];
    }
    free(start);
    free(tmp);
    return 0;
}

static PyObject *py_order_by(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t N, K;
    PyObject *o[3];
    if (!PyArg_ParseTuple(args, "nnOOO", &N, &K, &o[0], &o[1], &o[2]))
        return NULL;
    if (!nonnegative("N", N) || !nonnegative("K", K))
        return NULL;
    Py_buffer b[3];
    const Spec spec[3] = {{"key", 8, N, 0}, {"t", 8, N, 0}, {"order", 8, N, 1}};
    if (take_all(3, o, spec, b) < 0)
        return NULL;
    int rc;
    Py_ssize_t bad = -1;
    Py_BEGIN_ALLOW_THREADS
    rc = order_by(N, K, b[0].buf, b[1].buf, b[2].buf, &bad);
    Py_END_ALLOW_THREADS
    release_all(3, b);
    if (rc == -2)
        return PyErr_NoMemory();
    if (rc < 0) {
        PyErr_Format(PyExc_IndexError, "order_by: key[%zd] out of range", bad);
        return NULL;
    }
    Py_RETURN_NONE;
}

/* LineExtractor._split_gaps after the arc parameters: the points in the order by segment, then
 * t; cut where the segment changes or t steps by more than max_gap * s (s of the later point);
 * the pieces of at least min_points points kept: their points' positions in the input (pos),
 * their piece (0..P-1, in order) and each piece's segment (piece_seg). Returns the number of
 * kept points and *npieces; -1 where a segment is out of range (*bad), -2 out of memory. */
static Py_ssize_t gap_pieces(Py_ssize_t N, Py_ssize_t K, const int64_t *seg, const double *t,
                             const double *s, double max_gap, int64_t min_points, int64_t *pos,
                             int64_t *piece, int64_t *piece_seg, Py_ssize_t *npieces,
                             Py_ssize_t *bad)
{
    int64_t *order = malloc((size_t)(N > 0 ? N : 1) * sizeof(int64_t));
    if (order == NULL)
        return -2;
    int rc = order_by(N, K, seg, t, order, bad);
    if (rc < 0) {
        free(order);
        return rc;
    }
    Py_ssize_t n = 0, np = 0;
    for (Py_ssize_t a = 0; a < N;) {
        Py_ssize_t e = a + 1;
        while (e < N && seg[order[e]] == seg[order[e - 1]] &&
               !(t[order[e]] - t[order[e - 1]] > max_gap * s[order[e]]))
            e++;
        if (e - a >= min_points) {
            for (Py_ssize_t k = a; k < e; k++) {
                pos[n] = order[k];
                piece[n++] = np;
            }
            piece_seg[np++] = seg[order[a]];
        }
        a = e;
    }
    free(order);
    *npieces = np;
    return n;
}

static PyObject *py_gap_pieces(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t N, K;
    double max_gap;
    long long min_points;
    PyObject *o[6];
    if (!PyArg_ParseTuple(args, "nnOOOdLOOO", &N, &K, &o[0], &o[1], &o[2], &max_gap,
                          &min_points, &o[3], &o[4], &o[5]))
        return NULL;
    if (!nonnegative("N", N) || !nonnegative("K", K))
        return NULL;
    Py_buffer b[6];
    const Spec spec[6] = {
        {"seg", 8, N, 0}, {"t", 8, N, 0},     {"s", 8, N, 0},
        {"pos", 8, N, 1}, {"piece", 8, N, 1}, {"piece_seg", 8, N, 1},
    };
    if (take_all(6, o, spec, b) < 0)
        return NULL;
    Py_ssize_t n, np = 0, bad = -1;
    Py_BEGIN_ALLOW_THREADS
    n = gap_pieces(N, K, b[0].buf, b[1].buf, b[2].buf, max_gap, (int64_t)min_points, b[3].buf,
                   b[4].buf, b[5].buf, &np, &bad);
    Py_END_ALLOW_THREADS
    release_all(6, b);
    if (n == -2)
        return PyErr_NoMemory();
    if (n < 0) {
        PyErr_Format(PyExc_IndexError, "gap_pieces: seg[%zd] out of range", bad);
        return NULL;
    }
    return Py_BuildValue("nn", n, np);
}

/* LineExtractor._trim_ends after the arc parameters: a point is kept where it lies more than
 * trim * s (its own s) from both ends (min and max of t over its line, lab 0..L-1) and its
 * line keeps at least min_points points. Writes the kept points' positions (in input order)
 * and their lines renumbered 0.. among the lines kept; returns how many, -1 where a label is
 * out of range (*bad), -2 out of memory. */
static Py_ssize_t trim_ends(Py_ssize_t N, Py_ssize_t L, const int64_t *lab, const double *t,
                            const double *s, double trim, int64_t min_points, int64_t *pos,
                            int64_t *new_lab, Py_ssize_t *bad)
{
    double *lo = malloc((size_t)(L > 0 ? L : 1) * 2 * sizeof(double));
    int64_t *cnt = calloc((size_t)(L > 0 ? L : 1), sizeof(int64_t));
    if (lo == NULL || cnt == NULL) {
        free(lo);
        free(cnt);
        return -2;
    }
    double *hi = lo + L;
    for (Py_ssize_t l = 0; l < L; l++) {
        lo[l] = INFINITY;
        hi[l] = -INFINITY;
    }
    for (Py_ssize_t i = 0; i < N; i++) {
        int64_t l = lab[i];
        if (l < 0 || l >= L) {
            free(lo);
            free(cnt);
            *bad = i;
            return -1;
        }
        lo[l] = nan_min(lo[l], t[i]);
        hi[l] = nan_max(hi[l], t[i]);
    }
    for (Py_ssize_t i = 0; i < N; i++) {
        double lim = trim * s[i];
        if (t[i] - lo[lab[i]] > lim && hi[lab[i]] - t[i] > lim)
            cnt[lab[i]]++;
    }
    /* cnt: the new label of a kept line, -1 for a dropped one */
    int64_t nl = 0;
    for (Py_ssize_t l = 0; l < L; l++)
        cnt[l] = cnt[l] >= min_points ? nl++ : -1;
    Py_ssize_t n = 0;
    for (Py_ssize_t i = 0; i < N; i++) {
        int64_t l = lab[i];
        double lim = trim * s[i];
        if (cnt[l] >= 0 && t[i] - lo[l] > lim && hi[l] - t[i] > lim) {
            pos[n] = i;
            new_lab[n++] = cnt[l];
        }
    }
    free(lo);
    free(cnt);
    return n;
}

static PyObject *py_trim_ends(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t N, L;
    double trim;
    long long min_points;
    PyObject *o[5];
    if (!PyArg_ParseTuple(args, "nnOOOdLOO", &N, &L, &o[0], &o[1], &o[2], &trim, &min_points,
                          &o[3], &o[4]))
        return NULL;
    if (!nonnegative("N", N) || !nonnegative("L", L))
        return NULL;
    Py_buffer b[5];
    const Spec spec[5] = {
        {"lab", 8, N, 0}, {"t", 8, N, 0}, {"s", 8, N, 0}, {"pos", 8, N, 1}, {"new_lab", 8, N, 1},
    };
    if (take_all(5, o, spec, b) < 0)
        return NULL;
    Py_ssize_t n, bad = -1;
    Py_BEGIN_ALLOW_THREADS
    n = trim_ends(N, L, b[0].buf, b[1].buf, b[2].buf, trim, (int64_t)min_points, b[3].buf,
                  b[4].buf, &bad);
    Py_END_ALLOW_THREADS
    release_all(5, b);
    if (n == -2)
        return PyErr_NoMemory();
    if (n < 0) {
        PyErr_Format(PyExc_IndexError, "trim_ends: lab[%zd] out of range", bad);
        return NULL;
    }
    return PyLong_FromSsize_t(n);
}

/* LineExtractor._package's per-line figures, for points sorted by line (lab 0..L-1, each line
 * present, t, rays r and pixel angles s in that order) and the lines' normals: point counts,
 * end rays projected onto the circle and normalised, RMS residual (px), arc (t of the last
 * point minus the first's), mean s, and the NV sigmas along the middle ray and across it
 * (edge noise ``noise`` px). Every sum in point order from zero (np.bincount), the dot
 * products einsum's. -1 where the labels are not sorted, dense and in range (*bad). */
static int package(Py_ssize_t N, Py_ssize_t L, const double *r, const double *nrm,
                   const int64_t *lab, const double *t, const double *s, double noise,
                   int64_t *sizes, double *ends, double *resid, double *arc,
                   double *mean_scale, double *sigma, Py_ssize_t *bad)
{
    Py_ssize_t a = 0;
    for (Py_ssize_t l = 0; l < L; l++) {
        if (a >= N || lab[a] != l) {
            *bad = a;
            return -1;
        }
        Py_ssize_t e = a + 1;
        while (e < N && lab[e] == l)
            e++;
        if (e < N && lab[e] != l + 1) {
            *bad = e;
            return -1;
        }
        const double *n = nrm + 3 * l;
        double *en = ends + 6 * l;
        for (int q = 0; q < 2; q++) {
            const double *p = r + 3 * (q ? e - 1 : a);
            double *v = en + 3 * q;
            double d = dot3_seq(p, n); /* (the normals were eigh's view) */
            for (int k = 0; k < 3; k++)
                v[k] = p[k] - d * n[k];
            double len = sqrt((v[0] * v[0] + v[1] * v[1]) + v[2] * v[2]);
            for (int k = 0; k < 3; k++)
                v[k] = v[k] / len;
        }
        double px2 = 0.0, ssum = 0.0;
        for (Py_ssize_t i = a; i < e; i++) {
            double px = fabs(dot3(r + 3 * i, n)) / s[i];
            px2 = px2 + px * px;
            ssum = ssum + s[i];
        }
        double size = (double)(e - a);
        sizes[l] = e - a;
        resid[l] = sqrt(px2 / size);
        arc[l] = t[e - 1] - t[a];
        mean_scale[l] = ssum / size;
        double hint[3], m[3], tdir[3];
        for (int k = 0; k < 3; k++)
            hint[k] = en[k] + en[3 + k];
        completion(n, hint, m, tdir);
        double info_m = 0.0, info_t = 0.0;
        for (Py_ssize_t i = a; i < e; i++) {
            double ns = noise * s[i];
            double w = 1.0 / (ns * ns);
            double dm = dot3(r + 3 * i, m), dt = dot3(r + 3 * i, tdir);
            info_m = info_m + w * (dm * dm);
            info_t = info_t + w * (dt * dt);
        }
        sigma[2 * l] = 1.0 / sqrt(nan_max(info_m, 1e-300));
        sigma[2 * l + 1] = 1.0 / sqrt(nan_max(info_t, 1e-300));
        a = e;
    }
    if (a != N) {
        *bad = a;
        return -1;
    }
    return 0;
}

static PyObject *py_package(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t N, L;
    double noise;
    PyObject *o[11];
    if (!PyArg_ParseTuple(args, "nnOOOOOdOOOOOO", &N, &L, &o[0], &o[1], &o[2], &o[3], &o[4],
                          &noise, &o[5], &o[6], &o[7], &o[8], &o[9], &o[10]))
        return NULL;
    if (!nonnegative("N", N) || !nonnegative("L", L))
        return NULL;
    Py_buffer b[11];
    const Spec spec[11] = {
        {"rays", 8, 3 * N, 0}, {"normals", 8, 3 * L, 0}, {"lab", 8, N, 0},
        {"t", 8, N, 0},        {"s", 8, N, 0},           {"sizes", 8, L, 1},
        {"ends", 8, 6 * L, 1}, {"resid", 8, L, 1},       {"arc", 8, L, 1},
        {"mean_scale", 8, L, 1}, {"sigma", 8, 2 * L, 1},
    };
    if (take_all(11, o, spec, b) < 0)
        return NULL;
    int rc;
    Py_ssize_t bad = -1;
    Py_BEGIN_ALLOW_THREADS
    rc = package(N, L, b[0].buf, b[1].buf, b[2].buf, b[3].buf, b[4].buf, noise, b[5].buf,
                 b[6].buf, b[7].buf, b[8].buf, b[9].buf, b[10].buf, &bad);
    Py_END_ALLOW_THREADS
    release_all(11, b);
    if (rc < 0) {
        PyErr_Format(PyExc_ValueError, "package: the labels must be sorted and take every "
                     "value 0..%zd (at point %zd)", L - 1, bad);
        return NULL;
    }
    Py_RETURN_NONE;
}

/* LineExtractor._ransac's inlier test: |r . n[seg]| < tol (einsum's dot product) per point,
 * and the inliers' count per segment (float64, as np.bincount with the mask as weights). -1
 * where a segment index is out of range (*bad). */
static int inliers(Py_ssize_t N, Py_ssize_t S, const double *r, const double *n,
                   const int64_t *seg, const double *tol, uint8_t *inl, double *count,
                   Py_ssize_t *bad)
{
    for (Py_ssize_t s = 0; s < S; s++)
        count[s] = 0.0;
    for (Py_ssize_t i = 0; i < N; i++) {
        int64_t s = seg[i];
        if (s < 0 || s >= S) {
            *bad = i;
            return -1;
        }
        int in = fabs(dot3(r + 3 * i, n + 3 * s)) < tol[i];
        inl[i] = (uint8_t)in;
        count[s] = count[s] + (double)in;
    }
    return 0;
}

static PyObject *py_inliers(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t N, S;
    PyObject *o[6];
    if (!PyArg_ParseTuple(args, "nnOOOOOO", &N, &S, &o[0], &o[1], &o[2], &o[3], &o[4], &o[5]))
        return NULL;
    if (!nonnegative("N", N) || !nonnegative("S", S))
        return NULL;
    Py_buffer b[6];
    const Spec spec[6] = {
        {"rays", 8, 3 * N, 0}, {"normals", 8, 3 * S, 0}, {"seg", 8, N, 0},
        {"tol", 8, N, 0},      {"inl", 1, N, 1},         {"count", 8, S, 1},
    };
    if (take_all(6, o, spec, b) < 0)
        return NULL;
    int rc;
    Py_ssize_t bad = -1;
    Py_BEGIN_ALLOW_THREADS
    rc = inliers(N, S, b[0].buf, b[1].buf, b[2].buf, b[3].buf, b[4].buf, b[5].buf, &bad);
    Py_END_ALLOW_THREADS
    release_all(6, b);
    if (rc < 0) {
        PyErr_Format(PyExc_IndexError, "inliers: seg[%zd] out of range", bad);
        return NULL;
    }
    Py_RETURN_NONE;
}

/* LineExtractor._merge's arc coordinates: for each candidate pair (i, j) of pieces
 * (cand (C, 2)), the rays of piece i, then (after all pairs) those of piece j, each piece's
 * points in index order (idx of the points with label lab 0..L-1), in the basis of the circle
 * of piece i (completion_towards(normal_i, mean ray of piece i: np.add.reduceat's sum, the
 * first ray plus numpy's pairwise sum of the others, over the count)): y = r . e2, x = r . e1
 * (einsum's sums), T = sum of both sides' counts. -1 where an index is out of range (*bad:
 * points, then pairs), -2 out of memory. */
static int merge_xy(Py_ssize_t R, const double *rays, Py_ssize_t M, const int64_t *idx,
                    const int64_t *lab, Py_ssize_t L, const double *normals, Py_ssize_t C,
                    const int64_t *cand, Py_ssize_t T, double *y, double *x, Py_ssize_t *bad)
{
    int64_t *first = calloc((size_t)L + 1, sizeof(int64_t));
    int64_t *pts = malloc((size_t)(M > 0 ? M : 1) * sizeof(int64_t));
    double *buf = malloc((size_t)(M > 0 ? M : 1) * 3 * sizeof(double));
    if (first == NULL || pts == NULL || buf == NULL) {
        free(first);
        free(pts);
        free(buf);
        return -2;
    }
    int rc = 0;
    for (Py_ssize_t i = 0; i < M; i++) {
        if (lab[i] < 0 || lab[i] >= L || idx[i] < 0 || idx[i] >= R) {
            *bad = i;
            rc = -1;
            goto done;
        }
        first[lab[i] + 1]++;
    }
    for (Py_ssize_t l = 0; l < L; l++)
        first[l + 1] += first[l];
    {
        /* the points by piece, each piece's in index order (a stable counting sort) */
        int64_t *fill = malloc((size_t)(L > 0 ? L : 1) * sizeof(int64_t));
        if (fill == NULL) {
            rc = -2;
            goto done;
        }
        memcpy(fill, first, (size_t)L * sizeof(int64_t));
        for (Py_ssize_t i = 0; i < M; i++)
            pts[fill[lab[i]]++] = idx[i];
        free(fill);
    }
    Py_ssize_t total = 0;
    for (Py_ssize_t c = 0; c < C; c++)
        for (int side = 0; side < 2; side++) {
            int64_t p = cand[2 * c + side];
            if (p < 0 || p >= L) {
                *bad = M + c;
                rc = -1;
                goto done;
            }
            total += first[p + 1] - first[p];
        }
    if (total != T) {
        *bad = -1;
        rc = -1;
        goto done;
    }
    Py_ssize_t o1 = 0, o2 = 0;
    for (Py_ssize_t c = 0; c < C; c++) {
        int64_t pi = cand[2 * c];
        o2 += first[pi + 1] - first[pi];
    }
    for (Py_ssize_t c = 0; c < C; c++) {
        int64_t pi = cand[2 * c], pj = cand[2 * c + 1];
        Py_ssize_t ni = first[pi + 1] - first[pi], nj = first[pj + 1] - first[pj];
        for (Py_ssize_t k = 0; k < ni; k++)
            memcpy(buf + 3 * k, rays + 3 * pts[first[pi] + k], 3 * sizeof(double));
        double mean[3], e1[3], e2[3];
        for (int k = 0; k < 3; k++)
            mean[k] = (buf[k] + pairwise_sum_d(buf + 3 + k, ni - 1, 3)) / (double)ni;
        completion(normals + 3 * pi, mean, e1, e2);
        for (Py_ssize_t k = 0; k < ni; k++, o1++) {
            y[o1] = dot3(buf + 3 * k, e2);
            x[o1] = dot3(buf + 3 * k, e1);
        }
        for (Py_ssize_t k = 0; k < nj; k++, o2++) {
            const double *r = rays + 3 * pts[first[pj] + k];
            y[o2] = dot3(r, e2);
            x[o2] = dot3(r, e1);
        }
    }
done:
    free(first);
    free(pts);
    free(buf);
    return rc;
}

static PyObject *py_merge_xy(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t R, M, L, C, T;
    PyObject *o[7];
    if (!PyArg_ParseTuple(args, "nnnnnOOOOOOO", &R, &M, &L, &C, &T, &o[0], &o[1], &o[2], &o[3],
                          &o[4], &o[5], &o[6]))
        return NULL;
    if (!nonnegative("R", R) || !nonnegative("M", M) || !nonnegative("L", L) ||
        !nonnegative("C", C) || !nonnegative("T", T))
        return NULL;
    Py_buffer b[7];
    const Spec spec[7] = {
        {"rays", 8, 3 * R, 0}, {"idx", 8, M, 0}, {"lab", 8, M, 0}, {"normals", 8, 3 * L, 0},
        {"cand", 8, 2 * C, 0}, {"y", 8, T, 1},   {"x", 8, T, 1},
    };
    if (take_all(7, o, spec, b) < 0)
        return NULL;
    int rc;
    Py_ssize_t bad = -1;
    Py_BEGIN_ALLOW_THREADS
    rc = merge_xy(R, b[0].buf, M, b[1].buf, b[2].buf, L, b[3].buf, C, b[4].buf, T, b[5].buf,
                  b[6].buf, &bad);
    Py_END_ALLOW_THREADS
    release_all(7, b);
    if (rc == -2)
        return PyErr_NoMemory();
    if (rc < 0) {
        if (bad < 0)
            PyErr_SetString(PyExc_ValueError, "merge_xy: T is not the pairs' point count");
        else if (bad < M)
            PyErr_Format(PyExc_IndexError, "merge_xy: idx or lab [%zd] out of range", bad);
        else
            PyErr_Format(PyExc_IndexError, "merge_xy: cand[%zd] out of range", bad - M);
        return NULL;
    }
    Py_RETURN_NONE;
}

static int64_t find_halving(int64_t *parent, int64_t i)
{
    while (parent[i] != i) {
        parent[i] = parent[parent[i]];
        i = parent[i];
    }
    return i;
}

/* LineExtractor._merge's joins: with t the arc parameters merge_xy's coordinates give (its
 * layout), each pair's gap max(lo_j - hi_i, lo_i - hi_j) (np.minimum/maximum: NaN
 * propagates); the pairs with 0 <= gap <= max_gap joined in order by parent[find(i)] =
 * find(j) (path halving) and each piece's new label the rank of its root among the roots
 * (np.unique's inverse). The piece sizes come from lab (M points, 0..L-1). -1 where an index
 * is out of range or T wrong (*bad), -2 out of memory. */
static int merge_join(Py_ssize_t M, const int64_t *lab, Py_ssize_t L, Py_ssize_t C,
                      const int64_t *cand, Py_ssize_t T, const double *t, double max_gap,
                      int64_t *new_lab, Py_ssize_t *bad)
{
    int64_t *size = calloc((size_t)(L > 0 ? L : 1) * 2, sizeof(int64_t));
    if (size == NULL)
        return -2;
    int64_t *parent = size + L;
    for (Py_ssize_t i = 0; i < M; i++) {
        if (lab[i] < 0 || lab[i] >= L) {
            free(size);
            *bad = i;
            return -1;
        }
        size[lab[i]]++;
    }
    Py_ssize_t total = 0;
    for (Py_ssize_t c = 0; c < 2 * C; c++) {
        if (cand[c] < 0 || cand[c] >= L) {
            free(size);
            *bad = M + c / 2;
            return -1;
        }
        total += size[cand[c]];
    }
    if (total != T) {
        free(size);
        *bad = -1;
        return -1;
    }
    for (Py_ssize_t l = 0; l < L; l++)
        parent[l] = l;
    Py_ssize_t o1 = 0, o2 = 0;
    for (Py_ssize_t c = 0; c < C; c++)
        o2 += size[cand[2 * c]];
    for (Py_ssize_t c = 0; c < C; c++) {
        int64_t pi = cand[2 * c], pj = cand[2 * c + 1];
        double lo_i = t[o1], hi_i = t[o1], lo_j = t[o2], hi_j = t[o2];
        for (int64_t k = 1; k < size[pi]; k++) {
            lo_i = nan_min(lo_i, t[o1 + k]);
            hi_i = nan_max(hi_i, t[o1 + k]);
        }
        for (int64_t k = 1; k < size[pj]; k++) {
            lo_j = nan_min(lo_j, t[o2 + k]);
            hi_j = nan_max(hi_j, t[o2 + k]);
        }
        o1 += size[pi];
        o2 += size[pj];
        double gap = nan_max(lo_j - hi_i, lo_i - hi_j);
        if (gap >= 0.0 && gap <= max_gap)
            parent[find_halving(parent, pi)] = find_halving(parent, pj);
    }
    /* rank of each root: count the roots below it */
    for (Py_ssize_t l = 0; l < L; l++)
        new_lab[l] = find_halving(parent, l);
    int64_t *rank = size; /* reused: 1 where l is a root, then the prefix counts */
    for (Py_ssize_t l = 0; l < L; l++)
        rank[l] = 0;
    for (Py_ssize_t l = 0; l < L; l++)
        rank[new_lab[l]] = 1;
    for (Py_ssize_t l = 0, k = 0; l < L; l++) {
        int64_t is_root = rank[l];
        rank[l] = k;
        k += is_root;
    }
    for (Py_ssize_t l = 0; l < L; l++)
        new_lab[l] = rank[new_lab[l]];
    free(size);
    return 0;
}

static PyObject *py_merge_join(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t M, L, C, T;
    double max_gap;
    PyObject *o[4];
    if (!PyArg_ParseTuple(args, "nnnnOOOdO", &M, &L, &C, &T, &o[0], &o[1], &o[2], &max_gap,
                          &o[3]))
        return NULL;
    if (!nonnegative("M", M) || !nonnegative("L", L) || !nonnegative("C", C) ||
        !nonnegative("T", T))
        return NULL;
    Py_buffer b[4];
    const Spec spec[4] = {
        {"lab", 8, M, 0}, {"cand", 8, 2 * C, 0}, {"t", 8, T, 0}, {"new_lab", 8, L, 1},
    };
    if (take_all(4, o, spec, b) < 0)
        return NULL;
    int rc;
    Py_ssize_t bad = -1;
    Py_BEGIN_ALLOW_THREADS
    rc = merge_join(M, b[0].buf, L, C, b[1].buf, T, b[2].buf, max_gap, b[3].buf, &bad);
    Py_END_ALLOW_THREADS
    release_all(4, b);
    if (rc == -2)
        return PyErr_NoMemory();
    if (rc < 0) {
        if (bad < 0)
            PyErr_SetString(PyExc_ValueError, "merge_join: T is not the pairs' point count");
        else if (bad < M)
            PyErr_Format(PyExc_IndexError, "merge_join: lab[%zd] out of range", bad);
        else
            PyErr_Format(PyExc_IndexError, "merge_join: cand[%zd] out of range", bad - M);
        return NULL;
    }
    Py_RETURN_NONE;
}

/* LineExtractor._ransac's hypotheses: for the pairs of points (ia, ib) (S, H) the normal
 * r_a x r_b (np.cross) over its norm (np.linalg.norm; a zero norm divides by 1) rounded to
 * float32, written as (3, S, H) (x, y, z planes), and whether the norm is under 1e-9. -1 where
 * an index is out of range (*bad). */
static int hypotheses(Py_ssize_t N, Py_ssize_t S, Py_ssize_t H, const double *r,
                      const int64_t *ia, const int64_t *ib, float *hyp, uint8_t *degenerate,
                      Py_ssize_t *bad)
{
    Py_ssize_t SH = S * H;
    for (Py_ssize_t k = 0; k < SH; k++) {
        int64_t i = ia[k], j = ib[k];
        if (i < 0 || i >= N || j < 0 || j >= N) {
            *bad = k;
            return -1;
        }
        const double *a = r + 3 * i, *b = r + 3 * j;
        double c0 = a[1] * b[2] - a[2] * b[1];
        double c1 = a[2] * b[0] - a[0] * b[2];
        double c2 = a[0] * b[1] - a[1] * b[0];
        double hn = sqrt((c0 * c0 + c1 * c1) + c2 * c2);
        degenerate[k] = hn < 1e-9;
        double d = hn > 0.0 ? hn : 1.0;
        hyp[k] = (float)(c0 / d);
        hyp[SH + k] = (float)(c1 / d);
        hyp[2 * SH + k] = (float)(c2 / d);
    }
    return 0;
}

static PyObject *py_hypotheses(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t N, S, H;
    PyObject *o[5];
    if (!PyArg_ParseTuple(args, "nnnOOOOO", &N, &S, &H, &o[0], &o[1], &o[2], &o[3], &o[4]))
        return NULL;
    if (!nonnegative("N", N) || !nonnegative("S", S) || !nonnegative("H", H))
        return NULL;
    Py_buffer b[5];
    const Spec spec[5] = {
        {"rays", 8, 3 * N, 0}, {"ia", 8, S * H, 0}, {"ib", 8, S * H, 0},
        {"hyp", 4, 3 * S * H, 1}, {"degenerate", 1, S * H, 1},
    };
    if (take_all(5, o, spec, b) < 0)
        return NULL;
    int rc;
    Py_ssize_t bad = -1;
    Py_BEGIN_ALLOW_THREADS
    rc = hypotheses(N, S, H, b[0].buf, b[1].buf, b[2].buf, b[3].buf, b[4].buf, &bad);
    Py_END_ALLOW_THREADS
    release_all(5, b);
    if (rc < 0) {
        PyErr_Format(PyExc_IndexError, "hypotheses: pair %zd out of range", bad);
        return NULL;
    }
    Py_RETURN_NONE;
}

/* ---- tracking: the nearest edge point -------------------------------------------------------- */

/* For each query (x, y) the nearest of the points P (M, 2) within ``radius`` (squared distance
 * dx^2 + dy^2 < radius^2; of equal distances the lowest index), -1 where none is: what
 * LineTracker's KD-tree query gave, from a grid of cells ``radius`` wide (the 3x3 cells around
 * the query's hold every point within the radius). -2 out of memory. */
static int snap(Py_ssize_t M, const double *P, Py_ssize_t K, const double *Q, double radius,
                int64_t *nearest)
{
    if (M == 0 || !(radius > 0.0)) {
        for (Py_ssize_t k = 0; k < K; k++)
            nearest[k] = -1;
        return 0;
    }
    double x0 = P[0], y0 = P[1], x1 = P[0], y1 = P[1];
    for (Py_ssize_t i = 1; i < M; i++) {
        double x = P[2 * i], y = P[2 * i + 1];
        x0 = x < x0 ? x : x0;
        x1 = x > x1 ? x : x1;
        y0 = y < y0 ? y : y0;
        y1 = y > y1 ? y : y1;
    }
    if (!(x1 - x0 < 1e6 * radius && y1 - y0 < 1e6 * radius) || !(x0 == x0 && y0 == y0))
        return -3; /* not finite, or a grid far too large */
    int64_t nx = (int64_t)((x1 - x0) / radius) + 1, ny = (int64_t)((y1 - y0) / radius) + 1;
    if (nx * ny > 16 * (int64_t)M + 65536)
        return -3; /* sparse points: the caller falls back to its tree */
    int64_t *start = calloc((size_t)(nx * ny + 1), sizeof(int64_t));
    int64_t *cell = malloc((size_t)M * sizeof(int64_t));
    int64_t *pts = malloc((size_t)M * sizeof(int64_t));
    if (start == NULL || cell == NULL || pts == NULL) {
        free(start);
        free(cell);
        free(pts);
        return -2;
    }
    for (Py_ssize_t i = 0; i < M; i++) {
        int64_t cx = (int64_t)((P[2 * i] - x0) / radius), cy = (int64_t)((P[2 * i + 1] - y0) / radius);
        cx = cx < nx ? cx : nx - 1;
        cy = cy < ny ? cy : ny - 1;
        cell[i] = cy * nx + cx;
        start[cell[i] + 1]++;
    }
    for (int64_t c = 0; c < nx * ny; c++)
        start[c + 1] += start[c];
    for (Py_ssize_t i = 0; i < M; i++)
        pts[start[cell[i]]++] = i; /* start[c] becomes the end of cell c */
    for (int64_t c = nx * ny; c > 0; c--)
        start[c] = start[c - 1];
    start[0] = 0;
    double r2 = radius * radius;
    for (Py_ssize_t k = 0; k < K; k++) {
        double qx = Q[2 * k], qy = Q[2 * k + 1];
        nearest[k] = -1;
        double fx = (qx - x0) / radius, fy = (qy - y0) / radius;
        if (!(fx > -2.0 && fx < (double)nx + 1.0 && fy > -2.0 && fy < (double)ny + 1.0))
            continue; /* (NaN too) no cell within reach */
        int64_t cx = (int64_t)floor(fx), cy = (int64_t)floor(fy);
        double best = r2;
        int64_t bj = -1;
        for (int64_t gy = cy - 1; gy <= cy + 1; gy++) {
            if (gy < 0 || gy >= ny)
                continue;
            for (int64_t gx = cx - 1; gx <= cx + 1; gx++) {
                if (gx < 0 || gx >= nx)
                    continue;
                int64_t c = gy * nx + gx;
                for (int64_t q = start[c]; q < start[c + 1]; q++) {
                    int64_t j = pts[q];
                    double dx = P[2 * j] - qx, dy = P[2 * j + 1] - qy;
                    double d2 = dx * dx + dy * dy;
                    if (d2 < best || (d2 == best && bj >= 0 && j < bj)) {
                        best = d2;
                        bj = j;
                    }
                }
            }
        }
        nearest[k] = bj;
    }
    free(start);
    free(cell);
    free(pts);
    return 0;
}

/* The tracker's samples (LineTracker._samples): on each of the L lines (points
 * offsets[l]..offsets[l+1] of ``uv``, (P, 2)), k = max(1, floor(n / step)) points at
 * step = max(spacing, n / max_samples), the j-th at offsets[l] + (int64)((j + 0.5) n / k), and
 * the unit tangent there from the points 2 before and 2 after (clipped to the line; 0 where
 * they coincide), in numpy's float64 arithmetic. Pass 1 (``pos`` NULL) counts into ``k``;
 * pass 2 writes. Returns the number of samples, -1 where a line is empty (*bad: which). */
static Py_ssize_t line_samples(Py_ssize_t L, const int64_t *off, const double *uv,
                               double spacing, double max_samples, int64_t *k, int64_t *pos,
                               double *at, double *tan, int64_t *line, Py_ssize_t *bad)
{
    Py_ssize_t S = 0;
    for (Py_ssize_t l = 0; l < L; l++) {
        int64_t n = off[l + 1] - off[l];
        if (n <= 0) {
            *bad = l;
            return -1;
        }
        if (pos == NULL) {
            double step = (double)n / max_samples;
            if (!(step >= spacing)) /* np.maximum: spacing unless the quotient is larger */
                step = spacing;
            double q = floor((double)n / step);
            k[l] = q < 1.0 ? 1 : (int64_t)q;
        }
        for (int64_t j = 0; j < k[l]; j++, S++) {
            if (pos == NULL)
                continue;
            int64_t p = off[l] + (int64_t)(((double)j + 0.5) * (double)n / (double)k[l]);
            int64_t lo = p - 2 > off[l] ? p - 2 : off[l];
            int64_t hi = p + 2 < off[l + 1] - 1 ? p + 2 : off[l + 1] - 1;
            double tx = uv[2 * hi] - uv[2 * lo], ty = uv[2 * hi + 1] - uv[2 * lo + 1];
            double tn = sqrt(tx * tx + ty * ty);
            pos[S] = p;
            line[S] = l;
            at[2 * S] = uv[2 * p];
            at[2 * S + 1] = uv[2 * p + 1];
            tan[2 * S] = tn > 0.0 ? tx / tn : 0.0;
            tan[2 * S + 1] = tn > 0.0 ? ty / tn : 0.0;
        }
    }
    return S;
}

static PyObject *py_line_samples(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t L, P, S;
    double spacing, max_samples;
    PyObject *o[7];
    if (!PyArg_ParseTuple(args, "nnnOOddOOOOO", &L, &P, &S, &o[0], &o[1], &spacing, &max_samples,
                          &o[2], &o[3], &o[4], &o[5], &o[6]))
        return NULL;
    if (!nonnegative("L", L) || !nonnegative("P", P) || !nonnegative("S", S))
        return NULL;
    int count = o[3] == Py_None;
    Py_buffer b[7];
    const Spec spec[7] = {
        {"offsets", 8, L + 1, 0}, {"uv", 8, 2 * P, 0}, {"k", 8, L, 1}, {"pos", 8, S, 1},
        {"at", 8, 2 * S, 1},      {"tangent", 8, 2 * S, 1}, {"line", 8, S, 1},
    };
    if (take_all(count ? 3 : 7, o, spec, b) < 0)
        return NULL;
    const int64_t *off = b[0].buf;
    Py_ssize_t bad = -1, n = -2;
    if (L > 0 && (off[0] < 0 || off[L] > P)) {
        release_all(count ? 3 : 7, b);
        PyErr_Format(PyExc_ValueError, "line_samples: offsets outside the %zd points", P);
        return NULL;
    }
    for (Py_ssize_t l = 0; l < L && bad < 0; l++)
        if (off[l + 1] < off[l])
            bad = l;
    if (bad < 0) {
        Py_BEGIN_ALLOW_THREADS
        n = line_samples(L, off, b[1].buf, spacing, max_samples, b[2].buf,
                         count ? NULL : b[3].buf, count ? NULL : b[4].buf,
                         count ? NULL : b[5].buf, count ? NULL : b[6].buf, &bad);
        Py_END_ALLOW_THREADS
    }
    release_all(count ? 3 : 7, b);
    if (n < 0 || (!count && n != S)) {
        PyErr_Format(PyExc_ValueError, "line_samples: line %zd is empty or the offsets "
                     "decrease", bad);
        return NULL;
    }
    return PyLong_FromSsize_t(n);
}

static PyObject *py_snap(PyObject *Py_UNUSED(self), PyObject *args)
{
    Py_ssize_t M, K;
    double radius;
    PyObject *o[3];
    if (!PyArg_ParseTuple(args, "nnOOdO", &M, &K, &o[0], &o[1], &radius, &o[2]))
        return NULL;
    if (!nonnegative("M", M) || !nonnegative("K", K))
        return NULL;
    Py_buffer b[3];
    const Spec spec[3] = {{"points", 8, 2 * M, 0}, {"queries", 8, 2 * K, 0},
                          {"nearest", 8, K, 1}};
    if (take_all(3, o, spec, b) < 0)
        return NULL;
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = snap(M, b[0].buf, K, b[1].buf, radius, b[2].buf);
    Py_END_ALLOW_THREADS
    release_all(3, b);
    if (rc == -2)
        return PyErr_NoMemory();
    return PyBool_FromLong(rc == 0);
}

static PyMethodDef methods[] = {
    {"canny", py_canny, METH_VARARGS,
     "canny(h, w, dx16, dy16, low, high, edges): cv2.Canny on the gradients (L2), the edge map "
     "written"},
    {"line_samples", py_line_samples, METH_VARARGS,
     "line_samples(L, P, S, offsets, uv, spacing, max_samples, k, pos, at, tangent, line): the "
     "tracker's samples per line counted into k (pos None) or written; returns how many"},
    {"smallest_eigvec3", py_smallest_eigvec3, METH_VARARGS,
     "smallest_eigvec3(K, S, out): each symmetric 3x3 matrix's unit eigenvector of its smallest "
     "eigenvalue written (Jacobi rotations)"},
    {"sobel_gradients", py_sobel_gradients, METH_VARARGS,
     "sobel_gradients(h, w, img, dx16, dy16, dxy): gradients() of the image's Sobel derivatives "
     "written"},
    {"histogram", py_histogram, METH_VARARGS,
     "histogram(h, w, gh, gw, gray, mh, mw, mask, x0, y0, out): the float32 256-bin histogram "
     "of the region's pixels where the mask is not 0 written"},
    {"gradients", py_gradients, METH_VARARGS,
     "gradients(n, dx, dy, dx16, dy16, dxy): Canny's int16 gradients (int16)(8 d) and the "
     "interleaved (dx, dy) image written"},
    {"edge_points", py_edge_points, METH_VARARGS,
     "edge_points(h, w, edges, mh, mw, mask, mx, my, cap, pix, flat): the pixels where edges & "
     "mask (the mask from (mx, my) on) is not 0, row by row, written; returns how many"},
    {"long_chains", py_long_chains, METH_VARARGS,
     "long_chains(N, h, w, pix, flat, min_points, keep, out_pix, out_flat): the points of "
     "8-connected chains of at least min_points points marked and copied; returns how many"},
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
    {"scatter", py_scatter, METH_VARARGS,
     "scatter(N, S, rays, weight_or_None, seg, out): per-segment sums of w r r^T written"},
    {"arc_xy", py_arc_xy, METH_VARARGS,
     "arc_xy(N, G, rays, normals, group, y, x): each ray's coordinates in its group's circle "
     "basis written"},
    {"order_by", py_order_by, METH_VARARGS,
     "order_by(N, K, key, t, order): the order by key, then t, then index written"},
    {"gap_pieces", py_gap_pieces, METH_VARARGS,
     "gap_pieces(N, K, seg, t, s, max_gap, min_points, pos, piece, piece_seg): the points cut "
     "into pieces at gaps; returns (points kept, pieces)"},
    {"trim_ends", py_trim_ends, METH_VARARGS,
     "trim_ends(N, L, lab, t, s, trim, min_points, pos, new_lab): the points away from the "
     "lines' ends; returns how many"},
    {"package", py_package, METH_VARARGS,
     "package(N, L, rays, normals, lab, t, s, noise, sizes, ends, resid, arc, mean_scale, "
     "sigma): the lines' final figures written"},
    {"inliers", py_inliers, METH_VARARGS,
     "inliers(N, S, rays, normals, seg, tol, inl, count): inlier mask and counts written"},
    {"merge_xy", py_merge_xy, METH_VARARGS,
     "merge_xy(R, M, L, C, T, rays, idx, lab, normals, cand, y, x): the candidate pairs' arc "
     "coordinates written"},
    {"merge_join", py_merge_join, METH_VARARGS,
     "merge_join(M, L, C, T, lab, cand, t, max_gap, new_lab): the pieces' labels after the "
     "joins written"},
    {"hypotheses", py_hypotheses, METH_VARARGS,
     "hypotheses(N, S, H, rays, ia, ib, hyp, degenerate): the pairs' unit normals (float32, "
     "(3, S, H)) and degeneracy written"},
    {"snap", py_snap, METH_VARARGS,
     "snap(M, K, points, queries, radius, nearest): each query's nearest point within the "
     "radius (-1: none) written; False where the points suit no grid (nothing written)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_edges",
    "The line extractor's per-edge-point loops in C (omni_sfm.lines.edge_kernels).", -1,
    methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__edges(void) { return PyModule_Create(&module); }
