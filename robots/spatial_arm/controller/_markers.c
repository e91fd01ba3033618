/* The spatial arm's markers and their Jacobian for the controller's loop (markers.py):
 * the same piecewise-constant-curvature kinematics as kinematics.py and the ArmBody FMU, for
 * one configuration, with the derivatives by complex step (exact to rounding: no subtraction).
 *
 * Segment s bends by (u, v) = (theta_x, theta_y), W = u^2 + v^2,
 *   a(W) = sin(sqrt W) / sqrt W,  b(W) = (1 - cos(sqrt W)) / W,
 * its tip frame's origin in its base frame is r = (F u, F v, G), F = L b + L_p a,
 * G = 2 L_p + L a - L_p W b, and the tip frame is turned by R = I + a K + b K^2, K = [phi]x,
 * phi = (-v, u, 0). Below W = 1, a and b come from their Taylor series (terms until they fall
 * below 1e-17 of the sum), which are analytic in complex W too; above, from csin and ccos.
 *
 * markers(L, L_p, q, markers_out, jacobian_out): buffers of doubles; L, L_p of n segments,
 * q of 2 n bends; markers_out (n + 1) x 3 (row 0 the base origin), jacobian_out
 * (n + 1) x 3 x 2 n (row-major). Returns None.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <complex.h>
#include <math.h>
#include <string.h>

#define MAX_SEGMENTS 8
#define STEP 1e-30

typedef double complex cplx;

static void bend_functions(cplx W, cplx *a, cplx *b)
{
    if (cabs(W) < 1.0) {
        /* a = sum (-W)^k / (2k+1)!, b = sum (-W)^k / (2k+2)! */
        cplx term_a = 1.0, term_b = 0.5, sum_a = 1.0, sum_b = 0.5;
        for (int k = 1; k < 20; k++) {
            term_a *= -W / ((2.0 * k) * (2.0 * k + 1.0));
            term_b *= -W / ((2.0 * k + 1.0) * (2.0 * k + 2.0));
            sum_a += term_a;
            sum_b += term_b;
            if (cabs(term_a) < 1e-17 * cabs(sum_a) && cabs(term_b) < 1e-17 * cabs(sum_b))
                break;
        }
        *a = sum_a;
        *b = sum_b;
    } else {
        cplx t = csqrt(W);
        *a = csin(t) / t;
        *b = (1.0 - ccos(t)) / W;
    }
}

/* The endplates' positions (n + 1) x 3 at the complex bends q. */
static void chain(int n, const double *L, const double *Lp, const cplx *q, cplx *out)
{
    cplx R[3][3] = {{1, 0, 0}, {0, 1, 0}, {0, 0, 1}};
    cplx P[3] = {0, 0, 0};
    out[0] = out[1] = out[2] = 0;
    for (int s = 0; s < n; s++) {
        cplx u = q[2 * s], v = q[2 * s + 1];
        cplx W = u * u + v * v, a, b;
        bend_functions(W, &a, &b);
        cplx F = L[s] * b + Lp[s] * a;
        cplx G = 2.0 * Lp[s] + L[s] * a - Lp[s] * W * b;
        cplx r[3] = {F * u, F * v, G};
        for (int i = 0; i < 3; i++)
            P[i] += R[i][0] * r[0] + R[i][1] * r[1] + R[i][2] * r[2];
        /* K = [phi]x with phi = (-v, u, 0); R_loc = I + a K + b K^2 */
        cplx K[3][3] = {{0, 0, u}, {0, 0, v}, {-u, -v, 0}};
        cplx K2[3][3], loc[3][3], next[3][3];
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++) {
                K2[i][j] = K[i][0] * K[0][j] + K[i][1] * K[1][j] + K[i][2] * K[2][j];
            }
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++)
                loc[i][j] = (i == j ? 1.0 : 0.0) + a * K[i][j] + b * K2[i][j];
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++)
                next[i][j] = R[i][0] * loc[0][j] + R[i][1] * loc[1][j] + R[i][2] * loc[2][j];
        memcpy(R, next, sizeof R);
        for (int i = 0; i < 3; i++)
            out[3 * (s + 1) + i] = P[i];
    }
}

static int buffer_of(Py_buffer *view, Py_ssize_t doubles, const char *name)
{
    if (view->len != doubles * (Py_ssize_t)sizeof(double)) {
        PyErr_Format(PyExc_ValueError, "%s: %zd doubles expected, got %zd bytes", name, doubles,
                     view->len);
        return 0;
    }
    return 1;
}

static PyObject *markers(PyObject *self, PyObject *args)
{
    Py_buffer bL, bLp, bq, bm, bJ;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*y*y*w*w*", &bL, &bLp, &bq, &bm, &bJ))
        return NULL;
    PyObject *result = NULL;
    Py_ssize_t n = bL.len / (Py_ssize_t)sizeof(double);
    if (n < 1 || n > MAX_SEGMENTS) {
        PyErr_Format(PyExc_ValueError, "L: 1 to %d segments expected, got %zd", MAX_SEGMENTS, n);
        goto done;
    }
    int nq = (int)(2 * n), rows = (int)(3 * (n + 1));
    if (!buffer_of(&bLp, n, "L_p") || !buffer_of(&bq, nq, "q") ||
        !buffer_of(&bm, rows, "markers_out") || !buffer_of(&bJ, (Py_ssize_t)rows * nq, "jacobian_out"))
        goto done;
    const double *L = bL.buf, *Lp = bLp.buf, *q = bq.buf;
    double *m = bm.buf, *J = bJ.buf;
    cplx qc[2 * MAX_SEGMENTS], out[3 * (MAX_SEGMENTS + 1)];
    for (int j = 0; j < nq; j++)
        qc[j] = q[j];
    chain((int)n, L, Lp, qc, out);
    for (int i = 0; i < rows; i++)
        m[i] = creal(out[i]);
    for (int j = 0; j < nq; j++) {
        qc[j] = q[j] + I * STEP;
        chain((int)n, L, Lp, qc, out);
        qc[j] = q[j];
        for (int i = 0; i < rows; i++)
            J[i * nq + j] = cimag(out[i]) / STEP;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&bL);
    PyBuffer_Release(&bLp);
    PyBuffer_Release(&bq);
    PyBuffer_Release(&bm);
    PyBuffer_Release(&bJ);
    return result;
}

static PyMethodDef methods[] = {
    {"markers", markers, METH_VARARGS,
     "markers(L, L_p, q, markers_out, jacobian_out): the endplates and their Jacobian"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_spatial_markers", NULL, -1, methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__spatial_markers(void) { return PyModule_Create(&module); }
