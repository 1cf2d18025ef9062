#define _POSIX_C_SOURCE 199309L
#include <math.h>
#include <time.h>
#include "${header}"
#include "rscasadi_guard.h"
#include "${mpc}_rti.h"

#define NXP (${MPC}_NX * (${MPC}_HORIZON + 1))
#define NUP (${MPC}_NU * ${MPC}_HORIZON)
#define NROWS (${MPC}_NREF / ${MPC}_HORIZON)
#define MASS_INDEX ${mass_index}              /* the payload's mass in the parameters, or -1: none */
static const double NOMINAL[${MPC}_NP + 1] = {${nominal}};      /* the model's parameters (manifest.json) */
static const double TAU_MAX[${MPC}_NU] = {${tau_max}};          /* INFINITY: no limit */
static const double X_LO[${MPC}_NX] = {${x_lo}}, X_HI[${MPC}_NX] = {${x_hi}};      /* a plausible measurement */
static const double REF_LO[NROWS] = {${ref_lo}}, REF_HI[NROWS] = {${ref_hi}};  /* a reference column */
typedef char casadi_int_is_long_long[sizeof(casadi_int) == sizeof(long long) ? 1 : -1];
typedef char work_fits[sizeof(((${mpc}_t *)0)->w) >= sizeof(casadi_real) * (${mpc}_rti_SZ_W > ${mpc}_hold_SZ_W ? ${mpc}_rti_SZ_W : ${mpc}_hold_SZ_W) ? 1 : -1];
typedef char iwork_fits[sizeof(((${mpc}_t *)0)->iw) >= sizeof(casadi_int) * (${mpc}_rti_SZ_IW > ${mpc}_hold_SZ_IW ? ${mpc}_rti_SZ_IW : ${mpc}_hold_SZ_IW) ? 1 : -1];

size_t ${mpc}_sizeof(void) { return sizeof(${mpc}_t); }

double ${mpc}_step_seconds(const ${mpc}_t *c) { return c ? c->last_step_seconds : 0.0; }

int ${mpc}_set_payload_mass(${mpc}_t *c, double mass) {
  if (MASS_INDEX < 0) return ${MPC}_NO_PAYLOAD;
  if (!c || !isfinite(mass) || mass < 0) return ${MPC}_BAD_ARGUMENT;
  c->params[${MPC}_NU + MASS_INDEX] = mass;
  return 0;
}

static int finite_all(const double *v, int n) {
  if (!v) return 0;
  for (int i = 0; i < n; ++i)
    if (!isfinite(v[i])) return 0;
  return 1;
}

int ${mpc}_set_parameters(${mpc}_t *c, const double *p) {
  if (${MPC}_NP == 0 || !c || !finite_all(p, ${MPC}_NP)) return ${MPC}_BAD_ARGUMENT;
  for (int i = 0; i < ${MPC}_NP; ++i) c->params[${MPC}_NU + i] = p[i];
  return 0;
}

int ${mpc}_set_posture(${mpc}_t *c, const double *theta) {
  if (!c || !rscasadi_within(theta, X_LO, X_HI, ${MPC}_NU)) return ${MPC}_BAD_ARGUMENT;
  for (int i = 0; i < ${MPC}_NU; ++i) c->params[i] = theta[i];
  return 0;
}

/* ${mpc}_hold at x into X, U: the arm held still at x over the horizon; 0 if that plan is finite */
static int hold(${mpc}_t *c, const double *x, double *X, double *U) {
  const casadi_real *arg[${mpc}_hold_SZ_ARG + 1] = {x, c->params};
  casadi_real *res[${mpc}_hold_SZ_RES + 1] = {X, U};
  if (${mpc}_hold(arg, res, (casadi_int *)c->iw, c->w, 0) != 0) return ${MPC}_FAILED;
  return finite_all(X, NXP) && finite_all(U, NUP) ? 0 : ${MPC}_NOT_FINITE;
}

/* the safe output: the holding torque of the last good state, within the limits */
static int refuse(${mpc}_t *c, double *tau_out, int code) {
  if (hold(c, c->x_good, c->X_next, c->U_next) == 0)
    for (int i = 0; i < ${MPC}_NU; ++i) tau_out[i] = c->U_next[i];
  else
    rscasadi_zero(tau_out, ${MPC}_NU);
  rscasadi_clamp(tau_out, TAU_MAX, ${MPC}_NU);
  return code;
}

int ${mpc}_init(${mpc}_t *c, const double *x_measured) { return ${mpc}_init_parameters(c, x_measured, NOMINAL); }

int ${mpc}_init_parameters(${mpc}_t *c, const double *x_measured, const double *p) {
  if (!c) return ${MPC}_BAD_ARGUMENT;
  c->ready = 0;
  c->last_step_seconds = 0.0;
  if (!finite_all(p, ${MPC}_NP)) return ${MPC}_BAD_ARGUMENT;
  if (!rscasadi_within(x_measured, X_LO, X_HI, ${MPC}_NX)) return ${MPC}_BAD_MEASUREMENT;
  for (int i = 0; i < ${MPC}_NU; ++i) c->params[i] = x_measured[i];
  for (int i = 0; i < ${MPC}_NP; ++i) c->params[${MPC}_NU + i] = p[i];
  const int code = hold(c, x_measured, c->X, c->U);
  if (code) return code;
  for (int i = 0; i < ${MPC}_NX; ++i) c->x_good[i] = x_measured[i];
  c->ready = RSCASADI_READY;
  return 0;
}

static int reference_ok(const double *reference) {
  if (!reference) return 0;
  for (int k = 0; k < ${MPC}_HORIZON; ++k)
    if (!rscasadi_within(reference + NROWS * k, REF_LO, REF_HI, NROWS)) return 0;
  return 1;
}

static int step(${mpc}_t *c, const double *x_measured, const double *reference, double *tau_out) {
  if (!c || c->ready != RSCASADI_READY) {
    rscasadi_zero(tau_out, ${MPC}_NU);
    return ${MPC}_NOT_INITIALISED;
  }
  if (!rscasadi_within(x_measured, X_LO, X_HI, ${MPC}_NX)) return refuse(c, tau_out, ${MPC}_BAD_MEASUREMENT);
  for (int i = 0; i < ${MPC}_NX; ++i) c->x_good[i] = x_measured[i];
  if (!reference_ok(reference)) return refuse(c, tau_out, ${MPC}_BAD_REFERENCE);
  const casadi_real *arg[${mpc}_rti_SZ_ARG + 1] = {x_measured, reference, c->X, c->U, c->params};
  casadi_real *res[${mpc}_rti_SZ_RES + 1] = {tau_out, c->X_next, c->U_next};
  int code = ${mpc}_rti(arg, res, (casadi_int *)c->iw, c->w, 0) != 0 ? ${MPC}_FAILED : 0;
  if (!code && !(finite_all(c->X_next, NXP) && finite_all(c->U_next, NUP) && finite_all(tau_out, ${MPC}_NU)))
    code = ${MPC}_NOT_FINITE;
  if (code) {                             /* the plan restarts from the arm held here */
    refuse(c, tau_out, code);
    if (hold(c, x_measured, c->X, c->U) != 0) c->ready = 0;
    return code;
  }
  for (int i = 0; i < NXP; ++i) c->X[i] = c->X_next[i];
  for (int i = 0; i < NUP; ++i) c->U[i] = c->U_next[i];
  rscasadi_clamp(tau_out, TAU_MAX, ${MPC}_NU);
  return 0;
}

int ${mpc}_step(${mpc}_t *c, const double *x_measured, const double *reference, double *tau_out) {
  if (!tau_out) return ${MPC}_BAD_ARGUMENT;
  const double t0 = rscasadi_now();
  const int flag = step(c, x_measured, reference, tau_out);
  if (c) c->last_step_seconds = rscasadi_now() - t0;
  return flag;
}

/* the target held over the horizon at rest: joint space theta (n) and zero speeds; task space
 * p (3), zero velocity, and R (9, column-major) when the rotation is followed */
int ${mpc}_step_to(${mpc}_t *c, const double *x_measured, const double *target, double *tau_out) {
  if (!tau_out) return ${MPC}_BAD_ARGUMENT;
  if (!c) {
    rscasadi_zero(tau_out, ${MPC}_NU);
    return ${MPC}_NOT_INITIALISED;
  }
  if (!target) return ${mpc}_step(c, x_measured, NULL, tau_out);
  for (int k = 0; k < ${MPC}_HORIZON; ++k) {
    double *col = c->target_reference + NROWS * k;
    for (int i = 0; i < NROWS; ++i) col[i] = 0.0;
    if (${MPC}_TASK_SPACE) {
      for (int i = 0; i < 3; ++i) col[i] = target[i];
      for (int i = 0; i < NROWS - 6; ++i) col[6 + i] = target[3 + i];
    } else {
      for (int i = 0; i < ${MPC}_NU; ++i) col[i] = target[i];
    }
  }
  return ${mpc}_step(c, x_measured, c->target_reference, tau_out);
}
