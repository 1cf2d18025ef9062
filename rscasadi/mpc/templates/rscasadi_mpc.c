#define _POSIX_C_SOURCE 199309L
#include <math.h>
#include <time.h>
#include "${header}"
#include "rscasadi_guard.h"
#include "${casadi_header}"

#define NXP (${SYM}_NX * (${SYM}_HORIZON + 1))
#define NUP (${SYM}_NU * ${SYM}_HORIZON)
#define NROWS (${SYM}_NREF / ${SYM}_HORIZON)
#define MASS_INDEX ${mass_index}              /* the payload's mass in the parameters, or -1: none */
static const double NOMINAL[${SYM}_NP + 1] = {${nominal}};      /* the model's parameters (manifest.json) */
static const double TAU_MAX[${SYM}_NU] = {${tau_max}};          /* INFINITY: no limit */
static const double X_LO[${SYM}_NX] = {${x_lo}}, X_HI[${SYM}_NX] = {${x_hi}};      /* a plausible measurement */
static const double REF_LO[NROWS] = {${ref_lo}}, REF_HI[NROWS] = {${ref_hi}};  /* a reference column */
typedef char casadi_int_is_long_long[sizeof(casadi_int) == sizeof(long long) ? 1 : -1];
typedef char work_fits[sizeof(((${sym}_t *)0)->w) >= sizeof(casadi_real) * (${sz_w_check}) ? 1 : -1];
typedef char iwork_fits[sizeof(((${sym}_t *)0)->iw) >= sizeof(casadi_int) * (${sz_iw_check}) ? 1 : -1];
#define NPREPARED ${nprepared}
static const int PREP_OFF[NPREPARED + 1] = {${prep_offsets}};   /* each prepared output in c->prep */

size_t ${sym}_sizeof(void) { return sizeof(${sym}_t); }

double ${sym}_step_seconds(const ${sym}_t *c) { return c ? c->last_step_seconds : 0.0; }

double ${sym}_feedback_seconds(const ${sym}_t *c) { return c ? c->last_feedback_seconds : 0.0; }

int ${sym}_set_payload_mass(${sym}_t *c, double mass) {
  if (MASS_INDEX < 0) return ${SYM}_NO_PAYLOAD;
  if (!c || !isfinite(mass) || mass < 0) return ${SYM}_BAD_ARGUMENT;
  c->params[${SYM}_NU + MASS_INDEX] = mass;
  return 0;
}

static int finite_all(const double *v, int n) {
  if (!v) return 0;
  for (int i = 0; i < n; ++i)
    if (!isfinite(v[i])) return 0;
  return 1;
}

int ${sym}_set_parameters(${sym}_t *c, const double *p) {
  if (${SYM}_NP == 0 || !c || !finite_all(p, ${SYM}_NP)) return ${SYM}_BAD_ARGUMENT;
  for (int i = 0; i < ${SYM}_NP; ++i) c->params[${SYM}_NU + i] = p[i];
  return 0;
}

int ${sym}_set_posture(${sym}_t *c, const double *theta) {
  if (!c || !rscasadi_within(theta, X_LO, X_HI, ${SYM}_NU)) return ${SYM}_BAD_ARGUMENT;
  for (int i = 0; i < ${SYM}_NU; ++i) c->params[i] = theta[i];
  return 0;
}

/* ${sym}_hold at x into X, U: the arm held still at x over the horizon; 0 if that plan is finite */
static int hold(${sym}_t *c, const double *x, double *X, double *U) {
  const casadi_real *arg[${sym}_hold_SZ_ARG + 1] = {x, c->params};
  casadi_real *res[${sym}_hold_SZ_RES + 1] = {X, U};
  if (${sym}_hold(arg, res, (casadi_int *)c->iw, c->w, 0) != 0) return ${SYM}_FAILED;
  return finite_all(X, NXP) && finite_all(U, NUP) ? 0 : ${SYM}_NOT_FINITE;
}

/* the safe output: the holding torque of the last good state, within the limits */
static int refuse(${sym}_t *c, double *tau_out, int code) {
  if (hold(c, c->x_good, c->X_next, c->U_next) == 0)
    for (int i = 0; i < ${SYM}_NU; ++i) tau_out[i] = c->U_next[i];
  else
    rscasadi_zero(tau_out, ${SYM}_NU);
  rscasadi_clamp(tau_out, TAU_MAX, ${SYM}_NU);
  return code;
}

int ${sym}_init(${sym}_t *c, const double *x_measured) { return ${sym}_init_parameters(c, x_measured, NOMINAL); }

int ${sym}_init_parameters(${sym}_t *c, const double *x_measured, const double *p) {
  if (!c) return ${SYM}_BAD_ARGUMENT;
  c->ready = 0;
  c->prepared = 0;
  c->last_step_seconds = c->last_feedback_seconds = 0.0;
  if (!finite_all(p, ${SYM}_NP)) return ${SYM}_BAD_ARGUMENT;
  if (!rscasadi_within(x_measured, X_LO, X_HI, ${SYM}_NX)) return ${SYM}_BAD_MEASUREMENT;
  for (int i = 0; i < ${SYM}_NU; ++i) c->params[i] = x_measured[i];
  for (int i = 0; i < ${SYM}_NP; ++i) c->params[${SYM}_NU + i] = p[i];
  const int code = hold(c, x_measured, c->X, c->U);
  if (code) return code;
  for (int i = 0; i < ${SYM}_NX; ++i) c->x_good[i] = x_measured[i];
  c->ready = RSCASADI_READY;
  return 0;
}

static int reference_ok(const double *reference) {
  if (!reference) return 0;
  for (int k = 0; k < ${SYM}_HORIZON; ++k)
    if (!rscasadi_within(reference + NROWS * k, REF_LO, REF_HI, NROWS)) return 0;
  return 1;
}

int ${sym}_prepare(${sym}_t *c, const double *reference) {
  if (!c || c->ready != RSCASADI_READY) return ${SYM}_NOT_INITIALISED;
  int code = reference_ok(reference) ? 0 : ${SYM}_BAD_REFERENCE;
#if ${SYM}_SPLIT
  if (!code) {
    const casadi_real *arg[${sym}_rti_prepare_SZ_ARG + 1] = {reference, c->X, c->U, c->params};
    casadi_real *res[${sym}_rti_prepare_SZ_RES + 1];
    for (int i = 0; i < NPREPARED; ++i) res[i] = c->prep + PREP_OFF[i];
    if (${sym}_rti_prepare(arg, res, (casadi_int *)c->iw, c->w, 0) != 0) code = ${SYM}_FAILED;
    else if (!finite_all(c->prep, PREP_OFF[NPREPARED])) code = ${SYM}_NOT_FINITE;
  }
#else
  if (!code)
    for (int i = 0; i < ${SYM}_NREF; ++i) c->reference[i] = reference[i];
#endif
  c->prepared = code ? code : RSCASADI_READY;
  return code;
}

static int feedback(${sym}_t *c, const double *x_measured, double *tau_out) {
  if (!c || c->ready != RSCASADI_READY) {
    rscasadi_zero(tau_out, ${SYM}_NU);
    return ${SYM}_NOT_INITIALISED;
  }
  if (!rscasadi_within(x_measured, X_LO, X_HI, ${SYM}_NX)) return refuse(c, tau_out, ${SYM}_BAD_MEASUREMENT);
  for (int i = 0; i < ${SYM}_NX; ++i) c->x_good[i] = x_measured[i];
  int code = c->prepared == RSCASADI_READY ? 0 : (c->prepared ? c->prepared : ${SYM}_NOT_PREPARED);
  c->prepared = 0;                        /* a preparation serves one feedback */
  if (code == ${SYM}_BAD_REFERENCE || code == ${SYM}_NOT_PREPARED) return refuse(c, tau_out, code);
  if (!code) {
#if ${SYM}_SPLIT
    const casadi_real *arg[${sym}_rti_feedback_SZ_ARG + 1] = {x_measured, c->X, c->U};
    for (int i = 0; i < NPREPARED; ++i) arg[3 + i] = c->prep + PREP_OFF[i];
    casadi_real *res[${sym}_rti_feedback_SZ_RES + 1] = {tau_out, c->X_next, c->U_next};
    code = ${sym}_rti_feedback(arg, res, (casadi_int *)c->iw, c->w, 0) != 0 ? ${SYM}_FAILED : 0;
#else
    const casadi_real *arg[${sym}_rti_SZ_ARG + 1] = {x_measured, c->reference, c->X, c->U, c->params};
    casadi_real *res[${sym}_rti_SZ_RES + 1] = {tau_out, c->X_next, c->U_next};
    code = ${sym}_rti(arg, res, (casadi_int *)c->iw, c->w, 0) != 0 ? ${SYM}_FAILED : 0;
#endif
  }
  if (!code && !(finite_all(c->X_next, NXP) && finite_all(c->U_next, NUP) && finite_all(tau_out, ${SYM}_NU)))
    code = ${SYM}_NOT_FINITE;
  if (code) {                             /* the plan restarts from the arm held here */
    refuse(c, tau_out, code);
    if (hold(c, x_measured, c->X, c->U) != 0) c->ready = 0;
    return code;
  }
  for (int i = 0; i < NXP; ++i) c->X[i] = c->X_next[i];
  for (int i = 0; i < NUP; ++i) c->U[i] = c->U_next[i];
  rscasadi_clamp(tau_out, TAU_MAX, ${SYM}_NU);
  return 0;
}

int ${sym}_feedback(${sym}_t *c, const double *x_measured, double *tau_out) {
  if (!tau_out) return ${SYM}_BAD_ARGUMENT;
  const double t0 = rscasadi_now();
  const int flag = feedback(c, x_measured, tau_out);
  if (c) c->last_feedback_seconds = rscasadi_now() - t0;
  return flag;
}

int ${sym}_step(${sym}_t *c, const double *x_measured, const double *reference, double *tau_out) {
  if (!tau_out) return ${SYM}_BAD_ARGUMENT;
  const double t0 = rscasadi_now();
  ${sym}_prepare(c, reference);           /* its code, if any, is the feedback's */
  const int flag = ${sym}_feedback(c, x_measured, tau_out);
  if (c) c->last_step_seconds = rscasadi_now() - t0;
  return flag;
}

/* the target held over the horizon at rest: joint space theta (n) and zero speeds; task space
 * p (3), zero velocity, and R (9, column-major) when the rotation is followed */
int ${sym}_step_to(${sym}_t *c, const double *x_measured, const double *target, double *tau_out) {
  if (!tau_out) return ${SYM}_BAD_ARGUMENT;
  if (!c) {
    rscasadi_zero(tau_out, ${SYM}_NU);
    return ${SYM}_NOT_INITIALISED;
  }
  if (!target) return ${sym}_step(c, x_measured, NULL, tau_out);
  for (int k = 0; k < ${SYM}_HORIZON; ++k) {
    double *col = c->target_reference + NROWS * k;
    for (int i = 0; i < NROWS; ++i) col[i] = 0.0;
    if (${SYM}_TASK_SPACE) {
      for (int i = 0; i < 3; ++i) col[i] = target[i];
      for (int i = 0; i < NROWS - 6; ++i) col[6 + i] = target[3 + i];
    } else {
      for (int i = 0; i < ${SYM}_NU; ++i) col[i] = target[i];
    }
  }
  return ${sym}_step(c, x_measured, c->target_reference, tau_out);
}
