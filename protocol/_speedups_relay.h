/* Part of _speedups.c: the relay's group encode of delta entries (codec_relay). */

/* bits.k_of_histogram */
static int k_of_histogram(const int64_t *hist) {
    int64_t n = 0, below = 0;
    for (int b = 0; b < HIST; b++) n += hist[b];
    int k = 0;
    while (k < MAX_K) {
        below += hist[k];
        if (below - (n - below - hist[k + 1]) >= 0) break;
        k++;
    }
    return k;
}

typedef struct {
    int64_t user, stream, off;
    int64_t row[MAX_WIDTH], base[MAX_WIDTH];
} Entry;

/* One entry (user, stream, capture, codes, baseline) as C values; -1: take the pure path. */
static int entry_of(PyObject *e, int width, double base_time, Entry *out) {
    if (!PyTuple_Check(e) || PyTuple_GET_SIZE(e) != 5) return -1;
    out->user = PyLong_AsLongLong(PyTuple_GET_ITEM(e, 0));
    out->stream = PyLong_AsLongLong(PyTuple_GET_ITEM(e, 1));
    double t = PyFloat_AsDouble(PyTuple_GET_ITEM(e, 2));
    if (PyErr_Occurred()) return -1;
    if (out->user < 0 || out->user > ID_MAX || out->stream < 0 || out->stream > ID_MAX) return -1;
    /* codec_relay._offsets */
    if (!(t == t && fabs(t) < 1e12)) return -1;
    double o = nearbyint((base_time - t) * 1000.0);
    if (!(fabs(o) < (double)TIME_MS_LIMIT)) return -1;
    out->off = (int64_t)o;
    for (int which = 0; which < 2; which++) {
        PyObject *row = PyTuple_GET_ITEM(e, 3 + which);
        int64_t *dst = which ? out->base : out->row;
        if (!PyList_Check(row) || PyList_GET_SIZE(row) != width) return -1;
        for (int j = 0; j < width; j++) {
            int overflow;
            long long v = PyLong_AsLongLongAndOverflow(PyList_GET_ITEM(row, j), &overflow);
            if (overflow || (v == -1 && PyErr_Occurred())) return -1;
            /* Codes are small; the pure path handles anything else. */
            if (v < INT32_MIN || v > INT32_MAX) return -1;
            dst[j] = v;
        }
        if (dst[0] < 0 || dst[0] > 3) return -1;
    }
    return 0;
}

/* The values a user's block codes and their class (0 for the user's first entry),
 * as _delta_values: ug (not for the first), sg, time code, idx step, differences. */
typedef struct {
    uint64_t v[4 + MAX_WIDTH - 1];
    int n, cls;
} Coded;

static int code_entry(const Entry *e, const Entry *prev, int width, Coded *c,
                      int64_t (*hists)[2][HIST]) {
    const int64_t *r = e->row, *b = e->base;
    int64_t p[3];
    c->cls = prev != NULL;
    c->n = 0;
    if (prev) {
        c->v[c->n++] = 0;
        c->v[c->n++] = (uint64_t)(e->stream - prev->stream - 1);
        c->v[c->n++] = zz(e->off - prev->off);
    } else {
        c->v[c->n++] = (uint64_t)e->stream;
        c->v[c->n++] = zz(e->off);
    }
    c->v[c->n++] = (uint64_t)((r[0] - b[0]) & 3);
    if (r[0] == b[0])
        p[0] = b[1], p[1] = b[2], p[2] = b[3];
    else
        predict_row(b, (int)r[0], p);
    for (int j = 1; j < width; j++) {
        uint64_t z = zz(r[j] - (j < 4 ? p[j - 1] : b[j]));
        int bl = bit_length(z);
        if (bl >= HIST) return -1;
        hists[(j - 1) / 3][c->cls][bl]++;
        c->v[c->n++] = z;
    }
    return 0;
}

static uint32_t entry_check(const Entry *e, int width) {
    unsigned char packed[4 + 4 * MAX_WIDTH];
    packed[0] = e->user & 0xFF, packed[1] = (e->user >> 8) & 0xFF;
    packed[2] = e->stream & 0xFF, packed[3] = (e->stream >> 8) & 0xFF;
    for (int j = 0; j < width; j++) put_le32(packed + 4 + 4 * j, e->base[j]);
    return crc_update(0, packed, 4 + 4 * (size_t)width);
}

static PyObject *delta_result(const Entry *es, const Coded *cs, Py_ssize_t n, int width,
                              int64_t (*hists)[2][HIST], int kt) {
    int ks[4][2], groups = (width - 1) / 3;
    PyObject *nib = PyList_New(1 + 2 * groups), *blocks = PyList_New(0);
    if (nib == NULL || blocks == NULL) goto fail;
    PyList_SET_ITEM(nib, 0, PyLong_FromLong(kt));
    for (int g = 0; g < groups; g++)
        for (int cls = 0; cls < 2; cls++) {
            ks[g][cls] = k_of_histogram(hists[g][cls]);
            PyList_SET_ITEM(nib, 1 + 2 * g + cls, PyLong_FromLong(ks[g][cls]));
        }
    Writer w = {NULL, 0, 0};
    for (Py_ssize_t i = 0; i < n;) {
        Py_ssize_t j = i;
        uint32_t check = 0;
        if (w.buf) memset(w.buf, 0, w.cap);
        w.pos = 0;
        for (; j < n && es[j].user == es[i].user; j++) {
            const Coded *c = &cs[j];
            int head = c->cls ? 4 : 3; /* values before the differences */
            for (int f = 0; f < c->n; f++) {
                int k = f < head ? (!c->cls && f == 1 ? kt : 0) : ks[(f - head) / 3][c->cls];
                if (writer_eg(&w, c->v[f], k) < 0) {
                    PyMem_Free(w.buf);
                    goto fail;
                }
            }
            check ^= entry_check(&es[j], width);
        }
        PyObject *bits = writer_int(&w);
        PyObject *t = bits ? Py_BuildValue("(LnNnk)", (long long)es[i].user, j - i, bits, w.pos,
                                           (unsigned long)check)
                           : NULL;
        if (t == NULL || PyList_Append(blocks, t) < 0) {
            Py_XDECREF(t);
            PyMem_Free(w.buf);
            goto fail;
        }
        Py_DECREF(t);
        i = j;
    }
    PyMem_Free(w.buf);
    return Py_BuildValue("(NN)", blocks, nib);
fail:
    Py_XDECREF(nib);
    Py_XDECREF(blocks);
    return NULL;
}

static PyObject *py_delta_blocks(PyObject *self, PyObject *args) {
    PyObject *entries;
    double base_time;
    int velocity;
    if (!PyArg_ParseTuple(args, "O!dp", &PyList_Type, &entries, &base_time, &velocity))
        return NULL;
    Py_ssize_t n = PyList_GET_SIZE(entries);
    int width = velocity ? 13 : 7;
    if (n == 0) return Py_BuildValue("([][])");
    Entry *es = PyMem_Calloc(n, sizeof(Entry));
    Coded *cs = PyMem_Calloc(n, sizeof(Coded));
    int64_t hists[4][2][HIST];
    int64_t first_hist[HIST];
    PyObject *result = NULL;
    if (es == NULL || cs == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    memset(hists, 0, sizeof(hists));
    memset(first_hist, 0, sizeof(first_hist));
    for (Py_ssize_t i = 0; i < n; i++) {
        if (entry_of(PyList_GET_ITEM(entries, i), width, base_time, &es[i]) < 0) goto none;
        const Entry *prev = i && es[i - 1].user == es[i].user ? &es[i - 1] : NULL;
        if (prev && es[i].stream <= prev->stream) goto none; /* not sorted: pure path */
        if (i && !prev && es[i].user < es[i - 1].user) goto none;
        if (code_entry(&es[i], prev, width, &cs[i], hists) < 0) goto none;
        if (!prev) {
            int bl = bit_length(cs[i].v[1]);
            if (bl >= HIST) goto none;
            first_hist[bl]++;
        }
    }
    result = delta_result(es, cs, n, width, hists, k_of_histogram(first_hist));
    goto done;
none:
    PyErr_Clear();
    result = Py_NewRef(Py_None);
done:
    PyMem_Free(es);
    PyMem_Free(cs);
    return result;
}

/* ------------------------------------------------------------------ splicing */

static int put_uvarint(unsigned char *p, uint64_t v) {
    int n = 0;
    while (v >= 0x80) p[n++] = (unsigned char)((v & 0x7F) | 0x80), v >>= 7;
    p[n++] = (unsigned char)v;
    return n;
}

/* One section's blocks (_Block tuples) but ``exclude``'s, each after its user gap (EG 0). */
static int splice_section(Writer *w, PyObject *blocks, long long exclude, Py_ssize_t *n,
                          uint32_t *check) {
    long long prev = 0;
    for (Py_ssize_t i = 0; i < PyList_GET_SIZE(blocks); i++) {
        PyObject *b = PyList_GET_ITEM(blocks, i);
        if (!PyTuple_Check(b) || PyTuple_GET_SIZE(b) != 5) {
            PyErr_SetString(PyExc_TypeError, "blocks: (user, n, bits, nbits, check)");
            return -1;
        }
        long long user = PyLong_AsLongLong(PyTuple_GET_ITEM(b, 0));
        Py_ssize_t count = PyLong_AsSsize_t(PyTuple_GET_ITEM(b, 1));
        Py_ssize_t nbits = PyLong_AsSsize_t(PyTuple_GET_ITEM(b, 3));
        unsigned long c = PyLong_AsUnsignedLong(PyTuple_GET_ITEM(b, 4));
        if (PyErr_Occurred()) return -1;
        if (user == exclude) continue;
        if (user < prev) {
            PyErr_SetString(PyExc_ValueError, "blocks out of user order");
            return -1;
        }
        if (writer_eg(w, (uint64_t)(user - prev), 0) < 0 ||
            writer_put_int(w, PyTuple_GET_ITEM(b, 2), nbits) < 0)
            return -1;
        *n += count;
        *check ^= (uint32_t)c;
        prev = user;
    }
    return 0;
}

static int nibbles_of(PyObject *list, int *out, int at) {
    for (Py_ssize_t i = 0; i < PyList_GET_SIZE(list) && at < 16; i++) {
        long v = PyLong_AsLong(PyList_GET_ITEM(list, i));
        if (v < 0 || v > 15) {
            if (!PyErr_Occurred()) PyErr_SetString(PyExc_ValueError, "an order over 15");
            return -1;
        }
        out[at++] = (int)v;
    }
    return at;
}

static PyObject *py_splice(PyObject *self, PyObject *args) {
    Py_buffer head;
    PyObject *key, *delta, *knib, *dnib, *result = NULL;
    long long exclude;
    if (!PyArg_ParseTuple(args, "y*O!O!O!O!L", &head, &PyList_Type, &key, &PyList_Type, &delta,
                          &PyList_Type, &knib, &PyList_Type, &dnib, &exclude))
        return NULL;
    Writer w = {NULL, 0, 0};
    Py_ssize_t nk = 0, nd = 0;
    uint32_t check = 0, unused = 0;
    if (splice_section(&w, key, exclude, &nk, &unused) < 0) goto done;
    Py_ssize_t key_bits = w.pos;
    if (splice_section(&w, delta, exclude, &nd, &check) < 0) goto done;
    (void)key_bits;
    if (nk + nd == 0) {
        result = Py_BuildValue("(yi)", "", 0);
        goto done;
    }
    int nib[16], count = 0;
    if (nk && (count = nibbles_of(knib, nib, count)) < 0) goto done;
    if (nd && (count = nibbles_of(dnib, nib, count)) < 0) goto done;
    if (count % 2) nib[count++] = 0;
    Py_ssize_t body = (w.pos + 7) / 8, size = head.len + 20 + 4 + count / 2 + body;
    PyObject *out = PyBytes_FromStringAndSize(NULL, size);
    if (out == NULL) goto done;
    unsigned char *p = (unsigned char *)PyBytes_AS_STRING(out), *start = p;
    memcpy(p, head.buf, head.len);
    p += head.len;
    p += put_uvarint(p, (uint64_t)nk);
    p += put_uvarint(p, (uint64_t)nd);
    if (nd) put_le32(p, (int64_t)check), p += 4;
    for (int i = 0; i < count; i += 2) *p++ = (unsigned char)(nib[i] << 4 | nib[i + 1]);
    if (body) memcpy(p, w.buf, body);
    p += body;
    if (_PyBytes_Resize(&out, p - start) < 0) goto done;
    result = Py_BuildValue("(Nn)", out, nk + nd);
done:
    PyMem_Free(w.buf);
    PyBuffer_Release(&head);
    return result;
}
