/* Part of _speedups.c: the relay's upstream update path (codec_fast, _compact). */

/* uvarint at *pos (codec_frame._read_uvarint); -1 if truncated or over 10 bytes or
 * over 2**63 (any frame that large is refused by the caller either way). */
static int read_uvarint(const unsigned char *data, Py_ssize_t size, Py_ssize_t *pos,
                        uint64_t *out) {
    uint64_t value = 0;
    for (int i = 0; i < 10; i++) {
        if (*pos + i >= size) return -1;
        unsigned byte = data[*pos + i];
        if (7 * i >= 63 && (byte & 0x7F)) return -1;
        value |= (uint64_t)(byte & 0x7F) << (7 * i);
        if (byte < 0x80) {
            *pos += i + 1;
            *out = value;
            return value >> 62 ? -1 : 0;
        }
    }
    return -1;
}

typedef struct {
    int widths[3];
    int64_t top[3];
    int64_t key_bits, delta_bits;
} UpdateGeometry;

/* Streams and ms offsets of a section (codec_fast._update_ids). */
static int update_ids(Reader *r, int n, int k, int64_t *streams, int64_t *off) {
    uint64_t sg[SMALL_FRAME], same[SMALL_FRAME], z;
    if (read_eg_column(r, n, 0, sg) < 0 || read_eg_column(r, 1, k, &z) < 0 ||
        read_eg_column(r, n - 1, 0, same) < 0)
        return -1;
    int64_t s = (int64_t)sg[0], o = unzz(z);
    if (sg[0] > ID_MAX || o >= TIME_MS_LIMIT || -o >= TIME_MS_LIMIT) return -1;
    streams[0] = s, off[0] = o;
    for (int i = 1; i < n; i++) {
        int64_t step = unzz(same[i - 1]);
        if (sg[i] > ID_MAX || step >= TIME_MS_LIMIT || -step >= TIME_MS_LIMIT) return -1;
        s += (int64_t)sg[i] + 1;
        o += step;
        if (s > ID_MAX || o >= TIME_MS_LIMIT || -o >= TIME_MS_LIMIT) return -1;
        streams[i] = s, off[i] = o;
    }
    return 0;
}

/* Add one zigzag Exp-Golomb column of order k to column c of the rows listed. */
static int add_column(Reader *r, int64_t (*rows)[MAX_WIDTH], const int *which, int n, int c,
                      int k) {
    uint64_t z[SMALL_FRAME];
    if (read_eg_column(r, n, k, z) < 0) return -1;
    for (int i = 0; i < n; i++) rows[which[i]][c] += unzz(z[i]);
    return 0;
}

/* The rows of a key section after its ids (codec_fast._update_keys). */
static int update_keys(Reader *r, int n, int width, const int *nib, const UpdateGeometry *g,
                       int64_t (*rows)[MAX_WIDTH]) {
    if (read_fixed(r, n, 2, &rows[0][0], MAX_WIDTH) < 0) return -1;
    for (int j = 1; j < 4; j++) {
        if (read_fixed(r, n, ROTATION_BITS, &rows[0][j], MAX_WIDTH) < 0) return -1;
        for (int i = 0; i < n; i++) rows[i][j] -= M;
    }
    for (int j = 0; j < 3; j++)
        if (read_fixed(r, n, g->widths[j], &rows[0][4 + j], MAX_WIDTH) < 0) return -1;
    if (width == 13) {
        int all[SMALL_FRAME];
        for (int i = 0; i < n; i++) {
            all[i] = i;
            for (int c = 7; c < 13; c++) rows[i][c] = 0;
        }
        for (int c = 7; c < 13; c++)
            if (add_column(r, rows, all, n, c, nib[c < 10 ? 1 : 2]) < 0) return -1;
    }
    return 0;
}

/* The rows of a delta section after its ids (codec_fast._update_deltas). */
static int update_deltas(Reader *r, int n, int width, const int *nib, const int64_t *streams,
                         int64_t (*base)[MAX_WIDTH], int split, int64_t (*out)[MAX_WIDTH]) {
    uint64_t steps[SMALL_FRAME];
    if (read_eg_column(r, n, 0, steps) < 0) return -1;
    for (int i = 0; i < n; i++) {
        int64_t *b = base[i], *row = out[i];
        int idx = (int)((b[0] + (int64_t)steps[i]) & 3);
        memcpy(row, b, sizeof(int64_t) * MAX_WIDTH);
        if (idx != b[0]) {
            row[0] = idx;
            predict_row(b, idx, row + 1);
        }
    }
    /* Class 1: every stream but stream 0, when the frame splits classes. */
    int cls[2][SMALL_FRAME], count[2] = {0, 0};
    for (int i = 0; i < n; i++) {
        int want = split && streams[i] != 0;
        cls[want][count[want]++] = i;
    }
    for (int at = 0, lo = 1; lo < width; at++, lo += 3)
        for (int c = lo; c < lo + 3; c++)
            for (int want = 0; want < 2; want++)
                if (count[want] &&
                    add_column(r, out, cls[want], count[want], c, nib[1 + 2 * at + want]) < 0)
                    return -1;
    return 0;
}

/* codec_fast._rows_valid */
static int rows_valid(int64_t (*rows)[MAX_WIDTH], int n, int width, const UpdateGeometry *g) {
    const int64_t lim = 2 * (int64_t)M * M;
    for (int i = 0; i < n; i++) {
        const int64_t *r = rows[i];
        int64_t a = r[1], b = r[2], c = r[3];
        if (!(-M <= a && a <= M && -M <= b && b <= M && -M <= c && c <= M &&
              a * a + b * b + c * c <= lim))
            return 0;
        for (int j = 0; j < 3; j++)
            if (!(0 <= r[4 + j] && r[4 + j] <= g->top[j])) return 0;
        if (width == 13)
            for (int j = 0; j < 3; j++)
                if (llabs(r[7 + j]) > LIN_CODE_MAX || llabs(r[10 + j]) > ANG_CODE_MAX) return 0;
    }
    return 1;
}

/* Baseline rows of the delta streams, as the CRC the frame states; -1 if missing, of
 * another width or not int32 (the pure path returns None likewise). */
static int baselines_of(PyObject *baselines, const int64_t *streams, int n, int width,
                        int64_t (*base)[MAX_WIDTH], uint32_t *crc) {
    unsigned char packed[4 * MAX_WIDTH];
    *crc = 0;
    for (int i = 0; i < n; i++) {
        PyObject *key = PyLong_FromLongLong(streams[i]);
        if (key == NULL) return -2;
        PyObject *row = PyDict_GetItemWithError(baselines, key);
        Py_DECREF(key);
        if (row == NULL) return PyErr_Occurred() ? -2 : -1;
        if (!PyList_Check(row) || PyList_GET_SIZE(row) != width) return -1;
        for (int j = 0; j < width; j++) {
            int overflow;
            long long v = PyLong_AsLongLongAndOverflow(PyList_GET_ITEM(row, j), &overflow);
            if (overflow || (v == -1 && PyErr_Occurred())) {
                PyErr_Clear();
                return -1;
            }
            if (v < INT32_MIN || v > INT32_MAX) return -1;
            base[i][j] = v;
            put_le32(packed + 4 * j, v);
        }
        *crc = crc_update(*crc, packed, 4 * (size_t)width);
    }
    return 0;
}

static PyObject *int_list(const int64_t *v, int n, int stride) {
    PyObject *out = PyList_New(n);
    if (out == NULL) return NULL;
    for (int i = 0; i < n; i++) {
        PyObject *x = PyLong_FromLongLong(v[i * stride]);
        if (x == NULL) {
            Py_DECREF(out);
            return NULL;
        }
        PyList_SET_ITEM(out, i, x);
    }
    return out;
}

/* The header after the base time (codec_fast._update_header); -1: not this path's.
 * nib holds up to 12 orders (key 1 + 2, delta 5 + 4 with velocities). */
static int update_header(const unsigned char *data, Py_ssize_t size, Py_ssize_t *pos, int velocity,
                         int *nk, int *nd, int64_t *check, int *nib) {
    uint64_t k, d;
    if (read_uvarint(data, size, pos, &k) < 0 || read_uvarint(data, size, pos, &d) < 0) return -1;
    if (k + d == 0 || k + d > SMALL_FRAME) return -1;
    *nk = (int)k, *nd = (int)d, *check = -1;
    if (d) {
        if (*pos + 2 > size) return -1;
        *check = data[*pos] | data[*pos + 1] << 8;
        *pos += 2;
    }
    int n_nib = (k ? 1 + (velocity ? 2 : 0) : 0) + (d ? 5 + (velocity ? 4 : 0) : 0);
    Py_ssize_t end = *pos + (n_nib + 1) / 2;
    if (end > size) return -1;
    for (int i = 0; i < n_nib; i++) {
        unsigned byte = data[*pos + i / 2];
        nib[i] = i % 2 ? byte & 0x0F : byte >> 4;
    }
    if (n_nib % 2 && (data[end - 1] & 0x0F)) return -1;
    *pos = end;
    return 0;
}

/* A decoded update's rows; order[]: the rows in ascending stream order. */
typedef struct {
    int n, width;
    int64_t streams[2 * SMALL_FRAME], off[2 * SMALL_FRAME];
    int64_t rows[2 * SMALL_FRAME][MAX_WIDTH];
    int order[2 * SMALL_FRAME];
} Decoded;

/* codec_fast.decode_update_rows of the frame whose header up to the base time ends at
 * pos: 1 decoded, 0 not this path's (the caller returns None), -1 a Python error. */
static int decode_rows(const unsigned char *data, Py_ssize_t size, Py_ssize_t pos, int flags,
                       const UpdateGeometry *g, PyObject *baselines, Decoded *d) {
    int velocity = (flags & F_VELOCITY) != 0, width = velocity ? 13 : 7;
    int nk, nd, nib[12]; /* key 1 + 2, delta 5 + 4 with velocities */
    int64_t check;
    int64_t base[SMALL_FRAME][MAX_WIDTH];
    memset(base, 0, sizeof(base));
    d->width = width;
    if (pos < 0 || pos > size || update_header(data, size, &pos, velocity, &nk, &nd, &check, nib) < 0 ||
        nk * g->key_bits + nd * g->delta_bits > 8 * (int64_t)(size - pos))
        return 0;
    Reader r = {data + pos, 8 * (size - pos), 0};
    const int *dnib = nib;
    if (nk) {
        if (update_ids(&r, nk, nib[0], d->streams, d->off) < 0 ||
            update_keys(&r, nk, width, nib, g, d->rows) < 0)
            return 0;
        dnib = nib + 1 + (velocity ? 2 : 0);
    }
    if (nd) {
        uint32_t crc;
        if (update_ids(&r, nd, dnib[0], d->streams + nk, d->off + nk) < 0) return 0;
        int got = baselines_of(baselines, d->streams + nk, nd, width, base, &crc);
        if (got == -2) return -1;
        if (got < 0 || (int64_t)(crc & 0xFFFF) != check) return 0;
        if (update_deltas(&r, nd, width, dnib, d->streams + nk, base, flags & F_SPLIT,
                          d->rows + nk) < 0)
            return 0;
    }
    Py_ssize_t rest = r.size - r.pos;
    if (rest >= 8 || (rest && bits_at(&r, r.pos, (int)rest))) return 0;
    int n = d->n = nk + nd;
    if (!rows_valid(d->rows, n, width, g)) return 0;
    int *order = d->order;
    for (int i = 0; i < n; i++) order[i] = i;
    if (nk && nd) /* stable insertion sort by stream, as sorted() */
        for (int i = 1; i < n; i++)
            for (int j = i; j > 0 && d->streams[order[j - 1]] > d->streams[order[j]]; j--) {
                int t = order[j];
                order[j] = order[j - 1], order[j - 1] = t;
            }
    for (int i = 1; i < n; i++)
        for (int j = 0; j < i; j++)
            if (d->streams[order[i]] == d->streams[order[j]]) return 0;
    return 1;
}

static int parse_geometry(PyObject *t, UpdateGeometry *g, int velocity) {
    long long v[10];
    if (!PyTuple_Check(t) || PyTuple_GET_SIZE(t) != 10) return -1;
    for (int i = 0; i < 10; i++) {
        v[i] = PyLong_AsLongLong(PyTuple_GET_ITEM(t, i));
        if (v[i] == -1 && PyErr_Occurred()) return -1;
    }
    for (int j = 0; j < 3; j++) {
        /* A field wider than a Reader reads is not a volume's (Volume.bits <= 32). */
        if (v[j] < 0 || v[j] > 32) return -1;
        g->widths[j] = (int)v[j], g->top[j] = v[3 + j];
    }
    g->key_bits = v[6 + velocity];
    g->delta_bits = v[8 + velocity];
    return 0;
}

static int geometry_of(PyObject *t, UpdateGeometry *g, int velocity) {
    if (parse_geometry(t, g, velocity) == 0) return 0;
    if (!PyErr_Occurred()) PyErr_SetString(PyExc_TypeError, "geometry: a tuple of 10 ints");
    return -1;
}

static PyObject *py_decode_update_rows(PyObject *self, PyObject *args) {
    Py_buffer view;
    Py_ssize_t pos;
    int flags;
    PyObject *geometry, *baselines, *result = NULL;
    if (!PyArg_ParseTuple(args, "y*niOO!", &view, &pos, &flags, &geometry, &PyDict_Type,
                          &baselines))
        return NULL;
    UpdateGeometry g;
    Decoded d;
    int got = geometry_of(geometry, &g, (flags & F_VELOCITY) != 0) < 0
                  ? -1
                  : decode_rows(view.buf, view.len, pos, flags, &g, baselines, &d);
    if (got == 0) result = Py_NewRef(Py_None);
    if (got <= 0) goto done;
    PyObject *s = PyList_New(d.n), *o = PyList_New(d.n), *rs = PyList_New(d.n);
    if (s == NULL || o == NULL || rs == NULL) goto fail;
    for (int i = 0; i < d.n; i++) {
        int at = d.order[i];
        PyObject *a = PyLong_FromLongLong(d.streams[at]), *b = PyLong_FromLongLong(d.off[at]);
        PyObject *row = int_list(d.rows[at], d.width, 1);
        PyList_SET_ITEM(s, i, a);
        PyList_SET_ITEM(o, i, b);
        PyList_SET_ITEM(rs, i, row);
        if (a == NULL || b == NULL || row == NULL) goto fail;
    }
    result = Py_BuildValue("(NNN)", s, o, rs);
    goto done;
fail:
    Py_XDECREF(s);
    Py_XDECREF(o);
    Py_XDECREF(rs);
done:
    PyBuffer_Release(&view);
    return result;
}

/* ------------------------------------------------------------------ update records */

static double ROT_SCALE; /* math.sqrt(2.0) * M, set at import */
#define LIN_STEP (1.0 / 512.0)
#define ANG_STEP (1.0 / 256.0)

static int row_of(PyObject *row, int64_t *out, int width) {
    if (!PyList_Check(row) || PyList_GET_SIZE(row) != width) return -1;
    for (int j = 0; j < width; j++) {
        out[j] = PyLong_AsLongLong(PyList_GET_ITEM(row, j));
        if (out[j] == -1 && PyErr_Occurred()) return -1;
    }
    return (out[0] < 0 || out[0] > 3) ? -1 : 0;
}

/* One record: u16 stream, f32 time, 7 f32 pose [, 6 f16 velocity] (little-endian), from
 * codec_quant.dequantise_row / velocity_row's arithmetic and struct's rounding. */
static int pack_record(unsigned char *p, int64_t stream, double t, const int64_t *r, int width,
                       const double *lo, const double *step) {
    double x = (double)r[1] / ROT_SCALE, y = (double)r[2] / ROT_SCALE, z = (double)r[3] / ROT_SCALE;
    double q[4] = {0.0, 0.0, 0.0, 0.0}, v = 1.0 - ((x * x + z * z) + y * y);
    q[r[0]] = sqrt(v > 0.0 ? v : 0.0);
    const int *o = OTHERS[r[0]];
    q[o[0]] = x, q[o[1]] = y, q[o[2]] = z;
    double pose[7] = {lo[0] + (double)r[4] * step[0], lo[1] + (double)r[5] * step[1],
                      lo[2] + (double)r[6] * step[2], q[0], q[1], q[2], q[3]};
    p[0] = stream & 0xFF, p[1] = (stream >> 8) & 0xFF;
    if (PyFloat_Pack4(t, (char *)p + 2, 1) < 0) return -1;
    for (int j = 0; j < 7; j++)
        if (PyFloat_Pack4(pose[j], (char *)p + 6 + 4 * j, 1) < 0) return -1;
    if (width == 13)
        for (int j = 0; j < 6; j++)
            if (PyFloat_Pack2((double)r[7 + j] * (j < 3 ? LIN_STEP : ANG_STEP),
                              (char *)p + 34 + 2 * j, 1) < 0)
                return -1;
    return 0;
}

static PyObject *py_update_records(PyObject *self, PyObject *args) {
    long long base_us;
    PyObject *streams, *offsets, *rows;
    double lo[3], step[3];
    if (!PyArg_ParseTuple(args, "LO!O!O!(ddd)(ddd)", &base_us, &PyList_Type, &streams,
                          &PyList_Type, &offsets, &PyList_Type, &rows, &lo[0], &lo[1], &lo[2],
                          &step[0], &step[1], &step[2]))
        return NULL;
    Py_ssize_t n = PyList_GET_SIZE(rows);
    if (n == 0 || PyList_GET_SIZE(streams) != n || PyList_GET_SIZE(offsets) != n) {
        PyErr_SetString(PyExc_ValueError, "streams, offsets and rows of one length, not 0");
        return NULL;
    }
    int width = (int)PyList_GET_SIZE(PyList_GET_ITEM(rows, 0));
    if (width != 7 && width != 13) {
        PyErr_SetString(PyExc_ValueError, "rows of 7 or 13 codes");
        return NULL;
    }
    int record = width == 13 ? 46 : 34;
    PyObject *out = PyBytes_FromStringAndSize(NULL, n * record);
    if (out == NULL) return NULL;
    unsigned char *p = (unsigned char *)PyBytes_AS_STRING(out);
    double base = (double)base_us / 1e6;
    for (Py_ssize_t i = 0; i < n; i++, p += record) {
        int64_t r[MAX_WIDTH];
        long long s = PyLong_AsLongLong(PyList_GET_ITEM(streams, i));
        double o = (double)PyLong_AsLongLong(PyList_GET_ITEM(offsets, i));
        if (PyErr_Occurred() || row_of(PyList_GET_ITEM(rows, i), r, width) < 0 || s < 0 ||
            s > ID_MAX || pack_record(p, s, (base - o / 1000.0) - base, r, width, lo, step) < 0) {
            if (!PyErr_Occurred()) PyErr_SetString(PyExc_ValueError, "not a decoded row");
            Py_DECREF(out);
            return NULL;
        }
    }
    return out;
}

/* ------------------------------------------------------------------ the whole upstream decode */

#define F_RELATIVE 8
#define UPDATE_FLAGS (1 | F_VELOCITY | F_SPLIT | F_RELATIVE)

/* (number, base us) of the previous update, a tuple of two ints; -1 if not. */
static int previous_of(PyObject *previous, int64_t *number, int64_t *base_us) {
    if (!PyTuple_Check(previous) || PyTuple_GET_SIZE(previous) != 2) return -1;
    int overflow;
    long long a = PyLong_AsLongLongAndOverflow(PyTuple_GET_ITEM(previous, 0), &overflow);
    if (overflow || (a == -1 && PyErr_Occurred())) return -1;
    long long b = PyLong_AsLongLongAndOverflow(PyTuple_GET_ITEM(previous, 1), &overflow);
    if (overflow || (b == -1 && PyErr_Occurred())) return -1;
    *number = a, *base_us = b;
    return 0;
}

/* The header fields of _compact.UpstreamDecoder._decode_fast: number, base us and the
 * offset after them; 0 if not this path's (relative with no previous, out of range). */
static int update_fields(const unsigned char *data, Py_ssize_t size, PyObject *previous,
                         int64_t *number, int64_t *base_us, Py_ssize_t *pos) {
    if (size < 4 || data[0] != 0xC1) return 0;
    int flags = data[1];
    if ((flags & 0xF0) != 0x10 || (flags & 0x0F & ~UPDATE_FLAGS) || !(flags & 1)) return 0;
    uint64_t d, z;
    *pos = 2;
    /* read_uvarint refuses values of 2**62 and more: the reference path decides those. */
    if (read_uvarint(data, size, pos, &d) < 0 || read_uvarint(data, size, pos, &z) < 0) return 0;
    if (flags & F_RELATIVE) {
        int64_t n0, b0;
        if (previous == Py_None) return 0;
        if (previous_of(previous, &n0, &b0) < 0) {
            PyErr_Clear();
            return 0;
        }
        if (__builtin_add_overflow(n0, unzz(d), number) ||
            __builtin_add_overflow(b0, unzz(z), base_us))
            return 0;
    } else {
        *number = (int64_t)d, *base_us = unzz(z);
    }
    /* 0 <= number < 2**63 holds for any int64 >= 0 */
    if (*number < 0 || *base_us >= (INT64_C(1) << 62) || -*base_us >= (INT64_C(1) << 62)) return 0;
    return 1;
}

/* The PoseUpdate records of decoded rows (_compact._update_of_rows), in stream order. */
static PyObject *decoded_records(const Decoded *d, int64_t base_us, const double *lo,
                                 const double *step) {
    int record = d->width == 13 ? 46 : 34;
    PyObject *out = PyBytes_FromStringAndSize(NULL, (Py_ssize_t)d->n * record);
    if (out == NULL) return NULL;
    unsigned char *p = (unsigned char *)PyBytes_AS_STRING(out);
    double base = (double)base_us / 1e6;
    for (int i = 0; i < d->n; i++, p += record) {
        int at = d->order[i];
        double o = (double)d->off[at];
        if (pack_record(p, d->streams[at], (base - o / 1000.0) - base, d->rows[at], d->width, lo,
                        step) < 0) {
            Py_DECREF(out);
            return NULL;
        }
    }
    return out;
}

/* {stream: codes} of decoded rows, in stream order. */
static PyObject *decoded_codes(const Decoded *d) {
    PyObject *codes = PyDict_New();
    if (codes == NULL) return NULL;
    for (int i = 0; i < d->n; i++) {
        int at = d->order[i];
        PyObject *key = PyLong_FromLongLong(d->streams[at]);
        PyObject *row = int_list(d->rows[at], d->width, 1);
        int bad = key == NULL || row == NULL || PyDict_SetItem(codes, key, row) < 0;
        Py_XDECREF(key);
        Py_XDECREF(row);
        if (bad) {
            Py_DECREF(codes);
            return NULL;
        }
    }
    return codes;
}

static PyObject *py_decode_update(PyObject *self, PyObject *args) {
    Py_buffer view;
    PyObject *previous, *geometry, *baselines, *result = NULL;
    double lo[3], step[3];
    if (!PyArg_ParseTuple(args, "y*OOO!(ddd)(ddd)", &view, &previous, &geometry, &PyDict_Type,
                          &baselines, &lo[0], &lo[1], &lo[2], &step[0], &step[1], &step[2]))
        return NULL;
    const unsigned char *data = view.buf;
    int64_t number, base_us;
    Py_ssize_t pos;
    UpdateGeometry g;
    Decoded d;
    int got = update_fields(data, view.len, previous, &number, &base_us, &pos);
    if (got == 1)
        got = geometry_of(geometry, &g, (data[1] & F_VELOCITY) != 0) < 0
                  ? -1
                  : decode_rows(data, view.len, pos, data[1], &g, baselines, &d);
    if (got == 0) result = Py_NewRef(Py_None);
    if (got <= 0) goto done;
    PyObject *records = decoded_records(&d, base_us, lo, step);
    PyObject *codes = records ? decoded_codes(&d) : NULL;
    /* The baselines change only once nothing can fail but the update itself. */
    if (codes == NULL || PyDict_Update(baselines, codes) < 0) {
        Py_XDECREF(records);
        Py_XDECREF(codes);
        goto done;
    }
    result = Py_BuildValue("(LLNN)", (long long)number, (long long)base_us, records, codes);
done:
    PyBuffer_Release(&view);
    return result;
}
