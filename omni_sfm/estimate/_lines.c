/* The line bundle adjustment's per-observation loops over lines (omni_sfm.estimate.bundle):
 * the residuals of line observations and the lines' own Gauss-Newton iterations
 * (LineProblem._refit_lines), in C.
 *
 * Why C: these loops run after every step of every adjustment; in numpy each is some sixty
 * calls on arrays of a few thousand rows, and numpy's per-call overhead, not the arithmetic,
 * was most of the estimator's time (docs/estimator.md, "Speed"). Every formula is the one of
 * bundle.py, written out per observation in the same order of operations where numpy's is
 * known (element-wise products, sums in observation order); matrix products and the 4x4
 * solves round differently from numpy's BLAS and LAPACK, by about 1e-16 relative.
 *
 * Arrays come in through the buffer protocol, C-contiguous, float64 / int64 / uint8 as the
 * Python wrapper (omni_sfm.estimate.kernels) makes them; outputs are written into arrays it
 * allocates. Compiled with -ffp-contract=off so that no fused multiply-add changes the
 * rounding from one processor to another.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

enum { LOSS_LINEAR = 0, LOSS_HUBER = 1, LOSS_CAUCHY = 2 };

/* ---- buffers ---------------------------------------------------------------------------- */

/* take, release_all, Spec, take_all */
#include "../_buffers.h"

/* every observation's frame in 0..F-1 and line in 0..M-1 (else IndexError set, 0) */
static int in_range(Py_ssize_t K, const int64_t *f, Py_ssize_t F, const int64_t *t,
                    Py_ssize_t M)
{
    for (Py_ssize_t k = 0; k < K; k++)
        if (f[k] < 0 || f[k] >= F || t[k] < 0 || t[k] >= M) {
            PyErr_Format(PyExc_IndexError,
                         "observation %zd: frame %lld of %zd or line %lld of %zd out of range",
                         k, (long long)f[k], F, (long long)t[k], M);
            return 0;
        }
    return 1;
}

/* ---- geometry, per observation ---------------------------------------------------------- */

/* u = R^T ((p - c) x d), R row-major world_from_cam (bundle.predicted_normals) */
static void predict(const double *R, const double *c, const double *d, const double *p,
                    double u[3])
{
    double q0 = p[0] - c[0], q1 = p[1] - c[1], q2 = p[2] - c[2];
    double w0 = q1 * d[2] - q2 * d[1];
    double w1 = q2 * d[0] - q0 * d[2];
    double w2 = q0 * d[1] - q1 * d[0];
    for (int i = 0; i < 3; i++)
        u[i] = R[i] * w0 + R[3 + i] * w1 + R[6 + i] * w2;
}

/* e = B normalise(u); returns |u| */
static double residual(const double *B, const double u[3], double n[3], double e[2])
{
    double nu = sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
    n[0] = u[0] / nu;
    n[1] = u[1] / nu;
    n[2] = u[2] / nu;
    e[0] = B[0] * n[0] + B[1] * n[1] + B[2] * n[2];
    e[1] = B[3] * n[0] + B[4] * n[1] + B[5] * n[2];
    return nu;
}

/* robust cost rho(s) and IRLS weight of a squared norm s (omni_sfm.solver.loss_weights) */
static void loss(double s, int kind, double scale, double *rho, double *w)
{
    double f2 = scale * scale;
    if (kind == LOSS_LINEAR) {
        *rho = s;
        *w = 1.0;
    } else if (kind == LOSS_HUBER) {
        if (s <= f2) {
            *rho = s;
            *w = 1.0;
        } else {
            double r = sqrt(s);
            *rho = 2.0 * scale * r - f2;
            *w = scale / (r > 1e-300 ? r : 1e-300);
        }
    } else {
        *rho = f2 * log1p(s / f2);
        *w = 1.0 / (1.0 + s / f2);
    }
}

static void cross(const double a[3], const double b[3], double out[3])
{
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

/* e1 = normalise(d x h), e2 = d x e1, h = x where |d_x| < 0.6 else y
 * (bundle._tangent_basis: geometry.orthonormal_completion(switch=0.6)) */
static void tangent_basis(const double d[3], double e1[3], double e2[3])
{
    double h[3] = {0.0, 0.0, 0.0};
    if (fabs(d[0]) < 0.6)
        h[0] = 1.0;
    else
        h[1] = 1.0;
    double a[3];
    cross(d, h, a);
    double na = sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]);
    for (int i = 0; i < 3; i++)
        e1[i] = na > 0 ? a[i] / na : NAN;
    cross(d, e1, e2);
}


/* A = d e / d u = (B - (B n) n^T) / |u| (bundle._normal_derivative) */
static void normal_derivative(const double *B, const double u[3], double A[2][3])
{
    double n[3];
    double nu = sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
    n[0] = u[0] / nu;
    n[1] = u[1] / nu;
    n[2] = u[2] / nu;
    for (int r = 0; r < 2; r++) {
        double bn = B[3 * r] * n[0] + B[3 * r + 1] * n[1] + B[3 * r + 2] * n[2];
        for (int i = 0; i < 3; i++)
            A[r][i] = (B[3 * r + i] - bn * n[i]) / nu;
    }
}

/* d e / d line (2, 4) of one observation (LineProblem._line_jacobian): the line moved by
 * (a, b, s, t) has direction d + a e1 + b e2 and point p + s e1 + t e2; held columns zero */
static void line_row(const double *R, const double *c, const double *d, const double *p,
                     const double *e1, const double *e2, double A[2][3], const uint8_t *fr,
                     double J[2][4])
{
    double pc[3] = {p[0] - c[0], p[1] - c[1], p[2] - c[2]};
    double V[4][3];
    cross(pc, e1, V[0]);
    cross(pc, e2, V[1]);
    cross(e1, d, V[2]);
    cross(e2, d, V[3]);
    for (int a = 0; a < 4; a++) {
        double W[3];
        for (int i = 0; i < 3; i++)
            W[i] = R[i] * V[a][0] + R[3 + i] * V[a][1] + R[6 + i] * V[a][2];
        for (int r = 0; r < 2; r++)
            J[r][a] = fr[a] ? A[r][0] * W[0] + A[r][1] * W[1] + A[r][2] * W[2] : 0.0;
    }
}

/* ---- residuals ---------------------------------------------------------------------------- */

WIDE_LOOPS static void all_residuals(Py_ssize_t K, const double *R, const double *c, const double *d,
                          const double *p, const int64_t *f, const int64_t *t, const double *B,
                          double *e, double *u)
{
    double n[3];
    for (Py_ssize_t k = 0; k < K; k++) {
        predict(R + 9 * f[k], c + 3 * f[k], d + 3 * t[k], p + 3 * t[k], u + 3 * k);
        residual(B + 6 * k, u + 3 * k, n, e + 2 * k);
    }
}

static PyObject *py_residuals(PyObject *Py_UNUSED(self), PyObject *args)
{
    PyObject *oR, *oc, *od, *op, *of, *ot, *oB, *oe, *ou;
    Py_ssize_t F, M, K;
    if (!PyArg_ParseTuple(args, "nnnOOOOOOOOO", &F, &M, &K, &oR, &oc, &od, &op, &of, &ot, &oB,
                          &oe, &ou))
        return NULL;
    Py_buffer b[9];
    PyObject *in[9] = {oR, oc, od, op, of, ot, oB, oe, ou};
    const Spec spec[9] = {
        {"R", 8, 9 * F, 0},
        {"c", 8, 3 * F, 0},
        {"d", 8, 3 * M, 0},
        {"p", 8, 3 * M, 0},
        {"f", 8, K, 0},
        {"t", 8, K, 0},
        {"B", 8, 6 * K, 0},
        {"e", 8, 2 * K, 1},
        {"u", 8, 3 * K, 1},
    };
    if (take_all(9, in, spec, b) < 0)
        return NULL;
    if (!in_range(K, b[4].buf, F, b[5].buf, M))
        goto fail;
    all_residuals(K, b[0].buf, b[1].buf, b[2].buf, b[3].buf, b[4].buf, b[5].buf, b[6].buf,
                  b[7].buf, b[8].buf);
    release_all(9, b);
    Py_RETURN_NONE;
fail:
    release_all(9, b);
    return NULL;
}

/* ---- the lines' own iterations ------------------------------------------------------------ */

/* The diagonal of a line's 4x4 block ``Hm`` with the direction's two entries and the point's
   two each their mean over the free ones (``fr``; 0 where neither is): the damping of
   omni_sfm.solver.isotropic_diagonal, which does not depend on the line's tangent basis. */
static void pair_means(const double *Hm, const uint8_t *fr, double iso[4])
{
    for (int h = 0; h < 4; h += 2) {
        int nf = (fr[h] ? 1 : 0) + (fr[h + 1] ? 1 : 0);
        double sum = (fr[h] ? Hm[5 * h] : 0.0) + (fr[h + 1] ? Hm[5 * (h + 1)] : 0.0);
        iso[h] = iso[h + 1] = nf ? sum / nf : 0.0;
    }
}

/* Solve the n x n system A x = b (A row-major; a line's 4x4, a pose's 6x6) by Gaussian
 * elimination with partial pivoting (A, b overwritten); 0 where a pivot is exactly zero
 * (numpy.linalg.solve raises there). */
static int solve_small(int n, double *A, double *b, double *x)
{
    for (int col = 0; col < n; col++) {
        int piv = col;
        double best = fabs(A[n * col + col]);
        for (int r = col + 1; r < n; r++)
            if (fabs(A[n * r + col]) > best) {
                best = fabs(A[n * r + col]);
                piv = r;
            }
        if (A[n * piv + col] == 0.0)
            return 0;
        if (piv != col) {
            for (int j = 0; j < n; j++) {
                double tmp = A[n * col + j];
                A[n * col + j] = A[n * piv + j];
                A[n * piv + j] = tmp;
            }
            double tmp = b[col];
            b[col] = b[piv];
            b[piv] = tmp;
        }
        for (int r = col + 1; r < n; r++) {
            double m = A[n * r + col] / A[n * col + col];
            for (int j = col; j < n; j++)
                A[n * r + j] -= m * A[n * col + j];
            b[r] -= m * b[col];
        }
    }
    for (int r = n - 1; r >= 0; r--) {
        double s = b[r];
        for (int j = r + 1; j < n; j++)
            s -= A[n * r + j] * x[j];
        x[r] = s / A[n * r + r];
    }
    return 1;
}

typedef struct {
    Py_ssize_t F, M, K;
    const double *R, *c, *B;
    const int64_t *f, *t;
    const uint8_t *free; /* (M, 4) */
    int loss;
    double scale;
    int iterations;
    double *d, *p, *e, *u; /* in/out: lines; out: residuals and predicted normals */
} Refit;

/* LineProblem._refit_lines: ``iterations`` Gauss-Newton iterations of each line alone at the
 * poses; an iteration that does not lower a line's cost is undone and that line damped
 * tenfold more for the next. Returns 0 on success, -1 where memory ran out. */
WIDE_LOOPS static int refit(const Refit *q)
{
    Py_ssize_t M = q->M, K = q->K;
    double *work = malloc(sizeof(double) * (size_t)(M * (16 + 4 + 3 + 3 + 3 + 3 + 1 + 1 + 1 + 1)
                                                    + K * (2 + 3 + 1 + 1 + 1)));
    if (work == NULL)
        return -1;
    double *H = work, *g = H + 16 * M, *b1 = g + 4 * M, *b2 = b1 + 3 * M, *d3 = b2 + 3 * M,
           *p3 = d3 + 3 * M, *cost = p3 + 3 * M, *cost3 = cost + M, *mu = cost3 + M,
           *okl = mu + M, *e3 = okl + M, *u3 = e3 + 2 * K, *w = u3 + 3 * K, *w3 = w + K,
           *rho = w3 + K;
    const int64_t *f = q->f, *t = q->t;
    double *d = q->d, *p = q->p, *e = q->e, *u = q->u;
    double n[3];

    all_residuals(K, q->R, q->c, d, p, f, t, q->B, e, u);
    memset(cost, 0, sizeof(double) * (size_t)M);
    for (Py_ssize_t k = 0; k < K; k++) {
        loss(e[2 * k] * e[2 * k] + e[2 * k + 1] * e[2 * k + 1], q->loss, q->scale, &rho[k],
             &w[k]);
        cost[t[k]] += rho[k];
    }
    for (Py_ssize_t m = 0; m < M; m++)
        mu[m] = 1e-6;
    for (int it = 0; it < q->iterations; it++) {
        memset(H, 0, sizeof(double) * (size_t)(16 * M));
        memset(g, 0, sizeof(double) * (size_t)(4 * M));
        for (Py_ssize_t m = 0; m < M; m++)
            tangent_basis(d + 3 * m, b1 + 3 * m, b2 + 3 * m);
        for (Py_ssize_t k = 0; k < K; k++) {
            Py_ssize_t m = t[k];
            const double *R = q->R + 9 * f[k], *c = q->c + 3 * f[k], *Bk = q->B + 6 * k;
            const double *dm = d + 3 * m, *pm = p + 3 * m, *e1 = b1 + 3 * m, *e2 = b2 + 3 * m;
            const uint8_t *fr = q->free + 4 * m;
            double A[2][3], J[2][4];
            normal_derivative(Bk, u + 3 * k, A);
            line_row(R, c, dm, pm, e1, e2, A, fr, J);
            double wk = w[k], *Hm = H + 16 * m, *gm = g + 4 * m;
            const double *ek = e + 2 * k;
            for (int a = 0; a < 4; a++) {
                double wa0 = wk * J[0][a], wa1 = wk * J[1][a];
                for (int bb = 0; bb < 4; bb++)
                    Hm[4 * a + bb] += wa0 * J[0][bb] + wa1 * J[1][bb];
                gm[a] += wa0 * ek[0] + wa1 * ek[1];
            }
        }
        /* damped: H + mu diag(H), the diagonal of the direction's two parameters and of the
           point's two each their mean over the free ones (the damping then does not depend on
           the line's tangent basis), tiny diagonals floored at 1e-12 of the largest */
        double top = 0.0;
        for (Py_ssize_t m = 0; m < M; m++) {
            double iso[4];
            pair_means(H + 16 * m, q->free + 4 * m, iso);
            for (int a = 0; a < 4; a++)
                if (iso[a] > top)
                    top = iso[a];
        }
        double floor_ = 1e-12 * (top > 1e-30 ? top : 1e-30);
        int singular = 0;
        for (Py_ssize_t m = 0; m < M && !singular; m++) {
            const uint8_t *fr = q->free + 4 * m;
            double Am[16], bm[4], x[4];
            double iso[4];
            pair_means(H + 16 * m, fr, iso);
            for (int a = 0; a < 4; a++) {
                for (int bb = 0; bb < 4; bb++)
                    Am[4 * a + bb] = fr[a] && fr[bb] ? H[16 * m + 4 * a + bb] : 0.0;
                double dg = iso[a];
                Am[5 * a] = fr[a] ? Am[5 * a] + mu[m] * (dg > floor_ ? dg : floor_) : 1.0;
                bm[a] = g[4 * m + a];
            }
            if (!solve_small(4, Am, bm, x)) {
                singular = 1;
                break;
            }
            double s[4];
            for (int a = 0; a < 4; a++)
                s[a] = fr[a] ? -x[a] : 0.0;
            double *dm = d + 3 * m, *pm = p + 3 * m, *e1 = b1 + 3 * m, *e2 = b2 + 3 * m;
            double *dn = d3 + 3 * m, *pn = p3 + 3 * m;
            if (fr[0] || fr[1] || fr[2] || fr[3]) {
                double v[3], qq[3];
                for (int i = 0; i < 3; i++)
                    v[i] = dm[i] + s[0] * e1[i] + s[1] * e2[i];
                double nv = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
                for (int i = 0; i < 3; i++)
                    dn[i] = nv > 0 ? v[i] / nv : NAN;
                for (int i = 0; i < 3; i++)
                    qq[i] = pm[i] + s[2] * e1[i] + s[3] * e2[i];
                double qd = qq[0] * dn[0] + qq[1] * dn[1] + qq[2] * dn[2];
                for (int i = 0; i < 3; i++)
                    pn[i] = qq[i] - qd * dn[i];
            } else {
                memcpy(dn, dm, 3 * sizeof(double));
                memcpy(pn, pm, 3 * sizeof(double));
            }
        }
        if (singular)
            break;
        /* the moved lines' residuals and costs; each line keeps its move where its cost fell */
        memset(cost3, 0, sizeof(double) * (size_t)M);
        for (Py_ssize_t k = 0; k < K; k++) {
            Py_ssize_t m = t[k];
            predict(q->R + 9 * f[k], q->c + 3 * f[k], d3 + 3 * m, p3 + 3 * m, u3 + 3 * k);
            residual(q->B + 6 * k, u3 + 3 * k, n, e3 + 2 * k);
            double r3;
            loss(e3[2 * k] * e3[2 * k] + e3[2 * k + 1] * e3[2 * k + 1], q->loss, q->scale, &r3,
                 &w3[k]);
            cost3[m] += r3;
        }
        for (Py_ssize_t m = 0; m < M; m++) {
            int ok = isfinite(cost3[m]) && cost3[m] < cost[m];
            okl[m] = ok;
            if (ok) {
                memcpy(d + 3 * m, d3 + 3 * m, 3 * sizeof(double));
                memcpy(p + 3 * m, p3 + 3 * m, 3 * sizeof(double));
                cost[m] = cost3[m];
                mu[m] = mu[m] / 10.0;
            } else {
                mu[m] = mu[m] * 10.0;
            }
        }
        for (Py_ssize_t k = 0; k < K; k++)
            if (okl[t[k]] != 0.0) {
                memcpy(e + 2 * k, e3 + 2 * k, 2 * sizeof(double));
                memcpy(u + 3 * k, u3 + 3 * k, 3 * sizeof(double));
                w[k] = w3[k];
            }
    }
    free(work);
    return 0;
}

static PyObject *py_refit_lines(PyObject *Py_UNUSED(self), PyObject *args)
{
    PyObject *oR, *oc, *od, *op, *of, *ot, *oB, *ofree, *oe, *ou;
    Refit q;
    if (!PyArg_ParseTuple(args, "nnnOOOOOOOOidiOO", &q.F, &q.M, &q.K, &oR, &oc, &od, &op, &of,
                          &ot, &oB, &ofree, &q.loss, &q.scale, &q.iterations, &oe, &ou))
        return NULL;
    if (q.loss < LOSS_LINEAR || q.loss > LOSS_CAUCHY) {
        PyErr_Format(PyExc_ValueError, "unknown loss code %d", q.loss);
        return NULL;
    }
    Py_buffer b[10];
    PyObject *in[10] = {oR, oc, od, op, of, ot, oB, ofree, oe, ou};
    const Spec spec[10] = {
        {"R", 8, 9 * q.F, 0},
        {"c", 8, 3 * q.F, 0},
        {"d", 8, 3 * q.M, 1},
        {"p", 8, 3 * q.M, 1},
        {"f", 8, q.K, 0},
        {"t", 8, q.K, 0},
        {"B", 8, 6 * q.K, 0},
        {"free", 1, 4 * q.M, 0},
        {"e", 8, 2 * q.K, 1},
        {"u", 8, 3 * q.K, 1},
    };
    if (take_all(10, in, spec, b) < 0)
        return NULL;
    const int64_t *f = b[4].buf, *t = b[5].buf;
    if (!in_range(q.K, f, q.F, t, q.M))
        goto fail;
    q.R = b[0].buf;
    q.c = b[1].buf;
    q.d = b[2].buf;
    q.p = b[3].buf;
    q.f = f;
    q.t = t;
    q.B = b[6].buf;
    q.free = b[7].buf;
    q.e = b[8].buf;
    q.u = b[9].buf;
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = refit(&q);
    Py_END_ALLOW_THREADS
    release_all(10, b);
    if (rc < 0)
        return PyErr_NoMemory();
    Py_RETURN_NONE;
fail:
    release_all(10, b);
    return NULL;
}


/* ---- the adjustment's Jacobians and normal equations -------------------------------------- */

/* LineProblem.jacobian: per observation d e / d pose (2, 6) (rotation increment in the camera
 * frame, then the centre; bundle._pose_jacobian) and d e / d line (2, 4), held columns zero */
WIDE_LOOPS static void jacobians(Py_ssize_t K, const double *Rs, const double *cs, const double *d,
                      const double *p, const int64_t *f, const int64_t *t, const double *B,
                      const double *u, const uint8_t *pose_free, const uint8_t *line_free,
                      const double *b1, const double *b2, double *Jp, double *Jl)
{
    for (Py_ssize_t k = 0; k < K; k++) {
        const double *R = Rs + 9 * f[k], *uk = u + 3 * k, *dm = d + 3 * t[k];
        const uint8_t *pf = pose_free + 6 * f[k];
        double A[2][3], J[2][4];
        normal_derivative(B + 6 * k, uk, A);
        /* skew(u), and R^T skew(d) */
        double Su[3][3] = {{0.0, -uk[2], uk[1]}, {uk[2], 0.0, -uk[0]}, {-uk[1], uk[0], 0.0}};
        double Sd[3][3] = {{0.0, -dm[2], dm[1]}, {dm[2], 0.0, -dm[0]}, {-dm[1], dm[0], 0.0}};
        double RtSd[3][3];
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++)
                RtSd[i][j] = R[i] * Sd[0][j] + R[3 + i] * Sd[1][j] + R[6 + i] * Sd[2][j];
        double *jp = Jp + 12 * k;
        for (int r = 0; r < 2; r++)
            for (int j = 0; j < 3; j++) {
                double rot = A[r][0] * Su[0][j] + A[r][1] * Su[1][j] + A[r][2] * Su[2][j];
                double cen = A[r][0] * RtSd[0][j] + A[r][1] * RtSd[1][j] + A[r][2] * RtSd[2][j];
                jp[6 * r + j] = pf[j] ? rot : 0.0;
                jp[6 * r + 3 + j] = pf[3 + j] ? cen : 0.0;
            }
        line_row(R, cs + 3 * f[k], dm, p + 3 * t[k], b1 + 3 * t[k], b2 + 3 * t[k], A,
                 line_free + 4 * t[k], J);
        double *jl = Jl + 8 * k;
        for (int r = 0; r < 2; r++)
            for (int a = 0; a < 4; a++)
                jl[4 * r + a] = J[r][a];
    }
}

static PyObject *py_jacobians(PyObject *Py_UNUSED(self), PyObject *args)
{
    PyObject *o[14];
    Py_ssize_t F, M, K;
    if (!PyArg_ParseTuple(args, "nnnOOOOOOOOOOOOOO", &F, &M, &K, &o[0], &o[1], &o[2], &o[3],
                          &o[4], &o[5], &o[6], &o[7], &o[8], &o[9], &o[10], &o[11], &o[12],
                          &o[13]))
        return NULL;
    Py_buffer b[14];
    const Spec spec[14] = {
        {"R", 8, 9 * F, 0},
        {"c", 8, 3 * F, 0},
        {"d", 8, 3 * M, 0},
        {"p", 8, 3 * M, 0},
        {"f", 8, K, 0},
        {"t", 8, K, 0},
        {"B", 8, 6 * K, 0},
        {"u", 8, 3 * K, 0},
        {"pose_free", 1, 6 * F, 0},
        {"line_free", 1, 4 * M, 0},
        {"b1", 8, 3 * M, 0},
        {"b2", 8, 3 * M, 0},
        {"J_pose", 8, 12 * K, 1},
        {"J_line", 8, 8 * K, 1},
    };
    if (take_all(14, o, spec, b) < 0)
        return NULL;
    const int64_t *f = b[4].buf, *t = b[5].buf;
    if (!in_range(K, f, F, t, M))
        goto fail;
    Py_BEGIN_ALLOW_THREADS
    jacobians(K, b[0].buf, b[1].buf, b[2].buf, b[3].buf, f, t, b[6].buf, b[7].buf, b[8].buf,
              b[9].buf, b[10].buf, b[11].buf, b[12].buf, b[13].buf);
    Py_END_ALLOW_THREADS
    release_all(14, b);
    Py_RETURN_NONE;
fail:
    release_all(14, b);
    return NULL;
}

/* LineProblem.normal_equations: the blocks of J^T W J and J^T W e, summed per frame and line
 * in the order of the observations */
WIDE_LOOPS static void blocks(Py_ssize_t K, const double *Jp, const double *Jl, const double *e,
                   const double *w, const int64_t *f, const int64_t *t, double *Hpp,
                   double *Hll, double *Hpl, double *gp, double *gl)
{
    for (Py_ssize_t k = 0; k < K; k++) {
        const double *jp = Jp + 12 * k, *jl = Jl + 8 * k, *ek = e + 2 * k;
        double wk = w[k];
        double *hpp = Hpp + 36 * f[k], *hll = Hll + 16 * t[k], *hpl = Hpl + 24 * k;
        double *g1 = gp + 6 * f[k], *g2 = gl + 4 * t[k];
        for (int i = 0; i < 6; i++) {
            double a0 = wk * jp[i], a1 = wk * jp[6 + i];
            for (int j = 0; j < 6; j++)
                hpp[6 * i + j] += a0 * jp[j] + a1 * jp[6 + j];
            for (int j = 0; j < 4; j++)
                hpl[4 * i + j] = a0 * jl[j] + a1 * jl[4 + j];
            g1[i] += a0 * ek[0] + a1 * ek[1];
        }
        for (int i = 0; i < 4; i++) {
            double a0 = wk * jl[i], a1 = wk * jl[4 + i];
            for (int j = 0; j < 4; j++)
                hll[4 * i + j] += a0 * jl[j] + a1 * jl[4 + j];
            g2[i] += a0 * ek[0] + a1 * ek[1];
        }
    }
}

static PyObject *py_blocks(PyObject *Py_UNUSED(self), PyObject *args)
{
    PyObject *o[11];
    Py_ssize_t F, M, K;
    if (!PyArg_ParseTuple(args, "nnnOOOOOOOOOOO", &F, &M, &K, &o[0], &o[1], &o[2], &o[3],
                          &o[4], &o[5], &o[6], &o[7], &o[8], &o[9], &o[10]))
        return NULL;
    Py_buffer b[11];
    const Spec spec[11] = {
        {"J_pose", 8, 12 * K, 0},
        {"J_line", 8, 8 * K, 0},
        {"e", 8, 2 * K, 0},
        {"w", 8, K, 0},
        {"f", 8, K, 0},
        {"t", 8, K, 0},
        {"Hpp", 8, 36 * F, 1},
        {"Hll", 8, 16 * M, 1},
        {"Hpl", 8, 24 * K, 1},
        {"gp", 8, 6 * F, 1},
        {"gl", 8, 4 * M, 1},
    };
    if (take_all(11, o, spec, b) < 0)
        return NULL;
    const int64_t *f = b[4].buf, *t = b[5].buf;
    if (!in_range(K, f, F, t, M))
        goto fail;
    for (int i = 6; i < 11; i++)
        memset(b[i].buf, 0, (size_t)b[i].len);
    Py_BEGIN_ALLOW_THREADS
    blocks(K, b[0].buf, b[1].buf, b[2].buf, b[3].buf, f, t, b[6].buf, b[7].buf, b[8].buf,
           b[9].buf, b[10].buf);
    Py_END_ALLOW_THREADS
    release_all(11, b);
    Py_RETURN_NONE;
fail:
    release_all(11, b);
    return NULL;
}


/* ---- the poses eliminated (LineProblem.solve) ----------------------------------------------- */

/* L^-1 (6, 6) of the Cholesky factor L of symmetric positive definite H (6, 6); 0 where H is
 * not positive definite */
static int cholesky_inverse6(const double *H, double *Li)
{
    double L[6][6];
    memset(L, 0, sizeof(L));
    for (int j = 0; j < 6; j++) {
        double s = H[6 * j + j];
        for (int k = 0; k < j; k++)
            s -= L[j][k] * L[j][k];
        if (!(s > 0.0))
            return 0;
        L[j][j] = sqrt(s);
        for (int i = j + 1; i < 6; i++) {
            double v = H[6 * i + j];
            for (int k = 0; k < j; k++)
                v -= L[i][k] * L[j][k];
            L[i][j] = v / L[j][j];
        }
    }
    /* forward substitution, column by column of the identity */
    memset(Li, 0, 36 * sizeof(double));
    for (int c = 0; c < 6; c++)
        for (int i = c; i < 6; i++) {
            double v = i == c ? 1.0 : 0.0;
            for (int k = c; k < i; k++)
                v -= L[i][k] * Li[6 * k + c];
            Li[6 * i + c] = v / L[i][i];
        }
    return 1;
}

static PyObject *py_eliminate_poses(PyObject *Py_UNUSED(self), PyObject *args)
{
    PyObject *o[7];
    Py_ssize_t F, K;
    if (!PyArg_ParseTuple(args, "nnOOOOOOO", &F, &K, &o[0], &o[1], &o[2], &o[3], &o[4], &o[5],
                          &o[6]))
        return NULL;
    Py_buffer b[7];
    const Spec spec[7] = {
        {"Hpp", 8, 36 * F, 0},
        {"Hpl", 8, 24 * K, 0},
        {"gp", 8, 6 * F, 0},
        {"f", 8, K, 0},
        {"Linv", 8, 36 * F, 1},
        {"G", 8, 24 * K, 1},
        {"gpt", 8, 6 * F, 1},
    };
    if (take_all(7, o, spec, b) < 0)
        return NULL;
    const int64_t *f = b[3].buf;
    if (!in_range(K, f, F, f, F))
        goto fail;
    const double *Hpp = b[0].buf, *Hpl = b[1].buf, *gp = b[2].buf;
    double *Li = b[4].buf, *G = b[5].buf, *gpt = b[6].buf;
    int ok = 1;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < F && ok; i++) {
        ok = cholesky_inverse6(Hpp + 36 * i, Li + 36 * i);
        if (!ok)
            break;
        const double *l = Li + 36 * i, *g = gp + 6 * i;
        for (int r = 0; r < 6; r++) {
            double v = 0.0;
            for (int k = 0; k <= r; k++)
                v += l[6 * r + k] * g[k];
            gpt[6 * i + r] = v;
        }
    }
    if (ok)
        for (Py_ssize_t k = 0; k < K; k++) {
            const double *l = Li + 36 * f[k], *h = Hpl + 24 * k;
            double *gk = G + 24 * k;
            for (int r = 0; r < 6; r++)
                for (int a = 0; a < 4; a++) {
                    double v = 0.0;
                    for (int j = 0; j <= r; j++)
                        v += l[6 * r + j] * h[4 * j + a];
                    gk[4 * r + a] = v;
                }
        }
    Py_END_ALLOW_THREADS
    release_all(7, b);
    return PyBool_FromLong(ok);
fail:
    release_all(7, b);
    return NULL;
}

/* dp = -Hpp^-1 (gp + sum_k Hpl_k dl_t[k]) through L^-1: the poses' step once the lines' is
 * known */
static PyObject *py_back_substitute(PyObject *Py_UNUSED(self), PyObject *args)
{
    PyObject *o[7];
    Py_ssize_t F, M, K;
    if (!PyArg_ParseTuple(args, "nnnOOOOOOO", &F, &M, &K, &o[0], &o[1], &o[2], &o[3], &o[4],
                          &o[5], &o[6]))
        return NULL;
    Py_buffer b[7];
    const Spec spec[7] = {
        {"Linv", 8, 36 * F, 0},
        {"Hpl", 8, 24 * K, 0},
        {"gp", 8, 6 * F, 0},
        {"dl", 8, 4 * M, 0},
        {"f", 8, K, 0},
        {"t", 8, K, 0},
        {"dp", 8, 6 * F, 1},
    };
    if (take_all(7, o, spec, b) < 0)
        return NULL;
    const int64_t *f = b[4].buf, *t = b[5].buf;
    if (!in_range(K, f, F, t, M))
        goto fail;
    const double *Li = b[0].buf, *Hpl = b[1].buf, *gp = b[2].buf, *dl = b[3].buf;
    double *dp = b[6].buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < 6 * F; i++)
        dp[i] = -gp[i];
    for (Py_ssize_t k = 0; k < K; k++) {
        const double *h = Hpl + 24 * k, *x = dl + 4 * t[k];
        double *r = dp + 6 * f[k];
        for (int i = 0; i < 6; i++)
            r[i] -= h[4 * i] * x[0] + h[4 * i + 1] * x[1] + h[4 * i + 2] * x[2] +
                    h[4 * i + 3] * x[3];
    }
    for (Py_ssize_t i = 0; i < F; i++) {
        const double *l = Li + 36 * i;
        double *r = dp + 6 * i, y[6];
        for (int a = 0; a < 6; a++) {  /* y = L^-1 r */
            double v = 0.0;
            for (int j = 0; j <= a; j++)
                v += l[6 * a + j] * r[j];
            y[a] = v;
        }
        for (int a = 0; a < 6; a++) {  /* dp = L^-T y */
            double v = 0.0;
            for (int j = a; j < 6; j++)
                v += l[6 * j + a] * y[j];
            r[a] = v;
        }
    }
    Py_END_ALLOW_THREADS
    release_all(7, b);
    Py_RETURN_NONE;
fail:
    release_all(7, b);
    return NULL;
}


/* ``order`` (K,) a permutation's entries in 0..K-1 grouped by ``start`` (n + 1,): group g is
 * order[start[g]..start[g+1]), start rising from 0 to K. Returns the pairs of entries within
 * a group (each with itself included), or -1 with ValueError set where they do not fit. */
static Py_ssize_t grouped_pairs(const char *name, Py_ssize_t K, const int64_t *order,
                                Py_ssize_t n, const int64_t *start)
{
    Py_ssize_t pairs = 0;
    int ok = start[0] == 0 && start[n] == K;
    for (Py_ssize_t g = 0; g < n && ok; g++) {
        Py_ssize_t m = start[g + 1] - start[g];
        ok = m >= 0;
        pairs += m * (m + 1) / 2;
    }
    for (Py_ssize_t k = 0; k < K && ok; k++)
        ok = order[k] >= 0 && order[k] < K;
    if (!ok) {
        PyErr_Format(PyExc_ValueError, "%s: the observations' grouping does not fit", name);
        return -1;
    }
    return pairs;
}

/* ---- the lines' reduced system (bundle._ReducedSystem) -------------------------------------- */

static int cmp_i64(const void *a, const void *b)
{
    int64_t x = *(const int64_t *)a, y = *(const int64_t *)b;
    return (x > y) - (x < y);
}

/* The lines seen in one frame with each line ``tj`` (itself always included), sorted: the block rows
 * of ``tj``'s block column in S. ``by_frame``/``fb``: the observations in frame order and
 * each frame's first; ``by_line``/``lb``: the same by line. With ``rows`` NULL only their
 * counts ``nb`` are written, else ``rows`` (at ``ptr[tj]``) too. */
static int pattern(Py_ssize_t Ma, const int64_t *f, const int64_t *tc, const int64_t *by_frame,
                   const int64_t *fb, const int64_t *by_line, const int64_t *lb, int64_t *nb,
                   const int64_t *ptr, int64_t *rows)
{
    int64_t *mark = malloc(sizeof(int64_t) * (size_t)(Ma > 0 ? Ma : 1));
    if (mark == NULL)
        return -1;
    for (Py_ssize_t i = 0; i < Ma; i++)
        mark[i] = -1;
    for (Py_ssize_t tj = 0; tj < Ma; tj++) {
        /* the line itself first: its diagonal block is there even without an observation */
        int64_t n = 1;
        mark[tj] = tj;
        if (rows != NULL)
            rows[ptr[tj]] = tj;
        for (int64_t a = lb[tj]; a < lb[tj + 1]; a++) {
            int64_t fr = f[by_line[a]];
            for (int64_t b = fb[fr]; b < fb[fr + 1]; b++) {
                int64_t ti = tc[by_frame[b]];
                if (mark[ti] != tj) {
                    mark[ti] = tj;
                    if (rows != NULL)
                        rows[ptr[tj] + n] = ti;
                    n++;
                }
            }
        }
        nb[tj] = n;
        if (rows != NULL)
            qsort(rows + ptr[tj], (size_t)n, sizeof(int64_t), cmp_i64);
    }
    free(mark);
    return 0;
}

static PyObject *py_pattern(PyObject *Py_UNUSED(self), PyObject *args)
{
    PyObject *o[9];
    Py_ssize_t F, Ma, K, total;
    if (!PyArg_ParseTuple(args, "nnnnOOOOOOOOO", &F, &Ma, &K, &total, &o[0], &o[1], &o[2],
                          &o[3], &o[4], &o[5], &o[6], &o[7], &o[8]))
        return NULL;
    Py_buffer b[9];
    int with_rows = total >= 0;
    const Spec spec[9] = {
        {"f", 8, K, 0},
        {"tc", 8, K, 0},
        {"by_frame", 8, K, 0},
        {"frame_start", 8, F + 1, 0},
        {"by_line", 8, K, 0},
        {"line_start", 8, Ma + 1, 0},
        {"nb", 8, Ma, 1},
        {"ptr", 8, Ma + 1, 0},
        {"rows", 8, with_rows ? total : 0, 1},
    };
    if (take_all(9, o, spec, b) < 0)
        return NULL;
    if (!in_range(K, b[0].buf, F, b[1].buf, Ma) ||
        grouped_pairs("pattern", K, b[2].buf, F, b[3].buf) < 0 ||
        grouped_pairs("pattern", K, b[4].buf, Ma, b[5].buf) < 0)
        goto fail;
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = pattern(Ma, b[0].buf, b[1].buf, b[2].buf, b[3].buf, b[4].buf, b[5].buf, b[6].buf,
                 b[7].buf, with_rows ? b[8].buf : NULL);
    Py_END_ALLOW_THREADS
    release_all(9, b);
    if (rc < 0)
        return PyErr_NoMemory();
    Py_RETURN_NONE;
fail:
    release_all(9, b);
    return NULL;
}

/* Where block (row, col) of the block CSC matrix of ``pattern`` starts in its data: block
 * column col's column 4 col + c holds its block rows' 4 rows each, so the block's column c
 * is at the returned offset + c * 4 * (its number of block rows) */
static int64_t block_at(const int64_t *ptr, const int64_t *rows, int64_t row, int64_t col)
{
    const int64_t *lo = rows + ptr[col], *hi = rows + ptr[col + 1];
    const int64_t *hit = bsearch(&row, lo, (size_t)(hi - lo), sizeof(int64_t), cmp_i64);
    return 16 * ptr[col] + 4 * (hit - lo);
}

/* block_at of each pair of observations of a frame (b >= a, in the order reduce visits them),
 * for the block (row a, column b) and its transpose: offs[2 pair], offs[2 pair + 1] */
static void pair_offsets(Py_ssize_t F, const int64_t *tc, const int64_t *by_frame,
                         const int64_t *fb, const int64_t *ptr, const int64_t *rows,
                         int64_t *offs)
{
    Py_ssize_t pair = 0;
    for (Py_ssize_t fr = 0; fr < F; fr++)
        for (int64_t a = fb[fr]; a < fb[fr + 1]; a++)
            for (int64_t b = a; b < fb[fr + 1]; b++) {
                int64_t ti = tc[by_frame[a]], tj = tc[by_frame[b]];
                offs[2 * pair] = block_at(ptr, rows, ti, tj);
                offs[2 * pair + 1] = block_at(ptr, rows, tj, ti);
                pair++;
            }
}

static PyObject *py_pair_offsets(PyObject *Py_UNUSED(self), PyObject *args)
{
    PyObject *o[6];
    Py_ssize_t F, Ma, K, nrows, npairs;
    if (!PyArg_ParseTuple(args, "nnnnnOOOOOO", &F, &Ma, &K, &nrows, &npairs, &o[0], &o[1],
                          &o[2], &o[3], &o[4], &o[5]))
        return NULL;
    Py_buffer b[6];
    const Spec spec[6] = {
        {"tc", 8, K, 0},
        {"by_frame", 8, K, 0},
        {"frame_start", 8, F + 1, 0},
        {"ptr", 8, Ma + 1, 0},
        {"rows", 8, nrows, 0},
        {"offs", 8, 2 * npairs, 1},
    };
    if (take_all(6, o, spec, b) < 0)
        return NULL;
    Py_ssize_t pairs = grouped_pairs("pair_offsets", K, b[1].buf, F, b[2].buf);
    if (pairs >= 0 && pairs != npairs)
        PyErr_SetString(PyExc_ValueError, "pair_offsets: npairs does not fit the frames");
    if (pairs != npairs) {
        release_all(6, b);
        return NULL;
    }
    Py_BEGIN_ALLOW_THREADS
    pair_offsets(F, b[0].buf, b[1].buf, b[2].buf, b[3].buf, b[4].buf, b[5].buf);
    Py_END_ALLOW_THREADS
    release_all(6, b);
    Py_RETURN_NONE;
}

/* S = diag(Hll) - G^T G and rhs = -gl + G^T gpt, summed per frame over the pairs of its
 * observations: S dense (4 Ma)^2 row-major where ``ptr`` is NULL, else the data of the block
 * CSC matrix whose block column tj holds the block rows rows[ptr[tj]..ptr[tj+1]) */
WIDE_LOOPS static void reduce(Py_ssize_t Ma, Py_ssize_t F, const double *G, const int64_t *f,
                   const int64_t *tc, const int64_t *by_frame, const int64_t *fb,
                   const double *Hll, const double *gpt, const double *gl, const int64_t *ptr,
                   const int64_t *rows, const int64_t *offs, double *S, double *rhs)
{
    Py_ssize_t n4 = 4 * Ma, pair = 0;
    for (Py_ssize_t fr = 0; fr < F; fr++)
        for (int64_t a = fb[fr]; a < fb[fr + 1]; a++) {
            int64_t ka = by_frame[a], ti = tc[ka];
            const double *Ga = G + 24 * ka;
            for (int64_t b = a; b < fb[fr + 1]; b++) {  /* each pair once, and its transpose */
                int64_t kb = by_frame[b], tj = tc[kb];
                const double *Gb = G + 24 * kb;
                /* blk = Ga^T Gb, each entry summed over q in order (outer products, so
                 * that the compiler may compute the 16 entries side by side) */
                double blk[4][4] = {{0.0}};
                for (int q = 0; q < 6; q++)
                    for (int r = 0; r < 4; r++)
                        for (int c = 0; c < 4; c++)
                            blk[r][c] += Ga[4 * q + r] * Gb[4 * q + c];
                for (int side = 0; side < (b == a ? 1 : 2); side++) {
                    int64_t row = side ? tj : ti, col = side ? ti : tj;
                    if (ptr == NULL) {
                        double *at = S + 4 * row * n4 + 4 * col;
                        for (int r = 0; r < 4; r++)
                            for (int c = 0; c < 4; c++)
                                at[r * n4 + c] -= side ? blk[c][r] : blk[r][c];
                    } else {
                        int64_t nb = ptr[col + 1] - ptr[col], at = offs[2 * pair + side];
                        for (int c = 0; c < 4; c++)
                            for (int r = 0; r < 4; r++)
                                S[at + c * 4 * nb + r] -= side ? blk[c][r] : blk[r][c];
                    }
                }
                pair++;
            }
        }
    for (Py_ssize_t t = 0; t < Ma; t++) {
        const double *h = Hll + 16 * t;
        if (ptr == NULL) {
            double *at = S + 4 * t * n4 + 4 * t;
            for (int r = 0; r < 4; r++)
                for (int c = 0; c < 4; c++)
                    at[r * n4 + c] += h[4 * r + c];
        } else {
            int64_t nb = ptr[t + 1] - ptr[t], at = block_at(ptr, rows, t, t);
            for (int c = 0; c < 4; c++)
                for (int r = 0; r < 4; r++)
                    S[at + c * 4 * nb + r] += h[4 * r + c];
        }
    }
    for (Py_ssize_t i = 0; i < n4; i++)
        rhs[i] = -gl[i];
    for (Py_ssize_t fr = 0; fr < F; fr++)
        for (int64_t a = fb[fr]; a < fb[fr + 1]; a++) {
            int64_t k = by_frame[a];
            const double *Gk = G + 24 * k, *g = gpt + 6 * f[k];
            double *r = rhs + 4 * tc[k];
            for (int c = 0; c < 4; c++) {
                double v = 0.0;
                for (int q = 0; q < 6; q++)
                    v += Gk[4 * q + c] * g[q];
                r[c] += v;
            }
        }
}

static PyObject *py_reduce(PyObject *Py_UNUSED(self), PyObject *args)
{
    PyObject *o[13];
    Py_ssize_t F, Ma, K, nnz, npairs;
    if (!PyArg_ParseTuple(args, "nnnnnOOOOOOOOOOOOO", &F, &Ma, &K, &nnz, &npairs, &o[0], &o[1],
                          &o[2], &o[3], &o[4], &o[5], &o[6], &o[7], &o[8], &o[9], &o[10], &o[11],
                          &o[12]))
        return NULL;
    Py_buffer b[13];
    int sparse = nnz >= 0;
    const Spec spec[13] = {
        {"G", 8, 24 * K, 0},
        {"f", 8, K, 0},
        {"tc", 8, K, 0},
        {"by_frame", 8, K, 0},
        {"frame_start", 8, F + 1, 0},
        {"Hll", 8, 16 * Ma, 0},
        {"gpt", 8, 6 * F, 0},
        {"gl", 8, 4 * Ma, 0},
        {"ptr", 8, sparse ? Ma + 1 : 0, 0},
        {"rows", 8, sparse ? nnz / 16 : 0, 0},
        {"S", 8, sparse ? nnz : 16 * Ma * Ma, 1},
        {"rhs", 8, 4 * Ma, 1},
        {"offs", 8, sparse ? 2 * npairs : 0, 0},
    };
    if (take_all(13, o, spec, b) < 0)
        return NULL;
    Py_ssize_t pairs = grouped_pairs("reduce", K, b[3].buf, F, b[4].buf);
    if (pairs < 0 || !in_range(K, b[1].buf, F, b[2].buf, Ma))
        goto fail;
    if (sparse && pairs != npairs) {  /* the offsets must be those of these frames' pairs */
        PyErr_SetString(PyExc_ValueError, "reduce: the pair offsets do not fit the frames");
        goto fail;
    }
    memset(b[10].buf, 0, (size_t)b[10].len);
    Py_BEGIN_ALLOW_THREADS
    reduce(Ma, F, b[0].buf, b[1].buf, b[2].buf, b[3].buf, b[4].buf, b[5].buf, b[6].buf,
           b[7].buf, sparse ? b[8].buf : NULL, sparse ? b[9].buf : NULL,
           sparse ? b[12].buf : NULL, b[10].buf, b[11].buf);
    Py_END_ALLOW_THREADS
    release_all(13, b);
    Py_RETURN_NONE;
fail:
    release_all(13, b);
    return NULL;
}

/* ---- the reduced system's sparse Cholesky factorisation (bundle._ReducedSystem) ------------ */
/* S = L L^T with L block lower triangular (4x4 blocks), in a fill-reducing order ``perm``
 * (block k of the factor is line perm[k]; iperm its inverse). The structure of L is worked
 * out once per adjustment (chol_analyse: the elimination tree, then each row's pattern as the
 * union of the tree paths from the row's entries of S), and each step factors the new values
 * in it (chol_factor, "up-looking": row k of L from the rows above it) and solves
 * (chol_solve). Column i of L keeps its diagonal block first, then its blocks in increasing
 * row order: Lp/Li (block rows), 16 values a block, row-major. Row k's pattern (the columns
 * i < k of its blocks, increasing) is Rp/Ri, Rpos[j] where that block sits in its column. */

/* The counts (Li NULL: Lp and Rp written, cumulative) or the patterns (Li, Ri, Rpos written
 * from Lp and Rp); parent (Ma) written. -1: out of memory */
static int chol_analyse(Py_ssize_t Ma, const int64_t *ptr, const int64_t *rows,
                        const int64_t *perm, const int64_t *iperm, int64_t *parent,
                        int64_t *Lp, int64_t *Rp, int64_t *Li, int64_t *Ri, int64_t *Rpos)
{
    size_t n = (size_t)(Ma > 0 ? Ma : 1);
    int64_t *ancestor = malloc(sizeof(int64_t) * n), *mark = malloc(sizeof(int64_t) * n),
            *stack = malloc(sizeof(int64_t) * n), *next = malloc(sizeof(int64_t) * n);
    if (!ancestor || !mark || !stack || !next) {
        free(ancestor), free(mark), free(stack), free(next);
        return -1;
    }
    for (Py_ssize_t k = 0; k < Ma; k++) {  /* the elimination tree, path compression */
        parent[k] = ancestor[k] = -1;
        int64_t pk = perm[k];
        for (int64_t q = ptr[pk]; q < ptr[pk + 1]; q++) {
            int64_t i = iperm[rows[q]], inext;
            for (; i != -1 && i < k; i = inext) {
                inext = ancestor[i];
                ancestor[i] = k;
                if (inext == -1)
                    parent[i] = k;
            }
        }
    }
    for (Py_ssize_t k = 0; k < Ma; k++) {
        mark[k] = -1;
        next[k] = Li == NULL ? 1 : Lp[k] + 1;  /* counts (the diagonal), or the free slot */
    }
    if (Li == NULL)
        Rp[0] = 0;
    for (Py_ssize_t k = 0; k < Ma; k++) {
        int64_t pk = perm[k], m = 0;
        mark[k] = k;
        for (int64_t q = ptr[pk]; q < ptr[pk + 1]; q++)
            for (int64_t i = iperm[rows[q]]; i < k && mark[i] != k; i = parent[i]) {
                mark[i] = k;
                stack[m++] = i;
            }
        qsort(stack, (size_t)m, sizeof(int64_t), cmp_i64);
        if (Li == NULL) {
            for (int64_t j = 0; j < m; j++)
                next[stack[j]]++;
            Rp[k + 1] = Rp[k] + m;
        } else {
            Li[Lp[k]] = k;
            for (int64_t j = 0; j < m; j++) {
                int64_t i = stack[j], pos = next[i]++;
                Li[pos] = k;
                Ri[Rp[k] + j] = i;
                Rpos[Rp[k] + j] = pos;
            }
        }
    }
    if (Li == NULL) {
        Lp[0] = 0;
        for (Py_ssize_t k = 0; k < Ma; k++)
            Lp[k + 1] = Lp[k] + next[k];
    }
    free(ancestor), free(mark), free(stack), free(next);
    return 0;
}

/* The 4x4 lower Cholesky factor of the symmetric D (its lower triangle read), row-major;
 * 0 where D is not positive definite */
static int chol4(const double *D, double *L)
{
    for (int r = 0; r < 4; r++)
        for (int c = 0; c <= r; c++) {
            double v = D[4 * r + c];
            for (int s = 0; s < c; s++)
                v -= L[4 * r + s] * L[4 * c + s];
            if (r == c) {
                if (!(v > 0.0))
                    return 0;
                L[4 * r + r] = sqrt(v);
            } else
                L[4 * r + c] = v / L[4 * c + c];
        }
    for (int r = 0; r < 4; r++)
        for (int c = r + 1; c < 4; c++)
            L[4 * r + c] = 0.0;
    return 1;
}

/* The numbers of L for S's values (block CSC data, as reduce writes it). 0 where S is not
 * positive definite; X: 16 Ma of work space */
WIDE_LOOPS static int chol_factor(Py_ssize_t Ma, const int64_t *ptr, const int64_t *rows, const double *S,
                       const int64_t *perm, const int64_t *iperm, const int64_t *Lp,
                       const int64_t *Li, const int64_t *Rp, const int64_t *Ri,
                       const int64_t *Rpos, double *Lx, double *X)
{
    for (Py_ssize_t k = 0; k < Ma; k++) {
        int64_t pk = perm[k], nb = ptr[pk + 1] - ptr[pk];
        const double *col = S + 16 * ptr[pk];
        for (int64_t j = Rp[k]; j < Rp[k + 1]; j++)
            memset(X + 16 * Ri[j], 0, 16 * sizeof(double));
        memset(X + 16 * k, 0, 16 * sizeof(double));
        for (int64_t m = 0; m < nb; m++) {  /* X_i = S block (i, k), i <= k */
            int64_t i = iperm[rows[ptr[pk] + m]];
            if (i > k)
                continue;
            for (int r = 0; r < 4; r++)
                for (int c = 0; c < 4; c++)
                    X[16 * i + 4 * r + c] = col[4 * m + c * 4 * nb + r];
        }
        double D[16];
        memcpy(D, X + 16 * k, sizeof D);
        for (int64_t j = Rp[k]; j < Rp[k + 1]; j++) {
            int64_t i = Ri[j];
            const double *Xi = X + 16 * i, *Lii = Lx + 16 * Lp[i];
            double Y[16];  /* Y = L_ii^-1 X_i = L_ki^T */
            for (int c = 0; c < 4; c++)
                for (int r = 0; r < 4; r++) {
                    double v = Xi[4 * r + c];
                    for (int s = 0; s < r; s++)
                        v -= Lii[4 * r + s] * Y[4 * s + c];
                    Y[4 * r + c] = v / Lii[4 * r + r];
                }
            double *Lki = Lx + 16 * Rpos[j];
            for (int r = 0; r < 4; r++)
                for (int c = 0; c < 4; c++)
                    Lki[4 * r + c] = Y[4 * c + r];
            for (int64_t p = Lp[i] + 1; p < Rpos[j]; p++) {  /* X_r -= L_ri Y, r < k */
                const double *Lri = Lx + 16 * p;
                double *Xr = X + 16 * Li[p];
                for (int r = 0; r < 4; r++)
                    for (int c = 0; c < 4; c++) {
                        double v = 0.0;
                        for (int s = 0; s < 4; s++)
                            v += Lri[4 * r + s] * Y[4 * s + c];
                        Xr[4 * r + c] -= v;
                    }
            }
            for (int r = 0; r < 4; r++)  /* D -= Y^T Y */
                for (int c = 0; c < 4; c++) {
                    double v = 0.0;
                    for (int s = 0; s < 4; s++)
                        v += Y[4 * s + r] * Y[4 * s + c];
                    D[4 * r + c] -= v;
                }
        }
        if (!chol4(D, Lx + 16 * Lp[k]))
            return 0;
    }
    return 1;
}

/* x = S^-1 b through the factor (both 4 Ma, in the lines' own order); y: 4 Ma of work */
static void chol_solve(Py_ssize_t Ma, const int64_t *perm, const int64_t *Lp, const int64_t *Li,
                       const double *Lx, const double *b, double *x, double *y)
{
    for (Py_ssize_t k = 0; k < Ma; k++)
        memcpy(y + 4 * k, b + 4 * perm[k], 4 * sizeof(double));
    for (Py_ssize_t i = 0; i < Ma; i++) {  /* L z = y */
        const double *Lii = Lx + 16 * Lp[i];
        double *yi = y + 4 * i;
        for (int r = 0; r < 4; r++) {
            double v = yi[r];
            for (int s = 0; s < r; s++)
                v -= Lii[4 * r + s] * yi[s];
            yi[r] = v / Lii[4 * r + r];
        }
        for (int64_t p = Lp[i] + 1; p < Lp[i + 1]; p++) {
            const double *Lri = Lx + 16 * p;
            double *yr = y + 4 * Li[p];
            for (int r = 0; r < 4; r++) {
                double v = 0.0;
                for (int s = 0; s < 4; s++)
                    v += Lri[4 * r + s] * yi[s];
                yr[r] -= v;
            }
        }
    }
    for (Py_ssize_t i = Ma - 1; i >= 0; i--) {  /* L^T x = z */
        const double *Lii = Lx + 16 * Lp[i];
        double *yi = y + 4 * i;
        for (int64_t p = Lp[i] + 1; p < Lp[i + 1]; p++) {
            const double *Lri = Lx + 16 * p, *yr = y + 4 * Li[p];
            for (int s = 0; s < 4; s++) {
                double v = 0.0;
                for (int r = 0; r < 4; r++)
                    v += Lri[4 * r + s] * yr[r];
                yi[s] -= v;
            }
        }
        for (int r = 3; r >= 0; r--) {
            double v = yi[r];
            for (int s = r + 1; s < 4; s++)
                v -= Lii[4 * s + r] * yi[s];
            yi[r] = v / Lii[4 * r + r];
        }
    }
    for (Py_ssize_t k = 0; k < Ma; k++)
        memcpy(x + 4 * perm[k], y + 4 * k, 4 * sizeof(double));
}

/* perm a permutation of 0..Ma-1 and iperm its inverse (else ValueError set, 0) */
static int is_permutation(Py_ssize_t Ma, const int64_t *perm, const int64_t *iperm)
{
    for (Py_ssize_t k = 0; k < Ma; k++)
        if (perm[k] < 0 || perm[k] >= Ma || iperm[perm[k]] != k) {
            PyErr_SetString(PyExc_ValueError, "chol: perm is not a permutation with inverse iperm");
            return 0;
        }
    return 1;
}

/* rows[ptr[j]..ptr[j+1]) in 0..Ma-1, ptr non-decreasing from 0 to nrows */
static int valid_pattern(Py_ssize_t Ma, Py_ssize_t nrows, const int64_t *ptr,
                         const int64_t *rows)
{
    if (ptr[0] != 0 || ptr[Ma] != nrows)
        goto bad;
    for (Py_ssize_t j = 0; j < Ma; j++)
        if (ptr[j + 1] < ptr[j])
            goto bad;
    for (Py_ssize_t q = 0; q < nrows; q++)
        if (rows[q] < 0 || rows[q] >= Ma)
            goto bad;
    return 1;
bad:
    PyErr_SetString(PyExc_ValueError, "chol: ptr and rows are not a block pattern of Ma lines");
    return 0;
}

static PyObject *py_chol_analyse(PyObject *Py_UNUSED(self), PyObject *args)
{
    PyObject *o[9];
    Py_ssize_t Ma, nrows, nnzL;
    if (!PyArg_ParseTuple(args, "nnnOOOOOOOOO", &Ma, &nrows, &nnzL, &o[0], &o[1], &o[2], &o[3],
                          &o[4], &o[5], &o[6], &o[7], &o[8]))
        return NULL;
    Py_buffer b[9];
    int fill = nnzL >= 0;
    const Spec spec[9] = {
        {"ptr", 8, Ma + 1, 0},
        {"rows", 8, nrows, 0},
        {"perm", 8, Ma, 0},
        {"iperm", 8, Ma, 0},
        {"parent", 8, Ma, 1},
        {"Lp", 8, Ma + 1, !fill},
        {"Rp", 8, Ma + 1, !fill},
        {"Li", 8, fill ? nnzL : 0, 1},
        {"Ri_Rpos", 8, fill ? 2 * (nnzL - Ma) : 0, 1},
    };
    if (take_all(9, o, spec, b) < 0)
        return NULL;
    if (!valid_pattern(Ma, nrows, b[0].buf, b[1].buf) ||
        !is_permutation(Ma, b[2].buf, b[3].buf)) {
        release_all(9, b);
        return NULL;
    }
    int rc;
    int64_t *RR = b[8].buf;
    Py_BEGIN_ALLOW_THREADS
    rc = chol_analyse(Ma, b[0].buf, b[1].buf, b[2].buf, b[3].buf, b[4].buf, b[5].buf, b[6].buf,
                      fill ? b[7].buf : NULL, fill ? RR : NULL,
                      fill ? RR + (nnzL - Ma) : NULL);
    Py_END_ALLOW_THREADS
    release_all(9, b);
    if (rc < 0)
        return PyErr_NoMemory();
    Py_RETURN_NONE;
}

static PyObject *py_chol_factor(PyObject *Py_UNUSED(self), PyObject *args)
{
    PyObject *o[11];
    Py_ssize_t Ma, nrows, nnzL;
    if (!PyArg_ParseTuple(args, "nnnOOOOOOOOOOO", &Ma, &nrows, &nnzL, &o[0], &o[1], &o[2],
                          &o[3], &o[4], &o[5], &o[6], &o[7], &o[8], &o[9], &o[10]))
        return NULL;
    Py_buffer b[11];
    const Spec spec[11] = {
        {"ptr", 8, Ma + 1, 0},
        {"rows", 8, nrows, 0},
        {"S", 8, 16 * nrows, 0},
        {"perm", 8, Ma, 0},
        {"iperm", 8, Ma, 0},
        {"Lp", 8, Ma + 1, 0},
        {"Li", 8, nnzL, 0},
        {"Rp", 8, Ma + 1, 0},
        {"Ri_Rpos", 8, 2 * (nnzL - Ma), 0},
        {"Lx", 8, 16 * nnzL, 1},
        {"X", 8, 16 * Ma, 1},
    };
    if (take_all(11, o, spec, b) < 0)
        return NULL;
    int ok;
    const int64_t *RR = b[8].buf;
    Py_BEGIN_ALLOW_THREADS
    ok = chol_factor(Ma, b[0].buf, b[1].buf, b[2].buf, b[3].buf, b[4].buf, b[5].buf, b[6].buf,
                     b[7].buf, RR, RR + (nnzL - Ma), b[9].buf, b[10].buf);
    Py_END_ALLOW_THREADS
    release_all(11, b);
    return PyBool_FromLong(ok);
}

static PyObject *py_chol_solve(PyObject *Py_UNUSED(self), PyObject *args)
{
    PyObject *o[7];
    Py_ssize_t Ma, nnzL;
    if (!PyArg_ParseTuple(args, "nnOOOOOOO", &Ma, &nnzL, &o[0], &o[1], &o[2], &o[3], &o[4],
                          &o[5], &o[6]))
        return NULL;
    Py_buffer b[7];
    const Spec spec[7] = {
        {"perm", 8, Ma, 0},
        {"Lp", 8, Ma + 1, 0},
        {"Li", 8, nnzL, 0},
        {"Lx", 8, 16 * nnzL, 0},
        {"b", 8, 4 * Ma, 0},
        {"x", 8, 4 * Ma, 1},
        {"y", 8, 4 * Ma, 1},
    };
    if (take_all(7, o, spec, b) < 0)
        return NULL;
    Py_BEGIN_ALLOW_THREADS
    chol_solve(Ma, b[0].buf, b[1].buf, b[2].buf, b[3].buf, b[4].buf, b[5].buf, b[6].buf);
    Py_END_ALLOW_THREADS
    release_all(7, b);
    Py_RETURN_NONE;
}

/* ---- one camera's pose from lines held (bundle.resect_pose) -------------------------------- */

/* R <- R exp([w]x) (geometry.rotvec_to_matrix: the unit axis, normalised twice, and
   I + sin(t) K + (1 - cos(t)) K^2) */
static void rotate_by(const double R[9], const double w[3], double out[9])
{
    double t = sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]);
    double x = 0.0, y = 0.0, z = 1.0;
    if (t > 0) {
        x = w[0] / t;
        y = w[1] / t;
        z = w[2] / t;
    }
    double n = sqrt(x * x + y * y + z * z);
    x /= n;
    y /= n;
    z /= n;
    double K[9] = {0.0, -z, y, z, 0.0, -x, -y, x, 0.0};
    double s = sin(t), v = 1.0 - cos(t), E[9];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            double kk = K[3 * i] * K[j] + K[3 * i + 1] * K[3 + j] + K[3 * i + 2] * K[6 + j];
            E[3 * i + j] = (i == j ? 1.0 : 0.0) + s * K[3 * i + j] + v * kk;
        }
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            out[3 * i + j] = R[3 * i] * E[j] + R[3 * i + 1] * E[3 + j] + R[3 * i + 2] * E[6 + j];
}

typedef struct {
    Py_ssize_t K, J;
    const double *B, *d, *p, *m, *D;
    int kind;
    double scale;
} Pose;

/* the residuals e ((K + J) x 2), the predicted normals u (K x 3), each residual's IRLS weight w
   and the cost (half the sum of the robust costs) at the pose R, c */
static double pose_cost(const Pose *q, const double R[9], const double c[3], double *e,
                        double *u, double *w)
{
    double n[3], total = 0.0, rho;
    for (Py_ssize_t k = 0; k < q->K; k++) {
        predict(R, c, q->d + 3 * k, q->p + 3 * k, u + 3 * k);
        residual(q->B + 6 * k, u + 3 * k, n, e + 2 * k);
        loss(e[2 * k] * e[2 * k] + e[2 * k + 1] * e[2 * k + 1], q->kind, q->scale, &rho, w + k);
        total += rho;
    }
    for (Py_ssize_t j = 0; j < q->J; j++) {
        const double *m = q->m + 3 * j, *D = q->D + 3 * j;
        double r = 0.0;
        for (int i = 0; i < 3; i++)  /* m . R^T D */
            r += m[i] * (D[0] * R[i] + D[1] * R[3 + i] + D[2] * R[6 + i]);
        e[2 * (q->K + j)] = r;
        e[2 * (q->K + j) + 1] = 0.0;
        loss(r * r, q->kind, q->scale, &rho, w + q->K + j);
        total += rho;
    }
    return 0.5 * total;
}

/* the normal equations H (6x6), g (6) of the residuals e with weights w at R, u:
   d e / d w = A [u]x, d e / d c = A R^T [d]x (bundle._pose_jacobian), and for a direction-only
   normal d (m . R^T D) / d w = m x R^T D */
static void pose_normal_equations(const Pose *q, const double R[9], const double *e,
                                  const double *u, const double *w, double H[36], double g[6])
{
    memset(H, 0, 36 * sizeof(double));
    memset(g, 0, 6 * sizeof(double));
    double Jr[2][6];
    for (Py_ssize_t k = 0; k < q->K + q->J; k++) {
        int rows = 2;
        if (k < q->K) {
            double A[2][3];
            normal_derivative(q->B + 6 * k, u + 3 * k, A);
            const double *d = q->d + 3 * k;
            for (int r = 0; r < 2; r++) {
                cross(A[r], u + 3 * k, Jr[r]);  /* a^T [u]x = (a x u)^T */
                double Ra[3];
                for (int i = 0; i < 3; i++)
                    Ra[i] = R[3 * i] * A[r][0] + R[3 * i + 1] * A[r][1] + R[3 * i + 2] * A[r][2];
                cross(Ra, d, Jr[r] + 3);  /* a^T R^T [d]x = ((R a) x d)^T */
            }
        } else {
            const double *m = q->m + 3 * (k - q->K), *D = q->D + 3 * (k - q->K);
            double RtD[3];
            for (int i = 0; i < 3; i++)
                RtD[i] = D[0] * R[i] + D[1] * R[3 + i] + D[2] * R[6 + i];
            cross(m, RtD, Jr[0]);
            Jr[0][3] = Jr[0][4] = Jr[0][5] = 0.0;
            rows = 1;  /* the second component is 0, with a zero row */
        }
        for (int r = 0; r < rows; r++)
            for (int a = 0; a < 6; a++) {
                g[a] += w[k] * Jr[r][a] * e[2 * k + r];
                for (int b = 0; b < 6; b++)
                    H[6 * a + b] += w[k] * Jr[r][a] * Jr[r][b];
            }
    }
}

/* Levenberg-Marquardt over the pose (solver.levenberg_marquardt's loop on this problem: the first
   damping 1e-4, the diagonal of each 3-vector its mean, twelve tries a step each ten times
   more damped, the damping a tenth after an accepted step, stops on a relative decrease below
   ``tolerance``); R, c updated in place, e, u at the result; returns the iterations run, -1
   where memory runs out */
static int resect(const Pose *q, double R[9], double c[3], int iterations, double tolerance,
                  double *e, double *u)
{
    Py_ssize_t n = q->K + q->J;
    double *buf = malloc((size_t)(n > 0 ? n : 1) * 7 * sizeof(double));
    if (!buf)
        return -1;
    double *e2 = buf, *u2 = buf + 2 * n, *w2 = buf + 5 * n, *w = buf + 6 * n;
    double cost = pose_cost(q, R, c, e, u, w), lam = 1e-4;
    int it = 0;
    for (it = 1; it <= iterations; it++) {
        double H[36], g[6], R2[9], c2[3], new_cost = 0.0;
        pose_normal_equations(q, R, e, u, w, H, g);
        double dg[2];
        for (int part = 0; part < 2; part++) {
            double s = H[6 * (3 * part) + 3 * part] + H[6 * (3 * part + 1) + 3 * part + 1];
            s += H[6 * (3 * part + 2) + 3 * part + 2];
            dg[part] = s / 3.0;
            if (dg[part] < 1e-12)  /* numpy.maximum: NaN stays NaN */
                dg[part] = 1e-12;
        }
        int improved = 0;
        for (int attempt = 0; attempt < 12; attempt++) {
            double A[36], b[6], x[6];
            memcpy(A, H, sizeof A);
            for (int i = 0; i < 6; i++) {
                A[7 * i] = H[7 * i] + lam * dg[i / 3];
                b[i] = g[i];
            }
            if (!solve_small(6, A, b, x)) {
                lam *= 10.0;
                continue;
            }
            double wstep[3] = {-x[0], -x[1], -x[2]};
            rotate_by(R, wstep, R2);
            for (int i = 0; i < 3; i++)
                c2[i] = c[i] + -x[3 + i];
            new_cost = pose_cost(q, R2, c2, e2, u2, w2);
            if (isfinite(new_cost) && new_cost <= cost) {
                improved = 1;
                break;
            }
            lam *= 10.0;
        }
        if (!improved)
            break;
        double rel = (cost - new_cost) / (cost > 1e-300 ? cost : 1e-300);
        memcpy(R, R2, 9 * sizeof(double));
        memcpy(c, c2, 3 * sizeof(double));
        memcpy(e, e2, 2 * n * sizeof(double));
        memcpy(u, u2, 3 * q->K * sizeof(double));
        memcpy(w, w2, n * sizeof(double));
        cost = new_cost;
        lam = lam / 10.0 > 1e-12 ? lam / 10.0 : 1e-12;
        if (rel < tolerance || cost <= 1e-300)
            break;
    }
    free(buf);
    return it;
}

static PyObject *py_resect(PyObject *Py_UNUSED(self), PyObject *args)
{
    PyObject *o[9];
    Pose q;
    int iterations;
    double tolerance;
    if (!PyArg_ParseTuple(args, "nnOOOOOidOOidOO", &q.K, &q.J, &o[0], &o[1], &o[2], &o[3], &o[4],
                          &q.kind, &q.scale, &o[5], &o[6], &iterations, &tolerance, &o[7],
                          &o[8]))
        return NULL;
    Py_buffer b[9];
    const Spec spec[9] = {
        {"B", 8, 6 * q.K, 0},
        {"d", 8, 3 * q.K, 0},
        {"p", 8, 3 * q.K, 0},
        {"m", 8, 3 * q.J, 0},
        {"D", 8, 3 * q.J, 0},
        {"R", 8, 9, 1},
        {"c", 8, 3, 1},
        {"e", 8, 2 * (q.K + q.J), 1},
        {"u", 8, 3 * q.K, 1},
    };
    if (take_all(9, o, spec, b) < 0)
        return NULL;
    q.B = b[0].buf;
    q.d = b[1].buf;
    q.p = b[2].buf;
    q.m = b[3].buf;
    q.D = b[4].buf;
    int it = resect(&q, b[5].buf, b[6].buf, iterations, tolerance, b[7].buf, b[8].buf);
    release_all(9, b);
    if (it < 0)
        return PyErr_NoMemory();
    return PyLong_FromLong(it);
}

static PyMethodDef methods[] = {
    {"residuals", py_residuals, METH_VARARGS,
     "residuals(F, M, K, R, c, d, p, f, t, B, e, u): e (K, 2) and u (K, 3) written"},
    {"refit_lines", py_refit_lines, METH_VARARGS,
     "refit_lines(F, M, K, R, c, d, p, f, t, B, free, loss, scale, iterations, e, u): d, p "
     "moved in place, e and u written"},
    {"jacobians", py_jacobians, METH_VARARGS,
     "jacobians(F, M, K, R, c, d, p, f, t, B, u, pose_free, line_free, b1, b2, J_pose, "
     "J_line): J_pose (K, 2, 6) and J_line (K, 2, 4) written"},
    {"blocks", py_blocks, METH_VARARGS,
     "blocks(F, M, K, J_pose, J_line, e, w, f, t, Hpp, Hll, Hpl, gp, gl): the normal "
     "equations' blocks written"},
    {"eliminate_poses", py_eliminate_poses, METH_VARARGS,
     "eliminate_poses(F, K, Hpp, Hpl, gp, f, Linv, G, gpt): Linv, G = Linv_f Hpl and gpt = "
     "Linv gp written; False where a pose block is not positive definite"},
    {"back_substitute", py_back_substitute, METH_VARARGS,
     "back_substitute(F, M, K, Linv, Hpl, gp, dl, f, t, dp): the poses' step written"},
    {"pattern", py_pattern, METH_VARARGS,
     "pattern(F, Ma, K, total, f, tc, by_frame, frame_start, by_line, line_start, nb, ptr, "
     "rows): the block rows of each line's block column (total < 0: their counts only)"},
    {"pair_offsets", py_pair_offsets, METH_VARARGS,
     "pair_offsets(F, Ma, K, nrows, npairs, tc, by_frame, frame_start, ptr, rows, offs): "
     "where each pair of a frame's observations adds to the block-sparse S"},
    {"reduce", py_reduce, METH_VARARGS,
     "reduce(F, Ma, K, nnz, npairs, G, f, tc, by_frame, frame_start, Hll, gpt, gl, ptr, rows, "
     "S, rhs, offs): the reduced system written (nnz < 0: S dense)"},
    {"chol_analyse", py_chol_analyse, METH_VARARGS,
     "chol_analyse(Ma, nrows, nnzL, ptr, rows, perm, iperm, parent, Lp, Rp, Li, Ri_Rpos): the "
     "block Cholesky factor's structure (nnzL < 0: parent, Lp and Rp only)"},
    {"chol_factor", py_chol_factor, METH_VARARGS,
     "chol_factor(Ma, nrows, nnzL, ptr, rows, S, perm, iperm, Lp, Li, Rp, Ri_Rpos, Lx, X): the "
     "factor's values written; False where S is not positive definite"},
    {"chol_solve", py_chol_solve, METH_VARARGS,
     "chol_solve(Ma, nnzL, perm, Lp, Li, Lx, b, x, y): x = S^-1 b written"},
    {"resect", py_resect, METH_VARARGS,
     "resect(K, J, B, d, p, m, D, loss, scale, R, c, iterations, tolerance, e, u): one "
     "camera's pose from lines held (R, c updated, e, u at it); the iterations run"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_lines",
    "The line bundle adjustment's per-observation loops in C (omni_sfm.estimate.kernels).", -1,
    methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__lines(void) { return PyModule_Create(&module); }
