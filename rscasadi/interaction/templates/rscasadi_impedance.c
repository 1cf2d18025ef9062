#define _POSIX_C_SOURCE 199309L
#include <math.h>
#include <time.h>
#include "rscasadi_impedance.h"
#include "impedance.h"

static const double LIMIT[IMPEDANCE_NU] = {${limits}};
#define PASSIVE ${passive}                 /* 1: the motor-position (passive) design checks its margin */
typedef char casadi_int_is_long_long[sizeof(casadi_int) == sizeof(long long) ? 1 : -1];
typedef char work_fits[sizeof(((impedance_t *)0)->w) >= sizeof(casadi_real) * impedance_SZ_W ? 1 : -1];

static double now(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}

size_t impedance_sizeof(void) { return sizeof(impedance_t); }

double impedance_step_seconds(const impedance_t *c) { return c->last_step_seconds; }

int impedance_init(impedance_t *c, const double *x_measured) {
  for (int i = 0; i < IMPEDANCE_NX; ++i)
    if (!isfinite(x_measured[i])) return IMPEDANCE_NOT_FINITE;
  for (size_t i = 0; i < sizeof c->w / sizeof c->w[0]; ++i) c->w[i] = 0.0;
  c->last_step_seconds = 0.0;
  return 0;
}

static int refuse(double *tau_out, int code) {
  for (int i = 0; i < IMPEDANCE_NU; ++i) tau_out[i] = 0.0;
  return code;
}

/* impedance(theta, phi, dtheta, dphi, reference, stiffness, damping_ratio) -> tau, u, q_bar, margin */
int impedance_step(impedance_t *c, const double *x, const double *reference, const double *stiffness,
                   const double *damping_ratio, double *tau_out) {
  double t0 = now(), u[IMPEDANCE_NU], q_bar[IMPEDANCE_NU], margin;
  const casadi_real *arg[impedance_SZ_ARG + 1] = {x, x + IMPEDANCE_NU, x + 2 * IMPEDANCE_NU, x + 3 * IMPEDANCE_NU,
                                                  reference, stiffness, damping_ratio};
  casadi_real *res[impedance_SZ_RES + 1] = {tau_out, u, q_bar, &margin};
  int code = 0;
  if (impedance(arg, res, (casadi_int *)c->iw, c->w, 0) != 0) code = refuse(tau_out, IMPEDANCE_FAILED);
  for (int i = 0; i < IMPEDANCE_NU && !code; ++i)
    if (!isfinite(tau_out[i])) code = refuse(tau_out, IMPEDANCE_NOT_FINITE);
  if (!code && PASSIVE && !(margin > 0.0)) code = refuse(tau_out, IMPEDANCE_TOO_STIFF);
  for (int i = 0; i < IMPEDANCE_NU && !code; ++i) tau_out[i] = fmin(fmax(tau_out[i], -LIMIT[i]), LIMIT[i]);
  c->last_step_seconds = now() - t0;
  return code;
}
