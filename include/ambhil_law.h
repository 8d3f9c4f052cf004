/*
 * ambhil_law.h -- the C ABI of a control law for the ambhil testbench (`--law FILE.so`,
 * `[controller] law = "FILE.so"`).  A shared library exporting these four functions runs in the
 * controller's loop between the testbench's sensor and amplifier models, in process
 * (controller/law_c.py loads it with ctypes; controller/law.py is the interface it implements).
 *
 * Each controller period (the calls on one state never overlap: one at a time, the step once
 * per period, in order; the law need not be thread-safe):
 *
 *     y[a] = sensor(d[a])                 the testbench: the scene's sensor model of axis a
 *     rc   = ambhil_law_step(s, t, y, u)  your law
 *     i[a] = amplifier(u[a])              the testbench: limits, lag, slew, delay -> coil current
 *
 * Units.  y: the sensor outputs, one per axis in the order of `axes_csv` (the displacement in m
 * through the scene's [sensor] gain and lag: volts for the paper's scenes, metres for a unity
 * sensor).  u: the amplifier inputs, one per axis (the scene's [amplifier] gain turns them into
 * amperes: volts for the paper's scenes, amperes for a unity amplifier).  t: the simulation time of
 * the sample in seconds, k * period_s for the k-th sample (a restart resets the law, not the clock).
 *
 * Memory.  `ambhil_law_new` may allocate; `ambhil_law_step` need not and should not (the
 * example, examples/c_law/pid_law.c, uses fixed-size arrays).  `y` and `u` are the caller's arrays
 * of n_axes doubles, valid for the call only; write every u[a].  A non-finite u[a] is a fault of
 * the law (the run ends naming it).
 */
#ifndef AMBHIL_LAW_H
#define AMBHIL_LAW_H

#ifdef __cplusplus
extern "C" {
#endif

/* The version of this ABI (informative; the symbols below are the contract). */
#define AMBHIL_LAW_ABI_VERSION 1

/*
 * A new law for n_axes axes at the controller period period_s (s).
 *
 * axes_csv: the axis names, comma-separated, in the order of y and u ("A-x,A-y,B-x,...").
 * params_json: one JSON object (UTF-8, numbers written so that they read back to the same
 * doubles with strtod):
 *   "controller"    the scene's [controller] table as written (kp, ki, kd, derivative_filter,
 *                   sample_rate, discretisation, delay_samples, anti_windup, and any other key)
 *   "params"        its [controller.params] sub-table: the law's own parameters
 *   "axes"          the axis names (as axes_csv), "period_s" the period
 *   "i_op"          per axis: the operating-point coil current (A) the loop must deliver at y = 0
 *   "u_op"          per axis: the amplifier input holding i_op in steady state (where a law with
 *                   an integrator starts)
 *   "input_limit"   the amplifier's input range +-input_limit (null: none)
 *   "current_limit" the coil current limit in A (null: none)
 *   "discrete"      the built-in PID of the scene's gains discretised at period_s: the first-order
 *                   blocks "sensor", "integral", "derivative", "amplifier" (each {a, b, c, d}:
 *                   x' = a x + b e, out = c x + d e), "kp", "input_limit", "current_limit",
 *                   "anti_windup", "i_op" (what a port of the built-in law starts from)
 * Both strings are valid for the call only: copy what you keep.
 * Returns the law's state, or NULL if it cannot run with these (too many axes, a parameter
 * missing): the testbench then stops with an error naming the library.
 */
void *ambhil_law_new(int n_axes, double period_s, const char *axes_csv, const char *params_json);

/*
 * One period: sensor outputs y[n_axes] at time t (s) -> amplifier inputs u[n_axes].
 * Returns 0, or a non-zero fault code: the run ends with a fault naming the law, the code (and its
 * name, see ambhil_law_fault_name) and the step.
 */
int ambhil_law_step(void *state, double t, const double *y, double *u);

/*
 * Back to the state of a new law (called once after ambhil_law_new, and at each controller
 * restart of a fault schedule).
 */
void ambhil_law_reset(void *state);

/* The end of the law: free what ambhil_law_new allocated (called exactly once). */
void ambhil_law_free(void *state);

/*
 * Optional: the name of a non-zero fault code of ambhil_law_step (a static string, or NULL
 * when the code has none).  Without this export a fault is reported by its number alone.
 */
const char *ambhil_law_fault_name(int code);

#ifdef __cplusplus
}
#endif

#endif /* AMBHIL_LAW_H */
