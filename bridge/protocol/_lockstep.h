/* The lockstep loops' fast path: consecutive ordinary steps in one C call.
 *
 * bridge/process/plant_lockstep.py (plant) and bridge/process/controller_node.py (controller)
 * run their lockstep loops through these when the extension is built: every step whose
 * message is the fast-path one (decode_raw of _wire.h succeeds) and whose step object
 * behaves as before runs here without a Python bytecode of the loop's own; anything else returns to the
 * Python loop, which handles it exactly as its own fast path would have.  Same calls, same
 * order, same stamps as the Python loops (put, list appends, recv().payload.to_bytes(),
 * advance or step, time.time_ns()); progress is written to the loop object after each step,
 * so an exception raised by put/recv leaves the caller's bookkeeping exact.
 *
 * The interface is named on both sides.  Each loop is a type (PlantLockstep,
 * ControllerLockstep) whose fields Python sets and reads by name: one X-macro list per type
 * (in its file) names each field once (C struct member, Python attribute with its doc, garbage
 * collector visit).  run() returns a LoopCode; the module exports the codes as LOOP_DONE ...
 * LOOP_NONFINITE, which ambhil.bridge.protocol.wire.LoopCode mirrors (tests/test_protocol.py
 * checks that the two agree).
 *
 * Files: this header (what the two loop types share: the codes, the per-message helpers as
 * static inline, the field-list macros), _lockstep.c (the rest of their shared machinery and
 * their part of the module: the LOOP_* constants and the two types), _plant_lockstep.c
 * (PlantLockstep), _controller_lockstep.c (ControllerLockstep). */
#ifndef AMBHIL_LOCKSTEP_H
#define AMBHIL_LOCKSTEP_H

#include "_wire.h"
#include <stddef.h>
#include <structmember.h>
#include <time.h>

/* Why run() handed the loop back to Python (wire.LoopCode has the same names without LOOP_). */
enum LoopCode {
    LOOP_DONE = 0,      /* all steps done */
    LOOP_SLOW = 1,      /* the message in hand is not the fast-path one */
    LOOP_FLUSH = 2,     /* a step done, a Timing or RecordBatch flush is due (plant) */
    LOOP_CHECK = 3,     /* the step object returned another output object (or a status is set) */
    LOOP_RAISED = 4,    /* the step object raised */
    LOOP_NONFINITE = 5  /* the output to send is not finite (nothing sent) */
};

/* The step helpers return STEP_ON (go on with the step), STEP_FAILED (a Python exception is
 * set) or the LoopCode to hand back with. */
enum { STEP_ON = -2, STEP_FAILED = -1 };

/* interned attribute names (_lockstep.c, set by lockstep_ready) */
extern WIRE_INTERNAL PyObject *s_step_index, *s_status, *s_payload, *s_to_bytes;

static inline int64_t wall_ns(void)   /* time.time_ns() */
{
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

/* fn(arg) with the result dropped; -1 on error */
static inline int call1(PyObject *fn, PyObject *arg)
{
    PyObject *r = PyObject_CallOneArg(fn, arg);
    if (r == NULL)
        return -1;
    Py_DECREF(r);
    return 0;
}

static inline int set_mark(PyObject *wmark, long long v)   /* wmark[0] = v */
{
    PyObject *o = PyLong_FromLongLong(v);
    return o == NULL ? -1 : PyList_SetItem(wmark, 0, o);
}

/* recv().payload.to_bytes() */
WIRE_INTERNAL PyObject *recv_bytes(PyObject *recv);
/* The pending exception as an object if it is an Exception, else NULL with it still set. */
WIRE_INTERNAL PyObject *take_exception(void);
/* Buffers of the nb objects (writable[i]: a writable one), C-contiguous; -1: none held. */
WIRE_INTERNAL int get_buffers(PyObject *const *objs, Py_buffer *b, int nb, const int *writable);
/* A field's check before run() (an error naming the type and field; -1); check_id: a seal
 * (48 bytes) or a peer id (16, the all-zero key), which run() makes into a wire_seal once */
WIRE_INTERNAL int check_id(PyObject *o, const char *type, const char *field);
WIRE_INTERNAL int check_list(PyObject *o, const char *type, const char *field);
WIRE_INTERNAL int unset(const char *type, const char *field);
/* The keyword-only constructor of both types: each keyword sets the field of that name. */
WIRE_INTERNAL int kw_init(PyObject *self, PyObject *args, PyObject *kw);

/* The X-macro helpers of the field lists (each entry: X(name, doc)) */
#define DECL_OBJ(f, doc) PyObject *f;
#define DECL_INT(f, doc) long long f;
#define VISIT(f, doc) Py_VISIT(self->f);
#define CLEAR(f, doc) Py_CLEAR(self->f);

/* The two types (_plant_lockstep.c, _controller_lockstep.c) */
extern WIRE_INTERNAL PyTypeObject PlantLockstepType, ControllerLockstepType;

/* Their part of the module (PyInit__wire in _wire.c): lockstep_ready() before the module is
 * created (the interned names, the types readied), lockstep_add(m) after (the LOOP_*
 * constants and the two types added); -1 with an exception set on failure. */
WIRE_INTERNAL int lockstep_ready(void);
WIRE_INTERNAL int lockstep_add(PyObject *m);

#endif /* AMBHIL_LOCKSTEP_H */
