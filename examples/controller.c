/* A 1 kHz feedforward controller on rscasadi's generated code, for any arm: the number of
 * joints and the springs come from the generated header (ARM_NQ, ARM_K1).
 *
 * Desired link motion theta_d(t) = A (1 - cos(2 pi t / 2 s)), A = 0.5, 0.6, -0.7, 0.5, ... rad.
 * Every millisecond:
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
 * run:   ./controller [SECONDS]     (default 2)
 * prints every 10 ms: t theta[ARM_NQ] tau[ARM_NQ], then the largest tracking error; a failed
 * step says so on stderr (exit 1). */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include "rscasadi_arm.h"

#define N ARM_NQ
#define RATE_HZ 1000
static const double K1[N] = ARM_K1;            /* N m / rad, the model file's springs */
static const double PERIOD = 2.0;              /* s */
static const double KP = 0.5, KD = 0.05;       /* N m / rad, N m s / rad, motor side */

#define MAX(a, b) ((a) > (b) ? (a) : (b))
#define SZ_W MAX(inverse_dynamics_SZ_W, step_SZ_W)
#define SZ_IW MAX(inverse_dynamics_SZ_IW, step_SZ_IW)

static double amplitude(int i) { return (0.5 + 0.1 * (i % 3)) * (i % 3 == 2 ? -1.0 : 1.0); }   /* rad */

static void desired(double t, double *q, double *dq, double *ddq) {
  const double w = 2.0 * 3.14159265358979323846 / PERIOD;
  for (int i = 0; i < N; ++i) {
    q[i] = amplitude(i) * (1.0 - cos(w * t));
    dq[i] = amplitude(i) * w * sin(w * t);
    ddq[i] = amplitude(i) * w * w * cos(w * t);
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
  double seconds = 2.0;
  if (argc > 2) {
    fprintf(stderr, "usage: %s [SECONDS]\n", argv[0]);
    return 2;
  }
  if (argc == 2) {
    char *end;
    seconds = strtod(argv[1], &end);
    if (*end != '\0' || !(seconds > 0.0) || !isfinite(seconds)) {
      fprintf(stderr, "%s: SECONDS (%s) must be a positive number\n", argv[0], argv[1]);
      return 2;
    }
  }
  const double h = 1.0 / RATE_HZ;
  const long steps = (long)(seconds * RATE_HZ + 0.5);

  double x[4 * N], x_next[4 * N], tau[N], T[N], unused[N];
  double th_d[N], dth_d[N], ddth_d[N], ph_d[N];
  desired(0.0, th_d, dth_d, ddth_d);                    /* start at rest, spring-consistent */
  inverse(th_d, th_d, dth_d, dth_d, ddth_d, ddth_d, unused, T);
  for (int i = 0; i < N; ++i) {
    x[i] = th_d[i];
    x[N + i] = th_d[i] + T[i] / K1[i];
    x[2 * N + i] = x[3 * N + i] = 0.0;
  }
  double max_err = 0.0;
  for (long k = 0; k < steps; ++k) {
    const double t = k * h;
    desired(t, th_d, dth_d, ddth_d);
    inverse(th_d, th_d, dth_d, dth_d, ddth_d, ddth_d, unused, T);
    for (int i = 0; i < N; ++i) ph_d[i] = th_d[i] + T[i] / K1[i];
    inverse(th_d, ph_d, dth_d, dth_d, ddth_d, ddth_d, tau, T);
    for (int i = 0; i < N; ++i)
      tau[i] -= KP * (ph_d[i] - x[N + i]) + KD * (dth_d[i] - x[3 * N + i]);
    for (int i = 0; i < N; ++i) max_err = fmax(max_err, fabs(x[i] - th_d[i]));
    if (k % 10 == 0) {
      printf("%.3f", t);
      for (int i = 0; i < N; ++i) printf(" %.12e", x[i]);
      for (int i = 0; i < N; ++i) printf(" %.12e", tau[i]);
      printf("\n");
    }
    const casadi_real *arg[step_SZ_ARG] = {x, tau, &h};
    casadi_real *res[step_SZ_RES] = {x_next};
    casadi_int iw[SZ_IW + 1];
    casadi_real w[SZ_W + 1];
    if (step(arg, res, iw, w, 0)) {
      fprintf(stderr, "%s: step failed at t = %.3f s\n", argv[0], t);
      return 1;
    }
    for (int i = 0; i < 4 * N; ++i) {
      if (!isfinite(x_next[i])) {
        fprintf(stderr, "%s: the simulated state is not finite at t = %.3f s (the step is too long for "
                        "these springs?)\n", argv[0], t);
        return 1;
      }
      x[i] = x_next[i];
    }
  }
  printf("# max |theta - theta_d| = %.6e rad over %.3f s at %d Hz\n", max_err, seconds, RATE_HZ);
  return 0;
}
