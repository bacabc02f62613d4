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
    int key; /* no baseline: an absolute entry */
} Entry;

/* One entry (user, stream, capture, codes, baseline) as C values; -1: take the pure path.
 * A baseline of None makes a key entry where ``keys`` allows it. Rows are lists of
 * exactly ``width`` codes, or (``longer``) of at least that many, the first ones read. */
static int entry_fill(PyObject *user, PyObject *stream, PyObject *capture, PyObject *row_obj,
                      PyObject *base_obj, int width, double base_time, int keys, int longer,
                      Entry *out) {
    out->key = base_obj == Py_None;
    if (out->key && !keys) return -1;
    out->user = PyLong_AsLongLong(user);
    out->stream = PyLong_AsLongLong(stream);
    double t = PyFloat_AsDouble(capture);
    if (PyErr_Occurred()) return -1;
    if (out->user < 0 || out->user > ID_MAX || out->stream < 0 || out->stream > ID_MAX) return -1;
    /* codec_relay._offsets */
    if (!(t == t && fabs(t) < 1e12)) return -1;
    double o = nearbyint((base_time - t) * 1000.0);
    if (!(fabs(o) < (double)TIME_MS_LIMIT)) return -1;
    out->off = (int64_t)o;
    for (int which = 0; which < 2 - out->key; which++) {
        PyObject *row = which ? base_obj : row_obj;
        int64_t *dst = which ? out->base : out->row;
        if (!PyList_Check(row)) return -1;
        Py_ssize_t size = PyList_GET_SIZE(row);
        if (longer ? size < width : size != width) return -1;
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

static int entry_parse(PyObject *e, int width, double base_time, int keys, Entry *out) {
    if (!PyTuple_Check(e) || PyTuple_GET_SIZE(e) != 5) return -1;
    return entry_fill(PyTuple_GET_ITEM(e, 0), PyTuple_GET_ITEM(e, 1), PyTuple_GET_ITEM(e, 2),
                      PyTuple_GET_ITEM(e, 3), PyTuple_GET_ITEM(e, 4), width, base_time, keys, 0,
                      out);
}

static int entry_of(PyObject *e, int width, double base_time, Entry *out) {
    return entry_parse(e, width, base_time, 0, out);
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

/* A snapshot frame of ``nk`` key and ``nd`` delta entries whose bits are in ``w``:
 * ``head``, the two counts, the delta section's check, the order nibbles of the
 * sections present, the bits. Returns (bytes, nk + nd); NULL with an exception set. */
static PyObject *frame_of(const Py_buffer *head, Py_ssize_t nk, Py_ssize_t nd, uint32_t check,
                          PyObject *knib, PyObject *dnib, const Writer *w) {
    int nib[16], count = 0;
    if (nk && (count = nibbles_of(knib, nib, count)) < 0) return NULL;
    if (nd && (count = nibbles_of(dnib, nib, count)) < 0) return NULL;
    if (count % 2) nib[count++] = 0;
    Py_ssize_t body = (w->pos + 7) / 8, size = head->len + 20 + 4 + count / 2 + body;
    PyObject *out = PyBytes_FromStringAndSize(NULL, size);
    if (out == NULL) return NULL;
    unsigned char *p = (unsigned char *)PyBytes_AS_STRING(out), *start = p;
    memcpy(p, head->buf, head->len);
    p += head->len;
    p += put_uvarint(p, (uint64_t)nk);
    p += put_uvarint(p, (uint64_t)nd);
    if (nd) put_le32(p, (int64_t)check), p += 4;
    for (int i = 0; i < count; i += 2) *p++ = (unsigned char)(nib[i] << 4 | nib[i + 1]);
    if (body) memcpy(p, w->buf, body);
    p += body;
    if (_PyBytes_Resize(&out, p - start) < 0) return NULL;
    return Py_BuildValue("(Nn)", out, nk + nd);
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
    result = frame_of(&head, nk, nd, check, knib, dnib, &w);
done:
    PyMem_Free(w.buf);
    PyBuffer_Release(&head);
    return result;
}

/* ------------------------------------------------------------------ the whole group encode */

/* A group's blocks, packed for splicing (codec_relay.encode_group with the
 * accelerator): a count, then one record per block, then the blocks' bits, each
 * block starting on a byte. Only this module reads it (splice_packed checks it). */
typedef struct {
    int32_t user, n, section;
    uint32_t check;
    int64_t nbits, offset; /* offset: of the block's first byte in the data */
} PackedBlock;

typedef struct {
    PackedBlock *blocks;
    Py_ssize_t count, cap;
    Writer data;
} Packer;

static int append_int(PyObject *list, long v) {
    PyObject *x = PyLong_FromLong(v);
    int got = x == NULL ? -1 : PyList_Append(list, x);
    Py_XDECREF(x);
    return got;
}

static PackedBlock *packer_begin(Packer *p, int64_t user, int section) {
    if (p->count == p->cap) {
        Py_ssize_t cap = p->cap ? 2 * p->cap : 16;
        PackedBlock *b = PyMem_Realloc(p->blocks, cap * sizeof(PackedBlock));
        if (b == NULL) return NULL;
        p->blocks = b, p->cap = cap;
    }
    p->data.pos = (p->data.pos + 7) & ~(Py_ssize_t)7;
    PackedBlock *b = &p->blocks[p->count++];
    b->user = (int32_t)user, b->section = section, b->n = 0, b->check = 0;
    b->offset = p->data.pos / 8, b->nbits = 0;
    return b;
}

static void packer_end(Packer *p, PackedBlock *b) { b->nbits = p->data.pos - 8 * b->offset; }

typedef struct {
    int64_t user, stream;
    int at;
} SortKey;

static int sort_key_cmp(const void *a, const void *b) {
    const SortKey *x = a, *y = b;
    if (x->user != y->user) return x->user < y->user ? -1 : 1;
    if (x->stream != y->stream) return x->stream < y->stream ? -1 : 1;
    return 0;
}

/* The key section (codec_relay._key_blocks) of entries es[at[0..n)], sorted; 0 if a code
 * is out of range (the pure path decides), -1 on a Python error. */
static int key_section(Packer *p, const Entry *es, const int *at, int n, int velocity,
                       const int *bits, PyObject *nib) {
    int64_t first[HIST] = {0}, lin[HIST] = {0}, ang[HIST] = {0};
    for (int i = 0; i < n; i++) {
        const Entry *e = &es[at[i]];
        const int64_t *r = e->row;
        if (r[1] < -M || r[1] > M || r[2] < -M || r[2] > M || r[3] < -M || r[3] > M) return 0;
        for (int j = 0; j < 3; j++)
            if (r[4 + j] < 0 || r[4 + j] >= (INT64_C(1) << bits[j])) return 0;
        if (!i || es[at[i - 1]].user != e->user) first[bit_length(zz(e->off))]++;
        if (velocity)
            for (int c = 7; c < 13; c++) (c < 10 ? lin : ang)[bit_length(zz(r[c]))]++;
    }
    int kt = k_of_histogram(first), kv[2] = {0, 0};
    if (velocity) kv[0] = k_of_histogram(lin), kv[1] = k_of_histogram(ang);
    for (int i = 0; i < n;) {
        const Entry *head = &es[at[i]];
        PackedBlock *b = packer_begin(p, head->user, 0);
        if (b == NULL) return -1;
        Writer *w = &p->data;
        int j = i;
        for (; j < n && es[at[j]].user == head->user; j++) {
            const Entry *e = &es[at[j]], *prev = j > i ? &es[at[j - 1]] : NULL;
            const int64_t *r = e->row;
            int ok = (prev == NULL || writer_put(w, 1, 1) == 0) &&
                     writer_eg(w, (uint64_t)(prev ? e->stream - prev->stream - 1 : e->stream), 0) == 0 &&
                     writer_eg(w, zz(prev ? e->off - prev->off : e->off), prev ? 0 : kt) == 0 &&
                     writer_put(w, (uint64_t)r[0], 2) == 0;
            for (int c = 1; ok && c < 4; c++) ok = writer_put(w, (uint64_t)(r[c] + M), ROTATION_BITS) == 0;
            for (int c = 4; ok && c < 7; c++) ok = writer_put(w, (uint64_t)r[c], bits[c - 4]) == 0;
            for (int c = 7; ok && velocity && c < 13; c++)
                ok = writer_eg(w, zz(r[c]), kv[c < 10 ? 0 : 1]) == 0;
            if (!ok) return -1;
        }
        b->n = j - i;
        packer_end(p, b);
        i = j;
    }
    if (append_int(nib, kt) < 0) return -1;
    if (velocity)
        for (int g = 0; g < 2; g++)
            if (append_int(nib, kv[g]) < 0) return -1;
    return 1;
}

/* The delta section (codec_relay._delta_blocks) of entries es[at[0..n)], sorted; 0: take
 * the pure path, -1 on a Python error. */
static int delta_section(Packer *p, const Entry *es, const int *at, int n, int width,
                         PyObject *nib) {
    int64_t hists[4][2][HIST], first[HIST] = {0};
    int ks[4][2], groups = (width - 1) / 3;
    memset(hists, 0, sizeof(hists));
    Coded *cs = PyMem_Calloc(n, sizeof(Coded));
    if (cs == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    int got = 1;
    for (int i = 0; i < n && got == 1; i++) {
        const Entry *e = &es[at[i]];
        const Entry *prev = i && es[at[i - 1]].user == e->user ? &es[at[i - 1]] : NULL;
        if (code_entry(e, prev, width, &cs[i], hists) < 0) got = 0;
        else if (!prev) first[bit_length(cs[i].v[1])]++;
    }
    int kt = k_of_histogram(first);
    for (int g = 0; g < groups; g++)
        for (int cls = 0; cls < 2; cls++) ks[g][cls] = k_of_histogram(hists[g][cls]);
    for (int i = 0; i < n && got == 1;) {
        const Entry *head = &es[at[i]];
        PackedBlock *b = packer_begin(p, head->user, 1);
        if (b == NULL) {
            got = -1;
            break;
        }
        int j = i;
        for (; j < n && es[at[j]].user == head->user && got == 1; j++) {
            const Coded *c = &cs[j];
            int lead = c->cls ? 4 : 3; /* values before the differences */
            for (int f = 0; f < c->n; f++) {
                int k = f < lead ? (!c->cls && f == 1 ? kt : 0) : ks[(f - lead) / 3][c->cls];
                if (writer_eg(&p->data, c->v[f], k) < 0) got = -1;
            }
            b->check ^= entry_check(&es[at[j]], width);
        }
        b->n = j - i;
        packer_end(p, b);
        i = j;
    }
    PyMem_Free(cs);
    if (got != 1) return got;
    if (append_int(nib, kt) < 0) return -1;
    for (int g = 0; g < groups; g++)
        for (int cls = 0; cls < 2; cls++)
            if (append_int(nib, ks[g][cls]) < 0) return -1;
    return 1;
}

/* The packed blob of a packer: int64 count, the records, the data. */
static PyObject *packer_bytes(const Packer *p) {
    Py_ssize_t head = 8 + p->count * (Py_ssize_t)sizeof(PackedBlock), data = (p->data.pos + 7) / 8;
    PyObject *out = PyBytes_FromStringAndSize(NULL, head + data);
    if (out == NULL) return NULL;
    char *o = PyBytes_AS_STRING(out);
    int64_t count = p->count;
    memcpy(o, &count, 8);
    if (p->count) memcpy(o + 8, p->blocks, p->count * sizeof(PackedBlock));
    if (data) memcpy(o + head, p->data.buf, data);
    return out;
}

static int bits_of(const int *bits) {
    for (int j = 0; j < 3; j++)
        if (bits[j] < 1 || bits[j] > 32) {
            PyErr_SetString(PyExc_ValueError, "volume bits out of 1..32");
            return -1;
        }
    return 0;
}

/* The packed group of es[0..n) (any order): (packed, key nibbles, delta nibbles), None
 * where the pure path decides (a stream twice, a key code out of range), NULL on error. */
static PyObject *encode_entries(Entry *es, Py_ssize_t n, int velocity, const int *bits) {
    int width = velocity ? 13 : 7;
    SortKey *keys = PyMem_Calloc(n ? n : 1, sizeof(SortKey));
    int *at = PyMem_Calloc(n ? n : 1, sizeof(int));
    Packer p = {NULL, 0, 0, {NULL, 0, 0}};
    PyObject *knib = PyList_New(0), *dnib = PyList_New(0), *result = NULL;
    if (keys == NULL || at == NULL || knib == NULL || dnib == NULL) {
        if (!PyErr_Occurred()) PyErr_NoMemory();
        goto done;
    }
    if (n > INT32_MAX / 2) goto none;
    for (Py_ssize_t i = 0; i < n; i++)
        keys[i].user = es[i].user, keys[i].stream = es[i].stream, keys[i].at = (int)i;
    qsort(keys, n, sizeof(SortKey), sort_key_cmp);
    for (Py_ssize_t i = 1; i < n; i++)
        if (keys[i].user == keys[i - 1].user && keys[i].stream == keys[i - 1].stream) goto none;
    int nk = 0, nd = 0;
    for (Py_ssize_t i = 0; i < n; i++)
        if (es[keys[i].at].key) at[nk++] = keys[i].at;
    for (Py_ssize_t i = 0; i < n; i++)
        if (!es[keys[i].at].key) at[nk + nd++] = keys[i].at;
    int got = nk ? key_section(&p, es, at, nk, velocity, bits, knib) : 1;
    if (got == 1 && nd) got = delta_section(&p, es, at + nk, nd, width, dnib);
    if (got == 0) goto none;
    if (got < 0) goto done;
    PyObject *packed = packer_bytes(&p);
    if (packed == NULL) goto done;
    result = Py_BuildValue("(NOO)", packed, knib, dnib);
    goto done;
none:
    PyErr_Clear();
    result = Py_NewRef(Py_None);
done:
    Py_XDECREF(knib);
    Py_XDECREF(dnib);
    PyMem_Free(p.blocks);
    PyMem_Free(p.data.buf);
    PyMem_Free(keys);
    PyMem_Free(at);
    return result;
}

static PyObject *py_encode_group(PyObject *self, PyObject *args) {
    PyObject *entries, *result = NULL;
    long long base_us;
    int velocity, bits[3];
    if (!PyArg_ParseTuple(args, "O!Lp(iii)", &PyList_Type, &entries, &base_us, &velocity, &bits[0],
                          &bits[1], &bits[2]) ||
        bits_of(bits) < 0)
        return NULL;
    Py_ssize_t n = PyList_GET_SIZE(entries);
    double base = (double)base_us / 1e6;
    Entry *es = PyMem_Calloc(n ? n : 1, sizeof(Entry));
    if (es == NULL) return PyErr_NoMemory();
    for (Py_ssize_t i = 0; i < n; i++)
        if (entry_parse(PyList_GET_ITEM(entries, i), velocity ? 13 : 7, base, 1, &es[i]) < 0) {
            PyErr_Clear();
            result = Py_NewRef(Py_None);
            goto done;
        }
    result = encode_entries(es, n, velocity, bits);
done:
    PyMem_Free(es);
    return result;
}

/* ------------------------------------------------------------------ a room's store, gathered */

static PyObject *S_VERSION, *S_CODES, *S_HISTORY, *S_USER, *S_CAPTURE, *S_CODED, *S_APPEND;

static int stored_init(void) {
    S_VERSION = PyUnicode_InternFromString("version");
    S_CODES = PyUnicode_InternFromString("codes");
    S_HISTORY = PyUnicode_InternFromString("history");
    S_USER = PyUnicode_InternFromString("user");
    S_CAPTURE = PyUnicode_InternFromString("capture");
    S_CODED = PyUnicode_InternFromString("coded");
    S_APPEND = PyUnicode_InternFromString("append");
    return S_VERSION && S_CODES && S_HISTORY && S_USER && S_CAPTURE && S_CODED && S_APPEND ? 0
                                                                                         : -1;
}

/* (version, codes) item i of a history; borrowed codes, or NULL (an error set) */
static PyObject *history_item(PyObject *history, Py_ssize_t i, long long *version) {
    PyObject *item = PySequence_GetItem(history, i);
    if (item == NULL) return NULL;
    PyObject *codes = NULL;
    if (PyTuple_Check(item) && PyTuple_GET_SIZE(item) == 2) {
        *version = PyLong_AsLongLong(PyTuple_GET_ITEM(item, 0));
        if (!(*version == -1 && PyErr_Occurred())) codes = PyTuple_GET_ITEM(item, 1);
    } else {
        PyErr_SetString(PyExc_TypeError, "history: (version, codes) pairs");
    }
    Py_DECREF(item); /* the history still holds it, and so its codes */
    return codes;
}

/* Whether stream s has a version after since, read into *version: 1 yes, 0 no, -1 an
 * error. */
static int is_newer(PyObject *s, long long since, long long *version) {
    PyObject *v = PyObject_GetAttr(s, S_VERSION);
    if (v == NULL) return -1;
    *version = PyLong_AsLongLong(v);
    Py_DECREF(v);
    if (*version == -1 && PyErr_Occurred()) return -1;
    return *version > since;
}

/* One stored stream's codes (codec_relay._stored_entry): 1 an entry, 0 not newer than
 * since, -1 an error. *row and *base are new references (base may be None). */
static int stored_codes(PyObject *s, long long since, PyObject *volume, PyObject **row,
                        PyObject **base) {
    *row = *base = NULL;
    long long version;
    int newer = is_newer(s, since, &version);
    if (newer <= 0) return newer;
    PyObject *codes = PyObject_GetAttr(s, S_CODES);
    PyObject *history = codes ? PyObject_GetAttr(s, S_HISTORY) : NULL;
    Py_ssize_t size = history ? PySequence_Size(history) : -1;
    long long newest = -1;
    int fresh = 0;
    if (size > 0) {
        PyObject *last = history_item(history, size - 1, &newest);
        fresh = last != NULL && codes != Py_None && newest == version;
    }
    if (PyErr_Occurred()) goto fail;
    /* Where the search for the baseline starts: history[-1] is this version (newer
     * than since) once the stream is fresh or remembered here. */
    Py_ssize_t start = size - 2;
    if (fresh) {
        *row = codes;
        codes = NULL;
    } else if (codes != Py_None && PyList_Check(codes)) {
        /* coded() of a stream whose codes came with its update: remember this version */
        PyObject *pair = Py_BuildValue("(LO)", version, codes);
        PyObject *done = pair ? PyObject_CallMethodOneArg(history, S_APPEND, pair) : NULL;
        Py_XDECREF(pair);
        if (done == NULL) goto fail;
        Py_DECREF(done);
        *row = codes;
        codes = NULL;
        size = PySequence_Size(history);
        if (size < 0) goto fail;
        start = size - 2;
    } else {
        /* codes to compute, or this version to remember: the stream's own method */
        *row = PyObject_CallMethodOneArg(s, S_CODED, volume);
        if (*row == NULL) goto fail;
        Py_DECREF(history);
        history = PyObject_GetAttr(s, S_HISTORY);
        size = history ? PySequence_Size(history) : -1;
        if (size < 0) goto fail;
        start = size - 1;
    }
    Py_XDECREF(codes);
    codes = NULL;
    if (since >= 0)
        for (Py_ssize_t i = start; i >= 0 && *base == NULL; i--) {
            long long at;
            PyObject *c = history_item(history, i, &at);
            if (c == NULL) goto fail;
            if (at <= since) *base = Py_NewRef(c);
        }
    if (*base == NULL) *base = Py_NewRef(Py_None);
    Py_DECREF(history);
    return 1;
fail:
    Py_XDECREF(codes);
    Py_XDECREF(history);
    Py_CLEAR(*row);
    return -1;
}

/* A stream's CodeHistory (protocol/codec_store.py): a bytearray of int64 count, int64
 * capacity, then capacity entries of 120 bytes, oldest first. */
typedef struct {
    int64_t version;
    int64_t width;
    int64_t codes[13];
} RingEntry;

/* The entries of a history if it is a CodeHistory (NULL if it is not one). */
static RingEntry *ring_of(PyObject *history, int64_t *count, int64_t *capacity) {
    if (!PyByteArray_Check(history)) return NULL;
    Py_ssize_t size = PyByteArray_GET_SIZE(history);
    char *buf = PyByteArray_AS_STRING(history);
    if (size < 16) return NULL;
    memcpy(count, buf, 8);
    memcpy(capacity, buf + 8, 8);
    if (*capacity < 1 || *count < 0 || *count > *capacity ||
        size != 16 + *capacity * (Py_ssize_t)sizeof(RingEntry))
        return NULL;
    return (RingEntry *)(buf + 16);
}

/* The codes of a list of 7 or 13 int64 into e; -1 if it is not one. */
static int ring_codes(PyObject *row, RingEntry *e) {
    if (!PyList_Check(row)) return -1;
    Py_ssize_t width = PyList_GET_SIZE(row);
    if (width != 7 && width != 13) return -1;
    memset(e->codes, 0, sizeof(e->codes));
    for (Py_ssize_t j = 0; j < width; j++) {
        int overflow;
        long long v = PyLong_AsLongLongAndOverflow(PyList_GET_ITEM(row, j), &overflow);
        if (overflow || (v == -1 && PyErr_Occurred())) {
            PyErr_Clear();
            return -1;
        }
        e->codes[j] = v;
    }
    e->width = width;
    return 0;
}

/* codes (width >= want, idx 0..3, each within int32 as entry_fill wants) into dst;
 * -1 if not. */
static int ring_take(const RingEntry *e, int want, int64_t *dst) {
    if (e->width < want || e->codes[0] < 0 || e->codes[0] > 3) return -1;
    for (int j = 0; j < want; j++) {
        if (e->codes[j] < INT32_MIN || e->codes[j] > INT32_MAX) return -1;
        dst[j] = e->codes[j];
    }
    return 0;
}

/* stored_codes and entry_fill for a stream whose history is a CodeHistory: the entry
 * read from its bytes, this version remembered there as coded() would. 1 an entry, 0
 * not newer than since, -1 an error, -2 the pure path decides. */
static int stored_ring_entry(PyObject *s, PyObject *sid, long long version, PyObject *codes,
                             PyObject *history, long long since, PyObject *volume, int width,
                             double base_time, Entry *out) {
    int64_t n, capacity;
    RingEntry *ring = ring_of(history, &n, &capacity), row;
    if (ring == NULL) return -2;
    int64_t start = n - 2;
    if (codes != Py_None && n > 0 && ring[n - 1].version == version) {
        row = ring[n - 1];
    } else if (codes != Py_None && PyList_Check(codes)) {
        if (ring_codes(codes, &row) < 0) return -2;
        row.version = version;
        /* remember this version (CodeHistory.append) */
        if (n == capacity) {
            memmove(ring, ring + 1, (size_t)(n - 1) * sizeof(RingEntry));
            n--;
        }
        ring[n++] = row;
        memcpy(PyByteArray_AS_STRING(history), &n, 8);
        start = n - 2;
    } else {
        PyObject *got = PyObject_CallMethodOneArg(s, S_CODED, volume);
        if (got == NULL) return -1;
        int bad = ring_codes(got, &row);
        Py_DECREF(got);
        if (bad < 0) return -2;
        /* coded() may have changed the history: read it again */
        PyObject *again = PyObject_GetAttr(s, S_HISTORY);
        if (again == NULL) return -1;
        ring = ring_of(again, &n, &capacity);
        Py_DECREF(again); /* the stream still holds it */
        if (ring == NULL) return -2;
        start = n - 1;
    }
    out->key = 1;
    if (since >= 0)
        for (int64_t i = start; i >= 0; i--)
            if (ring[i].version <= since) {
                if (ring_take(&ring[i], width, out->base) < 0) return -2;
                out->key = 0;
                break;
            }
    if (ring_take(&row, width, out->row) < 0) return -2;
    PyObject *user = PyObject_GetAttr(s, S_USER);
    if (user == NULL) return -1;
    PyObject *capture = PyObject_GetAttr(s, S_CAPTURE);
    if (capture == NULL) {
        Py_DECREF(user);
        return -1;
    }
    out->user = PyLong_AsLongLong(user);
    out->stream = PyLong_AsLongLong(sid);
    double t = PyFloat_AsDouble(capture);
    Py_DECREF(user);
    Py_DECREF(capture);
    if (PyErr_Occurred()) {
        PyErr_Clear();
        return -2;
    }
    if (out->user < 0 || out->user > ID_MAX || out->stream < 0 || out->stream > ID_MAX) return -2;
    if (!(t == t && fabs(t) < 1e12)) return -2;
    double o = nearbyint((base_time - t) * 1000.0);
    if (!(fabs(o) < (double)TIME_MS_LIMIT)) return -2;
    out->off = (int64_t)o;
    return 1;
}

/* One stream of the store into es[*n] (codec_relay.encode_stored's gather): 0 done
 * (an entry or none), -1 an error, and *pure set where the pure path must decide. */
static int stored_one(PyObject *sid, PyObject *s, long long since, PyObject *volume,
                      int velocity, double base, Entry *e, Py_ssize_t *n, int *pure) {
    long long version;
    int newer = is_newer(s, since, &version);
    if (newer <= 0) return newer;
    PyObject *codes = PyObject_GetAttr(s, S_CODES);
    if (codes == NULL) return -1;
    PyObject *history = PyObject_GetAttr(s, S_HISTORY);
    if (history == NULL) {
        Py_DECREF(codes);
        return -1;
    }
    int got = -2;
    if (!*pure)
        got = stored_ring_entry(s, sid, version, codes, history, since, volume,
                                velocity ? 13 : 7, base, e);
    int ring = ring_of(history, &(int64_t){0}, &(int64_t){0}) != NULL;
    Py_DECREF(codes);
    Py_DECREF(history);
    if (got == -1) return -1;
    if (got == 1) {
        (*n)++;
        return 0;
    }
    if (ring) {
        /* the pure path decides; remember this version as coded() would */
        *pure = 1;
        PyObject *row = PyObject_CallMethodOneArg(s, S_CODED, volume);
        if (row == NULL) return -1;
        Py_DECREF(row);
        return 0;
    }
    /* a history of (version, codes) pairs */
    PyObject *row, *basecodes;
    got = stored_codes(s, since, volume, &row, &basecodes);
    if (got <= 0) return got;
    PyObject *user = PyObject_GetAttr(s, S_USER);
    PyObject *capture = user ? PyObject_GetAttr(s, S_CAPTURE) : NULL;
    if (capture != NULL && !*pure &&
        entry_fill(user, sid, capture, row, basecodes, velocity ? 13 : 7, base, 1, 1, e) < 0) {
        PyErr_Clear();
        *pure = 1; /* gather on, then let the pure path decide */
    }
    Py_XDECREF(user);
    Py_XDECREF(capture);
    Py_DECREF(row);
    Py_DECREF(basecodes);
    if (capture == NULL) return -1;
    (*n)++;
    return 0;
}

static PyObject *py_encode_stored(PyObject *self, PyObject *args) {
    PyObject *streams, *volume, *result = NULL;
    long long since, base_us;
    int velocity, bits[3];
    if (!PyArg_ParseTuple(args, "O!LOLp(iii)", &PyDict_Type, &streams, &since, &volume, &base_us,
                          &velocity, &bits[0], &bits[1], &bits[2]) ||
        bits_of(bits) < 0)
        return NULL;
    Py_ssize_t cap = PyDict_GET_SIZE(streams), n = 0;
    double base = (double)base_us / 1e6;
    Entry *es = PyMem_Calloc(cap ? cap : 1, sizeof(Entry));
    if (es == NULL) return PyErr_NoMemory();
    /* coded() is Python: were it to add or drop a stream, the dict would change under
     * PyDict_Next. Walk a list of its items instead. */
    PyObject *items = PyDict_Items(streams);
    if (items == NULL) goto done;
    int pure = 0;
    for (Py_ssize_t i = 0; i < PyList_GET_SIZE(items) && n < cap; i++) {
        PyObject *item = PyList_GET_ITEM(items, i);
        if (stored_one(PyTuple_GET_ITEM(item, 0), PyTuple_GET_ITEM(item, 1), since, volume,
                       velocity, base, &es[n], &n, &pure) < 0)
            goto done;
    }
    if (pure)
        result = Py_NewRef(Py_None);
    else if (n == 0)
        result = Py_NewRef(Py_False);
    else
        result = encode_entries(es, n, velocity, bits);
done:
    Py_XDECREF(items);
    PyMem_Free(es);
    return result;
}

/* Append nbits bits from src (MSB first, from its first byte) to the writer. */
static int writer_copy(Writer *w, const unsigned char *src, int64_t nbits) {
    Py_ssize_t need = (w->pos + nbits + 7) / 8 + 1;
    if (need > w->cap) {
        Py_ssize_t cap = w->cap * 2 > need ? w->cap * 2 : need + 64;
        unsigned char *buf = PyMem_Realloc(w->buf, cap);
        if (buf == NULL) return -1;
        memset(buf + w->cap, 0, cap - w->cap);
        w->buf = buf, w->cap = cap;
    }
    int sh = (int)(w->pos & 7);
    unsigned char *d = w->buf + (w->pos >> 3);
    int64_t whole = nbits / 8;
    int rest = (int)(nbits % 8);
    if (sh == 0) {
        memcpy(d, src, whole);
    } else {
        for (int64_t i = 0; i < whole; i++) {
            d[i] |= (unsigned char)(src[i] >> sh);
            d[i + 1] = (unsigned char)(src[i] << (8 - sh));
        }
    }
    w->pos += 8 * whole;
    if (rest) return writer_put(w, (uint64_t)(src[whole] >> (8 - rest)), rest);
    return 0;
}

/* The records of a packed blob, checked against its size; -1 (ValueError) if it is not one. */
static int packed_blocks(const char *blob, Py_ssize_t size, const PackedBlock **blocks,
                         int64_t *count, const unsigned char **data, Py_ssize_t *data_size) {
    if (size < 8) goto bad;
    memcpy(count, blob, 8);
    if (*count < 0 || *count > (size - 8) / (Py_ssize_t)sizeof(PackedBlock)) goto bad;
    Py_ssize_t head = 8 + *count * (Py_ssize_t)sizeof(PackedBlock);
    *data = (const unsigned char *)blob + head;
    *data_size = size - head;
    *blocks = (const PackedBlock *)(blob + 8);
    for (int64_t i = 0; i < *count; i++) {
        PackedBlock b;
        memcpy(&b, blob + 8 + i * sizeof(PackedBlock), sizeof(b));
        if (b.nbits < 0 || b.offset < 0 || b.offset > *data_size ||
            b.nbits > 8 * (*data_size - b.offset) || b.user < 0 || b.user > ID_MAX || b.n < 0 ||
            (b.section != 0 && b.section != 1))
            goto bad;
    }
    return 0;
bad:
    PyErr_SetString(PyExc_ValueError, "not a packed group");
    return -1;
}

static PyObject *py_splice_packed(PyObject *self, PyObject *args) {
    Py_buffer head, blob;
    PyObject *knib, *dnib, *result = NULL;
    long long exclude;
    if (!PyArg_ParseTuple(args, "y*y*O!O!L", &head, &blob, &PyList_Type, &knib, &PyList_Type,
                          &dnib, &exclude))
        return NULL;
    Writer w = {NULL, 0, 0};
    const PackedBlock *blocks;
    const unsigned char *data;
    Py_ssize_t data_size, n[2] = {0, 0};
    int64_t count;
    uint32_t check = 0;
    if (packed_blocks(blob.buf, blob.len, &blocks, &count, &data, &data_size) < 0) goto done;
    for (int section = 0; section < 2; section++) {
        int64_t prev = 0;
        for (int64_t i = 0; i < count; i++) {
            PackedBlock b;
            memcpy(&b, (const char *)blocks + i * sizeof(PackedBlock), sizeof(b));
            if (b.section != section || b.user == exclude) continue;
            if (b.user < prev) {
                PyErr_SetString(PyExc_ValueError, "blocks out of user order");
                goto done;
            }
            if (writer_eg(&w, (uint64_t)(b.user - prev), 0) < 0 ||
                writer_copy(&w, data + b.offset, b.nbits) < 0)
                goto done;
            n[section] += b.n;
            if (section) check ^= b.check;
            prev = b.user;
        }
    }
    if (n[0] + n[1] == 0) {
        result = Py_BuildValue("(yi)", "", 0);
        goto done;
    }
    result = frame_of(&head, n[0], n[1], check, knib, dnib, &w);
done:
    PyMem_Free(w.buf);
    PyBuffer_Release(&head);
    PyBuffer_Release(&blob);
    return result;
}
