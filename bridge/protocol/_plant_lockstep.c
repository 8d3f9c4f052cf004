/* PlantLockstep: steps k, k+1, ... of plant_lockstep.lockstep while they are ordinary.
 *
 * Publish sample k (encoded from y_mv, stamped, put, appended to ``sent``), receive the reply
 * to k from the paired controller (into rx_mv; (t1, data) appended to ``received``; rtt[k]
 * and tet[k] stored), ``advance(u)``.  run() returns
 *   LOOP_DONE       all steps done (k = k_end)
 *   LOOP_SLOW       sample k sent, ``data`` is not its fast-path reply (t0: the publish stamp)
 *   LOOP_FLUSH      a step done, k = the next one, a flush is due (k >= next_flush or
 *                   t1 >= rb_due)
 *   LOOP_CHECK      step k advanced, its output ``y`` needs the caller's check (a new object,
 *                   or a status set; t1: the reply's arrival)
 *   LOOP_RAISED     advance raised ``exc`` at step k
 *   LOOP_NONFINITE  y_mv is not finite at step k (nothing sent)
 * What it shares with ControllerLockstep is in _lockstep.h. */
#include "_lockstep.h"

#define PLANT_OBJECTS(X)                                                                      \
    X(y_mv, "the plant output's float64 view; sample k is encoded from it")                  \
    X(y_obj, "the object y_mv aliases (None: none); advance() returning another hands back") \
    X(rx_mv, "writable float64 view the reply's currents are decoded into")                   \
    X(u, "the argument of advance(u): the array rx_mv views")                                 \
    X(advance, "the plant's advance(u) -> y")                                                 \
    X(plant, "the plant step object (step_index and, with has_status, status are read)")      \
    X(put, "the sample publisher's put(bytes)")                                               \
    X(recv, "the reply subscriber's recv() (-> sample with payload.to_bytes())")              \
    X(sent, "list: each sample sent is appended (the recording)")                             \
    X(received, "list: (t1, reply bytes) of each reply is appended (the recording)")          \
    X(rtt, "int64 per step: the round trip t1 - t0 of step k at k")                           \
    X(tet, "int64 per step: the controller's publish - receive stamps of step k at k")        \
    X(wmark, "the watchdog's progress list: wmark[0] = k before step k")                      \
    X(me, "the plant's seal (48 bytes: id + sensors key; or a 16-byte id, zero key): every "   \
          "sample ends with the id and a mac under the key")                                  \
    X(peer, "the paired controller's seal (48 or 16 bytes): only replies with its id and a "  \
            "valid mac under its key are taken")
#define PLANT_RESULTS(X)                                                                      \
    X(data, "after LOOP_SLOW: the message in hand")                                           \
    X(y, "after LOOP_CHECK: advance()'s output")                                              \
    X(exc, "after LOOP_RAISED: the exception advance() raised")
#define PLANT_INTS(X)                                                                         \
    X(has_status, "true: the plant has a status, read after each advance")                    \
    X(period_ns, "the controller period, ns: sim_time_ns = step_index * period_ns")           \
    X(k_end, "the steps k < k_end are run")                                                   \
    X(next_flush, "hand back (LOOP_FLUSH) once the steps done reach it (a Timing batch)")     \
    X(rb_due, "... or once a reply's arrival t1 reaches it (time.time_ns; a RecordBatch)")    \
    X(k, "the next step: set before run(); after it, the step the code concerns")             \
    X(steps_done, "the steps done (written after each step)")                                 \
    X(sim_ns, "sim_time_ns of the last step begun")                                           \
    X(t0, "after LOOP_SLOW: the round trip's start (the publish stamp of sample k)")          \
    X(t1, "after LOOP_FLUSH, LOOP_CHECK: the round trip's end (the reply's arrival)")

typedef struct {
    PyObject_HEAD
    PLANT_OBJECTS(DECL_OBJ)
    PLANT_RESULTS(DECL_OBJ)
    PLANT_INTS(DECL_INT)
    wire_seal me_seal, peer_seal;    /* me and peer, made ready by run() (not attributes) */
} PlantLockstep;

/* Sample k published: STEP_ON with *t0 its stamp, LOOP_NONFINITE (y not finite, nothing
 * sent) or STEP_FAILED. */
static int plant_publish(PlantLockstep *self, const char *y, Py_ssize_t n, long long k,
                         int64_t *t0)
{
    PyObject *o = PyObject_GetAttr(self->plant, s_step_index);
    if (o == NULL)
        return STEP_FAILED;
    long long step_i = PyLong_AsLongLong(o);
    Py_DECREF(o);
    if (step_i == -1 && PyErr_Occurred())
        return STEP_FAILED;
    int64_t v[2] = {step_i * self->period_ns, 0};
    self->sim_ns = v[0];
    if (set_mark(self->wmark, k) < 0)
        return STEP_FAILED;
    *t0 = v[1] = wall_ns();                      /* publish stamp and round-trip start */
    if (!all_finite(y, n))
        return LOOP_NONFINITE;
    PyObject *msg = encode_raw(y, n, 1, (uint64_t)k, (uint64_t)step_i, v, &self->me_seal);
    if (msg == NULL)
        return STEP_FAILED;
    int r = call1(self->put, msg) < 0 || PyList_Append(self->sent, msg) < 0;
    Py_DECREF(msg);
    return r ? STEP_FAILED : STEP_ON;
}

/* The reply to k received into rx (n values): STEP_ON with *t1 its arrival (rtt[k], tet[k]
 * stored), LOOP_SLOW (another message in hand: self->data, self->t0) or STEP_FAILED. */
static int plant_receive(PlantLockstep *self, char *rx, Py_ssize_t n, long long k, int64_t t0,
                         int64_t *rtt, int64_t *tet, int64_t *t1)
{
    PyObject *data = recv_bytes(self->recv);
    if (data == NULL)
        return STEP_FAILED;
    uint64_t seq, step;
    int64_t sim, t[2];
    if (!decode_raw(PyBytes_AS_STRING(data), PyBytes_GET_SIZE(data), 2, n, (uint64_t)k,
                    &self->peer_seal, rx, &seq, &step, &sim, t)) {
        self->data = data;
        self->t0 = t0;
        return LOOP_SLOW;
    }
    *t1 = wall_ns();
    PyObject *kept = Py_BuildValue("(LN)", (long long)*t1, data);
    if (kept == NULL || PyList_Append(self->received, kept) < 0) {
        Py_XDECREF(kept);
        return STEP_FAILED;
    }
    Py_DECREF(kept);
    rtt[k] = *t1 - t0;
    tet[k] = t[1] - t[0];                        /* the controller's publish - receive stamps */
    return STEP_ON;
}

/* advance(u): STEP_ON (the same output object, no status), LOOP_CHECK (self->y),
 * LOOP_RAISED (self->exc) or STEP_FAILED. */
static int plant_advance(PlantLockstep *self)
{
    PyObject *y = PyObject_CallOneArg(self->advance, self->u);
    if (y == NULL) {
        self->exc = take_exception();
        return self->exc != NULL ? LOOP_RAISED : STEP_FAILED;
    }
    int check = y != self->y_obj;
    if (!check && self->has_status) {
        PyObject *s = PyObject_GetAttr(self->plant, s_status);
        check = s == NULL ? -1 : PyObject_IsTrue(s);
        Py_XDECREF(s);
        if (check < 0) {
            Py_DECREF(y);
            return STEP_FAILED;
        }
    }
    if (check) {
        self->y = y;
        return LOOP_CHECK;
    }
    Py_DECREF(y);
    return STEP_ON;
}

/* The steps from self->k on, buffers in hand; a LoopCode or STEP_FAILED. */
static int plant_steps(PlantLockstep *self, const char *y, char *rx, Py_ssize_t n,
                       int64_t *rtt, int64_t *tet)
{
    for (long long k = self->k; k < self->k_end; k++) {
        self->k = k;
        if (PyErr_CheckSignals() < 0)
            return STEP_FAILED;
        int64_t t0, t1 = 0;
        int r = plant_publish(self, y, n, k, &t0);
        if (r == STEP_ON)
            r = plant_receive(self, rx, n, k, t0, rtt, tet, &t1);
        if (r == STEP_ON)
            r = plant_advance(self);
        if (r == LOOP_CHECK)
            self->t1 = t1;
        if (r != STEP_ON)
            return r;
        self->steps_done = k + 1;
        if (k + 1 >= self->next_flush || t1 >= self->rb_due) {
            self->k = k + 1;
            self->t1 = t1;
            return LOOP_FLUSH;
        }
    }
    self->k = self->k_end;
    return LOOP_DONE;
}

static PyObject *PlantLockstep_run(PlantLockstep *self, PyObject *Py_UNUSED(ignored))
{
    static const char T[] = "PlantLockstep";
#define REQUIRE(f, doc) if (self->f == NULL) return unset(T, #f), NULL;
    PLANT_OBJECTS(REQUIRE)
#undef REQUIRE
    if (check_list(self->sent, T, "sent") < 0 || check_list(self->received, T, "received") < 0
        || check_list(self->wmark, T, "wmark") < 0 || check_id(self->me, T, "me") < 0
        || check_id(self->peer, T, "peer") < 0)
        return NULL;
    /* the seals as of this call (a MAC then costs one compression); a field set while run()
     * runs (from a callback) takes effect at the next call */
    seal_make(&self->me_seal, PyBytes_AS_STRING(self->me), PyBytes_GET_SIZE(self->me));
    seal_make(&self->peer_seal, PyBytes_AS_STRING(self->peer), PyBytes_GET_SIZE(self->peer));
    PLANT_RESULTS(CLEAR)
    PyObject *bobj[4] = {self->y_mv, self->rx_mv, self->rtt, self->tet};
    const int wr[4] = {0, 1, 1, 1};
    Py_buffer b[4];
    if (get_buffers(bobj, b, 4, wr) < 0)
        return NULL;
    Py_ssize_t n = b[0].len / 8;
    int code = STEP_FAILED;
    if (b[0].len % 8 || b[1].len != b[0].len || n == 0 || b[2].len < 8 * self->k_end
        || b[3].len < 8 * self->k_end || self->k < 0)
        PyErr_SetString(PyExc_ValueError, "PlantLockstep: buffer sizes do not match");
    else
        code = plant_steps(self, b[0].buf, b[1].buf, n, b[2].buf, b[3].buf);
    for (int i = 0; i < 4; i++)
        PyBuffer_Release(&b[i]);
    return code == STEP_FAILED ? NULL : PyLong_FromLong(code);
}

static int PlantLockstep_traverse(PlantLockstep *self, visitproc visit, void *arg)
{
    PLANT_OBJECTS(VISIT)
    PLANT_RESULTS(VISIT)
    return 0;
}

static int PlantLockstep_clear(PlantLockstep *self)
{
    PLANT_OBJECTS(CLEAR)
    PLANT_RESULTS(CLEAR)
    return 0;
}

static void PlantLockstep_dealloc(PlantLockstep *self)
{
    PyObject_GC_UnTrack(self);
    PlantLockstep_clear(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

#define P_OBJ(f, doc) {#f, T_OBJECT_EX, offsetof(PlantLockstep, f), 0, doc},
#define P_RES(f, doc) {#f, T_OBJECT, offsetof(PlantLockstep, f), READONLY, doc},
#define P_INT(f, doc) {#f, T_LONGLONG, offsetof(PlantLockstep, f), 0, doc},
static PyMemberDef PlantLockstep_members[] = {
    PLANT_OBJECTS(P_OBJ) PLANT_RESULTS(P_RES) PLANT_INTS(P_INT) {NULL}};

static PyMethodDef PlantLockstep_methods[] = {
    {"run", (PyCFunction)PlantLockstep_run, METH_NOARGS,
     "run() -> LoopCode: the steps from k on, until one needs Python (see the type's doc)"},
    {NULL}};

PyTypeObject PlantLockstepType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "ambhil.bridge.protocol._wire.PlantLockstep",
    .tp_basicsize = sizeof(PlantLockstep),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_doc = "PlantLockstep(**fields): the plant's lockstep loop in C; run() runs its ordinary "
              "steps and returns a LoopCode (bridge/protocol/_plant_lockstep.c, "
              "bridge/process/plant_lockstep.py)",
    .tp_new = PyType_GenericNew,
    .tp_init = kw_init,
    .tp_traverse = (traverseproc)PlantLockstep_traverse,
    .tp_clear = (inquiry)PlantLockstep_clear,
    .tp_dealloc = (destructor)PlantLockstep_dealloc,
    .tp_members = PlantLockstep_members,
    .tp_methods = PlantLockstep_methods,
};
