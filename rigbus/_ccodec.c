/* softhil's DBC codec in C: the plain case of `rigbus.codec.MessageCodec`, one call a frame.

   A plan (built in Python from a message's codec, `rigbus.ccodec`) is compiled once per message
   into a capsule; `pack(capsule, values)` encodes a frame's values (a tuple in the order of the
   codec's `names`) and `unpack(capsule, data)` decodes a payload into its typed frame with the
   same arithmetic as the codec's Python path, so the bytes and the values are the same bit for
   bit.

   Invariant: either function returns None for anything but the plain case (a value that is not
   a float, or an int for a signal without scale and offset; a value outside the codec's quick
   range, a sequence number given as an int taken modulo its range first as the Python path
   does; an index that does not match), and the caller then takes the Python path, which encodes it or raises the
   error it always raises. So this file never decides what is an error, only how fast the plain
   case is.

   Exactness, against the Python path (checked value by value in tests/test_ccodec.py):
   - the Python path's raw value is round((value - offset) / scale): a subtraction and a
     correctly rounded division of doubles (Python's int / int too, for ints below 2^52), then
     Python's round(float), round-half-even, written out as CPython writes it;
   - decoding follows Python's types: an int scale and offset keep the product an exact integer;
     a float scale makes it a double, to which the offset is added as a double; then the
     field's converter (float(v), int(v) truncating, bool(int(v))). */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>
#include <structmember.h>

#define ENCODER_NAME "softhil.codec.encoder"
#define DECODER_NAME "softhil.codec.decoder"
#define LIMIT 4503599627370496.0 /* 2^52: every integer below it is exact in a double */
#define MAX_FIELDS 64

enum { KIND_FLOAT = 0, KIND_INT = 1, KIND_BOOL = 2 };

typedef struct {
    int start;
    uint64_t mask;
    int identity;    /* scale 1 and offset 0 (ints): the raw value is the value */
    double scale;
    int skip_offset; /* an offset the Python path does not subtract (value - 0 is value) */
    double offset;
    double lo, hi;   /* the codec's quick range */
    double raw_lo, raw_hi; /* the raw values the field holds */
    long long modulus; /* a sequence number's range, taken modulo when given as an int; 0: none */
} EncodeSignal;

typedef struct {
    Py_ssize_t length;
    Py_ssize_t count;
    EncodeSignal signals[];
} Encoder;

typedef struct {
    int start;
    uint64_t mask;
    int length;
    int is_signed;
    int identity;
    int int_scale;     /* scale and offset both ints: the value stays an exact integer */
    long long scale_i, offset_i;
    int float_scale;   /* scale a float (else an int) */
    double scale, offset;
    int kind;          /* the field's converter: float, int or bool(int(v)) */
    Py_ssize_t field;  /* position of the field in the dataclass's order */
} DecodeSignal;

typedef struct {
    Py_ssize_t length;
    PyObject *cls;        /* the frame dataclass (owned) */
    Py_ssize_t n_fields;
    Py_ssize_t slot[MAX_FIELDS]; /* each field's place in an instance (its slot's offset) */
    PyObject *index;      /* the message's index (an int) or None (owned) */
    Py_ssize_t index_field;  /* field position of the index, or -1 */
    Py_ssize_t index_signal; /* signal position of the index field, or -1 */
    Py_ssize_t count;
    DecodeSignal signals[];
} Decoder;

static double round_half_even(double x) {
    /* CPython's float.__round__ without ndigits */
    double rounded = round(x);
    if (fabs(x - rounded) == 0.5) {
        rounded = 2.0 * round(x / 2.0);
    }
    return rounded;
}

static int as_double(PyObject *o, double *out) {
    *out = PyFloat_AsDouble(o);
    return !(*out == -1.0 && PyErr_Occurred());
}

/* ------------------------------------------------------------------------------ encoder */

static void encoder_free(PyObject *capsule) {
    Encoder *e = PyCapsule_GetPointer(capsule, ENCODER_NAME);
    if (e != NULL) {
        PyMem_Free(e);
    }
}

/* compile_encoder(length, ((start, mask, identity, scale, skip_offset, offset, lo, hi, raw_lo,
   raw_hi, modulus), ...)) -> capsule, the signals in the order of the codec's values */
static PyObject *compile_encoder(PyObject *self, PyObject *args) {
    Py_ssize_t length;
    PyObject *signals;
    (void)self;
    if (!PyArg_ParseTuple(args, "nO!", &length, &PyTuple_Type, &signals)) {
        return NULL;
    }
    if (length < 0 || length > 8) {
        PyErr_SetString(PyExc_ValueError, "the C codec handles 0..8 data bytes");
        return NULL;
    }
    Py_ssize_t count = PyTuple_GET_SIZE(signals);
    Encoder *e = PyMem_Calloc(1, sizeof(Encoder) + (size_t)count * sizeof(EncodeSignal));
    if (e == NULL) {
        return PyErr_NoMemory();
    }
    e->length = length;
    PyObject *capsule = PyCapsule_New(e, ENCODER_NAME, encoder_free);
    if (capsule == NULL) {
        PyMem_Free(e);
        return NULL;
    }
    for (Py_ssize_t k = 0; k < count; k++) {
        EncodeSignal *s = &e->signals[k];
        PyObject *scale, *offset, *lo, *hi;
        unsigned long long mask;
        long long raw_lo, raw_hi;
        if (!PyArg_ParseTuple(PyTuple_GET_ITEM(signals, k), "iKpOpOOOLLL", &s->start, &mask,
                              &s->identity, &scale, &s->skip_offset, &offset, &lo, &hi,
                              &raw_lo, &raw_hi, &s->modulus)) {
            Py_DECREF(capsule);
            return NULL;
        }
        if (s->start < 0 || s->start > 63) {
            PyErr_SetString(PyExc_ValueError, "the C codec handles signals in 64 bits");
            Py_DECREF(capsule);
            return NULL;
        }
        s->mask = mask;
        s->raw_lo = (double)raw_lo;
        s->raw_hi = (double)raw_hi;
        if (!as_double(scale, &s->scale) || !as_double(offset, &s->offset) ||
            !as_double(lo, &s->lo) || !as_double(hi, &s->hi)) {
            Py_DECREF(capsule);
            return NULL;
        }
        e->count = k + 1;
    }
    return capsule;
}

/* the raw value of `v` for signal `s`, or 0 with *plain = 0: not the plain case */
static double raw_value(const EncodeSignal *s, PyObject *v, int *plain) {
    if (PyFloat_Check(v)) {
        /* a float (or a subclass such as numpy.float64): within the quick range, or None */
        double x = PyFloat_AS_DOUBLE(v);
        if (!(s->lo <= x && x <= s->hi)) {
            *plain = 0;
            return 0.0;
        }
        if (s->identity) {
            return round_half_even(x);
        }
        return round_half_even((s->skip_offset ? x : x - s->offset) / s->scale);
    }
    if (PyLong_Check(v) && s->identity) {
        /* an int or a bool for a signal without scale or offset: the raw value itself */
        int overflow = 0;
        long long i = PyLong_AsLongLongAndOverflow(v, &overflow);
        if (overflow || (i == -1 && PyErr_Occurred()) || i >= LIMIT || i <= -LIMIT) {
            PyErr_Clear();
            *plain = 0;
            return 0.0;
        }
        if (s->modulus > 0 && PyLong_CheckExact(v)) {
            /* a sequence number given as an int: modulo its range, as Python's % (never < 0) */
            i %= s->modulus;
            if (i < 0) {
                i += s->modulus;
            }
        }
        double raw = (double)i;
        if (!(s->lo <= raw && raw <= s->hi)) {
            *plain = 0;
        }
        return raw;
    }
    *plain = 0;
    return 0.0;
}

/* pack(encoder, values: tuple) -> bytes, or None: not the plain case (the Python path decides) */
static PyObject *pack(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "pack(encoder, values)");
        return NULL;
    }
    Encoder *e = PyCapsule_GetPointer(args[0], ENCODER_NAME);
    if (e == NULL) {
        return NULL;
    }
    PyObject *values = args[1];
    if (!PyTuple_CheckExact(values) || PyTuple_GET_SIZE(values) != e->count) {
        Py_RETURN_NONE;
    }
    uint64_t bits = 0;
    for (Py_ssize_t k = 0; k < e->count; k++) {
        const EncodeSignal *s = &e->signals[k];
        int plain = 1;
        double raw = raw_value(s, PyTuple_GET_ITEM(values, k), &plain);
        /* a raw value its field does not hold: never in the quick range (the codec checks) */
        if (!plain || !(s->raw_lo <= raw && raw <= s->raw_hi)) {
            Py_RETURN_NONE;
        }
        bits |= ((uint64_t)(int64_t)raw & s->mask) << s->start;
    }
    unsigned char data[8];
    for (Py_ssize_t b = 0; b < e->length; b++) {
        data[b] = (unsigned char)(bits >> (8 * b));
    }
    return PyBytes_FromStringAndSize((const char *)data, e->length);
}

/* ------------------------------------------------------------------------------ decoder */

static void decoder_free(PyObject *capsule) {
    Decoder *d = PyCapsule_GetPointer(capsule, DECODER_NAME);
    if (d == NULL) {
        return;
    }
    Py_XDECREF(d->cls);
    Py_XDECREF(d->index);
    PyMem_Free(d);
}

/* the offset of slot `name` in instances of `cls`, or -1: not a plain writable slot */
static Py_ssize_t slot_offset(PyObject *cls, PyObject *name) {
    PyObject *descr = PyObject_GetAttr(cls, name);
    if (descr == NULL) {
        PyErr_Clear();
        return -1;
    }
    Py_ssize_t offset = -1;
    if (Py_TYPE(descr) == &PyMemberDescr_Type &&
        ((PyMemberDescrObject *)descr)->d_common.d_type == (PyTypeObject *)cls) {
        PyMemberDef *member = ((PyMemberDescrObject *)descr)->d_member;
        if (member->type == T_OBJECT_EX && !(member->flags & READONLY)) {
            offset = member->offset;
        }
    }
    Py_DECREF(descr);
    return offset;
}

/* compile_decoder(length, cls, fields, index, index_field, ((start, mask, length, signed,
   identity, scale, offset, kind, field), ...)) -> capsule; `fields` the names of the class's
   fields in order, each a plain slot of its own (ValueError otherwise: the Python path builds
   the frames); scale and offset as Python gives them (int or float) */
static PyObject *compile_decoder(PyObject *self, PyObject *args) {
    Py_ssize_t length, index_field;
    PyObject *cls, *fields, *index, *signals;
    (void)self;
    if (!PyArg_ParseTuple(args, "nO!O!OnO!", &length, &PyType_Type, &cls, &PyTuple_Type,
                          &fields, &index, &index_field, &PyTuple_Type, &signals)) {
        return NULL;
    }
    Py_ssize_t n_fields = PyTuple_GET_SIZE(fields);
    if (length < 0 || length > 8 || n_fields > MAX_FIELDS) {
        PyErr_SetString(PyExc_ValueError, "the C codec handles 0..8 data bytes, 64 fields");
        return NULL;
    }
    if (index_field >= n_fields || (index_field >= 0 && index == Py_None)) {
        PyErr_SetString(PyExc_ValueError, "index field out of the fields");
        return NULL;
    }
    Py_ssize_t count = PyTuple_GET_SIZE(signals);
    Decoder *d = PyMem_Calloc(1, sizeof(Decoder) + (size_t)count * sizeof(DecodeSignal));
    if (d == NULL) {
        return PyErr_NoMemory();
    }
    d->length = length;
    d->n_fields = n_fields;
    Py_INCREF(cls);
    d->cls = cls;
    Py_INCREF(index);
    d->index = index;
    d->index_field = index_field;
    d->index_signal = -1;
    PyObject *capsule = PyCapsule_New(d, DECODER_NAME, decoder_free);
    if (capsule == NULL) {
        Py_DECREF(cls);
        Py_DECREF(index);
        PyMem_Free(d);
        return NULL;
    }
    for (Py_ssize_t f = 0; f < n_fields; f++) {
        d->slot[f] = slot_offset(cls, PyTuple_GET_ITEM(fields, f));
        if (d->slot[f] < 0) {
            PyErr_SetString(PyExc_ValueError, "a field that is not a plain slot of the class");
            Py_DECREF(capsule);
            return NULL;
        }
    }
    for (Py_ssize_t k = 0; k < count; k++) {
        DecodeSignal *s = &d->signals[k];
        PyObject *scale, *offset;
        unsigned long long mask;
        if (!PyArg_ParseTuple(PyTuple_GET_ITEM(signals, k), "iKippOOin", &s->start, &mask,
                              &s->length, &s->is_signed, &s->identity, &scale, &offset,
                              &s->kind, &s->field)) {
            Py_DECREF(capsule);
            return NULL;
        }
        if (s->start < 0 || s->length < 1 || s->start + s->length > 64 || s->field < 0 ||
            s->field >= n_fields || s->kind < KIND_FLOAT || s->kind > KIND_BOOL) {
            PyErr_SetString(PyExc_ValueError, "a signal the C codec does not handle");
            Py_DECREF(capsule);
            return NULL;
        }
        s->mask = mask;
        s->int_scale = PyLong_CheckExact(scale) && PyLong_CheckExact(offset);
        s->float_scale = PyFloat_CheckExact(scale);
        if (!s->float_scale && !PyLong_CheckExact(scale)) {
            PyErr_SetString(PyExc_ValueError, "scale must be an int or a float");
            Py_DECREF(capsule);
            return NULL;
        }
        if (!PyFloat_CheckExact(offset) && !PyLong_CheckExact(offset)) {
            PyErr_SetString(PyExc_ValueError, "offset must be an int or a float");
            Py_DECREF(capsule);
            return NULL;
        }
        if (!s->float_scale) {
            s->scale_i = PyLong_AsLongLong(scale);
            if (s->scale_i == -1 && PyErr_Occurred()) {
                Py_DECREF(capsule);
                return NULL;
            }
        }
        if (s->int_scale) {
            s->offset_i = PyLong_AsLongLong(offset);
            if (s->offset_i == -1 && PyErr_Occurred()) {
                Py_DECREF(capsule);
                return NULL;
            }
        }
        if (!as_double(scale, &s->scale) || !as_double(offset, &s->offset)) {
            Py_DECREF(capsule);
            return NULL;
        }
        if (s->field == index_field) {
            d->index_signal = k;
        }
        d->count = k + 1;
    }
    return capsule;
}

/* the field's value of raw value `raw` (a new reference), or NULL with *plain = 0: not plain */
static PyObject *field_value(const DecodeSignal *s, int64_t raw, int *plain) {
    double value;
    if (s->identity) {
        if (s->kind == KIND_BOOL) {
            return PyBool_FromLong(raw != 0);
        }
        if (s->kind == KIND_INT) {
            return PyLong_FromLongLong(raw);
        }
        return PyFloat_FromDouble((double)raw); /* |raw| < 2^64, exact below 2^53 as Python */
    }
    if (s->int_scale) {
        /* raw * S + O in Python's ints: exact; beyond 2^52 the Python path does it */
        double product = (double)raw * (double)s->scale_i;
        if (!(fabs(product) < LIMIT) || !(fabs((double)s->offset_i) < LIMIT)) {
            *plain = 0;
            return NULL;
        }
        int64_t exact = raw * s->scale_i + s->offset_i;
        if (s->kind == KIND_BOOL) {
            return PyBool_FromLong(exact != 0);
        }
        if (s->kind == KIND_INT) {
            return PyLong_FromLongLong(exact);
        }
        return PyFloat_FromDouble((double)exact);
    }
    if (s->float_scale) {
        value = (double)raw * s->scale + s->offset;
    } else {
        /* an int scale with a float offset: the product is an exact int, then a double */
        double product = (double)raw * (double)s->scale_i;
        if (!(fabs(product) < LIMIT)) {
            *plain = 0;
            return NULL;
        }
        value = product + s->offset;
    }
    if (s->kind == KIND_FLOAT) {
        return PyFloat_FromDouble(value);
    }
    if (!(fabs(value) < LIMIT)) {
        *plain = 0;
        return NULL;
    }
    int64_t truncated = (int64_t)value; /* int(float) truncates towards zero, as C does */
    if (s->kind == KIND_BOOL) {
        return PyBool_FromLong(truncated != 0);
    }
    return PyLong_FromLongLong(truncated);
}

/* unpack(decoder, data) -> the typed frame, or None: not the plain case */
static PyObject *unpack(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "unpack(decoder, data)");
        return NULL;
    }
    Decoder *d = PyCapsule_GetPointer(args[0], DECODER_NAME);
    if (d == NULL) {
        return NULL;
    }
    Py_buffer view;
    if (PyObject_GetBuffer(args[1], &view, PyBUF_SIMPLE) < 0) {
        return NULL;
    }
    if (view.len != d->length) {
        PyBuffer_Release(&view);
        Py_RETURN_NONE;
    }
    uint64_t bits = 0;
    const unsigned char *bytes = view.buf;
    for (Py_ssize_t b = 0; b < view.len; b++) {
        bits |= (uint64_t)bytes[b] << (8 * b);
    }
    PyBuffer_Release(&view);

    Py_ssize_t n_fields = d->n_fields;
    PyObject *values[MAX_FIELDS];
    memset(values, 0, sizeof(values));
    PyObject *result = NULL;
    int plain = 1;
    for (Py_ssize_t k = 0; k < d->count; k++) {
        const DecodeSignal *s = &d->signals[k];
        uint64_t u = (bits >> s->start) & s->mask;
        int64_t raw = (int64_t)u;
        if (s->is_signed && s->length < 64 && (u >> (s->length - 1))) {
            raw = (int64_t)(u - ((uint64_t)1 << s->length));
        }
        if (!s->is_signed && s->length == 64 && (u >> 63)) {
            plain = 0; /* above int64: the Python path */
            goto done;
        }
        PyObject *value = field_value(s, raw, &plain);
        if (value == NULL) {
            goto done;
        }
        Py_XSETREF(values[s->field], value);
    }
    if (d->index_field >= 0) {
        if (d->index_signal >= 0) {
            int equal = PyObject_RichCompareBool(values[d->index_field], d->index, Py_EQ);
            if (equal < 0) {
                goto done;
            }
            if (!equal) {
                plain = 0; /* the Python path raises the mismatch */
                goto done;
            }
        }
        Py_INCREF(d->index);
        Py_XSETREF(values[d->index_field], d->index);
    }
    for (Py_ssize_t f = 0; f < n_fields; f++) {
        if (values[f] == NULL) {
            plain = 0; /* a field no signal fills */
            goto done;
        }
    }
    PyTypeObject *type = (PyTypeObject *)d->cls;
    PyObject *frame = type->tp_alloc(type, 0); /* what __init__ fills: each field's slot */
    if (frame == NULL) {
        goto done;
    }
    for (Py_ssize_t f = 0; f < d->n_fields; f++) {
        PyObject **slot = (PyObject **)((char *)frame + d->slot[f]);
        Py_XSETREF(*slot, values[f]); /* the reference moves into the frame */
        values[f] = NULL;
    }
    result = frame;
done:
    for (Py_ssize_t f = 0; f < n_fields; f++) {
        Py_XDECREF(values[f]);
    }
    if (result == NULL && !plain && !PyErr_Occurred()) {
        Py_RETURN_NONE;
    }
    return result;
}

/* ------------------------------------------------------------------ can.Message, made here

   `rigbus.canbus.unchecked_message` in C: a can.Message with every field given and none
   checked, as `object.__new__(can.Message)` and twelve attribute stores make it. python-can
   declares the fields as __slots__, so `bind_message(can.Message)` finds each field's place in
   the object once (its member descriptor's offset) and the message is filled in place. It binds
   only a class whose twelve fields are plain writable slots of its own; otherwise it returns
   False and Python makes the messages. */

enum {
    F_TIMESTAMP, F_ID, F_EXTENDED, F_REMOTE, F_ERROR, F_CHANNEL, F_DLC, F_DATA, F_FD, F_RX,
    F_BRS, F_ESI, N_FIELDS
};
static const char *FIELDS[N_FIELDS] = {
    "timestamp", "arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame",
    "channel", "dlc", "data", "is_fd", "is_rx", "bitrate_switch", "error_state_indicator",
};
static PyTypeObject *message_type = NULL; /* the bound class (owned) */
static Py_ssize_t field_offset[N_FIELDS];

static PyObject *bind_message(PyObject *self, PyObject *cls) {
    (void)self;
    if (!PyType_Check(cls)) {
        PyErr_SetString(PyExc_TypeError, "bind_message: a class");
        return NULL;
    }
    PyTypeObject *type = (PyTypeObject *)cls;
    Py_ssize_t offsets[N_FIELDS];
    for (int i = 0; i < N_FIELDS; i++) {
        PyObject *descr = PyDict_GetItemString(type->tp_dict, FIELDS[i]); /* borrowed */
        if (descr == NULL || Py_TYPE(descr) != &PyMemberDescr_Type) Py_RETURN_FALSE;
        PyMemberDef *member = ((PyMemberDescrObject *)descr)->d_member;
        if (member->type != T_OBJECT_EX || (member->flags & READONLY)) Py_RETURN_FALSE;
        offsets[i] = member->offset;
    }
    Py_INCREF(type);
    Py_XSETREF(message_type, type);
    memcpy(field_offset, offsets, sizeof offsets);
    Py_RETURN_TRUE;
}

/* a new message of the bound class, its fields the values given (borrowed) */
static PyObject *make_message(PyObject *const *values) {
    PyObject *m = message_type->tp_alloc(message_type, 0);
    if (m == NULL) return NULL;
    for (int i = 0; i < N_FIELDS; i++) {
        PyObject **slot = (PyObject **)((char *)m + field_offset[i]);
        Py_INCREF(values[i]);
        Py_XSETREF(*slot, values[i]);
    }
    return m;
}

static int bound(void) {
    if (message_type != NULL) return 1;
    PyErr_SetString(PyExc_RuntimeError, "no message class bound (bind_message)");
    return 0;
}

static PyObject *new_message(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != N_FIELDS) {
        PyErr_Format(PyExc_TypeError, "new_message: %d fields, got %zd", N_FIELDS, nargs);
        return NULL;
    }
    return bound() ? make_message(args) : NULL;
}

/* data_message(arbitration_id, data, timestamp): a classic data frame with an 11-bit id, received
   flag set, as rigbus.protocol.data_message makes it */
static PyObject *data_message(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "data_message(arbitration_id, data, timestamp)");
        return NULL;
    }
    if (!bound()) return NULL;
    PyObject *data = PyByteArray_FromObject(args[1]);
    if (data == NULL) return NULL;
    PyObject *dlc = PyLong_FromSsize_t(PyByteArray_GET_SIZE(data));
    if (dlc == NULL) {
        Py_DECREF(data);
        return NULL;
    }
    PyObject *values[N_FIELDS] = {
        args[2], args[0], Py_False, Py_False, Py_False, Py_None,
        dlc,     data,    Py_False, Py_True,  Py_False, Py_False,
    };
    PyObject *m = make_message(values);
    Py_DECREF(dlc);
    Py_DECREF(data);
    return m;
}

/* copy_message(message, channel): a message of the bound class as delivered on `channel`,
   every field the same and its data a copy (hil.bus.direct); None for another class or a
   message with a field unset, which Python copies (or fails on) instead */
static PyObject *copy_message(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "copy_message(message, channel)");
        return NULL;
    }
    PyObject *original = args[0];
    if (message_type == NULL || Py_TYPE(original) != message_type) Py_RETURN_NONE;
    PyObject *values[N_FIELDS];
    for (int i = 0; i < N_FIELDS; i++) {
        values[i] = *(PyObject **)((char *)original + field_offset[i]);
        if (values[i] == NULL) Py_RETURN_NONE;
    }
    PyObject *data = PyByteArray_FromObject(values[F_DATA]);
    if (data == NULL) return NULL;
    values[F_DATA] = data;
    values[F_CHANNEL] = args[1];
    PyObject *m = make_message(values);
    Py_DECREF(data);
    return m;
}

static PyMethodDef methods[] = {
    {"bind_message", bind_message, METH_O,
     "bind_message(cls) -> bool: make messages of cls here (its fields plain slots)."},
    {"new_message", (PyCFunction)(void (*)(void))new_message, METH_FASTCALL,
     "new_message(timestamp, arbitration_id, is_extended_id, is_remote_frame, is_error_frame, "
     "channel, dlc, data, is_fd, is_rx, bitrate_switch, error_state_indicator) -> message"},
    {"data_message", (PyCFunction)(void (*)(void))data_message, METH_FASTCALL,
     "data_message(arbitration_id, data, timestamp) -> message (a classic data frame)"},
    {"copy_message", (PyCFunction)(void (*)(void))copy_message, METH_FASTCALL,
     "copy_message(message, channel) -> message, or None if not of the bound class."},
    {"compile_encoder", compile_encoder, METH_VARARGS, "An encoder capsule from its plan."},
    {"compile_decoder", compile_decoder, METH_VARARGS, "A decoder capsule from its plan."},
    {"pack", (PyCFunction)(void (*)(void))pack, METH_FASTCALL,
     "pack(encoder, values) -> bytes, or None if not the plain case."},
    {"unpack", (PyCFunction)(void (*)(void))unpack, METH_FASTCALL,
     "unpack(decoder, data) -> frame, or None if not the plain case."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_softhil_ccodec", "softhil's DBC codec in C.", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__softhil_ccodec(void) { return PyModule_Create(&module); }
