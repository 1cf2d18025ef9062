/* The generated momentum observer detecting a push on an arm's tool, in C, for any arm: the
 * number of joints, the springs and the gear ratios come from the generated header (ARM_NQ,
 * ARM_K1, ARM_GEAR_RATIO); the arm needs a frame called `tool`.
 *
 * The arm rests at theta = (0, 0.3, -0.5, 0, 0.3, -0.5, ...) rad, its springs deflected to hold it and its motors
 * holding the rest torque; from 0.2 s to 0.5 s a force F pushes its tool.  The plant is the
 * complete model with the push in its forward dynamics (forward_dynamics_external from rscasadi
 * codegen --external tool, 4 RK4 substeps a millisecond); every millisecond the observer gets
 * the state, quantised like real encoders (speeds by backward differences), and the torque, and
 * returns the external torques on the links, and OBSERVER_COLLISION while one exceeds the
 * threshold it was generated with (1 N m).
 * Its state is an observer_t of this program: no allocation.
 *
 * build: rscasadi codegen problems/arm3_tool.toml --frames tool --external tool --out build/arm3_tool
 *        rscasadi controller observer problems/arm3_tool.toml --gain 50 --threshold 1 --out build/observer
 *        cc -std=c99 -Wall -Wextra -Werror -O2 -Ibuild/arm3_tool -Ibuild/observer examples/observer.c \
 *           -Lbuild/arm3_tool -Lbuild/observer -lrscasadi_arm -lrscasadi_observer \
 *           -Wl,-rpath,build/arm3_tool -Wl,-rpath,build/observer -lm -o observer
 * run:   ./observer [FX FY FZ]     (the push in N, world axes; default 3 -4 -10)
 * -DLINK_BITS=.. -DMOTOR_BITS=.. set the encoders' resolution: the speeds are differences of
 * quantised angles, and their noise, times the links' inertia and the gain, is what limits the
 * estimate on a heavy arm (on the Panda at gain 50: 3 % with ideal encoders, 70 % with these).
 * prints every 10 ms: t r_link[ARM_NQ] true_link[ARM_NQ] flag, then when the push was flagged
 * and the estimate's error at 0.45 s relative to J^T F; a refusal says why on stderr (exit 1). */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include "rscasadi_arm.h"
#include "rscasadi_observer.h"

#define N ARM_NQ
#define STEPS 800
static const double DT = 1e-3;                               /* s */
static const double K1[N] = ARM_K1;                          /* the model file's springs, N m/rad */
#ifndef LINK_BITS
#define LINK_BITS 19                                         /* a 19-bit link encoder */
#endif
#ifndef MOTOR_BITS
#define MOTOR_BITS 17                                        /* a 17-bit motor encoder */
#endif
static const double MU[N] = ARM_GEAR_RATIO;                  /* the gear ratios */
static double theta0(int i) { return i % 3 == 1 ? 0.3 : i % 3 == 2 ? -0.5 : 0.0; }   /* rad */
static observer_t observer;

/* forward_dynamics_external(theta, phi, dtheta, dphi, tau, f_tool) -> ddtheta, ddphi */
static void xdot(const double *x, const double *tau, const double *f, double *dx) {
  const casadi_real *arg[forward_dynamics_external_SZ_ARG + 1] = {x, x + N, x + 2 * N, x + 3 * N, tau, f};
  casadi_real *res[forward_dynamics_external_SZ_RES + 1] = {dx + 2 * N, dx + 3 * N};
  casadi_int iw[forward_dynamics_external_SZ_IW + 1];
  casadi_real w[forward_dynamics_external_SZ_W + 1];
  forward_dynamics_external(arg, res, iw, w, 0);
  for (int i = 0; i < 2 * N; ++i) dx[i] = x[2 * N + i];
}

static void advance(double *x, const double *tau, const double *f, double h) {
  double k[4][4 * N], z[4 * N];
  const double c[4] = {0.0, 0.5, 0.5, 1.0}, b[4] = {1.0, 2.0, 2.0, 1.0};
  for (int s = 0; s < 4; ++s) {
    for (int i = 0; i < 4 * N; ++i) z[i] = x[i] + (s ? c[s] * h * k[s - 1][i] : 0.0);
    xdot(z, tau, f, k[s]);
  }
  for (int i = 0; i < 4 * N; ++i) x[i] += h / 6.0 * (b[0] * k[0][i] + b[1] * k[1][i] + b[2] * k[2][i] + b[3] * k[3][i]);
}

/* inverse_dynamics(theta, phi, 0, 0, 0, 0) -> tau, T: the rest torques at theta */
static void rest(double *x, double *tau) {
  double zero[N] = {0}, T[N];
  const casadi_real *arg[inverse_dynamics_SZ_ARG + 1] = {x, x, zero, zero, zero, zero};
  casadi_real *res[inverse_dynamics_SZ_RES + 1] = {tau, T};
  casadi_int iw[inverse_dynamics_SZ_IW + 1];
  casadi_real w[inverse_dynamics_SZ_W + 1];
  inverse_dynamics(arg, res, iw, w, 0);           /* T: the springs' torque holding the links */
  for (int i = 0; i < N; ++i) x[N + i] = x[i] + T[i] / K1[i];
  arg[1] = x + N;
  inverse_dynamics(arg, res, iw, w, 0);           /* tau with the springs deflected */
}

/* the links' torques J^T F of a force F at the tool (J: frame_jacobian_tool_local_world_aligned,
 * 6 x N, its nonzeros in CasADi's compressed-column order: sp = {rows, cols, colind[cols + 1], row[nnz]}) */
static void link_torques(const double *theta, const double *F, double *out) {
  double Jnz[6 * N];
  const casadi_real *arg[frame_jacobian_tool_local_world_aligned_SZ_ARG + 1] = {theta};
  casadi_real *res[frame_jacobian_tool_local_world_aligned_SZ_RES + 1] = {Jnz};
  casadi_int iw[frame_jacobian_tool_local_world_aligned_SZ_IW + 1];
  casadi_real w[frame_jacobian_tool_local_world_aligned_SZ_W + 1];
  frame_jacobian_tool_local_world_aligned(arg, res, iw, w, 0);
  const casadi_int *sp = frame_jacobian_tool_local_world_aligned_sparsity_out(0), *colind = sp + 2, *row = sp + 3 + sp[1];
  for (int j = 0; j < N; ++j) {
    out[j] = 0.0;
    for (casadi_int k = colind[j]; k < colind[j + 1]; ++k)
      if (row[k] < 3) out[j] += Jnz[k] * F[row[k]];
  }
}

int main(int argc, char **argv) {
  double F[3] = {3.0, -4.0, -10.0};
  if (argc != 1 && argc != 4) {
    fprintf(stderr, "usage: %s [FX FY FZ]\n", argv[0]);
    return 2;
  }
  for (int i = 1; i < argc; ++i) {
    char *end;
    F[i - 1] = strtod(argv[i], &end);
    if (*end != '\0' || !isfinite(F[i - 1])) {
      fprintf(stderr, "%s: argument %d (%s) must be a number of newtons\n", argv[0], i, argv[i]);
      return 2;
    }
  }
  double x[4 * N] = {0}, tau[N], meas[4 * N], prev[2 * N], r[2 * N], truth[N], flagged_at = -1.0, error = NAN;
  for (int i = 0; i < N; ++i) x[i] = theta0(i);
  rest(x, tau);
  const int refused = observer_init(&observer, x);
  if (refused) {
    fprintf(stderr, "%s: observer_init refused the resting state (code %d)\n", argv[0], refused);
    return 1;
  }
  for (int i = 0; i < 2 * N; ++i) prev[i] = x[i];
  for (int k = 0; k < STEPS; ++k) {
    const double t = k * DT;
    double f[6] = {0};
    if (t >= 0.2 && t < 0.5)
      for (int i = 0; i < 3; ++i) f[i] = F[i];
    for (int s = 0; s < 4; ++s) advance(x, tau, f, DT / 4.0);
    for (int i = 0; i < 2 * N; ++i) {                         /* encoders, speeds by differences */
      const double q = 2.0 * 3.14159265358979323846 / (i < N ? ldexp(1.0, LINK_BITS) : ldexp(1.0, MOTOR_BITS) * MU[i - N]);
      meas[i] = q * round(x[i] / q);
      meas[2 * N + i] = (meas[i] - prev[i]) / DT;
      prev[i] = meas[i];
    }
    const int code = observer_step(&observer, meas, tau, r);
    if (code != 0 && code != OBSERVER_COLLISION) {
      fprintf(stderr, "%s: observer_step returned %d at t = %.3f s\n", argv[0], code, t);
      return 1;
    }
    link_torques(x, f, truth);
    const int flag = code == OBSERVER_COLLISION;
    if (flag && flagged_at < 0.0) flagged_at = t + DT;
    if (fabs(t + DT - 0.45) < 1e-9) {
      double e = 0.0, s = 0.0;
      for (int i = 0; i < N; ++i) e += pow(r[i] - truth[i], 2), s += truth[i] * truth[i];
      error = sqrt(e / s);
    }
    if ((k + 1) % 10 == 0) {
      printf("%.3f", t + DT);
      for (int i = 0; i < N; ++i) printf(" %.4f", r[i]);
      for (int i = 0; i < N; ++i) printf(" %.4f", truth[i]);
      printf(" %d\n", flag);
    }
  }
  printf("# push flagged at %.3f s (it started at 0.200 s); estimate at 0.45 s within %.1f %% of J^T F\n", flagged_at,
         100.0 * error);
  return 0;
}
