/* Compiled accelerator of the compact pose codec (posecast.protocol._speedups).
 *
 * Each function here has a pure-Python twin that is the reference: the same
 * inputs give the same outputs, byte for byte and value for value, and where the
 * twin would take another path (a frame it would not accept, a value out of
 * range) the function returns None and the caller takes the pure path, which
 * decides. protocol/_accel.py picks which set runs; tests run both.
 *
 *   eg_pack            protocol.bits.eg_pack
 *   decode_update_rows protocol.codec_fast.decode_update_rows (its small path)
 *   decode_update      protocol._compact.UpstreamDecoder._decode_fast (the whole of it)
 *   update_records     protocol._compact._update_of_rows (the record bytes)
 *   delta_blocks       protocol.codec_relay._delta_blocks
 *   splice             protocol.codec_relay.GroupSnapshot.frame
 *   encode_group       protocol.codec_relay.encode_group (trusted; packed for splice_packed)
 *   splice_packed      protocol.codec_relay.GroupSnapshot.frame of a packed group
 *   encode_stored      protocol.codec_relay.encode_stored (gathers a room's store, then as
 *                      encode_group)
 *
 * Floating-point results must equal CPython's: build without FMA contraction
 * (setup.py passes -ffp-contract=off) and round as Python does (nearbyint in the
 * default rounding mode is round-half-even, like round()).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#define MAX_EG_BITS 48
#define MAX_K 15
#define HIST 50 /* MAX_EG_BITS + 2 */
#define SMALL_FRAME 30
#define ID_MAX 0xFFFF
#define TIME_MS_LIMIT (INT64_C(1) << 30)
#define M 4095
#define ROTATION_BITS 13
#define LIN_CODE_MAX 32768
#define ANG_CODE_MAX 16384
#define MAX_WIDTH 13
#define F_VELOCITY 2
#define F_SPLIT 4
#ifndef SOURCE_HASH
#define SOURCE_HASH "unknown"
#endif

/* ------------------------------------------------------------------ CRC-32 */

static uint32_t crc_table[256];

static void crc_init(void) {
    for (uint32_t i = 0; i < 256; i++) {
        uint32_t c = i;
        for (int j = 0; j < 8; j++) c = (c & 1) ? 0xEDB88320u ^ (c >> 1) : c >> 1;
        crc_table[i] = c;
    }
}

/* zlib.crc32(data, crc): pass the running value (0 to start). */
static uint32_t crc_update(uint32_t crc, const unsigned char *p, size_t n) {
    crc = ~crc;
    while (n--) crc = crc_table[(crc ^ *p++) & 0xFF] ^ (crc >> 8);
    return ~crc;
}

static void put_le32(unsigned char *p, int64_t v) {
    uint32_t u = (uint32_t)v;
    p[0] = u & 0xFF;
    p[1] = (u >> 8) & 0xFF;
    p[2] = (u >> 16) & 0xFF;
    p[3] = (u >> 24) & 0xFF;
}

/* ------------------------------------------------------------------ zigzag, rotation predictor */

static inline uint64_t zz(int64_t v) { return ((uint64_t)v << 1) ^ (uint64_t)(v >> 63); }
static inline int64_t unzz(uint64_t z) { return (int64_t)(z >> 1) ^ -(int64_t)(z & 1); }
static inline int bit_length(uint64_t v) { return v ? 64 - __builtin_clzll(v) : 0; }

static const int OTHERS[4][3] = {{1, 2, 3}, {0, 2, 3}, {0, 1, 3}, {0, 1, 2}};
/* SOURCES[i0][idx]: where, in (a, b, c, dropped) of a row of largest index i0, the
 * components OTHERS[idx] and component idx (the sign) are (codec_small._sources). */
static int SOURCES[4][4][4];

static void sources_init(void) {
    for (int i0 = 0; i0 < 4; i0++)
        for (int idx = 0; idx < 4; idx++) {
            int at[4];
            for (int j = 0; j < 3; j++) at[OTHERS[i0][j]] = j;
            at[i0] = 3;
            for (int j = 0; j < 3; j++) SOURCES[i0][idx][j] = at[OTHERS[idx][j]];
            SOURCES[i0][idx][3] = at[idx];
        }
}

static inline int64_t clip(int64_t v) { return v < -M ? -M : (v > M ? M : v); }

/* codec_small.predict_row: the rotation of base re-expressed with largest index idx. */
static void predict_row(const int64_t *base, int idx, int64_t *out) {
    int64_t i0 = base[0], a = base[1], b = base[2], c = base[3];
    if (i0 == idx && -M <= a && a <= M && -M <= b && b <= M && -M <= c && c <= M) {
        out[0] = a, out[1] = b, out[2] = c;
        return;
    }
    int64_t rest = 2 * (int64_t)M * M - (a * a + b * b + c * c);
    if (rest < 0) rest = 0;
    int64_t full[4] = {a, b, c, ((int64_t)floor(sqrt(4.0 * (double)rest)) + 1) / 2};
    const int *s = SOURCES[i0 & 3][idx];
    int64_t sign = full[s[3]] < 0 ? -1 : 1;
    for (int j = 0; j < 3; j++) out[j] = clip(sign * full[s[j]]);
}

/* ------------------------------------------------------------------ bit writer */

typedef struct {
    unsigned char *buf;
    Py_ssize_t cap;  /* bytes */
    Py_ssize_t pos;  /* bits written */
} Writer;

static int writer_put(Writer *w, uint64_t value, int width) {
    Py_ssize_t need = (w->pos + width + 7) / 8;
    if (need > w->cap) {
        Py_ssize_t cap = w->cap * 2 > need ? w->cap * 2 : need + 64;
        unsigned char *buf = PyMem_Realloc(w->buf, cap);
        if (buf == NULL) return -1;
        memset(buf + w->cap, 0, cap - w->cap);
        w->buf = buf, w->cap = cap;
    }
    while (width > 0) {
        int room = 8 - (int)(w->pos & 7), take = width < room ? width : room;
        unsigned bits = (unsigned)(value >> (width - take)) & ((1u << take) - 1);
        w->buf[w->pos >> 3] |= (unsigned char)(bits << (room - take));
        w->pos += take, width -= take;
    }
    return 0;
}

/* The non-negative int ``v`` (< 2**nbits) in nbits bits. */
static int writer_put_int(Writer *w, PyObject *v, Py_ssize_t nbits) {
    Py_ssize_t nbytes = (nbits + 7) / 8;
    unsigned char small[512], *buf = nbytes <= (Py_ssize_t)sizeof(small) ? small : PyMem_Malloc(nbytes);
    int ok = 0;
    if (buf == NULL) return -1;
    if (nbytes) {
#if PY_VERSION_HEX >= 0x030D0000
        Py_ssize_t got = PyLong_AsNativeBytes(
            v, buf, nbytes, Py_ASNATIVEBYTES_BIG_ENDIAN | Py_ASNATIVEBYTES_UNSIGNED_BUFFER);
        ok = got >= 0 && got <= nbytes ? 0 : -1;
#else
        ok = _PyLong_AsByteArray((PyLongObject *)v, buf, nbytes, 0, 0);
#endif
        int lead = (int)(8 * nbytes - nbits);
        if (ok == 0 && writer_put(w, buf[0] & ((1u << (8 - lead)) - 1), 8 - lead) < 0) ok = -1;
        for (Py_ssize_t i = 1; ok == 0 && i < nbytes; i++)
            if (writer_put(w, buf[i], 8) < 0) ok = -1;
    }
    if (buf != small) PyMem_Free(buf);
    return ok;
}

/* The whole Exp-Golomb code of order k of v (bits.eg_code); v < 2**63. */
static int writer_eg(Writer *w, uint64_t v, int k) {
    if ((v >> k) == 0) return writer_put(w, ((uint64_t)1 << k) | v, k + 1);
    int width = 2 * (bit_length(v) - 1) - k + 2;
    if (width > 64) {
        if (writer_put(w, 0, width - 64) < 0) return -1;
        width = 64;
    }
    return writer_put(w, v, width);
}

/* The bits written so far as a Python int (the stream read as one big-endian number). */
static PyObject *writer_int(Writer *w) {
    Py_ssize_t nbytes = (w->pos + 7) / 8;
    int pad = (int)(8 * nbytes - w->pos);
    if (nbytes == 0) return PyLong_FromLong(0);
    PyObject *whole = _PyLong_FromByteArray(w->buf, nbytes, 0, 0);
    if (whole == NULL || pad == 0) return whole;
    PyObject *shift = PyLong_FromLong(pad);
    PyObject *out = shift ? PyNumber_Rshift(whole, shift) : NULL;
    Py_XDECREF(shift);
    Py_DECREF(whole);
    return out;
}

/* ------------------------------------------------------------------ bit reader */

typedef struct {
    const unsigned char *buf;
    Py_ssize_t size; /* bits */
    Py_ssize_t pos;
} Reader;

static inline int bit_at(const Reader *r, Py_ssize_t p) {
    return (r->buf[p >> 3] >> (7 - (p & 7))) & 1;
}

static uint64_t bits_at(const Reader *r, Py_ssize_t p, int width) {
    uint64_t v = 0;
    while (width > 0) {
        int off = (int)(p & 7), avail = 8 - off, take = avail < width ? avail : width;
        unsigned byte = r->buf[p >> 3];
        v = (v << take) | ((byte >> (avail - take)) & ((1u << take) - 1));
        p += take, width -= take;
    }
    return v;
}

/* n fixed fields of width bits; -1 past the end. */
static int read_fixed(Reader *r, int n, int width, int64_t *out, int stride) {
    if (r->pos + (Py_ssize_t)n * width > r->size) return -1;
    for (int i = 0; i < n; i++, r->pos += width) out[i * stride] = (int64_t)bits_at(r, r->pos, width);
    return 0;
}

/* A column of n Exp-Golomb codes of order k (every prefix, then every suffix), as
 * IntReader.eg_column; -1 if truncated or a prefix runs over MAX_EG_BITS - k zeros. */
static int read_eg_column(Reader *r, int n, int k, uint64_t *out) {
    int lengths[SMALL_FRAME];
    Py_ssize_t pos = r->pos;
    int reach = MAX_EG_BITS - k + 1;
    if (n > SMALL_FRAME) return -1;
    for (int i = 0; i < n; i++) {
        int L = 0;
        while (1) {
            if (L >= reach || pos + L >= r->size) return -1;
            if (bit_at(r, pos + L)) break;
            L++;
        }
        lengths[i] = L;
        pos += L + 1;
    }
    for (int i = 0; i < n; i++) {
        int L = lengths[i], width = L ? L - 1 + k : k;
        if (pos + width > r->size) return -1;
        uint64_t s = bits_at(r, pos, width);
        pos += width;
        out[i] = L ? s | ((uint64_t)1 << width) : s;
    }
    r->pos = pos;
    return 0;
}

/* ------------------------------------------------------------------ eg_pack */

static PyObject *py_eg_pack(PyObject *self, PyObject *args) {
    PyObject *values, *orders;
    if (!PyArg_ParseTuple(args, "OO", &values, &orders)) return NULL;
    PyObject *vs = PySequence_Fast(values, "values must be a sequence");
    if (vs == NULL) return NULL;
    PyObject *ks = PySequence_Fast(orders, "orders must be a sequence");
    if (ks == NULL) {
        Py_DECREF(vs);
        return NULL;
    }
    PyObject *result = NULL;
    Writer w = {NULL, 0, 0};
    Py_ssize_t n = PySequence_Fast_GET_SIZE(vs);
    if (n != PySequence_Fast_GET_SIZE(ks)) {
        PyErr_SetString(PyExc_ValueError, "as many values as orders");
        goto done;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        long long v = PyLong_AsLongLong(PySequence_Fast_GET_ITEM(vs, i));
        long k = PyLong_AsLong(PySequence_Fast_GET_ITEM(ks, i));
        if (PyErr_Occurred() || v < 0 || k < 0 || k > MAX_K) {
            PyErr_Clear();
            result = Py_NewRef(Py_None); /* the pure path decides */
            goto done;
        }
        if (writer_eg(&w, (uint64_t)v, (int)k) < 0) goto done;
    }
    PyObject *acc = writer_int(&w);
    if (acc != NULL) result = Py_BuildValue("(Nn)", acc, w.pos);
done:
    PyMem_Free(w.buf);
    Py_DECREF(vs);
    Py_DECREF(ks);
    return result;
}

#include "_speedups_update.h"
#include "_speedups_relay.h"

/* ------------------------------------------------------------------ module */

static PyMethodDef methods[] = {
    {"eg_pack", py_eg_pack, METH_VARARGS,
     "eg_pack(values, orders) -> (bits, bit count) or None: bits.eg_pack."},
    {"decode_update_rows", py_decode_update_rows, METH_VARARGS,
     "decode_update_rows(data, pos, flags, geometry, baselines) -> (streams, offsets, rows) "
     "or None: codec_fast.decode_update_rows."},
    {"decode_update", py_decode_update, METH_VARARGS,
     "decode_update(data, previous, geometry, baselines, lo, step) -> (number, base_us, "
     "records, codes) or None: _compact.UpstreamDecoder._decode_fast; updates baselines."},
    {"update_records", py_update_records, METH_VARARGS,
     "update_records(base_us, streams, offsets, rows, lo, step) -> bytes: the PoseUpdate "
     "records of decoded rows (_compact._update_of_rows)."},
    {"splice", py_splice, METH_VARARGS,
     "splice(head, key_blocks, delta_blocks, key_nibbles, delta_nibbles, exclude) -> "
     "(bytes, entries): codec_relay.GroupSnapshot.frame (exclude -1: nobody)."},
    {"delta_blocks", py_delta_blocks, METH_VARARGS,
     "delta_blocks(entries, base) -> ([(user, n, bits, nbits, check)], nibbles) or None: "
     "codec_relay._delta_blocks."},
    {"encode_group", py_encode_group, METH_VARARGS,
     "encode_group(entries, base_us, velocity, bits) -> (packed, key_nibbles, delta_nibbles) "
     "or None: codec_relay.encode_group's sections, packed for splice_packed."},
    {"encode_stored", py_encode_stored, METH_VARARGS,
     "encode_stored(streams, since, volume, base_us, velocity, bits) -> (packed, key_nibbles, "
     "delta_nibbles), False (no stream newer than since) or None: codec_relay.encode_stored."},
    {"splice_packed", py_splice_packed, METH_VARARGS,
     "splice_packed(head, packed, key_nibbles, delta_nibbles, exclude) -> (bytes, entries): "
     "GroupSnapshot.frame of a packed group (exclude -1: nobody)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "posecast.protocol._speedups",
    "Compiled accelerator of the compact pose codec (see protocol/_accel.py).", -1, methods,
};

PyMODINIT_FUNC PyInit__speedups(void) {
    crc_init();
    sources_init();
    ROT_SCALE = sqrt(2.0) * M;
    if (stored_init() < 0) return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m == NULL) return NULL;
    /* The constants compiled in; protocol/_accel.py refuses the module if they differ. */
    if (PyModule_AddObject(m, "__all__",
                           Py_BuildValue("[sssssssss]", "decode_update", "decode_update_rows",
                                         "delta_blocks", "eg_pack", "encode_group",
                                         "encode_stored", "splice",
                                         "splice_packed", "update_records")) < 0 ||
        PyModule_AddStringConstant(m, "SOURCE_HASH", SOURCE_HASH) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    if (PyModule_AddObject(m, "CONSTANTS",
                           Py_BuildValue("{s:i,s:i,s:i,s:i,s:i,s:i,s:i}", "MAX_EG_BITS", MAX_EG_BITS,
                                         "MAX_K", MAX_K, "SMALL_FRAME", SMALL_FRAME, "M", M,
                                         "ROTATION_BITS", ROTATION_BITS, "LIN_CODE_MAX",
                                         LIN_CODE_MAX, "ANG_CODE_MAX", ANG_CODE_MAX)) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
