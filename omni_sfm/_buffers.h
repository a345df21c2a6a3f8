/* Argument arrays of omni-sfm's C extensions (omni_sfm/estimate/_lines.c,
 * omni_sfm/lines/_edges.c): each comes in through the buffer protocol, C-contiguous, with the
 * item size and count the Python wrapper promises, or the call fails with a ValueError. */
#ifndef OMNI_SFM_BUFFERS_H
#define OMNI_SFM_BUFFERS_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>

/* The hottest loops are compiled twice on x86-64 Linux with GCC, for AVX2 and for any x86-64,
 * the one to run chosen when the module loads: the compiler computes independent entries side
 * by side in wider registers, and no sum changes its order (no fused multiply-add either,
 * -ffp-contract=off), so both give the same bits. */
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__)
#define WIDE_LOOPS __attribute__((target_clones("avx2", "default")))
#else
#define WIDE_LOOPS
#endif

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

#endif
