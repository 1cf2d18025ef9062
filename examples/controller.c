/* A 1 kHz feedforward controller on rscasadi's generated code (reference arm, 3 joints).
 *
 * Desired link motion theta_d(t) = A (1 - cos(2 pi t / 2 s)).  Every millisecond:
 *   T_d   = inverse_dynamics(theta_d, theta_d, ...).T       SEA torque the links need (eq. 26)
 *   phi_d = theta_d + T_d / k1                              spring-consistent rotor angle
 *   tau   = inverse_dynamics(theta_d, phi_d, ...).tau       motor feedforward (eq. 22)
 *         - KP (phi_d - phi) - KD (dphi_d - dphi)           a small motor-side PD
 * and the arm is simulated with step (one RK4 step of the complete model).
 * No allocation; all work arrays are sized by the generated *_SZ_* macros.
 *
 * build: rscasadi codegen problems/arm3.toml --out build/arm3
 *        cc -std=c99 -Wall -Wextra -Werror -O2 -Ibuild/arm3 examples/controller.c \
 *           -Lbuild/arm3 -lrscasadi_arm -Wl,-rpath,build/arm3 -lm -o controller
 * run:   ./controller K1_1 K1_2 K1_3 [SECONDS]     (k1 of each SEA, from the model file)
 * prints every 10 ms: t theta[3] tau[3], then the largest tracking error. */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include "rscasadi_arm.h"

#define N 3
#define RATE_HZ 1000
static const double A[N] = {0.5, 0.6, -0.7}; /* rad */
static const double PERIOD = 2.0;              /* s */
static const double KP = 0.5, KD = 0.05;       /* N m / rad, N m s / rad, motor side */

#define MAX(a, b) ((a) > (b) ? (a) : (b))
#define SZ_W MAX(inverse_dynamics_SZ_W, step_SZ_W)
#define SZ_IW MAX(inverse_dynamics_SZ_IW, step_SZ_IW)

static void desired(double t, double *q, double *dq, double *ddq) {
  const double w = 2.0 * 3.14159265358979323846 / PERIOD;
  for (int i = 0; i < N; ++i) {
    q[i] = A[i] * (1.0 - cos(w * t));
    dq[i] = A[i] * w * sin(w * t);
    ddq[i] = A[i] * w * w * cos(w * t);
  }
}

/* inverse_dynamics(theta, phi, dtheta, dphi, ddtheta, ddphi) -> tau, T */
static void inverse(const double *th, const double *ph, const double *dth, const double *dph,
                    const double *ddth, const double *ddph, double *tau, double *T) {
  const casadi_real *arg[inverse_dynamics_SZ_ARG] = {th, ph, dth, dph, ddth, ddph};
  casadi_real *res[inverse_dynamics_SZ_RES] = {tau, T};
  casadi_int iw[SZ_IW + 1];
  casadi_real w[SZ_W + 1];
  inverse_dynamics(arg, res, iw, w, 0);
}

int main(int argc, char **argv) {
  if (argc < 4) {
    fprintf(stderr, "usage: %s K1_1 K1_2 K1_3 [SECONDS]\n", argv[0]);
    return 2;
  }
  double k1[N], seconds = 2.0;
  for (int i = 0; i < N + 1 && 1 + i < argc; ++i) {
    char *end;
    const double v = strtod(argv[1 + i], &end);
    if (*end != '\0' || !(v > 0.0) || !isfinite(v)) {
      fprintf(stderr, "%s: argument %d (%s) must be a positive number\n", argv[0], 1 + i, argv[1 + i]);
      return 2;
    }
    if (i < N) k1[i] = v; else seconds = v;
  }
  const double h = 1.0 / RATE_HZ;
  const long steps = (long)(seconds * RATE_HZ + 0.5);

  double x[4 * N], x_next[4 * N], tau[N], T[N], unused[N];
  double th_d[N], dth_d[N], ddth_d[N], ph_d[N];
  desired(0.0, th_d, dth_d, ddth_d);                    /* start at rest, spring-consistent */
  inverse(th_d, th_d, dth_d, dth_d, ddth_d, ddth_d, unused, T);
  for (int i = 0; i < N; ++i) {
    x[i] = th_d[i];
    x[N + i] = th_d[i] + T[i] / k1[i];
    x[2 * N + i] = x[3 * N + i] = 0.0;
  }
  double max_err = 0.0;
  for (long k = 0; k < steps; ++k) {
    const double t = k * h;
    desired(t, th_d, dth_d, ddth_d);
    inverse(th_d, th_d, dth_d, dth_d, ddth_d, ddth_d, unused, T);
    for (int i = 0; i < N; ++i) ph_d[i] = th_d[i] + T[i] / k1[i];
    inverse(th_d, ph_d, dth_d, dth_d, ddth_d, ddth_d, tau, T);
    for (int i = 0; i < N; ++i)
      tau[i] -= KP * (ph_d[i] - x[N + i]) + KD * (dth_d[i] - x[3 * N + i]);
    for (int i = 0; i < N; ++i) max_err = fmax(max_err, fabs(x[i] - th_d[i]));
    if (k % 10 == 0)
      printf("%.3f %.12e %.12e %.12e %.12e %.12e %.12e\n", t, x[0], x[1], x[2], tau[0], tau[1], tau[2]);
    const casadi_real *arg[step_SZ_ARG] = {x, tau, &h};
    casadi_real *res[step_SZ_RES] = {x_next};
    casadi_int iw[SZ_IW + 1];
    casadi_real w[SZ_W + 1];
    if (step(arg, res, iw, w, 0)) return 1;
    for (int i = 0; i < 4 * N; ++i) x[i] = x_next[i];
  }
  printf("# max |theta - theta_d| = %.6e rad over %.3f s at %d Hz\n", max_err, seconds, RATE_HZ);
  return 0;
}
