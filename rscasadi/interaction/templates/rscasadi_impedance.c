#define _POSIX_C_SOURCE 199309L
#include <math.h>
#include <time.h>
#include "${header}"
#include "rscasadi_guard.h"
#include "${casadi_header}"

static const double LIMIT[${SYM}_NU] = {${limits}};                      /* INFINITY: no limit */
static const double X_LO[${SYM}_NX] = {${x_lo}}, X_HI[${SYM}_NX] = {${x_hi}};
static const double REF_LO[${SYM}_NREF] = {${ref_lo}}, REF_HI[${SYM}_NREF] = {${ref_hi}};
static const double K_LO[${SYM}_NK] = {${k_lo}}, K_HI[${SYM}_NK] = {${k_hi}};
static const double Z_LO[${SYM}_NK] = {${z_lo}}, Z_HI[${SYM}_NK] = {${z_hi}};
#define PASSIVE ${passive}                 /* 1: the motor-position (passive) design checks its margin */
typedef char casadi_int_is_long_long[sizeof(casadi_int) == sizeof(long long) ? 1 : -1];
typedef char work_fits[sizeof(((${sym}_t *)0)->w) >= sizeof(casadi_real) * (${sz_w_check}) ? 1 : -1];
typedef char iwork_fits[sizeof(((${sym}_t *)0)->iw) >= sizeof(casadi_int) * (${sz_iw_check}) ? 1 : -1];

size_t ${sym}_sizeof(void) { return sizeof(${sym}_t); }

double ${sym}_step_seconds(const ${sym}_t *c) { return c ? c->last_step_seconds : 0.0; }

int ${sym}_init(${sym}_t *c, const double *x_measured) {
  if (!c) return ${SYM}_BAD_ARGUMENT;
  c->ready = 0;
  c->last_step_seconds = 0.0;
  if (!rscasadi_within(x_measured, X_LO, X_HI, ${SYM}_NX)) return ${SYM}_BAD_MEASUREMENT;
  for (size_t i = 0; i < sizeof c->w / sizeof c->w[0]; ++i) c->w[i] = 0.0;
  for (int i = 0; i < ${SYM}_NX; ++i) c->x_good[i] = x_measured[i];
  c->ready = RSCASADI_READY;
  return 0;
}

/* the safe output: the holding torque of the last good state, within the limits */
static int refuse(${sym}_t *c, double *tau_out, int code) {
  const casadi_real *arg[${sym}_hold_SZ_ARG + 1] = {c->x_good, c->x_good + ${SYM}_NU};
  casadi_real *res[${sym}_hold_SZ_RES + 1] = {tau_out};
  if (${sym}_hold(arg, res, (casadi_int *)c->iw, c->w, 0) != 0) rscasadi_zero(tau_out, ${SYM}_NU);
  rscasadi_clamp(tau_out, LIMIT, ${SYM}_NU);
  return code;
}

/* ${sym}_law(theta, phi, dtheta, dphi, reference, stiffness, damping_ratio) -> tau, u, q_bar, margin */
static int step(${sym}_t *c, const double *x, const double *reference, const double *stiffness,
                const double *damping_ratio, double *tau_out) {
  double u[${SYM}_NU], q_bar[${SYM}_NU], margin;
  if (!c || c->ready != RSCASADI_READY) {
    rscasadi_zero(tau_out, ${SYM}_NU);
    return ${SYM}_NOT_INITIALISED;
  }
  if (!rscasadi_within(x, X_LO, X_HI, ${SYM}_NX)) return refuse(c, tau_out, ${SYM}_BAD_MEASUREMENT);
  for (int i = 0; i < ${SYM}_NX; ++i) c->x_good[i] = x[i];
  if (!rscasadi_within(reference, REF_LO, REF_HI, ${SYM}_NREF) || !rscasadi_within(stiffness, K_LO, K_HI, ${SYM}_NK)
      || !rscasadi_within(damping_ratio, Z_LO, Z_HI, ${SYM}_NK))
    return refuse(c, tau_out, ${SYM}_BAD_REFERENCE);
  const casadi_real *arg[${sym}_law_SZ_ARG + 1] = {x, x + ${SYM}_NU, x + 2 * ${SYM}_NU, x + 3 * ${SYM}_NU,
                                                  reference, stiffness, damping_ratio};
  casadi_real *res[${sym}_law_SZ_RES + 1] = {tau_out, u, q_bar, &margin};
  if (${sym}_law(arg, res, (casadi_int *)c->iw, c->w, 0) != 0) return refuse(c, tau_out, ${SYM}_FAILED);
  for (int i = 0; i < ${SYM}_NU; ++i)
    if (!isfinite(tau_out[i])) return refuse(c, tau_out, ${SYM}_NOT_FINITE);
  if (PASSIVE && !(margin > 0.0)) return refuse(c, tau_out, ${SYM}_TOO_STIFF);
  rscasadi_clamp(tau_out, LIMIT, ${SYM}_NU);
  return 0;
}

int ${sym}_step(${sym}_t *c, const double *x_measured, const double *reference, const double *stiffness,
                   const double *damping_ratio, double *tau_out) {
  if (!tau_out) return ${SYM}_BAD_ARGUMENT;
  const double t0 = rscasadi_now();
  const int code = step(c, x_measured, reference, stiffness, damping_ratio, tau_out);
  if (c) c->last_step_seconds = rscasadi_now() - t0;
  return code;
}
