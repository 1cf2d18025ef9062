#define _POSIX_C_SOURCE 199309L
#include <math.h>
#include <time.h>
#include "rscasadi_observer.h"
#include "rscasadi_guard.h"
#include "observer_terms.h"

static const double DT = ${dt};
static const double K[OBSERVER_NQ] = {${gains}};
static const double THRESHOLD = ${threshold};           /* N m on any link: OBSERVER_COLLISION */
static const double X_LO[OBSERVER_NX] = {${x_lo}}, X_HI[OBSERVER_NX] = {${x_hi}};   /* a plausible measurement */
static const double TAU_LO[OBSERVER_NU] = {${tau_lo}}, TAU_HI[OBSERVER_NU] = {${tau_hi}};  /* a plausible torque */
typedef char casadi_int_is_long_long[sizeof(casadi_int) == sizeof(long long) ? 1 : -1];
typedef char work_fits[sizeof(((observer_t *)0)->w) >= sizeof(casadi_real) * observer_terms_SZ_W ? 1 : -1];

size_t observer_sizeof(void) { return sizeof(observer_t); }

double observer_step_seconds(const observer_t *obs) { return obs ? obs->last_step_seconds : 0.0; }

/* observer_terms(theta, phi, dtheta, dphi, tau) -> p = M dq, beta = dM dq - G(q, dq, 0, tau) */
static int terms(observer_t *obs, const double *x, const double *tau, double *p, double *beta) {
  const casadi_real *arg[observer_terms_SZ_ARG + 1] = {x, x + OBSERVER_NU, x + 2 * OBSERVER_NU, x + 3 * OBSERVER_NU, tau};
  casadi_real *res[observer_terms_SZ_RES + 1] = {p, beta};
  return observer_terms(arg, res, (casadi_int *)obs->iw, obs->w, 0);
}

int observer_init(observer_t *obs, const double *x_measured) {
  double zero[OBSERVER_NU] = {0}, beta[OBSERVER_NQ];
  if (!obs) return OBSERVER_BAD_ARGUMENT;
  obs->ready = 0;
  obs->last_step_seconds = 0.0;
  if (!rscasadi_within(x_measured, X_LO, X_HI, OBSERVER_NX)) return OBSERVER_BAD_MEASUREMENT;
  if (terms(obs, x_measured, zero, obs->p0, beta) != 0) return OBSERVER_FAILED;
  for (int i = 0; i < OBSERVER_NQ; ++i) {
    if (!isfinite(obs->p0[i])) return OBSERVER_NOT_FINITE;
    obs->integral[i] = obs->r[i] = obs->beta[i] = 0.0;
  }
  obs->started = 0;
  obs->ready = RSCASADI_READY;
  return 0;
}

/* a refused sample: the last r, the observer's state kept */
static int refuse(const observer_t *obs, double *r_out, int code) {
  for (int i = 0; i < OBSERVER_NQ; ++i) r_out[i] = obs->r[i];
  return code;
}

/* the integral of beta by the trapezoidal rule (the first sample: the rectangle rule), r held */
static int step(observer_t *obs, const double *x_measured, const double *tau_applied, double *r_out) {
  double p[OBSERVER_NQ], beta[OBSERVER_NQ], integral[OBSERVER_NQ], r[OBSERVER_NQ];
  int finite = 1;
  if (!obs || obs->ready != RSCASADI_READY) {
    rscasadi_zero(r_out, OBSERVER_NQ);
    return OBSERVER_NOT_INITIALISED;
  }
  if (!rscasadi_within(x_measured, X_LO, X_HI, OBSERVER_NX)) return refuse(obs, r_out, OBSERVER_BAD_MEASUREMENT);
  if (!rscasadi_within(tau_applied, TAU_LO, TAU_HI, OBSERVER_NU)) return refuse(obs, r_out, OBSERVER_BAD_TORQUE);
  if (terms(obs, x_measured, tau_applied, p, beta) != 0) return refuse(obs, r_out, OBSERVER_FAILED);
  for (int i = 0; i < OBSERVER_NQ; ++i) {
    const double before = obs->started ? obs->beta[i] : beta[i];
    integral[i] = obs->integral[i] + DT * (0.5 * (beta[i] + before) + obs->r[i]);
    r[i] = K[i] * (p[i] - obs->p0[i] - integral[i]);
    finite = finite && isfinite(r[i]);
  }
  if (!finite) return refuse(obs, r_out, OBSERVER_NOT_FINITE);
  for (int i = 0; i < OBSERVER_NQ; ++i) {
    obs->integral[i] = integral[i];
    obs->beta[i] = beta[i];
    r_out[i] = obs->r[i] = r[i];
  }
  obs->started = 1;
  for (int i = 0; i < OBSERVER_NU; ++i)
    if (fabs(r[i]) > THRESHOLD) return OBSERVER_COLLISION;
  return 0;
}

int observer_step(observer_t *obs, const double *x_measured, const double *tau_applied, double *r_out) {
  if (!r_out) return OBSERVER_BAD_ARGUMENT;
  const double t0 = rscasadi_now();
  const int code = step(obs, x_measured, tau_applied, r_out);
  if (obs) obs->last_step_seconds = rscasadi_now() - t0;
  return code;
}
