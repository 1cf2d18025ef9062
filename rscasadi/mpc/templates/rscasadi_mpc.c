#define _POSIX_C_SOURCE 199309L
#include <math.h>
#include <time.h>
#include "rscasadi_mpc.h"
#include "mpc_rti.h"

#define MAX(a, b) ((a) > (b) ? (a) : (b))
#define NXP (MPC_NX * (MPC_HORIZON + 1))
#define NUP (MPC_NU * MPC_HORIZON)
static casadi_real X[NXP], U[NUP], X_next[NXP], U_next[NUP];
static casadi_real target_reference[MPC_NREF];
static casadi_real w[MAX(mpc_rti_SZ_W, mpc_hold_SZ_W) + 1];
static casadi_int iw[MAX(mpc_rti_SZ_IW, mpc_hold_SZ_IW) + 1];
static double last_step_seconds;

static double now(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}

double mpc_step_seconds(void) { return last_step_seconds; }

int mpc_init(const double *x_measured) {
  const casadi_real *arg[mpc_hold_SZ_ARG + 1] = {x_measured};
  casadi_real *res[mpc_hold_SZ_RES + 1] = {X, U};
  return mpc_hold(arg, res, iw, w, 0);
}

static int step(const double *x_measured, const double *reference, double *tau_out) {
  const casadi_real *arg[mpc_rti_SZ_ARG + 1] = {x_measured, reference, X, U};
  casadi_real *res[mpc_rti_SZ_RES + 1] = {tau_out, X_next, U_next};
  int finite = 1;
  if (mpc_rti(arg, res, iw, w, 0) != 0) {
    for (int i = 0; i < MPC_NU; ++i) tau_out[i] = U[i];
    return MPC_FAILED;
  }
  for (int i = 0; i < NXP; ++i) finite = finite && isfinite(X_next[i]);
  for (int i = 0; i < NUP; ++i) finite = finite && isfinite(U_next[i]);
  if (!finite) {                          /* e.g. a NaN measurement: keep the plan, its first torque */
    for (int i = 0; i < MPC_NU; ++i) tau_out[i] = U[i];
    return MPC_NOT_FINITE;
  }
  for (int i = 0; i < NXP; ++i) X[i] = X_next[i];
  for (int i = 0; i < NUP; ++i) U[i] = U_next[i];
  return 0;
}

int mpc_step(const double *x_measured, const double *reference, double *tau_out) {
  const double t0 = now();
  const int flag = step(x_measured, reference, tau_out);
  last_step_seconds = now() - t0;
  return flag;
}

int mpc_step_to(const double *x_measured, const double *theta_target, double *tau_out) {
  for (int k = 0; k < MPC_HORIZON; ++k)
    for (int i = 0; i < MPC_NU; ++i) {
      target_reference[2 * MPC_NU * k + i] = theta_target[i];
      target_reference[2 * MPC_NU * k + MPC_NU + i] = 0.0;
    }
  return mpc_step(x_measured, target_reference, tau_out);
}
