/* The camera's picture in C: `hil.vision.Camera.picture`'s draws and arithmetic, one call.

   A picture draws, per marker, its noise, its dropout and its outlier from three numpy random
   streams of its own. numpy's Generator draws through the functions of numpy's C random API
   (`numpy/random/lib/libnpyrandom.a`, the library numpy ships for code that draws from a
   Generator's bit generator in C): `Generator.normal(0.0, 1.0, n)` is n calls of
   `random_normal(bitgen, 0.0, 1.0)`, and `Generator.random(n)` is one call of
   `random_standard_uniform_fill`. This file calls the same functions on the same bit generators
   (from `bit_generator.capsule`), in the same order per stream, so the draws, and every value
   computed from them here (with no fused multiply-add, as numpy computes them), are the same bit
   for bit; tests/test_vision.py checks pictures and the streams' states against numpy's path.

   What numpy does better stays there: the rare outlier (the direction's norm, `np.linalg.norm`,
   whose summation order is numpy's to choose) is finished in Python from the directions drawn
   here, and occlusion bursts are applied in Python.

   The bit generators' locks are not taken: a camera's streams are its own, drawn from by the
   thread that steps it, and this call holds the GIL throughout. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>

#include "numpy/random/bitgen.h"

/* numpy's C random API (numpy/random/distributions.h), the two functions used */
extern double random_normal(bitgen_t *bitgen_state, double loc, double scale);
extern void random_standard_uniform_fill(bitgen_t *bitgen_state, Py_ssize_t cnt, double *out);

#define BITGEN_NAME "BitGenerator" /* the name numpy gives a bit generator's capsule */
#define MAX_MARKERS 4096

static bitgen_t *bitgen_of(PyObject *capsule) {
    return (bitgen_t *)PyCapsule_GetPointer(capsule, BITGEN_NAME);
}

/* A buffer of `count` items of `itemsize` bytes, C-contiguous (writable if asked). */
static int get_buffer(PyObject *obj, Py_buffer *view, Py_ssize_t itemsize, int writable,
                      const char *what) {
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) != 0)
        return -1;
    if (view->itemsize != itemsize) {
        PyErr_Format(PyExc_TypeError, "%s: items of %zd bytes, not %zd", what, view->itemsize,
                     itemsize);
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

/* picture(noise_gen, dropout_gen, outlier_gen, true_points, points, dropped, outlier, direction,
           noise, dropout, outlier_rate) -> flags

   M markers of D coordinates: true_points, points and direction hold M x D doubles, dropped and
   outlier M bools. Fills points = true_points + N(0, 1) * noise (noise stream), dropped = U <
   dropout (dropout stream), outlier = U < outlier_rate and direction = N(0, 1) per coordinate
   (outlier stream: the M uniforms, then the M x D normals). flags: 1 if a marker is dropped, 2
   if one is an outlier (the caller then moves it along its direction). */
static PyObject *picture(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != 11) {
        PyErr_SetString(PyExc_TypeError, "picture() takes 11 arguments");
        return NULL;
    }
    bitgen_t *gens[3];
    for (int i = 0; i < 3; i++)
        if ((gens[i] = bitgen_of(args[i])) == NULL)
            return NULL;
    double noise = PyFloat_AsDouble(args[8]);
    double dropout = PyFloat_AsDouble(args[9]);
    double outlier_rate = PyFloat_AsDouble(args[10]);
    if (PyErr_Occurred())
        return NULL;
    Py_buffer truth, points, dropped, outlier, direction;
    if (get_buffer(args[3], &truth, sizeof(double), 0, "true_points") != 0)
        return NULL;
    PyObject *result = NULL;
    if (get_buffer(args[4], &points, sizeof(double), 1, "points") != 0)
        goto no_points;
    if (get_buffer(args[5], &dropped, 1, 1, "dropped") != 0)
        goto no_dropped;
    if (get_buffer(args[6], &outlier, 1, 1, "outlier") != 0)
        goto no_outlier;
    if (get_buffer(args[7], &direction, sizeof(double), 1, "direction") != 0)
        goto no_direction;
    const Py_ssize_t M = dropped.len;
    const Py_ssize_t n = truth.len / (Py_ssize_t)sizeof(double);
    if (M < 1 || M > MAX_MARKERS || n % M != 0 || outlier.len != M ||
        points.len != truth.len || direction.len != truth.len) {
        PyErr_SetString(PyExc_ValueError, "picture(): buffers of mismatched sizes");
        goto done;
    }
    const double *t = truth.buf;
    double *p = points.buf, *d = direction.buf;
    uint8_t *drop = dropped.buf, *out = outlier.buf;
    double draws[MAX_MARKERS];
    long flags = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        double z = random_normal(gens[0], 0.0, 1.0) * noise;
        p[i] = t[i] + z;
    }
    random_standard_uniform_fill(gens[1], M, draws);
    for (Py_ssize_t m = 0; m < M; m++) {
        drop[m] = draws[m] < dropout;
        if (drop[m])
            flags |= 1;
    }
    random_standard_uniform_fill(gens[2], M, draws);
    for (Py_ssize_t m = 0; m < M; m++) {
        out[m] = draws[m] < outlier_rate;
        if (out[m])
            flags |= 2;
    }
    for (Py_ssize_t i = 0; i < n; i++)
        d[i] = random_normal(gens[2], 0.0, 1.0);
    result = PyLong_FromLong(flags);
done:
    PyBuffer_Release(&direction);
no_direction:
    PyBuffer_Release(&outlier);
no_outlier:
    PyBuffer_Release(&dropped);
no_dropped:
    PyBuffer_Release(&points);
no_points:
    PyBuffer_Release(&truth);
    return result;
}

static PyMethodDef methods[] = {
    {"picture", (PyCFunction)(void (*)(void))picture, METH_FASTCALL,
     "A picture's draws and points (see the file's head)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_softhil_cvision", "The camera's picture in C.", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__softhil_cvision(void) { return PyModule_Create(&module); }
