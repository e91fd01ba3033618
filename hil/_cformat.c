/* Python's repr of a float, in C: the text of a signals.csv row without a Python call per value.
 *
 * `repr(x)` of a float is the shortest decimal that reads back as x (of several, the nearest to
 * x), written in fixed notation when its decimal point falls within 16 digits of its first
 * digit and in exponent notation otherwise. CPython finds the digits with David Gay's dtoa on
 * arbitrary-precision integers (about 0.5 us a value); this file finds the same digits with Ulf
 * Adams's Ryu algorithm ("Ryu: fast float-to-string conversion", PLDI 2018), which needs only
 * 128-bit products against a table of powers of five, and writes them as repr does. The table
 * (`POW5_INV_SPLIT`, `POW5_SPLIT`) is computed by hil/cformat.py with Python's exact integers
 * and prepended to this source before it is compiled. The tests compare every value written
 * here with repr over millions of doubles of every exponent, subnormals and powers of two.
 *
 * format_row(list) -> str | None: the CSV line of a row of floats and ints ("1.5,-0.0,,3\n"),
 * each value as repr writes it and a NaN float as an empty cell, which is what csv.writer
 * writes for the row `hil.recording.SignalRecorder` hands it; None for a row it does not
 * write (another type, or a one-cell NaN row, which csv quotes), which Python then writes.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#define MANTISSA_BITS 52
#define EXPONENT_BIAS 1023
#define POW5_INV_BITCOUNT 125
#define POW5_BITCOUNT 125

/* ceil(log2(5^e)) for e >= 1, and 1 for e = 0; 0 <= e <= 3528 */
static inline int32_t pow5bits(int32_t e) { return (int32_t)(((uint32_t)e * 1217359u) >> 19) + 1; }
/* floor(log10(2^e)) for 0 <= e <= 1650 */
static inline uint32_t log10pow2(int32_t e) { return ((uint32_t)e * 78913u) >> 18; }
/* floor(log10(5^e)) for 0 <= e <= 2620 */
static inline uint32_t log10pow5(int32_t e) { return ((uint32_t)e * 732923u) >> 20; }

static inline uint32_t pow5factor(uint64_t value) /* value > 0 */
{
    uint32_t count = 0;
    while (value % 5 == 0) {
        value /= 5;
        count++;
    }
    return count;
}

static inline int multiple_of_pow5(uint64_t value, uint32_t p) { return pow5factor(value) >= p; }
static inline int multiple_of_pow2(uint64_t value, uint32_t p)
{
    return (value & ((1ull << p) - 1)) == 0;
}

/* (m * mul) >> j, mul a 128-bit table entry (low, high), 64 < j < 192 */
static inline uint64_t mul_shift(uint64_t m, const uint64_t *mul, int32_t j)
{
    const unsigned __int128 low = (unsigned __int128)m * mul[0];
    const unsigned __int128 high = (unsigned __int128)m * mul[1];
    return (uint64_t)(((low >> 64) + high) >> (j - 64));
}

/* The shortest decimal digits of a finite positive double (its IEEE mantissa and biased
 * exponent): x = *digits * 10^*exponent, the nearest to x of the shortest that read back as x. */
static void shortest(uint64_t ieee_mantissa, uint32_t ieee_exponent, uint64_t *digits,
                     int32_t *exponent)
{
    int32_t e2;
    uint64_t m2;
    if (ieee_exponent == 0) {
        e2 = 1 - EXPONENT_BIAS - MANTISSA_BITS - 2;
        m2 = ieee_mantissa;
    } else {
        e2 = (int32_t)ieee_exponent - EXPONENT_BIAS - MANTISSA_BITS - 2;
        m2 = (1ull << MANTISSA_BITS) | ieee_mantissa;
    }
    /* the interval of reals that read back as x: [4 m2 - 1 - shift, 4 m2 + 2] * 2^e2 / 4 ... in
     * units of 2^e2, its bounds included when m2 is even (round half to even reads them as x) */
    const int accept_bounds = (m2 & 1) == 0;
    const uint64_t mv = 4 * m2;
    const uint32_t mm_shift = ieee_mantissa != 0 || ieee_exponent <= 1;
    uint64_t vr, vp, vm;
    int32_t e10;
    int vm_trailing_zeros = 0, vr_trailing_zeros = 0;
    if (e2 >= 0) {
        const uint32_t q = log10pow2(e2) - (e2 > 3);
        e10 = (int32_t)q;
        const int32_t k = POW5_INV_BITCOUNT + pow5bits((int32_t)q) - 1;
        const int32_t i = -e2 + (int32_t)q + k;
        vr = mul_shift(mv, POW5_INV_SPLIT[q], i);
        vp = mul_shift(mv + 2, POW5_INV_SPLIT[q], i);
        vm = mul_shift(mv - 1 - mm_shift, POW5_INV_SPLIT[q], i);
        if (q <= 21) {
            /* only here can a bound be a multiple of 10^q (one of them at most) */
            if (mv % 5 == 0)
                vr_trailing_zeros = multiple_of_pow5(mv, q);
            else if (accept_bounds)
                vm_trailing_zeros = multiple_of_pow5(mv - 1 - mm_shift, q);
            else
                vp -= (uint64_t)multiple_of_pow5(mv + 2, q);
        }
    } else {
        const uint32_t q = log10pow5(-e2) - (-e2 > 1);
        e10 = (int32_t)q + e2;
        const int32_t i = -e2 - (int32_t)q;
        const int32_t k = pow5bits(i) - POW5_BITCOUNT;
        const int32_t j = (int32_t)q - k;
        vr = mul_shift(mv, POW5_SPLIT[i], j);
        vp = mul_shift(mv + 2, POW5_SPLIT[i], j);
        vm = mul_shift(mv - 1 - mm_shift, POW5_SPLIT[i], j);
        if (q <= 1) {
            /* mv = 4 m2 has at least 2 trailing zero bits: vr is exact */
            vr_trailing_zeros = 1;
            if (accept_bounds)
                vm_trailing_zeros = mm_shift == 1; /* mm = mv - 1 - mm_shift: odd iff shift 0 */
            else
                --vp; /* mp = mv + 2 is a multiple of 2^q: exclude it */
        } else if (q < 63) {
            vr_trailing_zeros = multiple_of_pow2(mv, q);
        }
    }
    /* drop digits while the interval (vm, vp) still holds a shorter decimal */
    int32_t removed = 0;
    uint8_t last_removed = 0;
    uint64_t output;
    if (vm_trailing_zeros || vr_trailing_zeros) {
        while (vp / 10 > vm / 10) {
            vm_trailing_zeros &= vm % 10 == 0;
            vr_trailing_zeros &= last_removed == 0;
            last_removed = (uint8_t)(vr % 10);
            vr /= 10;
            vp /= 10;
            vm /= 10;
            removed++;
        }
        if (vm_trailing_zeros) {
            while (vm % 10 == 0) {
                vr_trailing_zeros &= last_removed == 0;
                last_removed = (uint8_t)(vr % 10);
                vr /= 10;
                vp /= 10;
                vm /= 10;
                removed++;
            }
        }
        if (vr_trailing_zeros && last_removed == 5 && vr % 2 == 0)
            last_removed = 4; /* exactly halfway: round to even */
        output = vr + ((vr == vm && (!accept_bounds || !vm_trailing_zeros)) || last_removed >= 5);
    } else {
        int round_up = 0;
        while (vp / 10 > vm / 10) {
            round_up = vr % 10 >= 5;
            vr /= 10;
            vp /= 10;
            vm /= 10;
            removed++;
        }
        output = vr + (vr == vm || round_up);
    }
    *digits = output;
    *exponent = e10 + removed;
}

/* repr(x) into out (at most 25 characters, no terminator); its length */
static int float_repr(double x, char *out)
{
    uint64_t bits;
    memcpy(&bits, &x, sizeof bits);
    const int negative = (int)(bits >> 63);
    const uint64_t ieee_mantissa = bits & ((1ull << MANTISSA_BITS) - 1);
    const uint32_t ieee_exponent = (uint32_t)((bits >> MANTISSA_BITS) & 0x7ff);
    char *p = out;
    if (ieee_exponent == 0x7ff) {
        if (ieee_mantissa != 0) {
            memcpy(p, "nan", 3);
            return 3;
        }
        if (negative)
            *p++ = '-';
        memcpy(p, "inf", 3);
        return (int)(p - out) + 3;
    }
    if (negative)
        *p++ = '-';
    if (ieee_exponent == 0 && ieee_mantissa == 0) {
        memcpy(p, "0.0", 3);
        return (int)(p - out) + 3;
    }
    uint64_t value;
    int32_t exponent;
    shortest(ieee_mantissa, ieee_exponent, &value, &exponent);
    char digits[20];
    int n = 0;
    for (uint64_t v = value; v; v /= 10)
        digits[19 - n++] = (char)('0' + v % 10);
    const char *d = digits + 20 - n;
    const int point = n + exponent; /* the decimal point after `point` digits */
    if (point > -4 && point <= 16) { /* repr's fixed notation */
        if (point <= 0) {
            *p++ = '0';
            *p++ = '.';
            for (int z = 0; z < -point; z++)
                *p++ = '0';
            memcpy(p, d, (size_t)n);
            p += n;
        } else if (point >= n) {
            memcpy(p, d, (size_t)n);
            p += n;
            for (int z = 0; z < point - n; z++)
                *p++ = '0';
            *p++ = '.';
            *p++ = '0';
        } else {
            memcpy(p, d, (size_t)point);
            p += point;
            *p++ = '.';
            memcpy(p, d + point, (size_t)(n - point));
            p += n - point;
        }
    } else { /* d[.ddd]e[+-]XX: at least two exponent digits */
        *p++ = d[0];
        if (n > 1) {
            *p++ = '.';
            memcpy(p, d + 1, (size_t)(n - 1));
            p += n - 1;
        }
        int e = point - 1;
        *p++ = 'e';
        *p++ = e < 0 ? '-' : '+';
        if (e < 0)
            e = -e;
        if (e >= 100)
            *p++ = (char)('0' + e / 100);
        *p++ = (char)('0' + e / 10 % 10);
        *p++ = (char)('0' + e % 10);
    }
    return (int)(p - out);
}

#define CELL_MAX 32 /* a float's repr: at most 24 characters */

static PyObject *format_row(PyObject *self, PyObject *row)
{
    (void)self;
    if (!PyList_CheckExact(row)) {
        PyErr_SetString(PyExc_TypeError, "format_row: a list of values");
        return NULL;
    }
    const Py_ssize_t n = PyList_GET_SIZE(row);
    char stack[64 * CELL_MAX];
    char *text = stack, *heap = NULL;
    Py_ssize_t capacity = (Py_ssize_t)sizeof stack;
    Py_ssize_t length = 0;
    PyObject *result = NULL;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *value = PyList_GET_ITEM(row, i);
        const char *cell = NULL;
        Py_ssize_t size = 0;
        char number[CELL_MAX];
        PyObject *text_of_int = NULL;
        if (PyFloat_CheckExact(value)) {
            const double x = PyFloat_AS_DOUBLE(value);
            if (x != x) {
                if (n == 1)
                    goto decline; /* csv writes a row of one empty cell as "" */
                size = 0;         /* NaN: an empty cell */
            } else {
                size = float_repr(x, number);
            }
            cell = number;
        } else if (PyLong_CheckExact(value)) {
            text_of_int = PyObject_Repr(value);
            if (text_of_int == NULL)
                goto fail;
            cell = PyUnicode_AsUTF8AndSize(text_of_int, &size);
            if (cell == NULL) {
                Py_DECREF(text_of_int);
                goto fail;
            }
        } else {
            goto decline;
        }
        if (length + size + 2 > capacity) {
            Py_ssize_t grown = 2 * (capacity + size + 2);
            char *bigger = PyMem_Malloc((size_t)grown);
            if (bigger == NULL) {
                Py_XDECREF(text_of_int);
                PyErr_NoMemory();
                goto fail;
            }
            memcpy(bigger, text, (size_t)length);
            PyMem_Free(heap);
            text = heap = bigger;
            capacity = grown;
        }
        memcpy(text + length, cell, (size_t)size);
        length += size;
        text[length++] = i + 1 < n ? ',' : '\n';
        Py_XDECREF(text_of_int);
    }
    if (n == 0)
        text[length++] = '\n';
    result = PyUnicode_New(length, 127);
    if (result != NULL)
        memcpy(PyUnicode_DATA(result), text, (size_t)length);
    PyMem_Free(heap);
    return result;
decline:
    PyMem_Free(heap);
    Py_RETURN_NONE;
fail:
    PyMem_Free(heap);
    return NULL;
}

static PyObject *float_text(PyObject *self, PyObject *value)
{
    (void)self;
    const double x = PyFloat_AsDouble(value);
    if (x == -1.0 && PyErr_Occurred())
        return NULL;
    char number[CELL_MAX];
    const int size = float_repr(x, number);
    return PyUnicode_FromStringAndSize(number, size);
}

static PyMethodDef methods[] = {
    {"format_row", format_row, METH_O,
     "format_row(list) -> str | None: the CSV line of a row of floats and ints (repr of each, "
     "a NaN float empty), None for a row with any other value"},
    {"float_repr", float_text, METH_O, "float_repr(x) -> str: repr(float(x)), computed in C"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_softhil_cformat", "repr of floats and CSV rows in C", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__softhil_cformat(void) { return PyModule_Create(&module); }
