#include <math.h>
#include "rscasadi_impedance.h"
#include "impedance.h"

static const double LIMIT[IMPEDANCE_NU] = {${limits}};
typedef char casadi_int_is_long_long[sizeof(casadi_int) == sizeof(long long) ? 1 : -1];
typedef char work_fits[sizeof(((impedance_t *)0)->w) >= sizeof(casadi_real) * impedance_SZ_W ? 1 : -1];

size_t impedance_sizeof(void) { return sizeof(impedance_t); }

int impedance_init(impedance_t *c, const double *x_measured) {
  for (int i = 0; i < IMPEDANCE_NX; ++i)
    if (!isfinite(x_measured[i])) return IMPEDANCE_NOT_FINITE;
  for (size_t i = 0; i < sizeof c->w / sizeof c->w[0]; ++i) c->w[i] = 0.0;
  return 0;
}

/* impedance(theta, phi, dtheta, dphi, pose_desired, stiffness, damping_ratio) -> tau, T_d */
int impedance_step(impedance_t *c, const double *x, const double *pose_desired, const double *stiffness,
                   const double *damping_ratio, double *tau_out) {
  double T_d[IMPEDANCE_NU];
  const casadi_real *arg[impedance_SZ_ARG + 1] = {x, x + IMPEDANCE_NU, x + 2 * IMPEDANCE_NU, x + 3 * IMPEDANCE_NU,
                                                  pose_desired, stiffness, damping_ratio};
  casadi_real *res[impedance_SZ_RES + 1] = {tau_out, T_d};
  if (impedance(arg, res, (casadi_int *)c->iw, c->w, 0) != 0) return IMPEDANCE_FAILED;
  int finite = 1;
  for (int i = 0; i < IMPEDANCE_NU; ++i) finite = finite && isfinite(tau_out[i]);
  if (!finite) {
    for (int i = 0; i < IMPEDANCE_NU; ++i) tau_out[i] = 0.0;
    return IMPEDANCE_NOT_FINITE;
  }
  for (int i = 0; i < IMPEDANCE_NU; ++i) tau_out[i] = fmin(fmax(tau_out[i], -LIMIT[i]), LIMIT[i]);
  return 0;
}
