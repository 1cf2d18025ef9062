#include <math.h>
#include "${header}"
#include "rscasadi_guard.h"
#include "rscasadi_arm.h"

#define N ${n}
static const double TAU_MAX[N] = {${tau_max}};                              /* INFINITY: no limit */
static const double THETA_LO[N] = {${theta_lo_c}}, THETA_HI[N] = {${theta_hi_c}};
static const double SPEED_HI[N] = {${speed_c}};
static const double H_LO = ${h_lo}, H_HI = ${h_hi}, ACCEL = ${accel};
typedef char casadi_int_is_long_long[sizeof(casadi_int) == sizeof(long long) ? 1 : -1];
#define MAXOF(a, b) ((a) > (b) ? (a) : (b))
typedef char work_fits[sizeof(((${p}ff_t *)0)->w) >= sizeof(casadi_real) * MAXOF(MAXOF(${p}feedforward_init_SZ_W, ${p}feedforward_step_SZ_W), ${p}inverse_dynamics_SZ_W) ? 1 : -1];
typedef char iwork_fits[sizeof(((${p}ff_t *)0)->iw) >= sizeof(casadi_int) * MAXOF(MAXOF(${p}feedforward_init_SZ_IW, ${p}feedforward_step_SZ_IW), ${p}inverse_dynamics_SZ_IW) ? 1 : -1];

size_t ${p}ff_sizeof(void) { return sizeof(${p}ff_t); }

static int sample_ok(const double *th, const double *dth, const double *ddth) {
  double speed_lo[N], accel_lo[N], accel_hi[N];
  for (int i = 0; i < N; ++i) speed_lo[i] = -SPEED_HI[i], accel_lo[i] = -ACCEL, accel_hi[i] = ACCEL;
  return rscasadi_within(th, THETA_LO, THETA_HI, N) && rscasadi_within(dth, speed_lo, SPEED_HI, N)
         && rscasadi_within(ddth, accel_lo, accel_hi, N);
}

static int finite_all(const double *v, int n) {
  for (int i = 0; i < n; ++i)
    if (!isfinite(v[i])) return 0;
  return 1;
}

/* the safe output: the holding torque of the last good sample (theta_good, phi = theta + psi) */
static int refuse(${p}ff_t *c, double *tau_out, int code) {
  double phi[N], zero[N] = {0}, T[N];
  for (int i = 0; i < N; ++i) phi[i] = c->theta_good[i] + c->state[i];
  const casadi_real *arg[${p}inverse_dynamics_SZ_ARG + 1] = {c->theta_good, phi, zero, zero, zero, zero};
  casadi_real *res[${p}inverse_dynamics_SZ_RES + 1] = {tau_out, T};
  if (${p}inverse_dynamics(arg, res, (casadi_int *)c->iw, c->w, 0) != 0) rscasadi_zero(tau_out, N);
  rscasadi_clamp(tau_out, TAU_MAX, N);
  return code;
}

int ${p}ff_init(${p}ff_t *c, const double *theta_d, const double *dtheta_d, const double *ddtheta_d, double *tau_out) {
  double state[4 * N];
  if (!c || !tau_out) return FF_BAD_ARGUMENT;
  c->ready = 0;
  rscasadi_zero(tau_out, N);
  if (!sample_ok(theta_d, dtheta_d, ddtheta_d)) return FF_BAD_REFERENCE;
  const casadi_real *arg[${p}feedforward_init_SZ_ARG + 1] = {theta_d, dtheta_d, ddtheta_d};
  casadi_real *res[${p}feedforward_init_SZ_RES + 1] = {tau_out, state};
  if (${p}feedforward_init(arg, res, (casadi_int *)c->iw, c->w, 0) != 0) {
    rscasadi_zero(tau_out, N);
    return FF_FAILED;
  }
  if (!finite_all(tau_out, N) || !finite_all(state, 4 * N)) {
    rscasadi_zero(tau_out, N);
    return FF_NOT_FINITE;
  }
  for (int i = 0; i < 4 * N; ++i) c->state[i] = state[i];
  for (int i = 0; i < N; ++i) c->theta_good[i] = theta_d[i];
  rscasadi_clamp(tau_out, TAU_MAX, N);
  c->ready = RSCASADI_READY;
  return 0;
}

int ${p}ff_step(${p}ff_t *c, const double *theta_d, const double *dtheta_d, const double *ddtheta_d, double h,
                double *tau_out) {
  double next[4 * N];
  if (!tau_out) return FF_BAD_ARGUMENT;
  if (!c || c->ready != RSCASADI_READY) {
    rscasadi_zero(tau_out, N);
    return FF_NOT_INITIALISED;
  }
  if (!sample_ok(theta_d, dtheta_d, ddtheta_d) || !(h >= H_LO && h <= H_HI)) return refuse(c, tau_out, FF_BAD_REFERENCE);
  const casadi_real *arg[${p}feedforward_step_SZ_ARG + 1] = {c->state, theta_d, dtheta_d, ddtheta_d, &h};
  casadi_real *res[${p}feedforward_step_SZ_RES + 1] = {tau_out, next};
  if (${p}feedforward_step(arg, res, (casadi_int *)c->iw, c->w, 0) != 0) return refuse(c, tau_out, FF_FAILED);
  if (!finite_all(tau_out, N) || !finite_all(next, 4 * N)) return refuse(c, tau_out, FF_NOT_FINITE);
  for (int i = 0; i < 4 * N; ++i) c->state[i] = next[i];
  for (int i = 0; i < N; ++i) c->theta_good[i] = theta_d[i];
  rscasadi_clamp(tau_out, TAU_MAX, N);
  return 0;
}
