#define _POSIX_C_SOURCE 199309L
#include <math.h>
#include <time.h>
#include "rscasadi_mpc.h"
#include "mpc_rti.h"

#define NXP (MPC_NX * (MPC_HORIZON + 1))
#define NUP (MPC_NU * MPC_HORIZON)
#define NROWS (MPC_NREF / MPC_HORIZON)
#define MASS_INDEX ${mass_index}              /* the payload's mass in the parameters, or -1: none */
static const double NOMINAL[MPC_NP + 1] = {${nominal}};      /* the model's parameters (manifest.json) */
typedef char casadi_int_is_long_long[sizeof(casadi_int) == sizeof(long long) ? 1 : -1];
typedef char work_fits[sizeof(((mpc_t *)0)->w) >= sizeof(casadi_real) * (mpc_rti_SZ_W > mpc_hold_SZ_W ? mpc_rti_SZ_W : mpc_hold_SZ_W) ? 1 : -1];
typedef char iwork_fits[sizeof(((mpc_t *)0)->iw) >= sizeof(casadi_int) * (mpc_rti_SZ_IW > mpc_hold_SZ_IW ? mpc_rti_SZ_IW : mpc_hold_SZ_IW) ? 1 : -1];

static double now(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}

size_t mpc_sizeof(void) { return sizeof(mpc_t); }

double mpc_step_seconds(const mpc_t *c) { return c->last_step_seconds; }

int mpc_set_payload_mass(mpc_t *c, double mass) {
  if (MASS_INDEX < 0) return MPC_NO_PAYLOAD;
  if (!isfinite(mass) || mass < 0) return MPC_BAD_ARGUMENT;
  c->params[MPC_NU + MASS_INDEX] = mass;
  return 0;
}

int mpc_set_parameters(mpc_t *c, const double *p) {
  if (MPC_NP == 0) return MPC_BAD_ARGUMENT;
  for (int i = 0; i < MPC_NP; ++i)
    if (!isfinite(p[i])) return MPC_BAD_ARGUMENT;
  for (int i = 0; i < MPC_NP; ++i) c->params[MPC_NU + i] = p[i];
  return 0;
}

int mpc_set_posture(mpc_t *c, const double *theta) {
  for (int i = 0; i < MPC_NU; ++i)
    if (!isfinite(theta[i])) return MPC_BAD_ARGUMENT;
  for (int i = 0; i < MPC_NU; ++i) c->params[i] = theta[i];
  return 0;
}

int mpc_init(mpc_t *c, const double *x_measured) { return mpc_init_parameters(c, x_measured, NOMINAL); }

int mpc_init_parameters(mpc_t *c, const double *x_measured, const double *p) {
  for (int i = 0; i < MPC_NP; ++i)
    if (!isfinite(p[i])) return MPC_BAD_ARGUMENT;
  for (int i = 0; i < MPC_NU; ++i) c->params[i] = x_measured[i];
  for (int i = 0; i < MPC_NP; ++i) c->params[MPC_NU + i] = p[i];
  c->last_step_seconds = 0.0;
  const casadi_real *arg[mpc_hold_SZ_ARG + 1] = {x_measured, c->params};
  casadi_real *res[mpc_hold_SZ_RES + 1] = {c->X, c->U};
  return mpc_hold(arg, res, (casadi_int *)c->iw, c->w, 0);
}

static int step(mpc_t *c, const double *x_measured, const double *reference, double *tau_out) {
  const casadi_real *arg[mpc_rti_SZ_ARG + 1] = {x_measured, reference, c->X, c->U, c->params};
  casadi_real *res[mpc_rti_SZ_RES + 1] = {tau_out, c->X_next, c->U_next};
  int finite = 1;
  if (mpc_rti(arg, res, (casadi_int *)c->iw, c->w, 0) != 0) {
    for (int i = 0; i < MPC_NU; ++i) tau_out[i] = c->U[i];
    return MPC_FAILED;
  }
  for (int i = 0; i < NXP; ++i) finite = finite && isfinite(c->X_next[i]);
  for (int i = 0; i < NUP; ++i) finite = finite && isfinite(c->U_next[i]);
  if (!finite) {                          /* e.g. a NaN measurement: keep the plan, its first torque */
    for (int i = 0; i < MPC_NU; ++i) tau_out[i] = c->U[i];
    return MPC_NOT_FINITE;
  }
  for (int i = 0; i < NXP; ++i) c->X[i] = c->X_next[i];
  for (int i = 0; i < NUP; ++i) c->U[i] = c->U_next[i];
  return 0;
}

int mpc_step(mpc_t *c, const double *x_measured, const double *reference, double *tau_out) {
  const double t0 = now();
  const int flag = step(c, x_measured, reference, tau_out);
  c->last_step_seconds = now() - t0;
  return flag;
}

/* the target held over the horizon at rest: joint space theta (n) and zero speeds; task space
 * p (3), zero velocity, and R (9, column-major) when the rotation is followed */
int mpc_step_to(mpc_t *c, const double *x_measured, const double *target, double *tau_out) {
  for (int k = 0; k < MPC_HORIZON; ++k) {
    double *col = c->target_reference + NROWS * k;
    for (int i = 0; i < NROWS; ++i) col[i] = 0.0;
    if (MPC_TASK_SPACE) {
      for (int i = 0; i < 3; ++i) col[i] = target[i];
      for (int i = 0; i < NROWS - 6; ++i) col[6 + i] = target[3 + i];
    } else {
      for (int i = 0; i < MPC_NU; ++i) col[i] = target[i];
    }
  }
  return mpc_step(c, x_measured, c->target_reference, tau_out);
}
