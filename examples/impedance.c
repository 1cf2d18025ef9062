/* The generated Cartesian impedance controller holding an arm's tool, pushed, in C, for any arm:
 * the number of joints and the springs come from the generated header (ARM_NQ, ARM_K1); the arm
 * needs a frame called `tool`.  It starts at theta = (0, 0.3, -0.5, 0, 0.3, -0.5, ...) rad.
 *
 * The tool is held at its start pose with a commanded stiffness K (N/m); from 0.3 s on a force F
 * pushes it.  The plant is the complete model with the push in its forward dynamics
 * (forward_dynamics_external from rscasadi codegen --external tool, 4 RK4 substeps a
 * millisecond); every millisecond the controller gets the state and returns the motor torques.
 * At rest the tool is displaced by F / K: the springs between motors and links do not soften the
 * commanded stiffness.  The controller's memory is an impedance_t of this program: no allocation.
 *
 * build: rscasadi codegen problems/arm3_tool.toml --frames tool --external tool --out build/arm3_tool
 *        rscasadi controller impedance problems/arm3_tool.toml --frame tool --out build/impedance
 *        cc -std=c99 -Wall -Wextra -Werror -O2 -Ibuild/arm3_tool -Ibuild/impedance examples/impedance.c \
 *           -Lbuild/arm3_tool -Lbuild/impedance -lrscasadi_arm -lrscasadi_impedance \
 *           -Wl,-rpath,build/arm3_tool -Wl,-rpath,build/impedance -lm -o impedance
 * run:   ./impedance [K [FZ [SECONDS]]]     (default 1000 N/m, -15 N downwards, 2.5 s)
 * prints every 10 ms: t tool[3] tau[ARM_NQ], then the tool's displacement at the end against
 * F / K; a refusal says why on stderr (exit 1). */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include "rscasadi_arm.h"
#include "rscasadi_impedance.h"

#define N ARM_NQ
#define MAX_STEPS 20000
static const double DT = 1e-3;
static const double K1[N] = ARM_K1;                          /* the model file's springs, N m/rad */
static double theta0(int i) { return i % 3 == 1 ? 0.3 : i % 3 == 2 ? -0.5 : 0.0; }   /* rad */
static impedance_t controller;

static void xdot(const double *x, const double *tau, const double *f, double *dx) {
  const casadi_real *arg[forward_dynamics_external_SZ_ARG + 1] = {x, x + N, x + 2 * N, x + 3 * N, tau, f};
  casadi_real *res[forward_dynamics_external_SZ_RES + 1] = {dx + 2 * N, dx + 3 * N};
  casadi_int iw[forward_dynamics_external_SZ_IW + 1];
  casadi_real w[forward_dynamics_external_SZ_W + 1];
  forward_dynamics_external(arg, res, iw, w, 0);
  for (int i = 0; i < 2 * N; ++i) dx[i] = x[2 * N + i];
}

/* one RK4 step of the complete model with the wrench f at the tool */
static void advance(double *x, const double *tau, const double *f, double h) {
  double k[4][4 * N], z[4 * N];
  const double c[4] = {0.0, 0.5, 0.5, 1.0};
  for (int s = 0; s < 4; ++s) {
    for (int i = 0; i < 4 * N; ++i) z[i] = x[i] + (s ? c[s] * h * k[s - 1][i] : 0.0);
    xdot(z, tau, f, k[s]);
  }
  for (int i = 0; i < 4 * N; ++i) x[i] += h / 6.0 * (k[0][i] + 2.0 * k[1][i] + 2.0 * k[2][i] + k[3][i]);
}

/* frame_placement_tool(theta) -> R (column-major), p */
static void tool(const double *theta, double *R, double *p) {
  const casadi_real *arg[frame_placement_tool_SZ_ARG + 1] = {theta};
  casadi_real *res[frame_placement_tool_SZ_RES + 1] = {R, p};
  casadi_int iw[frame_placement_tool_SZ_IW + 1];
  casadi_real w[frame_placement_tool_SZ_W + 1];
  frame_placement_tool(arg, res, iw, w, 0);
}

/* the springs deflected to hold the links at rest: T from inverse_dynamics, phi = theta + T / k1 */
static void rest(double *x) {
  double zero[N] = {0}, tau[N], T[N];
  const casadi_real *arg[inverse_dynamics_SZ_ARG + 1] = {x, x, zero, zero, zero, zero};
  casadi_real *res[inverse_dynamics_SZ_RES + 1] = {tau, T};
  casadi_int iw[inverse_dynamics_SZ_IW + 1];
  casadi_real w[inverse_dynamics_SZ_W + 1];
  inverse_dynamics(arg, res, iw, w, 0);
  for (int i = 0; i < N; ++i) x[N + i] = x[i] + T[i] / K1[i];
}

int main(int argc, char **argv) {
  double args[3] = {1000.0, -15.0, 2.5};
  if (argc > 4) {
    fprintf(stderr, "usage: %s [K [FZ [SECONDS]]]\n", argv[0]);
    return 2;
  }
  for (int i = 1; i < argc; ++i) {
    char *end;
    args[i - 1] = strtod(argv[i], &end);
    if (*end != '\0' || !isfinite(args[i - 1]) || (i != 2 && !(args[i - 1] > 0.0))) {
      fprintf(stderr, "%s: argument %d (%s) must be a %snumber\n", argv[0], i, argv[i], i != 2 ? "positive " : "");
      return 2;
    }
  }
  const double K = args[0], FZ = args[1];
  const long steps = (long)(args[2] / DT + 0.5);
  if (steps > MAX_STEPS) {
    fprintf(stderr, "%s: at most %g s\n", argv[0], MAX_STEPS * DT);
    return 2;
  }
  double x[4 * N] = {0}, tau[N], pose[12], p[3], p0[3];
  const double stiffness[6] = {K, K, K, 0.0, 0.0, 0.0}, zeta[6] = {0.7, 0.7, 0.7, 0.7, 0.7, 0.7};
  for (int i = 0; i < N; ++i) x[i] = theta0(i);
  rest(x);
  tool(x, pose + 3, pose);                               /* hold the start pose: p, then R */
  for (int i = 0; i < 3; ++i) p0[i] = pose[i];
  const int refused = impedance_init(&controller, x);
  if (refused) {
    fprintf(stderr, "%s: impedance_init refused the resting state (code %d)\n", argv[0], refused);
    return 1;
  }
  for (long k = 0; k < steps; ++k) {
    double f[6] = {0};
    if (k * DT >= 0.3) f[2] = FZ;
    const int code = impedance_step(&controller, x, pose, stiffness, zeta, tau);
    if (code) {
      fprintf(stderr, "%s: impedance_step returned %d at t = %.3f s\n", argv[0], code, k * DT);
      return 1;
    }
    for (int s = 0; s < 4; ++s) advance(x, tau, f, DT / 4.0);
    if ((k + 1) % 10 == 0) {
      double R[9];
      tool(x, R, p);
      printf("%.3f %.6f %.6f %.6f", (k + 1) * DT, p[0], p[1], p[2]);
      for (int i = 0; i < N; ++i) printf(" %.5f", tau[i]);
      printf("\n");
    }
  }
  double R[9];
  tool(x, R, p);
  printf("# displacement at the end = %.6f m along z (F / K = %.6f m), %.6f m across\n", p[2] - p0[2], FZ / K,
         hypot(p[0] - p0[0], p[1] - p0[1]));
  return 0;
}
