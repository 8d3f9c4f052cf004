/* A controller FMU for co-simulation: a discrete PID per axis, FMI 2.0 (default) or FMI 3.0
 * (-DFMI_VERSION=3), compiled by build_fmu.py against the standard's headers (fmpy ships them).
 *
 * Each doStep(t, h), for every axis a with e = -y[a] (the negated sensor output):
 *
 *     d[a]  = (td d[a] + kd (e - e_prev[a])) / (td + h)      filtered derivative, backward Euler
 *     u[a]  = u_op[a] + kp e + i[a] + d[a]                     the amplifier input, until the next step
 *     i[a] += ki h e                                           integral, forward Euler
 *
 * Variables (value references): 1 kp, 2 ki, 3 kd, 4 td (parameters, Real / Float64),
 * 5 fail_after (parameter, Integer / Int32: when > 0, doStep fails with Error from that step on,
 * a test hook), 100 + a the input y_<axis>, 200 + a the output u_<axis>, 300 + a the parameter
 * u_op_<axis>; FMI 3.0 also 0 time (independent).  build_fmu.py writes the modelDescription.xml
 * of the same layout and passes N_AXES and the start values (KP_START, ...) as macros.
 *
 * Every other function of the standard is a stub that returns Error (build_fmu.py generates
 * them from the header's function types).
 */
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#if FMI_VERSION == 3
#include "fmi3Functions.h"
#define S_OK fmi3OK
#define S_ERROR fmi3Error
#else
#include "fmi2Functions.h"
#define S_OK fmi2OK
#define S_ERROR fmi2Error
#endif

#if !defined(N_AXES) || !defined(KP_START) || !defined(KI_START) || !defined(KD_START) || !defined(TD_START)
#error "N_AXES and KP_START, KI_START, KD_START, TD_START must be defined (build_fmu.py does)"
#endif

enum { VR_TIME = 0, VR_KP = 1, VR_KI = 2, VR_KD = 3, VR_TD = 4, VR_FAIL_AFTER = 5,
       VR_Y = 100, VR_U = 200, VR_UOP = 300 };

typedef struct {
    double kp, ki, kd, td, u_op[N_AXES];                 /* parameters */
    int fail_after;
    double y[N_AXES], u[N_AXES];                         /* inputs, outputs */
    double integral[N_AXES], deriv[N_AXES], e_prev[N_AXES];
    double time;
    long steps;
    char name[64];
#if FMI_VERSION == 3
    fmi3InstanceEnvironment env;
    fmi3LogMessageCallback log;
#else
    const fmi2CallbackFunctions *cb;
#endif
} Law;

static void log_error(Law *L, const char *fmt, ...) {
    char msg[256];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(msg, sizeof msg, fmt, ap);
    va_end(ap);
#if FMI_VERSION == 3
    if (L->log) L->log(L->env, fmi3Error, "logStatusError", msg);
#else
    if (L->cb && L->cb->logger) L->cb->logger(L->cb->componentEnvironment, L->name, fmi2Error, "logStatusError", "%s", msg);
#endif
}

/* start values: parameters as in modelDescription.xml, inputs, outputs and state zero */
static void set_defaults(Law *L) {
    L->kp = KP_START; L->ki = KI_START; L->kd = KD_START; L->td = TD_START;
    L->fail_after = 0;
    for (int a = 0; a < N_AXES; a++) {
        L->u_op[a] = 0.0; L->y[a] = 0.0; L->u[a] = 0.0;
        L->integral[a] = 0.0; L->deriv[a] = 0.0; L->e_prev[a] = 0.0;
    }
    L->time = 0.0;
    L->steps = 0;
}

static Law *new_law(const char *name) {
    Law *L = calloc(1, sizeof *L);
    if (!L) return NULL;
    snprintf(L->name, sizeof L->name, "%s", name ? name : "pid_law");
    set_defaults(L);
    return L;
}

/* leaving initialisation: the state at rest, the output the operating point */
static void start(Law *L) {
    for (int a = 0; a < N_AXES; a++) {
        L->integral[a] = 0.0; L->deriv[a] = 0.0; L->e_prev[a] = 0.0;
        L->u[a] = L->u_op[a];
    }
    L->steps = 0;
}

static int law_step(Law *L, double h) {
    if (L->fail_after > 0 && L->steps >= L->fail_after) {
        log_error(L, "fail_after = %d steps reached (t = %g s)", L->fail_after, L->time);
        return 0;
    }
    for (int a = 0; a < N_AXES; a++) {
        double e = -L->y[a];
        double d = (L->td * L->deriv[a] + L->kd * (e - L->e_prev[a])) / (L->td + h);
        L->u[a] = L->u_op[a] + L->kp * e + L->integral[a] + d;
        L->integral[a] += L->ki * h * e;
        L->deriv[a] = d;
        L->e_prev[a] = e;
    }
    L->steps++;
    L->time += h;
    return 1;
}

/* the Real variable of a value reference (NULL: none; outputs and time only when reading) */
static double *real_at(Law *L, unsigned vr, int writing) {
    switch (vr) {
    case VR_KP: return &L->kp;
    case VR_KI: return &L->ki;
    case VR_KD: return &L->kd;
    case VR_TD: return &L->td;
    case VR_TIME: return writing ? NULL : &L->time;
    }
    if (vr >= VR_Y && vr < VR_Y + N_AXES) return &L->y[vr - VR_Y];
    if (vr >= VR_UOP && vr < VR_UOP + N_AXES) return &L->u_op[vr - VR_UOP];
    if (!writing && vr >= VR_U && vr < VR_U + N_AXES) return &L->u[vr - VR_U];
    return NULL;
}

static int get_real(Law *L, const unsigned vr[], size_t n, double v[]) {
    for (size_t k = 0; k < n; k++) {
        double *p = real_at(L, vr[k], 0);
        if (!p) { log_error(L, "get: no Real variable with value reference %u", vr[k]); return 0; }
        v[k] = *p;
    }
    return 1;
}

static int set_real(Law *L, const unsigned vr[], size_t n, const double v[]) {
    for (size_t k = 0; k < n; k++) {
        double *p = real_at(L, vr[k], 1);
        if (!p) { log_error(L, "set: no settable Real variable with value reference %u", vr[k]); return 0; }
        *p = v[k];
    }
    return 1;
}

static int get_int(Law *L, const unsigned vr[], size_t n, int v[]) {
    for (size_t k = 0; k < n; k++) {
        if (vr[k] != VR_FAIL_AFTER) { log_error(L, "get: no Integer variable with value reference %u", vr[k]); return 0; }
        v[k] = L->fail_after;
    }
    return 1;
}

static int set_int(Law *L, const unsigned vr[], size_t n, const int v[]) {
    for (size_t k = 0; k < n; k++) {
        if (vr[k] != VR_FAIL_AFTER) { log_error(L, "set: no Integer variable with value reference %u", vr[k]); return 0; }
        L->fail_after = v[k];
    }
    return 1;
}

#define STATUS(ok) ((ok) ? S_OK : S_ERROR)

#if FMI_VERSION == 3

const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Status fmi3SetDebugLogging(fmi3Instance instance, fmi3Boolean loggingOn, size_t nCategories,
                               const fmi3String categories[]) {
    (void)instance; (void)loggingOn; (void)nCategories; (void)categories;
    return fmi3OK;
}

fmi3Instance fmi3InstantiateCoSimulation(fmi3String instanceName, fmi3String instantiationToken,
        fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn, fmi3Boolean eventModeUsed,
        fmi3Boolean earlyReturnAllowed, const fmi3ValueReference requiredIntermediateVariables[],
        size_t nRequiredIntermediateVariables, fmi3InstanceEnvironment instanceEnvironment,
        fmi3LogMessageCallback logMessage, fmi3IntermediateUpdateCallback intermediateUpdate) {
    (void)instantiationToken; (void)resourcePath; (void)visible; (void)loggingOn;
    (void)earlyReturnAllowed; (void)requiredIntermediateVariables; (void)nRequiredIntermediateVariables;
    (void)intermediateUpdate;
    if (eventModeUsed) {
        if (logMessage) logMessage(instanceEnvironment, fmi3Error, "logStatusError", "event mode is not supported");
        return NULL;
    }
    Law *L = new_law(instanceName);
    if (!L) return NULL;
    L->env = instanceEnvironment;
    L->log = logMessage;
    return L;
}

void fmi3FreeInstance(fmi3Instance instance) { free(instance); }

fmi3Status fmi3EnterInitializationMode(fmi3Instance instance, fmi3Boolean toleranceDefined,
        fmi3Float64 tolerance, fmi3Float64 startTime, fmi3Boolean stopTimeDefined, fmi3Float64 stopTime) {
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
    ((Law *)instance)->time = startTime;
    return fmi3OK;
}

fmi3Status fmi3ExitInitializationMode(fmi3Instance instance) { start(instance); return fmi3OK; }

fmi3Status fmi3Terminate(fmi3Instance instance) { (void)instance; return fmi3OK; }

fmi3Status fmi3Reset(fmi3Instance instance) { set_defaults(instance); return fmi3OK; }

fmi3Status fmi3GetFloat64(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                          fmi3Float64 values[], size_t nValues) {
    return nValues == nvr ? STATUS(get_real(instance, vr, nvr, values)) : fmi3Error;
}

fmi3Status fmi3SetFloat64(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                          const fmi3Float64 values[], size_t nValues) {
    return nValues == nvr ? STATUS(set_real(instance, vr, nvr, values)) : fmi3Error;
}

fmi3Status fmi3GetInt32(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                        fmi3Int32 values[], size_t nValues) {
    return nValues == nvr ? STATUS(get_int(instance, vr, nvr, values)) : fmi3Error;
}

fmi3Status fmi3SetInt32(fmi3Instance instance, const fmi3ValueReference vr[], size_t nvr,
                        const fmi3Int32 values[], size_t nValues) {
    return nValues == nvr ? STATUS(set_int(instance, vr, nvr, values)) : fmi3Error;
}

fmi3Status fmi3DoStep(fmi3Instance instance, fmi3Float64 currentCommunicationPoint,
        fmi3Float64 communicationStepSize, fmi3Boolean noSetFMUStatePriorToCurrentPoint,
        fmi3Boolean *eventHandlingNeeded, fmi3Boolean *terminateSimulation, fmi3Boolean *earlyReturn,
        fmi3Float64 *lastSuccessfulTime) {
    (void)noSetFMUStatePriorToCurrentPoint;
    Law *L = instance;
    L->time = currentCommunicationPoint;
    int ok = law_step(L, communicationStepSize);
    *eventHandlingNeeded = fmi3False;
    *terminateSimulation = fmi3False;
    *earlyReturn = fmi3False;
    *lastSuccessfulTime = ok ? currentCommunicationPoint + communicationStepSize : currentCommunicationPoint;
    return STATUS(ok);
}

#else

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }

const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[]) {
    (void)c; (void)loggingOn; (void)nCategories; (void)categories;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation, const fmi2CallbackFunctions *functions,
                              fmi2Boolean visible, fmi2Boolean loggingOn) {
    (void)fmuGUID; (void)fmuResourceLocation; (void)visible; (void)loggingOn;
    if (fmuType != fmi2CoSimulation) {
        if (functions && functions->logger)
            functions->logger(functions->componentEnvironment, instanceName, fmi2Error, "logStatusError",
                              "%s", "this FMU supports co-simulation only");
        return NULL;
    }
    Law *L = new_law(instanceName);
    if (!L) return NULL;
    L->cb = functions;
    return L;
}

void fmi2FreeInstance(fmi2Component c) { free(c); }

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime) {
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
    ((Law *)c)->time = startTime;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) { (void)c; return fmi2OK; }

fmi2Status fmi2ExitInitializationMode(fmi2Component c) { start(c); return fmi2OK; }

fmi2Status fmi2Terminate(fmi2Component c) { (void)c; return fmi2OK; }

fmi2Status fmi2Reset(fmi2Component c) { set_defaults(c); return fmi2OK; }

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[]) {
    return STATUS(get_real(c, vr, nvr, value));
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[]) {
    return STATUS(set_real(c, vr, nvr, value));
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[]) {
    return STATUS(get_int(c, vr, nvr, value));
}

fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer value[]) {
    return STATUS(set_int(c, vr, nvr, value));
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint, fmi2Real communicationStepSize,
                      fmi2Boolean noSetFMUStatePriorToCurrentPoint) {
    (void)noSetFMUStatePriorToCurrentPoint;
    Law *L = c;
    L->time = currentCommunicationPoint;
    return STATUS(law_step(L, communicationStepSize));
}

#endif
