/*
 * pid_law.c -- the testbench's built-in PID (the paper's eq. 7) as a C law of include/ambhil_law.h,
 * written as firmware would be: fixed-size state, coefficients read once at start-up, no
 * allocation and no library call in the step.
 *
 *   e = -y                                 (the sensor output, negated)
 *   u = kp e + I[e] + D[e]                 I = ki/s, D = kd s/(Td s + 1), each a first-order block
 *                                          x' = a x + b e, out = c x + d e at the loop's period
 *   anti-windup: the integrator holds while u is beyond the amplifier's input range and e
 *                drives it further
 *
 * The coefficients are the testbench's own ("discrete" of params_json), and the arithmetic is
 * controller/pid_law.py's pid_step, operation for operation, so the currents equal the built-in
 * law's bit for bit when compiled without floating-point contraction (no fused multiply-add):
 *
 *     cc -O2 -shared -fPIC -ffp-contract=off -I include -o pid_law.so examples/c_law/pid_law.c
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "ambhil_law.h"

#define MAX_AXES 16

enum { FAULT_NONE = 0, FAULT_SENSOR_NOT_FINITE = 1 };

typedef struct { double a, b, c, d; } block_t;   /* x' = a x + b e, out = c x + d e */

typedef struct {
    int n_axes;
    block_t integral, derivative;
    double kp;
    double u_max;                /* the amplifier's input range, +-u_max (INFINITY: none) */
    int anti_windup;
    double u_op[MAX_AXES];       /* where the integrator starts: the input holding i_op */
    double x_i[MAX_AXES];        /* integrator state */
    double x_d[MAX_AXES];        /* derivative filter state */
} pid_law_t;

/* ---- start-up: the few numbers of params_json this law needs ----------------------------- */

static const char *skip_ws(const char *p)
{
    while (*p == ' ' || *p == '\t' || *p == '\n' || *p == '\r')
        p++;
    return p;
}

/* The value after the last "key": in [from, end) (NULL if there is none). */
static const char *find_key(const char *from, const char *end, const char *key)
{
    size_t n = strlen(key);
    const char *found = NULL;
    for (const char *p = strchr(from, '"'); p && p + n + 2 <= end; p = strchr(p + 1, '"')) {
        if (strncmp(p + 1, key, n) == 0 && p[n + 1] == '"') {
            const char *q = skip_ws(p + n + 2);
            if (*q == ':')
                found = skip_ws(q + 1);
        }
    }
    return found;
}

/* A JSON number at p (null: +infinity, for a limit that is not there); 0 if it is neither. */
static int read_number(const char *p, double *out)
{
    char *stop;
    if (p == NULL)
        return 0;
    if (strncmp(p, "null", 4) == 0) {
        *out = INFINITY;
        return 1;
    }
    *out = strtod(p, &stop);
    return stop != p;
}

static int read_block(const char *disc, const char *end, const char *name, block_t *blk)
{
    const char *p = find_key(disc, end, name);
    const char *close = p ? strchr(p, '}') : NULL;
    return close != NULL
        && read_number(find_key(p, close, "a"), &blk->a) && read_number(find_key(p, close, "b"), &blk->b)
        && read_number(find_key(p, close, "c"), &blk->c) && read_number(find_key(p, close, "d"), &blk->d);
}

static int read_array(const char *p, double *out, int n)
{
    if (p == NULL || *p != '[')
        return 0;
    for (int k = 0; k < n; k++) {
        char *stop;
        p = skip_ws(p + 1);
        out[k] = strtod(p, &stop);
        if (stop == p)
            return 0;
        p = skip_ws(stop);
        if (*p != (k + 1 < n ? ',' : ']'))
            return 0;
    }
    return 1;
}

void *ambhil_law_new(int n_axes, double period_s, const char *axes_csv, const char *params_json)
{
    (void)period_s;              /* the coefficients below are already at this period */
    (void)axes_csv;
    if (n_axes < 1 || n_axes > MAX_AXES || params_json == NULL)
        return NULL;
    const char *end = params_json + strlen(params_json);
    /* "discrete" is the last member params_json writes: after the scene's own tables, whatever
       keys they hold; "u_op" is the last of its name before it */
    const char *disc = find_key(params_json, end, "discrete");
    if (disc == NULL)
        return NULL;
    pid_law_t *s = calloc(1, sizeof *s);
    if (s == NULL)
        return NULL;
    const char *aw = find_key(disc, end, "anti_windup");
    s->n_axes = n_axes;
    if (!read_block(disc, end, "integral", &s->integral) || !read_block(disc, end, "derivative", &s->derivative)
        || !read_number(find_key(disc, end, "kp"), &s->kp)
        || !read_number(find_key(disc, end, "input_limit"), &s->u_max)
        || aw == NULL || !read_array(find_key(params_json, disc, "u_op"), s->u_op, n_axes)) {
        free(s);
        return NULL;
    }
    s->anti_windup = strncmp(aw, "true", 4) == 0;
    ambhil_law_reset(s);
    return s;
}

void ambhil_law_reset(void *state)
{
    pid_law_t *s = state;
    for (int a = 0; a < s->n_axes; a++) {
        /* the integrator preloaded so that the law holds u_op at zero displacement */
        s->x_i[a] = s->integral.c != 0.0 ? s->u_op[a] / s->integral.c : 0.0;
        s->x_d[a] = 0.0;
    }
}

/* ---- the period: controller/pid_law.py pid_step, the same operations in the same order ------ */

int ambhil_law_step(void *state, double t, const double *y, double *u)
{
    pid_law_t *s = state;
    const block_t *I = &s->integral, *D = &s->derivative;
    (void)t;
    for (int a = 0; a < s->n_axes; a++) {
        if (!isfinite(y[a]))
            return FAULT_SENSOR_NOT_FINITE;
        double e = -y[a];
        double xi = s->x_i[a];
        double ui = I->c * xi + I->d * e;
        double xd = s->x_d[a];
        double ud = D->c * xd + D->d * e;
        s->x_d[a] = D->a * xd + D->b * e;
        double v = s->kp * e + ui + ud;
        int sat = v > s->u_max || v < -s->u_max;
        if (!(sat && s->anti_windup && e * v > 0.0))
            s->x_i[a] = I->a * xi + I->b * e;
        u[a] = v;
    }
    return FAULT_NONE;
}

void ambhil_law_free(void *state)
{
    free(state);
}

const char *ambhil_law_fault_name(int code)
{
    switch (code) {
    case FAULT_SENSOR_NOT_FINITE:
        return "sensor output not finite";
    default:
        return NULL;
    }
}
