/* BLASFEO's 4x4 product kernels and its 4-row matrix-vector kernels on panel-major 4-row panels,
   written in GCC's vector extensions and compiled for this processor, in front of the CasADi
   wheel's BLASFEO:
     kernel_dgemm_nt_4x4_lib4   D = beta C + alpha A B'   (fatrop's and HPIPM's Riccati recursions)
     kernel_dgemm_nn_4x4_lib4   D = beta C + alpha A B    (HPIPM's partial condensing, its solves)
     kernel_dgemv_n_4_lib4      z = beta y + alpha A x    (4 rows of A: fatrop's residuals, the
     kernel_dgemv_t_4_lib4      z = beta y + alpha A' x    solves of the Riccati recursion)

   The wheel's BLASFEO is its GENERIC target (plain C, scalar); the two products were 14 % of a
   fatrop solve of problem (b) and 31 % of the Panda's Riccati MPC step at N = 10, the two
   matrix-vector kernels 21 % of fatrop's own (serial) time in the Panda's minimum-time solve
   (perf, 2026-11-28).  The wheel's library calls them through its procedure linkage table, so a
   definition found before the library's own binds for every caller inside it: fatrop loads this
   file's library into the process's global scope (rscasadi/ocp/fatrop/blasfeo.py, which checks
   each against the wheel's kernel); a Riccati MPC's library holds it, ahead of libblasfeo in its
   lookup scope.  The definitions are weak: two controllers' libraries link into one program.
   Same signatures and arithmetic as BLASFEO's kernel/generic/kernel_dgemm_4x4_lib4.c (beta C is
   formed even for beta = 0) and kernel_dgemv_4_lib4.c (y is not read for beta = 0); sums in
   another order, so equal up to rounding. */
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

/* A, B: kmax columns of a 4-row panel each (column k at 4 k); C, D: 4 x 4, column-major.  Even
   and odd k in two sets of sums: eight independent chains keep both FMA units busy (four wait
   on each other's latency). */
__attribute__((weak)) void kernel_dgemm_nt_4x4_lib4(int kmax, double* alpha, double* A, double* B, double* beta,
                                                    double* C, double* D) {
  v4 d0 = {0}, d1 = {0}, d2 = {0}, d3 = {0}, e0 = {0}, e1 = {0}, e2 = {0}, e3 = {0};
  int k = 0;
  for (; k < kmax - 1; k += 2) {
    v4 a = load4(A + 4 * k), b = load4(A + 4 * k + 4);     /* columns k, k + 1 of A: 4 rows at once */
    d0 += a * B[4 * k + 0];
    d1 += a * B[4 * k + 1];
    d2 += a * B[4 * k + 2];
    d3 += a * B[4 * k + 3];
    e0 += b * B[4 * k + 4];
    e1 += b * B[4 * k + 5];
    e2 += b * B[4 * k + 6];
    e3 += b * B[4 * k + 7];
  }
  if (k < kmax) {
    v4 a = load4(A + 4 * k);
    d0 += a * B[4 * k + 0];
    d1 += a * B[4 * k + 1];
    d2 += a * B[4 * k + 2];
    d3 += a * B[4 * k + 3];
  }
  scale_store(alpha, beta, C, D, d0 + e0, d1 + e1, d2 + e2, d3 + e3);
}

/* A: kmax columns of a 4-row panel; B: kmax rows of 4 columns, panel-major with panel stride sdb
   (columns), its first row offsetB rows into the panel B points to.  Even and odd k in two sets
   of sums, as above. */
#define NEXT_ROW() do { if (++row == 4) { row = 0; b += 4 * sdb - 3; } else { ++b; } } while (0)
__attribute__((weak)) void kernel_dgemm_nn_4x4_lib4(int kmax, double* alpha, double* A, int offsetB, double* B,
                                                    int sdb, double* beta, double* C, double* D) {
  v4 d0 = {0}, d1 = {0}, d2 = {0}, d3 = {0}, e0 = {0}, e1 = {0}, e2 = {0}, e3 = {0};
  const double* b = B + offsetB;
  int row = offsetB, k = 0;                                 /* b's row within its panel */
  for (; k < kmax - 1; k += 2) {
    v4 a = load4(A + 4 * k), a1 = load4(A + 4 * k + 4);
    d0 += a * b[0];
    d1 += a * b[4];
    d2 += a * b[8];
    d3 += a * b[12];
    NEXT_ROW();
    e0 += a1 * b[0];
    e1 += a1 * b[4];
    e2 += a1 * b[8];
    e3 += a1 * b[12];
    NEXT_ROW();
  }
  if (k < kmax) {
    v4 a = load4(A + 4 * k);
    d0 += a * b[0];
    d1 += a * b[4];
    d2 += a * b[8];
    d3 += a * b[12];
  }
  scale_store(alpha, beta, C, D, d0 + e0, d1 + e1, d2 + e2, d3 + e3);
}
#undef NEXT_ROW

/* z = alpha s + beta y, y not read when beta is 0 (BLASFEO's generic matrix-vector kernels) */
static inline void axpby_store(const double* alpha, const double* beta, const double* y, double* z, v4 s) {
  store4(z, beta[0] == 0.0 ? alpha[0] * s : alpha[0] * s + beta[0] * load4(y));
  rsc_tuned_reached = 1;
}

/* A: kmax columns of a 4-row panel; z, y: 4 entries.  Four partial sums: independent chains. */
__attribute__((weak)) void kernel_dgemv_n_4_lib4(int kmax, double* alpha, double* A, double* x, double* beta,
                                                 double* y, double* z) {
  v4 s0 = {0}, s1 = {0}, s2 = {0}, s3 = {0};
  int k = 0;
  for (; k < kmax - 3; k += 4) {
    s0 += load4(A + 4 * k) * x[k];
    s1 += load4(A + 4 * k + 4) * x[k + 1];
    s2 += load4(A + 4 * k + 8) * x[k + 2];
    s3 += load4(A + 4 * k + 12) * x[k + 3];
  }
  for (; k < kmax; ++k) s0 += load4(A + 4 * k) * x[k];
  axpby_store(alpha, beta, y, z, (s0 + s1) + (s2 + s3));
}

/* A: kmax rows of 4 columns, panel-major with panel stride sda (columns), its first row offA rows
   into the panel A points into (A points at that row); z, y: 4 entries.  Whole panels as four
   column sums of 4 rows each, the rows before and after them one by one. */
__attribute__((weak)) void kernel_dgemv_t_4_lib4(int kmax, double* alpha, int offA, double* A, int sda, double* x,
                                                 double* beta, double* y, double* z) {
  v4 c0 = {0}, c1 = {0}, c2 = {0}, c3 = {0}, rows = {0};
  int k = 0;
  if (offA != 0) {
    int end = 4 - offA < kmax ? 4 - offA : kmax;
    for (; k < end; ++k, ++A) rows += (v4){A[0], A[4], A[8], A[12]} * x[k];
    A += 4 * (sda - 1);
  }
  for (; k < kmax - 3; k += 4, A += 4 * sda) {
    v4 xk = load4(x + k);
    c0 += load4(A) * xk;
    c1 += load4(A + 4) * xk;
    c2 += load4(A + 8) * xk;
    c3 += load4(A + 12) * xk;
  }
  for (; k < kmax; ++k, ++A) rows += (v4){A[0], A[4], A[8], A[12]} * x[k];
  rows += (v4){c0[0] + c0[1] + c0[2] + c0[3], c1[0] + c1[1] + c1[2] + c1[3],
               c2[0] + c2[1] + c2[2] + c2[3], c3[0] + c3[1] + c3[2] + c3[3]};
  axpby_store(alpha, beta, y, z, rows);
}
