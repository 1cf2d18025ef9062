/* BLASFEO's 4x4 kernel of D = beta C + alpha A B' on panel-major 4-row panels, written in GCC's
   vector extensions and compiled for this processor (rscasadi/ocp/fatrop/blasfeo.py).

   The CasADi wheel's BLASFEO is its GENERIC target (plain C, scalar), and this one kernel was 14 %
   of a fatrop solve of problem (b) (perf, one thread): the Riccati recursion's products of 4x4
   blocks.  The wheel's library calls it through its procedure linkage table, so a definition
   loaded into the process's global scope before it binds replaces it for every caller inside the
   library.  Same signature and arithmetic as BLASFEO's kernel/generic/kernel_dgemm_4x4_lib4.c
   (0.1.4.2: beta C is formed even for beta = 0); sums in another order, so equal up to rounding
   (checked against the wheel's own kernel before it is loaded). */
#include <string.h>

typedef double v4 __attribute__((vector_size(4 * sizeof(double))));

static inline v4 load4(const double* p) { v4 v; memcpy(&v, p, sizeof v); return v; }
static inline void store4(double* p, v4 v) { memcpy(p, &v, sizeof v); }

/* set by the kernel: blasfeo.py checks that the wheel's calls reach it */
int rsc_tuned_reached = 0;

/* A, B: kmax columns of a 4-row panel each (column k at 4 k); C, D: 4 x 4, column-major */
void kernel_dgemm_nt_4x4_lib4(int kmax, double* alpha, double* A, double* B, double* beta, double* C, double* D) {
  v4 d0 = {0}, d1 = {0}, d2 = {0}, d3 = {0};
  int k;
  for (k = 0; k < kmax; ++k) {
    v4 a = load4(A + 4 * k);                                /* column k of A: 4 rows at once */
    d0 += a * B[4 * k + 0];
    d1 += a * B[4 * k + 1];
    d2 += a * B[4 * k + 2];
    d3 += a * B[4 * k + 3];
  }
  store4(D + 0, beta[0] * load4(C + 0) + alpha[0] * d0);
  store4(D + 4, beta[0] * load4(C + 4) + alpha[0] * d1);
  store4(D + 8, beta[0] * load4(C + 8) + alpha[0] * d2);
  store4(D + 12, beta[0] * load4(C + 12) + alpha[0] * d3);
  rsc_tuned_reached = 1;
}
