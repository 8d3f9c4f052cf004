/* ControllerLockstep: the controller's side of controller_node.py's loop.
 *
 * Receive sample last_seq + 1 from the paired plant into y_mv, ``c = step(y_in)``, encode
 * c_mv stamped with the receive and publish times, put; last_seq and steps after each reply
 * sent, wmark[0] = steps.  run() returns to the caller (which handles the message as its own
 * loop would) with
 *   LOOP_SLOW       ``data`` (received at t_rx) is not the next fast-path sample, or a sample
 *                   at or past restarts[0] (the list the caller's event callback appends
 *                   scheduled restarts to): not acted on here
 *   LOOP_CHECK      step() returned another object ``c`` than c_obj (h: the decoded
 *                   (seq, step, sim_time_ns, publish_wall_ns); t_rx; last_seq = seq)
 *   LOOP_RAISED     step() raised ValueError or TypeError ``exc`` (h; last_seq = seq)
 *   LOOP_NONFINITE  c_mv is not finite (h, t_rx; nothing sent; last_seq = seq)
 * What it shares with PlantLockstep is in _lockstep.h. */
#include "_lockstep.h"

#define CONTROLLER_OBJECTS(X)                                                                 \
    X(recv, "the sample subscriber's recv() (-> sample with payload.to_bytes())")             \
    X(put, "the reply publisher's put(bytes)")                                                \
    X(y_mv, "writable float64 view the sample's displacements are decoded into")              \
    X(y_in, "the argument of step(y): the array y_mv views")                                  \
    X(step, "the controller's step(y) -> currents")                                           \
    X(c_obj, "the object c_mv views; step() returning another hands back")                    \
    X(c_mv, "the currents' float64 view; the reply is encoded from it")                       \
    X(me, "the controller's seal (48 bytes: id + currents key; or a 16-byte id, zero key): "  \
          "every reply ends with the id and a mac under the key")                             \
    X(peer, "the paired plant's seal (48 or 16 bytes): only samples with its id and a valid " \
            "mac under its key are answered")                                                 \
    X(wmark, "the watchdog's progress list: wmark[0] = steps after each reply")               \
    X(restarts, "list of steps before which the controller restarts (scheduled faults)")
#define CONTROLLER_RESULTS(X)                                                                 \
    X(data, "after LOOP_SLOW: the message in hand")                                           \
    X(c, "after LOOP_CHECK: step()'s output")                                                 \
    X(h, "after LOOP_CHECK, LOOP_RAISED, LOOP_NONFINITE: (seq, step, sim_time_ns, "           \
         "publish_wall_ns) of the sample")                                                    \
    X(exc, "after LOOP_RAISED: the exception step() raised")
#define CONTROLLER_INTS(X)                                                                    \
    X(last_seq, "the seq of the last sample taken (the next expected is last_seq + 1)")      \
    X(steps, "the replies sent")                                                              \
    X(t_rx, "after LOOP_SLOW, LOOP_CHECK, LOOP_NONFINITE: the sample's arrival (time_ns)")

typedef struct {
    PyObject_HEAD
    CONTROLLER_OBJECTS(DECL_OBJ)
    CONTROLLER_RESULTS(DECL_OBJ)
    CONTROLLER_INTS(DECL_INT)
    wire_seal me_seal, peer_seal;    /* me and peer, made ready by run() (not attributes) */
} ControllerLockstep;

/* The next sample decoded into y (n values): STEP_ON (seq, step, sim, t[0] filled), LOOP_SLOW
 * (self->data, self->t_rx) or STEP_FAILED. */
static int controller_receive(ControllerLockstep *self, char *y, Py_ssize_t n, uint64_t *seq,
                              uint64_t *step, int64_t *sim, int64_t *t)
{
    PyObject *data = recv_bytes(self->recv);
    if (data == NULL)
        return STEP_FAILED;
    self->t_rx = wall_ns();
    int restart = 0;
    int ok = decode_raw(PyBytes_AS_STRING(data), PyBytes_GET_SIZE(data), 1, n,
                        (uint64_t)(self->last_seq + 1), &self->peer_seal, y, seq, step, sim, t);
    if (ok && PyList_GET_SIZE(self->restarts) > 0) {   /* appended by a zenoh callback thread */
        long long r0 = PyLong_AsLongLong(PyList_GET_ITEM(self->restarts, 0));
        if (r0 == -1 && PyErr_Occurred()) {
            Py_DECREF(data);
            return STEP_FAILED;
        }
        restart = r0 <= (long long)*step;
    }
    if (!ok || restart) {
        self->data = data;
        return LOOP_SLOW;
    }
    Py_DECREF(data);
    return STEP_ON;
}

/* c = step(y_in) for the sample (seq, step, sim, t0): STEP_ON (c is c_obj), LOOP_CHECK
 * (self->c, self->h), LOOP_RAISED (ValueError / TypeError: self->exc, self->h; other
 * exceptions propagate) or STEP_FAILED. */
static int controller_step(ControllerLockstep *self, uint64_t seq, uint64_t step, int64_t sim,
                           int64_t t0)
{
    PyObject *c = PyObject_CallOneArg(self->step, self->y_in), *e = NULL;
    if (c == self->c_obj) {
        Py_DECREF(c);
        return STEP_ON;
    }
    if (c == NULL) {     /* ValueError / TypeError: the caller's fault; others propagate */
        if (!PyErr_ExceptionMatches(PyExc_ValueError) && !PyErr_ExceptionMatches(PyExc_TypeError))
            return STEP_FAILED;
        if ((e = take_exception()) == NULL)
            return STEP_FAILED;
    }
    self->h = Py_BuildValue("(KKLL)", (unsigned long long)seq, (unsigned long long)step,
                            (long long)sim, (long long)t0);
    if (self->h == NULL) {
        Py_XDECREF(c);
        Py_XDECREF(e);
        return STEP_FAILED;
    }
    self->c = c;
    self->exc = e;
    return c != NULL ? LOOP_CHECK : LOOP_RAISED;
}

/* The replies from last_seq + 1 on, buffers in hand; a LoopCode or STEP_FAILED. */
static int controller_replies(ControllerLockstep *self, char *y, Py_ssize_t n, const char *c,
                              Py_ssize_t nc)
{
    for (;;) {
        if (PyErr_CheckSignals() < 0)
            return STEP_FAILED;
        uint64_t seq, step;
        int64_t sim, t[2];
        int r = controller_receive(self, y, n, &seq, &step, &sim, t);
        if (r != STEP_ON)
            return r;
        self->last_seq = (long long)seq;
        if ((r = controller_step(self, seq, step, sim, t[0])) != STEP_ON)
            return r;
        if (!all_finite(c, nc)) {
            self->h = Py_BuildValue("(KKLL)", (unsigned long long)seq, (unsigned long long)step,
                                    (long long)sim, (long long)t[0]);
            return self->h == NULL ? STEP_FAILED : LOOP_NONFINITE;
        }
        int64_t v[3] = {sim, self->t_rx, wall_ns()};
        PyObject *msg = encode_raw(c, nc, 2, seq, step, v, &self->me_seal);
        if (msg == NULL)
            return STEP_FAILED;
        r = call1(self->put, msg);
        Py_DECREF(msg);
        if (r < 0)
            return STEP_FAILED;
        self->steps += 1;
        if (set_mark(self->wmark, self->steps) < 0)
            return STEP_FAILED;
    }
}

static PyObject *ControllerLockstep_run(ControllerLockstep *self, PyObject *Py_UNUSED(ignored))
{
    static const char T[] = "ControllerLockstep";
#define REQUIRE(f, doc) if (self->f == NULL) return unset(T, #f), NULL;
    CONTROLLER_OBJECTS(REQUIRE)
#undef REQUIRE
    if (check_id(self->me, T, "me") < 0 || check_id(self->peer, T, "peer") < 0
        || check_list(self->wmark, T, "wmark") < 0 || check_list(self->restarts, T, "restarts") < 0)
        return NULL;
    /* the seals as of this call (a MAC then costs one compression); a field set while run()
     * runs (from a callback) takes effect at the next call */
    seal_make(&self->me_seal, PyBytes_AS_STRING(self->me), PyBytes_GET_SIZE(self->me));
    seal_make(&self->peer_seal, PyBytes_AS_STRING(self->peer), PyBytes_GET_SIZE(self->peer));
    CONTROLLER_RESULTS(CLEAR)
    PyObject *bobj[2] = {self->y_mv, self->c_mv};
    const int wr[2] = {1, 0};
    Py_buffer b[2];
    if (get_buffers(bobj, b, 2, wr) < 0)
        return NULL;
    Py_ssize_t n = b[0].len / 8, nc = b[1].len / 8;
    int code = STEP_FAILED;
    if (b[0].len % 8 || b[1].len % 8 || n == 0 || nc == 0)
        PyErr_SetString(PyExc_ValueError, "ControllerLockstep: buffer sizes do not match");
    else
        code = controller_replies(self, b[0].buf, n, b[1].buf, nc);
    for (int i = 0; i < 2; i++)
        PyBuffer_Release(&b[i]);
    return code == STEP_FAILED ? NULL : PyLong_FromLong(code);
}

static int ControllerLockstep_traverse(ControllerLockstep *self, visitproc visit, void *arg)
{
    CONTROLLER_OBJECTS(VISIT)
    CONTROLLER_RESULTS(VISIT)
    return 0;
}

static int ControllerLockstep_clear(ControllerLockstep *self)
{
    CONTROLLER_OBJECTS(CLEAR)
    CONTROLLER_RESULTS(CLEAR)
    return 0;
}

static void ControllerLockstep_dealloc(ControllerLockstep *self)
{
    PyObject_GC_UnTrack(self);
    ControllerLockstep_clear(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

#define C_OBJ(f, doc) {#f, T_OBJECT_EX, offsetof(ControllerLockstep, f), 0, doc},
#define C_RES(f, doc) {#f, T_OBJECT, offsetof(ControllerLockstep, f), READONLY, doc},
#define C_INT(f, doc) {#f, T_LONGLONG, offsetof(ControllerLockstep, f), 0, doc},
static PyMemberDef ControllerLockstep_members[] = {
    CONTROLLER_OBJECTS(C_OBJ) CONTROLLER_RESULTS(C_RES) CONTROLLER_INTS(C_INT) {NULL}};

static PyMethodDef ControllerLockstep_methods[] = {
    {"run", (PyCFunction)ControllerLockstep_run, METH_NOARGS,
     "run() -> LoopCode: answer the ordinary samples until one needs Python (see the type's doc)"},
    {NULL}};

PyTypeObject ControllerLockstepType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "ambhil.bridge.protocol._wire.ControllerLockstep",
    .tp_basicsize = sizeof(ControllerLockstep),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_doc = "ControllerLockstep(**fields): the controller's lockstep loop in C; run() answers "
              "the ordinary samples and returns a LoopCode (bridge/process/controller_node.py)",
    .tp_new = PyType_GenericNew,
    .tp_init = kw_init,
    .tp_traverse = (traverseproc)ControllerLockstep_traverse,
    .tp_clear = (inquiry)ControllerLockstep_clear,
    .tp_dealloc = (destructor)ControllerLockstep_dealloc,
    .tp_members = ControllerLockstep_members,
    .tp_methods = ControllerLockstep_methods,
};
