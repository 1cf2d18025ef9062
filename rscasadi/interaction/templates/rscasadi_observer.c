#define _POSIX_C_SOURCE 199309L
#include <math.h>
#include <time.h>
#include "${header}"
#include "rscasadi_guard.h"
#include "${casadi_header}"

static const double DT = ${dt};
static const double K[${SYM}_NQ] = {${gains}};
static const double THRESHOLD = ${threshold};           /* N m on any link: ${SYM}_COLLISION */
static const double X_LO[${SYM}_NX] = {${x_lo}}, X_HI[${SYM}_NX] = {${x_hi}};   /* a plausible measurement */
static const double TAU_LO[${SYM}_NU] = {${tau_lo}}, TAU_HI[${SYM}_NU] = {${tau_hi}};  /* a plausible torque */
typedef char casadi_int_is_long_long[sizeof(casadi_int) == sizeof(long long) ? 1 : -1];
typedef char work_fits[sizeof(((${sym}_t *)0)->w) >= sizeof(casadi_real) * (${sz_w_check}) ? 1 : -1];

size_t ${sym}_sizeof(void) { return sizeof(${sym}_t); }

double ${sym}_step_seconds(const ${sym}_t *obs) { return obs ? obs->last_step_seconds : 0.0; }

/* ${sym}_terms(theta, phi, dtheta, dphi, tau) -> p = M dq, beta = dM dq - G(q, dq, 0, tau) */
static int terms(${sym}_t *obs, const double *x, const double *tau, double *p, double *beta) {
  const casadi_real *arg[${sym}_terms_SZ_ARG + 1] = {x, x + ${SYM}_NU, x + 2 * ${SYM}_NU, x + 3 * ${SYM}_NU, tau};
  casadi_real *res[${sym}_terms_SZ_RES + 1] = {p, beta};
  return ${sym}_terms(arg, res, (casadi_int *)obs->iw, obs->w, 0);
}

int ${sym}_init(${sym}_t *obs, const double *x_measured) {
  double zero[${SYM}_NU] = {0}, beta[${SYM}_NQ];
  if (!obs) return ${SYM}_BAD_ARGUMENT;
  obs->ready = 0;
  obs->last_step_seconds = 0.0;
  if (!rscasadi_within(x_measured, X_LO, X_HI, ${SYM}_NX)) return ${SYM}_BAD_MEASUREMENT;
  if (terms(obs, x_measured, zero, obs->p0, beta) != 0) return ${SYM}_FAILED;
  for (int i = 0; i < ${SYM}_NQ; ++i) {
    if (!isfinite(obs->p0[i])) return ${SYM}_NOT_FINITE;
    obs->integral[i] = obs->r[i] = obs->beta[i] = 0.0;
  }
  obs->started = 0;
  obs->ready = RSCASADI_READY;
  return 0;
}

/* a refused sample: the last r, the observer's state kept */
static int refuse(const ${sym}_t *obs, double *r_out, int code) {
  for (int i = 0; i < ${SYM}_NQ; ++i) r_out[i] = obs->r[i];
  return code;
}

/* the integral of beta by the trapezoidal rule (the first sample: the rectangle rule), r held */
static int step(${sym}_t *obs, const double *x_measured, const double *tau_applied, double *r_out) {
  double p[${SYM}_NQ], beta[${SYM}_NQ], integral[${SYM}_NQ], r[${SYM}_NQ];
  int finite = 1;
  if (!obs || obs->ready != RSCASADI_READY) {
    rscasadi_zero(r_out, ${SYM}_NQ);
    return ${SYM}_NOT_INITIALISED;
  }
  if (!rscasadi_within(x_measured, X_LO, X_HI, ${SYM}_NX)) return refuse(obs, r_out, ${SYM}_BAD_MEASUREMENT);
  if (!rscasadi_within(tau_applied, TAU_LO, TAU_HI, ${SYM}_NU)) return refuse(obs, r_out, ${SYM}_BAD_TORQUE);
  if (terms(obs, x_measured, tau_applied, p, beta) != 0) return refuse(obs, r_out, ${SYM}_FAILED);
  for (int i = 0; i < ${SYM}_NQ; ++i) {
    const double before = obs->started ? obs->beta[i] : beta[i];
    integral[i] = obs->integral[i] + DT * (0.5 * (beta[i] + before) + obs->r[i]);
    r[i] = K[i] * (p[i] - obs->p0[i] - integral[i]);
    finite = finite && isfinite(r[i]);
  }
  if (!finite) return refuse(obs, r_out, ${SYM}_NOT_FINITE);
  for (int i = 0; i < ${SYM}_NQ; ++i) {
    obs->integral[i] = integral[i];
    obs->beta[i] = beta[i];
    r_out[i] = obs->r[i] = r[i];
  }
  obs->started = 1;
  for (int i = 0; i < ${SYM}_NU; ++i)
    if (fabs(r[i]) > THRESHOLD) return ${SYM}_COLLISION;
  return 0;
}

int ${sym}_step(${sym}_t *obs, const double *x_measured, const double *tau_applied, double *r_out) {
  if (!r_out) return ${SYM}_BAD_ARGUMENT;
  const double t0 = rscasadi_now();
  const int code = step(obs, x_measured, tau_applied, r_out);
  if (obs) obs->last_step_seconds = rscasadi_now() - t0;
  return code;
}
