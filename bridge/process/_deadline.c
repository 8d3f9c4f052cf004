/* A receive deadline for the real-time loop that needs neither the GIL nor a wake-up on the
 * loop's CPU (bridge/deadline.py, docs/performance.md "10 kHz").
 *
 * The real-time plant blocks in its FIFO subscriber's recv(), which has no timeout.  This
 * timer thread, started from C and pinned to another CPU, sleeps until the end of the
 * current reply window (clock_nanosleep, CLOCK_MONOTONIC = time.perf_counter_ns) and, only
 * if the reply for that window has not been marked received, takes the GIL and calls
 * ``fire(seq)`` (a session-local put that wakes recv()).  The loop only stores integers:
 *
 *     arm(seq, window_end_ns)   before it blocks for the reply to seq
 *     done(seq)                 when the reply to seq arrived (or the window was closed)
 *
 * Between windows the thread sleeps until the predicted next window end (last one + one
 * period) and re-reads; so it wakes about once a period, on its own CPU, and the loop makes
 * no system call for it.  close() stops and joins the thread (before the interpreter ends).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <errno.h>
#include <pthread.h>
#include <sched.h>
#include <stdatomic.h>
#include <stdint.h>
#include <time.h>

typedef struct {
    PyObject_HEAD
    PyObject *fire;
    int64_t period_ns;
    int cpu;
    _Atomic int64_t gen;          /* seqlock over (armed_seq, window_end): odd while arming */
    _Atomic int64_t armed_seq;
    _Atomic int64_t window_end;
    _Atomic int64_t done_seq;
    _Atomic int64_t fired_seq;
    _Atomic int64_t wakes;
    _Atomic int64_t fires;
    _Atomic int stop;
    int started;
    pthread_t thread;
} Timer;

static int64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static void sleep_until(int64_t t)
{
    struct timespec ts = {(time_t)(t / 1000000000LL), (long)(t % 1000000000LL)};
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR)
        ;
}

static void *run(void *arg)
{
    Timer *t = (Timer *)arg;
    if (t->cpu >= 0) {
        cpu_set_t set;
        CPU_ZERO(&set);
        CPU_SET(t->cpu, &set);
        pthread_setaffinity_np(pthread_self(), sizeof(set), &set);
    }
    int64_t poll = t->period_ns / 4 > 20000 ? t->period_ns / 4 : 20000;
    int64_t last_end = 0;
    while (!atomic_load(&t->stop)) {
        int64_t g = atomic_load(&t->gen);
        if (g & 1) {
            sched_yield();                /* the loop is arming: read again */
            continue;
        }
        int64_t s = atomic_load(&t->armed_seq);
        int64_t w = atomic_load(&t->window_end);
        if (atomic_load(&t->gen) != g)
            continue;
        int64_t n = now_ns();
        if (s > atomic_load(&t->done_seq) && s > atomic_load(&t->fired_seq)) {
            if (n < w) {                  /* an open window: sleep to its end, then re-read */
                sleep_until(w);
                atomic_fetch_add(&t->wakes, 1);
                continue;
            }
            /* the window is over and its reply not received: wake the loop */
            if (atomic_load(&t->gen) != g || atomic_load(&t->done_seq) >= s)
                continue;                 /* the loop moved on meanwhile */
            atomic_store(&t->fired_seq, s);
            atomic_fetch_add(&t->fires, 1);
            if (atomic_load(&t->stop))
                break;
            PyGILState_STATE g = PyGILState_Ensure();
            PyObject *r = PyObject_CallFunction(t->fire, "L", (long long)s);
            if (r == NULL)
                PyErr_WriteUnraisable(t->fire);
            Py_XDECREF(r);
            PyGILState_Release(g);
            last_end = w;
            continue;
        }
        /* nothing outstanding: sleep until the next window is expected to end */
        if (w > last_end)
            last_end = w;
        int64_t next = last_end + t->period_ns;
        if (next <= n)
            next = n + poll;              /* the loop is late arming: look again soon */
        sleep_until(next);
        atomic_fetch_add(&t->wakes, 1);
    }
    return NULL;
}

static int Timer_init(Timer *self, PyObject *args, PyObject *kw)
{
    static char *names[] = {"fire", "period_ns", "cpu", NULL};
    PyObject *fire;
    long long period;
    int cpu = -1;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OL|i", names, &fire, &period, &cpu))
        return -1;
    if (!PyCallable_Check(fire)) {
        PyErr_SetString(PyExc_TypeError, "DeadlineTimer: fire must be callable");
        return -1;
    }
    if (period <= 0) {
        PyErr_SetString(PyExc_ValueError, "DeadlineTimer: period_ns must be > 0");
        return -1;
    }
    if (self->started) {
        PyErr_SetString(PyExc_RuntimeError, "DeadlineTimer: already started");
        return -1;
    }
    Py_INCREF(fire);
    self->fire = fire;
    self->period_ns = period;
    self->cpu = cpu;
    atomic_store(&self->gen, 0);
    atomic_store(&self->armed_seq, -1);
    atomic_store(&self->done_seq, -1);
    atomic_store(&self->fired_seq, -1);
    atomic_store(&self->window_end, 0);
    atomic_store(&self->stop, 0);
    int rc = pthread_create(&self->thread, NULL, run, self);
    if (rc != 0) {
        PyErr_Format(PyExc_OSError, "DeadlineTimer: pthread_create failed (%d)", rc);
        return -1;
    }
    self->started = 1;
    return 0;
}

static void stop_join(Timer *self)
{
    if (!self->started)
        return;
    atomic_store(&self->stop, 1);
    self->started = 0;
    Py_BEGIN_ALLOW_THREADS
    pthread_join(self->thread, NULL);
    Py_END_ALLOW_THREADS
}

static PyObject *Timer_close(Timer *self, PyObject *unused)
{
    stop_join(self);
    Py_RETURN_NONE;
}

static PyObject *Timer_arm(Timer *self, PyObject *const *a, Py_ssize_t n)
{
    if (n != 2) {
        PyErr_SetString(PyExc_TypeError, "arm(seq, window_end_ns)");
        return NULL;
    }
    long long s = PyLong_AsLongLong(a[0]), w = PyLong_AsLongLong(a[1]);
    if (PyErr_Occurred())
        return NULL;
    atomic_fetch_add(&self->gen, 1);      /* odd: the pair is being written */
    atomic_store(&self->armed_seq, s);
    atomic_store(&self->window_end, w);
    atomic_fetch_add(&self->gen, 1);
    Py_RETURN_NONE;
}

static PyObject *Timer_done(Timer *self, PyObject *arg)
{
    long long s = PyLong_AsLongLong(arg);
    if (s == -1 && PyErr_Occurred())
        return NULL;
    atomic_store(&self->done_seq, s);
    Py_RETURN_NONE;
}

static PyObject *Timer_stats(Timer *self, PyObject *unused)
{
    return Py_BuildValue("{s:L,s:L}", "timer_wakes", (long long)atomic_load(&self->wakes),
                         "timer_fires", (long long)atomic_load(&self->fires));
}

static void Timer_dealloc(Timer *self)
{
    stop_join(self);
    Py_XDECREF(self->fire);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyMethodDef Timer_methods[] = {
    {"arm", (PyCFunction)(void (*)(void))Timer_arm, METH_FASTCALL,
     "arm(seq, window_end_ns): the reply to seq is due by window_end_ns (perf_counter_ns)"},
    {"done", (PyCFunction)Timer_done, METH_O, "done(seq): the reply to seq arrived"},
    {"close", (PyCFunction)Timer_close, METH_NOARGS, "stop and join the thread"},
    {"stats", (PyCFunction)Timer_stats, METH_NOARGS, "{'wakes': ..., 'fires': ...}"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject TimerType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "ambhil.bridge.process._deadline.DeadlineTimer",
    .tp_basicsize = sizeof(Timer),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "DeadlineTimer(fire, period_ns, cpu=-1): calls fire(seq) when an armed reply "
              "window ends without done(seq); a C thread on cpu, no GIL until it fires",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Timer_init,
    .tp_dealloc = (destructor)Timer_dealloc,
    .tp_methods = Timer_methods,
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_deadline",
                                    "Receive deadline of the real-time loop (see deadline.py).",
                                    -1, NULL};

PyMODINIT_FUNC PyInit__deadline(void)
{
    if (PyType_Ready(&TimerType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m == NULL)
        return NULL;
    Py_INCREF(&TimerType);
    if (PyModule_AddObject(m, "DeadlineTimer", (PyObject *)&TimerType) < 0) {
        Py_DECREF(&TimerType);
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
