/* Two threads evaluate the generated functions at once; each must get exactly what a
 * lone evaluation gives.  Generated code is reentrant: no malloc, no mutable globals. */
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

typedef struct { double x[4 * N], tau[N], h, out[4 * N * 5 * N], ref[4 * N * 5 * N]; int bad; } job_t;

static void eval(job_t *j, double *out) {
  const casadi_real *arg[step_jacobian_SZ_ARG] = {j->x, j->tau, &j->h};
  casadi_real *res[step_jacobian_SZ_RES] = {out, out + 4 * N * 4 * N};
  casadi_int iw[step_jacobian_SZ_IW + 1];
  casadi_real w[step_jacobian_SZ_W + 1];
  step_jacobian(arg, res, iw, w, 0);
  const casadi_real *fa[forward_dynamics_SZ_ARG] = {j->x, j->x + N, j->x + 2 * N, j->x + 3 * N, j->tau};
  casadi_real *fr[forward_dynamics_SZ_RES] = {out + 4 * N * 5 * N - 2 * N, out + 4 * N * 5 * N - N};
  casadi_real fw[forward_dynamics_SZ_W + 1];
  forward_dynamics(fa, fr, iw, fw, 0);
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
    jobs[k].h = 1e-3;
    eval(&jobs[k], jobs[k].ref);
  }
  if (memcmp(jobs[0].ref, jobs[1].ref, sizeof jobs[0].ref) == 0) { puts("inputs do not differ"); return 1; }
  pthread_t t[2];
  for (int k = 0; k < 2; ++k) pthread_create(&t[k], NULL, run, &jobs[k]);
  for (int k = 0; k < 2; ++k) pthread_join(t[k], NULL);
  printf("thread results %s\n", jobs[0].bad || jobs[1].bad ? "DIFFER" : "identical");
  return jobs[0].bad || jobs[1].bad;
}
