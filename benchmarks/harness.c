/* ns per call of CasADi-generated functions in a shared library, through the standard
 * interface (fname, fname_work, fname_sparsity_in, ...).  Median of many batches.
 * usage: harness LIB SYMBOL [SYMBOL ...]   prints "SYMBOL ns_per_call" lines. */
#define _POSIX_C_SOURCE 199309L
#include <dlfcn.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

typedef long long int casadi_int;
typedef int (*eval_t)(const double **, double **, casadi_int *, double *, int);
typedef int (*work_t)(casadi_int *, casadi_int *, casadi_int *, casadi_int *);
typedef const casadi_int *(*sp_t)(casadi_int);
typedef casadi_int (*n_t)(void);

static double now(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}

static int cmp(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return (x > y) - (x < y);
}

static void *sym(void *lib, const char *base, const char *suffix) {
  char name[256];
  snprintf(name, sizeof name, "%s%s", base, suffix);
  void *p = dlsym(lib, name);
  if (!p) { fprintf(stderr, "missing symbol %s\n", name); exit(2); }
  return p;
}

static casadi_int nnz(const casadi_int *sp) {   /* CasADi's compressed column storage; */
  return sp[2] ? sp[0] * sp[1] : sp[2 + sp[1]];  /* {nrow, ncol, 1} is its dense form   */
}

int main(int argc, char **argv) {
  if (argc < 3) { fprintf(stderr, "usage: %s LIB SYMBOL...\n", argv[0]); return 2; }
  void *lib = dlopen(argv[1], RTLD_NOW);
  if (!lib) { fprintf(stderr, "%s\n", dlerror()); return 2; }
  for (int s = 2; s < argc; ++s) {
    const char *f = argv[s];
    eval_t eval = (eval_t)sym(lib, f, "");
    casadi_int sz_arg, sz_res, sz_iw, sz_w;
    ((work_t)sym(lib, f, "_work"))(&sz_arg, &sz_res, &sz_iw, &sz_w);
    casadi_int n_in = ((n_t)sym(lib, f, "_n_in"))(), n_out = ((n_t)sym(lib, f, "_n_out"))();
    sp_t sp_in = (sp_t)sym(lib, f, "_sparsity_in"), sp_out = (sp_t)sym(lib, f, "_sparsity_out");
    const double **arg = calloc(sz_arg, sizeof *arg);
    double **res = calloc(sz_res, sizeof *res);
    casadi_int *iw = calloc(sz_iw + 1, sizeof *iw);
    double *w = calloc(sz_w + 1, sizeof *w);
    srand(1);
    for (casadi_int i = 0; i < n_in; ++i) {
      casadi_int k = nnz(sp_in(i));
      double *x = malloc((k + 1) * sizeof *x);
      for (casadi_int j = 0; j < k; ++j) x[j] = 0.5 * rand() / RAND_MAX - 0.25;
      if (k == 1) x[0] = 1e-3;                          /* a step size h */
      arg[i] = x;
    }
    for (casadi_int i = 0; i < n_out; ++i) res[i] = malloc((nnz(sp_out(i)) + 1) * sizeof(double));
    long batch = 1;
    for (;;) {                                          /* batches of at least 20 ms */
      double t0 = now();
      for (long r = 0; r < batch; ++r) eval(arg, res, iw, w, 0);
      if (now() - t0 > 0.02) break;
      batch *= 2;
    }
    enum { BATCHES = 15 };
    double t[BATCHES];
    for (int b = 0; b < BATCHES; ++b) {
      double t0 = now();
      for (long r = 0; r < batch; ++r) eval(arg, res, iw, w, 0);
      t[b] = (now() - t0) / batch * 1e9;
    }
    qsort(t, BATCHES, sizeof t[0], cmp);
    printf("%s %.1f\n", f, t[BATCHES / 2]);
    for (casadi_int i = 0; i < n_in; ++i) free((void *)arg[i]);
    for (casadi_int i = 0; i < n_out; ++i) free(res[i]);
    free(arg); free(res); free(iw); free(w);
  }
  return 0;
}
