/* The generated nonlinear MPC at 1 kHz, in C, on the arm it was generated for: the reference arm
 * (3 joints) or, e.g., the Panda with SEAs (7; problems/mpc_panda.toml).
 *
 * Desired link motion theta_d(t) = theta_0 + A (1 - cos(2 pi t / 2 s)) (A below for 3 joints,
 * else 0.15 rad of alternating sign; theta_0 zero on 3 joints, on 7 the Panda's ready pose, inside
 * its joint ranges: the MPC keeps the link angles in them).  Every millisecond the controller
 * gets the state and the reference at the ends of its N intervals (theta_d, dtheta_d at
 * t + k h), returns the motor torques, and the arm (the same complete model, one RK4 step of
 * `step` from rscasadi codegen per millisecond, 4 substeps) moves.  Each mpc_step is timed with
 * clock_gettime.  No allocation: the controller's state is a static mpc_t of this program.  Like a real 1 kHz loop it is paced: after each step it sleeps until
 * the next millisecond (clock_nanosleep, absolute), its memory is locked (mlockall: no page fault
 * in the loop), and with `rt` it runs under SCHED_FIFO (needs the privilege; else it says so and
 * goes on); a step that does not finish within its millisecond is a deadline miss.
 *
 * build: rscasadi codegen problems/arm3.toml --out build/arm3
 *        rscasadi mpc problems/mpc_arm3.toml --out build/mpc
 *        cc -std=c99 -Wall -Wextra -Werror -O2 -Ibuild/arm3 -Ibuild/mpc examples/mpc.c \
 *           -Lbuild/arm3 -Lbuild/mpc -lrscasadi_arm -lrscasadi_mpc \
 *           -Wl,-rpath,build/arm3 -Wl,-rpath,build/mpc -lm -o mpc_example
 *        (the Panda: rscasadi codegen problems/panda_sea.toml, rscasadi mpc problems/mpc_panda.toml)
 * run:   ./mpc_example INTERVAL_S [SECONDS [rt]]     (INTERVAL_S: the problem file's interval, 0.01;
 *        SECONDS includes 0.5 s of settling at rest before the motion; rt: real-time scheduling)
 * Each sample runs the split real-time iteration as a controller would: mpc_feedback with the new
 * measurement (the latency from measurement to torque), the torque applied, then mpc_prepare for
 * the next sample while waiting for it.
 * prints every 10 ms: t theta[N] tau[N], then the largest tracking error, the times per sample
 * (prepare + feedback: median, 99.9th percentile, worst), the feedback's alone and the deadline
 * misses. */
#define _POSIX_C_SOURCE 200112L
#include <math.h>
#include <sched.h>
#include <string.h>
#include <sys/mman.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "rscasadi_arm.h"
#include "rscasadi_mpc.h"

#define N MPC_NU
#define RATE_HZ 1000
#define MAX_STEPS 100000
static const double A3[3] = {0.5, 0.6, -0.7};  /* rad, the reference arm's */
static const double READY7[7] = {0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785};   /* rad, the Panda's ready pose */
static const double PERIOD = 2.0;              /* s */
static double step_times[MAX_STEPS], feedback_times[MAX_STEPS];
static mpc_t controller;                      /* the controller's state: the caller's memory */

static double now(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}

static int cmp(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return (x > y) - (x < y);
}

static const double SETTLE = 0.5;              /* s at rest first: the arm starts without spring deflection */

static void desired(double t, double *q, double *dq) {
  const double w = 2.0 * 3.14159265358979323846 / PERIOD;
  t = t > SETTLE ? t - SETTLE : 0.0;
  for (int i = 0; i < N; ++i) {
    const double a = N == 3 ? A3[i % 3] : (i % 2 ? -0.15 : 0.15);
    q[i] = (N == 7 ? READY7[i % 7] : 0.0) + a * (1.0 - cos(w * t));
    dq[i] = a * w * sin(w * t);
  }
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

/* the usual set-up of a real-time loop: memory locked; SCHED_FIFO if asked for and allowed */
static void realtime(int fifo) {
  if (mlockall(MCL_CURRENT | MCL_FUTURE) != 0) printf("# mlockall refused: page faults may delay steps\n");
  if (!fifo) return;
  struct sched_param sp;
  memset(&sp, 0, sizeof sp);
  sp.sched_priority = 80;
  if (sched_setscheduler(0, SCHED_FIFO, &sp) != 0) printf("# SCHED_FIFO refused: running with normal priority\n");
}

static void sleep_until(struct timespec *next, long period_ns) {
  next->tv_nsec += period_ns;
  while (next->tv_nsec >= 1000000000L) {
    next->tv_nsec -= 1000000000L;
    next->tv_sec += 1;
  }
  clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, next, NULL);
}

int main(int argc, char **argv) {
  if (argc < 2 || argc > 4 || (argc == 4 && strcmp(argv[3], "rt") != 0)) {
    fprintf(stderr, "usage: %s INTERVAL_S [SECONDS [rt]]\n", argv[0]);
    return 2;
  }
  double args[2] = {0.0, 2.0};
  for (int i = 0; i < 2 && 1 + i < argc; ++i) {
    char *end;
    args[i] = strtod(argv[1 + i], &end);
    if (*end != '\0' || !(args[i] > 0.0) || !isfinite(args[i])) {
      fprintf(stderr, "%s: argument %d (%s) must be a positive number\n", argv[0], 1 + i, argv[1 + i]);
      return 2;
    }
  }
  const double interval = args[0], seconds = args[1], dt = 1.0 / RATE_HZ;
  const long steps = (long)(seconds * RATE_HZ + 0.5);
  if (steps > MAX_STEPS) {
    fprintf(stderr, "%s: at most %d s\n", argv[0], MAX_STEPS / RATE_HZ);
    return 2;
  }
  /* start at theta = phi = theta_0 at rest, springs undeflected: the MPC settles the arm during
   * SETTLE, then the motion starts; the tracking error is counted from then on */
  double x[4 * N] = {0}, tau[N], reference[MPC_NREF], max_err = 0.0;
  long misses = 0;
  desired(0.0, x, x + 2 * N);
  for (int i = 0; i < N; ++i) x[N + i] = x[i];
  int code = mpc_init(&controller, x);
  if (code != 0) {
    fprintf(stderr, "%s: mpc_init refused the start state (code %d)\n", argv[0], code);
    return 1;
  }
  realtime(argc == 4);
  struct timespec next;
  clock_gettime(CLOCK_MONOTONIC, &next);
  double prepare_time = 0.0;
  for (long k = 0; k < steps; ++k) {
    const double t = k * dt;
    if (k == 0) {                       /* afterwards prepared at the end of the sample before */
      for (int j = 0; j < MPC_HORIZON; ++j) desired(t + (j + 1) * interval, reference + 2 * N * j, reference + 2 * N * j + N);
      mpc_prepare(&controller, reference);
    }
    const double t0 = now();
    if ((code = mpc_feedback(&controller, x, tau)) != 0) {
      fprintf(stderr, "%s: mpc_feedback returned %d at t = %.3f s (rscasadi_mpc.h: the failure policy)\n", argv[0], code, t);
      return 1;
    }
    feedback_times[k] = now() - t0;
    step_times[k] = feedback_times[k] + prepare_time;
    if (k % 10 == 0) {
      printf("%.3f", t);
      for (int i = 0; i < N; ++i) printf(" %.9f", x[i]);
      for (int i = 0; i < N; ++i) printf(" %.9f", tau[i]);
      printf("\n");
    }
    for (int s = 0; s < 4; ++s) advance(x, tau, dt / 4);
    double q[N], dq[N];
    desired(t + dt, q, dq);
    for (int i = 0; i < N && t + dt > SETTLE; ++i) max_err = fmax(max_err, fabs(x[i] - q[i]));
    for (int j = 0; j < MPC_HORIZON; ++j)
      desired(t + dt + (j + 1) * interval, reference + 2 * N * j, reference + 2 * N * j + N);
    const double t1 = now();
    mpc_prepare(&controller, reference);           /* a refused reference: the next feedback says so */
    prepare_time = now() - t1;
    misses += feedback_times[k] + prepare_time > dt;
    sleep_until(&next, (long)(1e9 * dt));
  }
  qsort(step_times, (size_t)steps, sizeof step_times[0], cmp);
  qsort(feedback_times, (size_t)steps, sizeof feedback_times[0], cmp);
  printf("# max tracking error = %.3e rad; mpc_step median %.1f us, 99.9%% %.1f us, worst %.1f us over %ld steps "
         "(prepare + feedback); mpc_feedback median %.1f us, 99.9%% %.1f us, worst %.1f us; "
         "%ld deadline misses (> 1 ms)\n", max_err, 1e6 * step_times[steps / 2], 1e6 * step_times[steps - 1 - steps / 1000],
         1e6 * step_times[steps - 1], steps, 1e6 * feedback_times[steps / 2],
         1e6 * feedback_times[steps - 1 - steps / 1000], 1e6 * feedback_times[steps - 1], misses);
  return 0;
}
