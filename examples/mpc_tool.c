/* The generated task-space MPC on the reference arm with a tool (3 joints), in C.
 *
 * The tool follows a polyline at a mean 0.2 m/s (the path of problems/mpc_arm3_tool.toml), its
 * links kept clear of a ball by the controller's soft obstacle term.  Every millisecond the
 * controller gets the state and the tool's reference position and velocity at the ends of its N
 * intervals, returns the motor torques, and the arm (the complete model without a payload, one
 * RK4 step of `step` from rscasadi codegen per millisecond) moves.  The controller's model holds
 * a 0.05 kg payload; mpc_set_payload_mass tells it the arm holds none.  Its state is an mpc_t
 * of this program: no allocation, no static data in the library.
 *
 * build: rscasadi codegen problems/arm3_tool.toml --frames tool --out build/arm3_tool
 *        rscasadi mpc problems/mpc_arm3_tool.toml --out build/mpc_tool
 *        cc -std=c99 -Wall -Wextra -Werror -O2 -Ibuild/arm3_tool -Ibuild/mpc_tool examples/mpc_tool.c \
 *           -Lbuild/arm3_tool -Lbuild/mpc_tool -lrscasadi_arm -lrscasadi_mpc \
 *           -Wl,-rpath,build/arm3_tool -Wl,-rpath,build/mpc_tool -lm -o mpc_tool
 * run:   ./mpc_tool [SECONDS]     (default 2: 0.3 s settling at the start, the path, then holding)
 * prints every 10 ms: t tool[3] tau[3], then the largest distance from the reference point and
 * from the path, and the step times (median, worst). */
#define _POSIX_C_SOURCE 200112L
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "rscasadi_arm.h"
#include "rscasadi_mpc.h"

#define N ARM_NQ
#if ARM_NQ != 3 || MPC_NU != 3
#error "this example flies problems/mpc_arm3_tool.toml's path from its start pose: build it on that 3-joint arm"
#endif
#define RATE_HZ 1000
#define MAX_STEPS 20000
#define POINTS 3
static const double PATH[POINTS][3] = {{0.628388, 0.0, 0.393831}, {0.528388, 0.1, 0.393831}, {0.478388, 0.1, 0.493831}};
static const double SPEED = 0.2, SETTLE = 0.3;  /* m/s, s */
static const double PI = 3.14159265358979323846;
static const double THETA_START[N] = {0.0, 0.3, -0.5};
static double step_times[MAX_STEPS];
static mpc_t controller;                         /* the controller's state: this program's memory */

static double now(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}

static int cmp(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return (x > y) - (x < y);
}

static double path_length(void) {
  double L = 0.0;
  for (int k = 1; k < POINTS; ++k)
    L += sqrt(pow(PATH[k][0] - PATH[k - 1][0], 2) + pow(PATH[k][1] - PATH[k - 1][1], 2) + pow(PATH[k][2] - PATH[k - 1][2], 2));
  return L;
}

/* the point at arc length s along the polyline */
static void at_arc(double s, double *p) {
  for (int k = 1; k < POINTS; ++k) {
    double d[3], len = 0.0;
    for (int i = 0; i < 3; ++i) d[i] = PATH[k][i] - PATH[k - 1][i], len += d[i] * d[i];
    len = sqrt(len);
    if (s <= len || k == POINTS - 1) {
      const double u = fmin(fmax(s / len, 0.0), 1.0);
      for (int i = 0; i < 3; ++i) p[i] = PATH[k - 1][i] + u * d[i];
      return;
    }
    s -= len;
  }
}

/* the reference point at time t of the path's clock: rest to rest, s = L (tau - sin(2 pi tau) / 2 pi) */
static void reference_point(double t, double *p) {
  const double L = path_length(), T = L / SPEED, tau = fmin(fmax(t / T, 0.0), 1.0);
  at_arc(L * (tau - sin(2.0 * PI * tau) / (2.0 * PI)), p);
}

static double distance_to_path(const double *p) {
  double best = INFINITY;
  for (int k = 1; k < POINTS; ++k) {
    double d[3], w[3], dd = 0.0, wd = 0.0, e = 0.0;
    for (int i = 0; i < 3; ++i) d[i] = PATH[k][i] - PATH[k - 1][i], w[i] = p[i] - PATH[k - 1][i];
    for (int i = 0; i < 3; ++i) dd += d[i] * d[i], wd += w[i] * d[i];
    const double u = fmin(fmax(wd / dd, 0.0), 1.0);
    for (int i = 0; i < 3; ++i) e += pow(w[i] - u * d[i], 2);
    best = fmin(best, sqrt(e));
  }
  return best;
}

/* step(x, tau, h) -> x_next: one RK4 step of the complete model */
static void advance(double *x, const double *tau, double h) {
  double next[4 * N];
  const casadi_real *arg[step_SZ_ARG + 1] = {x, tau, &h};
  casadi_real *res[step_SZ_RES + 1] = {next};
  casadi_int iw[step_SZ_IW + 1];
  casadi_real w[step_SZ_W + 1];
  step(arg, res, iw, w, 0);
  for (int i = 0; i < 4 * N; ++i) x[i] = next[i];
}

/* frame_placement_tool(theta) -> R, p */
static void tool(const double *theta, double *p) {
  double R[9];
  const casadi_real *arg[frame_placement_tool_SZ_ARG + 1] = {theta};
  casadi_real *res[frame_placement_tool_SZ_RES + 1] = {R, p};
  casadi_int iw[frame_placement_tool_SZ_IW + 1];
  casadi_real w[frame_placement_tool_SZ_W + 1];
  frame_placement_tool(arg, res, iw, w, 0);
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
      fprintf(stderr, "%s: argument 1 (%s) must be a positive number of seconds\n", argv[0], argv[1]);
      return 2;
    }
  }
  const long steps = (long)(seconds * RATE_HZ + 0.5);
  if (steps > MAX_STEPS) {
    fprintf(stderr, "%s: at most %d s\n", argv[0], MAX_STEPS / RATE_HZ);
    return 2;
  }
  const double dt = 1.0 / RATE_HZ, h = 0.01;     /* the problem file's sample time and interval */
  double x[4 * N] = {0}, tau[N], reference[MPC_NREF], p[3], max_err = 0.0, max_off = 0.0;
  for (int i = 0; i < N; ++i) x[i] = x[N + i] = THETA_START[i];   /* springs undeflected: settled first */
  int code = mpc_init(&controller, x);
  if (code == 0) code = mpc_set_payload_mass(&controller, 0.0);
  if (code != 0) {
    fprintf(stderr, "%s: mpc_init or mpc_set_payload_mass refused (code %d)\n", argv[0], code);
    return 1;
  }
  for (long k = 0; k < steps; ++k) {
    const double t = k * dt - SETTLE;                   /* the path's clock */
    for (int j = 0; j < MPC_HORIZON; ++j) {
      double *col = reference + 6 * j, ahead[3], behind[3];
      const double tj = t + (j + 1) * h, eps = 1e-4;
      reference_point(tj, col);
      reference_point(tj + eps, ahead);
      reference_point(tj - eps, behind);
      for (int i = 0; i < 3; ++i) col[3 + i] = (ahead[i] - behind[i]) / (2.0 * eps);
    }
    const double t0 = now();
    if ((code = mpc_step(&controller, x, reference, tau)) != 0) {
      fprintf(stderr, "%s: mpc_step returned %d at t = %.3f s (rscasadi_mpc.h: the failure policy)\n", argv[0], code, t);
      return 1;
    }
    step_times[k] = now() - t0;
    advance(x, tau, dt);
    tool(x, p);
    if (t > 0.0) {                                       /* counted once the path has started */
      double r[3], e = 0.0;
      reference_point(t + dt, r);
      for (int i = 0; i < 3; ++i) e += (p[i] - r[i]) * (p[i] - r[i]);
      max_err = fmax(max_err, sqrt(e));
      max_off = fmax(max_off, distance_to_path(p));
    }
    if ((k + 1) % 10 == 0)
      printf("%.3f %.6f %.6f %.6f %.6f %.6f %.6f\n", (k + 1) * dt, p[0], p[1], p[2], tau[0], tau[1], tau[2]);
  }
  qsort(step_times, steps, sizeof step_times[0], cmp);
  printf("# largest distance from the reference point = %.3e m, from the path = %.3e m; mpc_step median %.1f us, "
         "worst %.1f us over %ld steps\n", max_err, max_off, 1e6 * step_times[steps / 2], 1e6 * step_times[steps - 1], steps);
  return 0;
}
