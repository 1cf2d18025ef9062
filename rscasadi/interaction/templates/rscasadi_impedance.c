#define _POSIX_C_SOURCE 199309L
#include <math.h>
#include <time.h>
#include "rscasadi_impedance.h"
#include "rscasadi_guard.h"
#include "impedance.h"

static const double LIMIT[IMPEDANCE_NU] = {${limits}};                      /* INFINITY: no limit */
static const double X_LO[IMPEDANCE_NX] = {${x_lo}}, X_HI[IMPEDANCE_NX] = {${x_hi}};
static const double REF_LO[IMPEDANCE_NREF] = {${ref_lo}}, REF_HI[IMPEDANCE_NREF] = {${ref_hi}};
static const double K_LO[IMPEDANCE_NK] = {${k_lo}}, K_HI[IMPEDANCE_NK] = {${k_hi}};
static const double Z_LO[IMPEDANCE_NK] = {${z_lo}}, Z_HI[IMPEDANCE_NK] = {${z_hi}};
#define PASSIVE ${passive}                 /* 1: the motor-position (passive) design checks its margin */
typedef char casadi_int_is_long_long[sizeof(casadi_int) == sizeof(long long) ? 1 : -1];
typedef char work_fits[sizeof(((impedance_t *)0)->w) >= sizeof(casadi_real) * (impedance_SZ_W > impedance_hold_SZ_W ? impedance_SZ_W : impedance_hold_SZ_W) ? 1 : -1];
typedef char iwork_fits[sizeof(((impedance_t *)0)->iw) >= sizeof(casadi_int) * (impedance_SZ_IW > impedance_hold_SZ_IW ? impedance_SZ_IW : impedance_hold_SZ_IW) ? 1 : -1];

size_t impedance_sizeof(void) { return sizeof(impedance_t); }

double impedance_step_seconds(const impedance_t *c) { return c ? c->last_step_seconds : 0.0; }

int impedance_init(impedance_t *c, const double *x_measured) {
  if (!c) return IMPEDANCE_BAD_ARGUMENT;
  c->ready = 0;
  c->last_step_seconds = 0.0;
  if (!rscasadi_within(x_measured, X_LO, X_HI, IMPEDANCE_NX)) return IMPEDANCE_BAD_MEASUREMENT;
  for (size_t i = 0; i < sizeof c->w / sizeof c->w[0]; ++i) c->w[i] = 0.0;
  for (int i = 0; i < IMPEDANCE_NX; ++i) c->x_good[i] = x_measured[i];
  c->ready = RSCASADI_READY;
  return 0;
}

/* the safe output: the holding torque of the last good state, within the limits */
static int refuse(impedance_t *c, double *tau_out, int code) {
  const casadi_real *arg[impedance_hold_SZ_ARG + 1] = {c->x_good, c->x_good + IMPEDANCE_NU};
  casadi_real *res[impedance_hold_SZ_RES + 1] = {tau_out};
  if (impedance_hold(arg, res, (casadi_int *)c->iw, c->w, 0) != 0) rscasadi_zero(tau_out, IMPEDANCE_NU);
  rscasadi_clamp(tau_out, LIMIT, IMPEDANCE_NU);
  return code;
}

/* impedance(theta, phi, dtheta, dphi, reference, stiffness, damping_ratio) -> tau, u, q_bar, margin */
static int step(impedance_t *c, const double *x, const double *reference, const double *stiffness,
                const double *damping_ratio, double *tau_out) {
  double u[IMPEDANCE_NU], q_bar[IMPEDANCE_NU], margin;
  if (!c || c->ready != RSCASADI_READY) {
    rscasadi_zero(tau_out, IMPEDANCE_NU);
    return IMPEDANCE_NOT_INITIALISED;
  }
  if (!rscasadi_within(x, X_LO, X_HI, IMPEDANCE_NX)) return refuse(c, tau_out, IMPEDANCE_BAD_MEASUREMENT);
  for (int i = 0; i < IMPEDANCE_NX; ++i) c->x_good[i] = x[i];
  if (!rscasadi_within(reference, REF_LO, REF_HI, IMPEDANCE_NREF) || !rscasadi_within(stiffness, K_LO, K_HI, IMPEDANCE_NK)
      || !rscasadi_within(damping_ratio, Z_LO, Z_HI, IMPEDANCE_NK))
    return refuse(c, tau_out, IMPEDANCE_BAD_REFERENCE);
  const casadi_real *arg[impedance_SZ_ARG + 1] = {x, x + IMPEDANCE_NU, x + 2 * IMPEDANCE_NU, x + 3 * IMPEDANCE_NU,
                                                  reference, stiffness, damping_ratio};
  casadi_real *res[impedance_SZ_RES + 1] = {tau_out, u, q_bar, &margin};
  if (impedance(arg, res, (casadi_int *)c->iw, c->w, 0) != 0) return refuse(c, tau_out, IMPEDANCE_FAILED);
  for (int i = 0; i < IMPEDANCE_NU; ++i)
    if (!isfinite(tau_out[i])) return refuse(c, tau_out, IMPEDANCE_NOT_FINITE);
  if (PASSIVE && !(margin > 0.0)) return refuse(c, tau_out, IMPEDANCE_TOO_STIFF);
  rscasadi_clamp(tau_out, LIMIT, IMPEDANCE_NU);
  return 0;
}

int impedance_step(impedance_t *c, const double *x_measured, const double *reference, const double *stiffness,
                   const double *damping_ratio, double *tau_out) {
  if (!tau_out) return IMPEDANCE_BAD_ARGUMENT;
  const double t0 = rscasadi_now();
  const int code = step(c, x_measured, reference, stiffness, damping_ratio, tau_out);
  if (c) c->last_step_seconds = rscasadi_now() - t0;
  return code;
}
