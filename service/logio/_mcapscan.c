/* Fast path for reading energyctl's own MCAP logs in replay: walks a sequence of MCAP records (a
 * decompressed chunk, or the top level of a file) and turns the JSON messages of the wanted channels
 * into rows of doubles without creating a Python object per message.
 *
 * Only flat JSON objects whose keys are exactly the expected ones, in order, with number or boolean
 * values, are accepted (what energyctl's recorder writes from its templates); anything else raises
 * ValueError and the caller falls back to the general reader (mcap + json). Numbers go through
 * strtod, which rounds correctly, as Python's float() does, so the doubles are the ones json.loads
 * would give (replay compares commands with ==, so a difference could not hide).
 *
 * MCAP record: opcode u8, length u64 (little-endian), content. Channel (0x04): id u16, schema_id u16,
 * topic (u32 length + bytes), ... Message (0x05): channel_id u16, sequence u32, log_time u64,
 * publish_time u64, data (the rest).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define MAXF 8 /* values per row after the channel code */

static uint64_t rd64(const unsigned char *p)
{
    uint64_t v;
    memcpy(&v, p, 8); /* MCAP is little-endian, as is every machine this builds on (checked at import) */
    return v;
}

static uint16_t rd16(const unsigned char *p)
{
    uint16_t v;
    memcpy(&v, p, 2);
    return v;
}

static uint32_t rd32(const unsigned char *p)
{
    uint32_t v;
    memcpy(&v, p, 4);
    return v;
}

/* The record at p: its opcode, content and content length; returns where the next record starts, or NULL at
 * the end or at a record cut off (a killed writer: everything before it is still read). */
static const unsigned char *record(const unsigned char *p, const unsigned char *end, int *op,
                                   const unsigned char **content, uint64_t *len)
{
    if (end - p < 9)
        return NULL;
    uint64_t l = rd64(p + 1);
    if (l > (uint64_t)(end - p - 9))
        return NULL;
    *op = p[0];
    *content = p + 9;
    *len = l;
    return p + 9 + l;
}

/* Append a new reference to a list; on failure clear the list (the caller returns NULL). */
static void append_new(PyObject **list, PyObject *item)
{
    if (item == NULL || PyList_Append(*list, item) < 0)
        Py_CLEAR(*list);
    Py_XDECREF(item);
}

/* channels(records) -> [(channel_id, topic bytes), ...] for every Channel record in the sequence */
static PyObject *mcap_channels(PyObject *self, PyObject *args)
{
    (void)self;
    Py_buffer b;
    if (!PyArg_ParseTuple(args, "y*", &b))
        return NULL;
    PyObject *out = PyList_New(0);
    const unsigned char *end = (const unsigned char *)b.buf + b.len, *c, *nx;
    int op;
    uint64_t len;
    for (const unsigned char *p = b.buf; out != NULL && (nx = record(p, end, &op, &c, &len)) != NULL; p = nx) {
        if (op == 0x04 && len >= 8 && rd32(c + 4) <= len - 8)
            append_new(&out, Py_BuildValue("(iy#)", (int)rd16(c), (const char *)c + 8, (Py_ssize_t)rd32(c + 4)));
    }
    PyBuffer_Release(&b);
    return out;
}

/* Parse {"k0":x0,"k1":x1,...} against the expected keys; 0 on success. */
static int parse_row(const unsigned char *s, Py_ssize_t n, PyObject *keys, double *row)
{
    Py_ssize_t nk = PyTuple_GET_SIZE(keys), i = 0;
    if (n < 2 || s[0] != '{')
        return -1;
    i = 1;
    for (Py_ssize_t k = 0; k < nk; k++) {
        PyObject *key = PyTuple_GET_ITEM(keys, k);
        const char *kn = PyBytes_AS_STRING(key);
        Py_ssize_t kl = PyBytes_GET_SIZE(key);
        int skip = kl > 0 && kn[0] == '~'; /* "~name": the key must be there, its value is not needed */
        if (skip) {
            kn++;
            kl--;
        }
        if (i + kl + 3 > n || s[i] != '"' || memcmp(s + i + 1, kn, (size_t)kl) != 0 ||
            s[i + 1 + kl] != '"' || s[i + 2 + kl] != ':')
            return -1;
        i += kl + 3;
        char tok[64];
        Py_ssize_t j = 0;
        while (i < n && s[i] != ',' && s[i] != '}') {
            if (j >= 63)
                return -1;
            tok[j++] = (char)s[i++];
        }
        tok[j] = 0;
        if (i >= n || j == 0)
            return -1;
        int digits = 1;
        for (Py_ssize_t q = 0; q < j; q++)
            digits &= tok[q] >= '0' && tok[q] <= '9';
        if (skip)
            row[k] = 0.0;
        else if (digits && j <= 15) { /* an integer (seq): exact without strtod */
            double v = 0.0;
            for (Py_ssize_t q = 0; q < j; q++)
                v = v * 10.0 + (tok[q] - '0');
            row[k] = v;
        } else if (strcmp(tok, "true") == 0)
            row[k] = 1.0;
        else if (strcmp(tok, "false") == 0)
            row[k] = 0.0;
        else {
            char *e;
            /* JSON numbers, plus Python's NaN / Infinity / -Infinity */
            if (!(tok[0] == '-' || (tok[0] >= '0' && tok[0] <= '9') || tok[0] == 'N' || tok[0] == 'I'))
                return -1;
            row[k] = strtod(tok, &e);
            if (*e != 0)
                return -1;
        }
        char want = (k == nk - 1) ? '}' : ',';
        if (s[i] != want)
            return -1;
        i++;
    }
    return i == n ? 0 : -1;
}

/* scan(records, table, keys) -> bytes: one row of 1 + MAXF doubles (code, values...) per Message record
 * whose channel id maps to a code in table (bytes of 65536, 255 = not wanted); keys[code] is the tuple of
 * expected JSON keys (bytes; "~key": present, value not parsed, 0.0 in the row). Rows are in record order. */
static PyObject *mcap_scan(PyObject *self, PyObject *args)
{
    (void)self;
    Py_buffer b, tb;
    PyObject *keys, *res = NULL;
    if (!PyArg_ParseTuple(args, "y*y*O!", &b, &tb, &PyTuple_Type, &keys))
        return NULL;
    if (tb.len != 65536) {
        PyErr_SetString(PyExc_ValueError, "scan(): table must be 65536 bytes");
        goto done;
    }
    for (Py_ssize_t c = 0; c < PyTuple_GET_SIZE(keys); c++) {
        PyObject *kt = PyTuple_GET_ITEM(keys, c);
        if (!PyTuple_Check(kt) || PyTuple_GET_SIZE(kt) > MAXF) {
            PyErr_SetString(PyExc_ValueError, "scan(): keys[code] must be a tuple of at most 8 bytes keys");
            goto done;
        }
        for (Py_ssize_t k = 0; k < PyTuple_GET_SIZE(kt); k++)
            if (!PyBytes_Check(PyTuple_GET_ITEM(kt, k))) {
                PyErr_SetString(PyExc_ValueError, "scan(): keys must be bytes");
                goto done;
            }
    }
    const unsigned char *tab = tb.buf;
    const unsigned char *p0 = b.buf, *end = p0 + b.len, *c, *nx;
    int op;
    uint64_t len;
    Py_ssize_t count = 0;
    for (const unsigned char *p = p0; (nx = record(p, end, &op, &c, &len)) != NULL; p = nx) /* how many rows */
        count += op == 0x05 && len >= 22 && tab[rd16(c)] != 255;
    res = PyBytes_FromStringAndSize(NULL, count * (Py_ssize_t)((1 + MAXF) * sizeof(double)));
    if (res == NULL)
        goto done;
    double *row = (double *)PyBytes_AS_STRING(res);
    for (const unsigned char *p = p0; (nx = record(p, end, &op, &c, &len)) != NULL; p = nx) {
        int code = op == 0x05 && len >= 22 ? tab[rd16(c)] : 255;
        if (code == 255)
            continue;
        if (code >= PyTuple_GET_SIZE(keys)) {
            PyErr_SetString(PyExc_ValueError, "scan(): a code has no keys");
            Py_CLEAR(res);
            goto done;
        }
        memset(row, 0, (1 + MAXF) * sizeof(double));
        row[0] = code;
        if (parse_row(c + 22, (Py_ssize_t)len - 22, PyTuple_GET_ITEM(keys, code), row + 1) != 0) {
            PyErr_Format(PyExc_ValueError, "scan(): a message on channel %d is not the expected flat JSON",
                         (int)rd16(c));
            Py_CLEAR(res);
            goto done;
        }
        row += 1 + MAXF;
    }
done:
    PyBuffer_Release(&b);
    PyBuffer_Release(&tb);
    return res;
}

/* raw(records, channel_id) -> [data bytes, ...] of that channel's Message records, in order */
static PyObject *mcap_raw(PyObject *self, PyObject *args)
{
    (void)self;
    Py_buffer b;
    int cid;
    if (!PyArg_ParseTuple(args, "y*i", &b, &cid))
        return NULL;
    PyObject *out = PyList_New(0);
    const unsigned char *end = (const unsigned char *)b.buf + b.len, *c, *nx;
    int op;
    uint64_t len;
    for (const unsigned char *p = b.buf; out != NULL && (nx = record(p, end, &op, &c, &len)) != NULL; p = nx) {
        if (op == 0x05 && len >= 22 && rd16(c) == cid)
            append_new(&out, PyBytes_FromStringAndSize((const char *)c + 22, (Py_ssize_t)len - 22));
    }
    PyBuffer_Release(&b);
    return out;
}

static PyMethodDef methods[] = {
    {"raw", mcap_raw, METH_VARARGS, "data of one channel's Message records"},
    {"channels", mcap_channels, METH_VARARGS, "Channel records in a record sequence: [(id, topic)]"},
    {"scan", mcap_scan, METH_VARARGS, "Rows of doubles from the wanted channels' flat JSON messages"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {.m_base = PyModuleDef_HEAD_INIT, .m_name = "clients._mcapscan",
                                    .m_doc = "Fast reader for energyctl's MCAP logs (replay).", .m_size = -1,
                                    .m_methods = methods};

PyMODINIT_FUNC PyInit__mcapscan(void)
{
    PyObject *m = PyModule_Create(&module);
    if (m != NULL && PyModule_AddIntConstant(m, "ROW", 1 + MAXF) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
