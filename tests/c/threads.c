/* Two threads evaluate the generated functions at once; each must get exactly what a
 * lone evaluation gives.  Generated code is reentrant: no malloc, no mutable globals.
 * -DFRAMES: also the task-space functions of a library generated with --frames tool
 * --external tool (the tool's placement, its world Jacobian, the dynamics with a wrench at it);
 * thread 0's lone results are printed on the first line. */
#include <pthread.h>
#include <stdio.h>
#include <string.h>
#include "rscasadi_arm.h"

#ifndef N
#define N 3   /* joints; -DN=... for another library */
#endif
#ifndef REPEAT
#define REPEAT 20000
#endif
#define MAX(a, b) ((a) > (b) ? (a) : (b))
#define NSTEP (4 * N * 5 * N)
#ifdef FRAMES
#define NOUT (NSTEP + 9 + 3 + 6 * N + 2 * N)
#define SZ_W MAX(MAX(step_jacobian_SZ_W, forward_dynamics_SZ_W), \
                 MAX(MAX(frame_placement_tool_SZ_W, frame_jacobian_tool_world_SZ_W), forward_dynamics_external_SZ_W))
#define SZ_IW MAX(MAX(step_jacobian_SZ_IW, forward_dynamics_SZ_IW), \
                  MAX(MAX(frame_placement_tool_SZ_IW, frame_jacobian_tool_world_SZ_IW), forward_dynamics_external_SZ_IW))
#else
#define NOUT NSTEP
#define SZ_W MAX(step_jacobian_SZ_W, forward_dynamics_SZ_W)
#define SZ_IW MAX(step_jacobian_SZ_IW, forward_dynamics_SZ_IW)
#endif

typedef struct { double x[4 * N], tau[N], h, f[6], out[NOUT], ref[NOUT]; int bad; } job_t;

static void eval(job_t *j, double *out) {
  casadi_int iw[SZ_IW + 1];
  casadi_real w[SZ_W + 1];
  const casadi_real *arg[step_jacobian_SZ_ARG] = {j->x, j->tau, &j->h};
  casadi_real *res[step_jacobian_SZ_RES] = {out, out + 4 * N * 4 * N};
  step_jacobian(arg, res, iw, w, 0);
  const casadi_real *fa[forward_dynamics_SZ_ARG] = {j->x, j->x + N, j->x + 2 * N, j->x + 3 * N, j->tau};
  casadi_real *fr[forward_dynamics_SZ_RES] = {out + NSTEP - 2 * N, out + NSTEP - N};
  forward_dynamics(fa, fr, iw, w, 0);
#ifdef FRAMES
  double *o = out + NSTEP;
  const casadi_real *pa[1] = {j->x};
  casadi_real *pr[2] = {o, o + 9};
  frame_placement_tool(pa, pr, iw, w, 0);
  casadi_real *jr[1] = {o + 12};
  frame_jacobian_tool_world(pa, jr, iw, w, 0);
  const casadi_real *ea[6] = {j->x, j->x + N, j->x + 2 * N, j->x + 3 * N, j->tau, j->f};
  casadi_real *er[2] = {o + 12 + 6 * N, o + 12 + 7 * N};
  forward_dynamics_external(ea, er, iw, w, 0);
#endif
}

static void *run(void *p) {
  job_t *j = p;
  for (int r = 0; r < REPEAT; ++r) {
    eval(j, j->out);
    if (memcmp(j->out, j->ref, sizeof j->out) != 0) { j->bad = 1; break; }
  }
  return NULL;
}

int main(void) {
  job_t jobs[2];
  memset(jobs, 0, sizeof jobs);
  for (int k = 0; k < 2; ++k) {
    for (int i = 0; i < 4 * N; ++i) jobs[k].x[i] = 0.1 * (i + 1) * (k ? -1.0 : 1.0);
    for (int i = 0; i < N; ++i) jobs[k].tau[i] = 0.05 * (k + 1) * (i + 1);
    for (int i = 0; i < 6; ++i) jobs[k].f[i] = (k + 1) * (i - 2.5);
    jobs[k].h = 1e-3;
    eval(&jobs[k], jobs[k].ref);
  }
  if (memcmp(jobs[0].ref, jobs[1].ref, sizeof jobs[0].ref) == 0) { puts("inputs do not differ"); return 1; }
#ifdef FRAMES
  for (int i = NSTEP; i < NOUT; ++i)
    printf("%.17g%c", jobs[0].ref[i], i + 1 < NOUT ? ' ' : '\n');
#endif
  pthread_t t[2];
  for (int k = 0; k < 2; ++k) pthread_create(&t[k], NULL, run, &jobs[k]);
  for (int k = 0; k < 2; ++k) pthread_join(t[k], NULL);
  printf("thread results %s\n", jobs[0].bad || jobs[1].bad ? "DIFFER" : "identical");
  return jobs[0].bad || jobs[1].bad;
}
