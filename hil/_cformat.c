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
 *
 * candump_lines(prefix, messages, end, bits) -> (str, int) | None: the candump lines of a list of
 * classic data frames as python-can's CanutilsLogWriter writes them ("(stamp) can0 " prefix,
 * "1A3#00FF", " T\n" end) and the sum of bits[len(data)]; None if any frame is not one.
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

/* ------------------------------------------------------------------ candump lines */

/* A growing text: a stack buffer first, the heap beyond it. */
struct text {
    char *data, *heap;
    Py_ssize_t length, capacity;
};

static int text_room(struct text *t, Py_ssize_t more) /* 0, or -1 with MemoryError */
{
    if (t->length + more <= t->capacity)
        return 0;
    const Py_ssize_t grown = 2 * (t->capacity + more);
    char *bigger = PyMem_Malloc((size_t)grown);
    if (bigger == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    memcpy(bigger, t->data, (size_t)t->length);
    PyMem_Free(t->heap);
    t->data = t->heap = bigger;
    t->capacity = grown;
    return 0;
}

static PyObject *s_arbitration_id, *s_is_extended_id, *s_is_error_frame, *s_is_remote_frame,
    *s_is_fd, *s_data;

/* 1 if message.<name> is true, 0 if false, -1 with an exception */
static int flag(PyObject *message, PyObject *name)
{
    PyObject *value = PyObject_GetAttr(message, name);
    if (value == NULL)
        return -1;
    const int truth = PyObject_IsTrue(value);
    Py_DECREF(value);
    return truth;
}

static const char HEX[] = "0123456789ABCDEF";

static PyObject *candump_lines(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs != 4 || !PyUnicode_Check(args[0]) || !PyUnicode_Check(args[2]) ||
        !PyTuple_Check(args[3])) {
        PyErr_SetString(PyExc_TypeError,
                        "candump_lines(prefix: str, messages, end: str, bits: tuple)");
        return NULL;
    }
    Py_ssize_t prefix_size, end_size;
    const char *prefix = PyUnicode_AsUTF8AndSize(args[0], &prefix_size);
    const char *end = prefix ? PyUnicode_AsUTF8AndSize(args[2], &end_size) : NULL;
    if (end == NULL)
        return NULL;
    PyObject *messages = PySequence_Fast(args[1], "candump_lines: a sequence of messages");
    if (messages == NULL)
        return NULL;
    PyObject *bits_of = args[3];
    const Py_ssize_t count = PySequence_Fast_GET_SIZE(messages);
    char stack[4096];
    struct text t = {stack, NULL, 0, (Py_ssize_t)sizeof stack};
    long long bits = 0;
    PyObject *result = NULL;
    for (Py_ssize_t i = 0; i < count; i++) {
        PyObject *message = PySequence_Fast_GET_ITEM(messages, i);
        /* classic data frames only: error, remote and FD frames are python-can's to write */
        int odd = flag(message, s_is_error_frame);
        if (odd == 0)
            odd = flag(message, s_is_remote_frame);
        if (odd == 0)
            odd = flag(message, s_is_fd);
        if (odd < 0)
            goto fail;
        if (odd)
            goto decline;
        const int extended = flag(message, s_is_extended_id);
        if (extended < 0)
            goto fail;
        PyObject *ident = PyObject_GetAttr(message, s_arbitration_id);
        if (ident == NULL)
            goto fail;
        if (!PyLong_CheckExact(ident)) {
            Py_DECREF(ident);
            goto decline;
        }
        const unsigned long long can_id = PyLong_AsUnsignedLongLong(ident);
        Py_DECREF(ident);
        if (can_id == (unsigned long long)-1 && PyErr_Occurred()) {
            PyErr_Clear(); /* negative or huge: python-can's writer says what it makes of it */
            goto decline;
        }
        PyObject *data = PyObject_GetAttr(message, s_data);
        if (data == NULL)
            goto fail;
        const char *bytes;
        Py_ssize_t size;
        if (PyByteArray_CheckExact(data)) {
            bytes = PyByteArray_AS_STRING(data);
            size = PyByteArray_GET_SIZE(data);
        } else if (PyBytes_CheckExact(data)) {
            bytes = PyBytes_AS_STRING(data);
            size = PyBytes_GET_SIZE(data);
        } else {
            Py_DECREF(data);
            goto decline;
        }
        if (size >= PyTuple_GET_SIZE(bits_of)) {
            Py_DECREF(data);
            goto decline;
        }
        const long frame_bits = PyLong_AsLong(PyTuple_GET_ITEM(bits_of, size));
        if (frame_bits == -1 && PyErr_Occurred()) {
            Py_DECREF(data);
            goto fail;
        }
        bits += frame_bits;
        if (text_room(&t, prefix_size + 17 + 1 + 2 * size + end_size) < 0) {
            Py_DECREF(data);
            goto fail;
        }
        char *p = t.data + t.length;
        memcpy(p, prefix, (size_t)prefix_size);
        p += prefix_size;
        /* the id in hex, upper case, at least 3 digits (8 extended): "{id:03X}#" */
        char digits[16];
        int n = 0;
        for (unsigned long long v = can_id; v || n == 0; v >>= 4)
            digits[n++] = HEX[v & 15];
        for (int z = n; z < (extended ? 8 : 3); z++)
            *p++ = '0';
        while (n)
            *p++ = digits[--n];
        *p++ = '#';
        for (Py_ssize_t k = 0; k < size; k++) {
            const unsigned char byte = (unsigned char)bytes[k];
            *p++ = HEX[byte >> 4];
            *p++ = HEX[byte & 15];
        }
        Py_DECREF(data);
        memcpy(p, end, (size_t)end_size);
        p += end_size;
        t.length = p - t.data;
    }
    {
        PyObject *text = PyUnicode_New(t.length, 127);
        if (text == NULL)
            goto fail;
        memcpy(PyUnicode_DATA(text), t.data, (size_t)t.length);
        result = Py_BuildValue("(NL)", text, bits);
    }
    PyMem_Free(t.heap);
    Py_DECREF(messages);
    return result;
decline:
    PyMem_Free(t.heap);
    Py_DECREF(messages);
    Py_RETURN_NONE;
fail:
    PyMem_Free(t.heap);
    Py_DECREF(messages);
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
    {"candump_lines", (PyCFunction)(void (*)(void))candump_lines, METH_FASTCALL,
     "candump_lines(prefix, messages, end, bits) -> (str, int) | None: each classic data "
     "frame's candump line, prefix + ID#DATA + end, and the sum of bits[len(data)]; None if "
     "any is an error, remote or FD frame (python-can writes those)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_softhil_cformat", "repr of floats and CSV rows in C", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__softhil_cformat(void)
{
    if (!(s_arbitration_id = PyUnicode_InternFromString("arbitration_id")) ||
        !(s_is_extended_id = PyUnicode_InternFromString("is_extended_id")) ||
        !(s_is_error_frame = PyUnicode_InternFromString("is_error_frame")) ||
        !(s_is_remote_frame = PyUnicode_InternFromString("is_remote_frame")) ||
        !(s_is_fd = PyUnicode_InternFromString("is_fd")) ||
        !(s_data = PyUnicode_InternFromString("data")))
        return NULL;
    return PyModule_Create(&module);
}
