/* BLASFEO's two 4x4 product kernels on panel-major 4-row panels, written in GCC's vector
   extensions and compiled for this processor, in front of the CasADi wheel's BLASFEO:
     kernel_dgemm_nt_4x4_lib4   D = beta C + alpha A B'   (fatrop's and HPIPM's Riccati recursions)
     kernel_dgemm_nn_4x4_lib4   D = beta C + alpha A B    (HPIPM's partial condensing, its solves)

   The wheel's BLASFEO is its GENERIC target (plain C, scalar); these two kernels were 14 % of a
   fatrop solve of problem (b) and 31 % of the Panda's Riccati MPC step at N = 10 (perf, one
   thread).  The wheel's library calls them through its procedure linkage table, so a definition
   found before the library's own binds for every caller inside it: fatrop loads this file's
   library into the process's global scope (rscasadi/ocp/fatrop/blasfeo.py, which checks both
   against the wheel's kernels); a Riccati MPC's library holds it, ahead of libblasfeo in its
   lookup scope.  The definitions are weak: two controllers' libraries link into one program.
   Same signatures and arithmetic as BLASFEO's kernel/generic/kernel_dgemm_4x4_lib4.c (beta C is
   formed even for beta = 0); sums in another order, so equal up to rounding. */
#include <string.h>

typedef double v4 __attribute__((vector_size(4 * sizeof(double))));

static inline v4 load4(const double* p) { v4 v; memcpy(&v, p, sizeof v); return v; }
static inline void store4(double* p, v4 v) { memcpy(p, &v, sizeof v); }

/* set by the kernels: blasfeo.py checks that the wheel's calls reach them */
__attribute__((weak)) int rsc_tuned_reached = 0;

static inline void scale_store(const double* alpha, const double* beta, const double* C, double* D,
                               v4 d0, v4 d1, v4 d2, v4 d3) {
  store4(D + 0, beta[0] * load4(C + 0) + alpha[0] * d0);
  store4(D + 4, beta[0] * load4(C + 4) + alpha[0] * d1);
  store4(D + 8, beta[0] * load4(C + 8) + alpha[0] * d2);
  store4(D + 12, beta[0] * load4(C + 12) + alpha[0] * d3);
  rsc_tuned_reached = 1;
}

/* A, B: kmax columns of a 4-row panel each (column k at 4 k); C, D: 4 x 4, column-major */
__attribute__((weak)) void kernel_dgemm_nt_4x4_lib4(int kmax, double* alpha, double* A, double* B, double* beta,
                                                    double* C, double* D) {
  v4 d0 = {0}, d1 = {0}, d2 = {0}, d3 = {0};
  for (int k = 0; k < kmax; ++k) {
    v4 a = load4(A + 4 * k);                                /* column k of A: 4 rows at once */
    d0 += a * B[4 * k + 0];
    d1 += a * B[4 * k + 1];
    d2 += a * B[4 * k + 2];
    d3 += a * B[4 * k + 3];
  }
  scale_store(alpha, beta, C, D, d0, d1, d2, d3);
}

/* A: kmax columns of a 4-row panel; B: kmax rows of 4 columns, panel-major with panel stride sdb
   (columns), its first row offsetB rows into the panel B points to */
__attribute__((weak)) void kernel_dgemm_nn_4x4_lib4(int kmax, double* alpha, double* A, int offsetB, double* B,
                                                    int sdb, double* beta, double* C, double* D) {
  v4 d0 = {0}, d1 = {0}, d2 = {0}, d3 = {0};
  const double* b = B + offsetB;
  int row = offsetB;                                        /* b's row within its panel */
  for (int k = 0; k < kmax; ++k) {
    v4 a = load4(A + 4 * k);
    d0 += a * b[0];
    d1 += a * b[4];
    d2 += a * b[8];
    d3 += a * b[12];
    if (++row == 4) {                                       /* on to the next panel */
      row = 0;
      b += 4 * sdb - 3;
    } else {
      ++b;
    }
  }
  scale_store(alpha, beta, C, D, d0, d1, d2, d3);
}
