/* The structured step-Jacobian kernel (rscasadi/codegen/step_kernel.py): @NAME@ its public symbol,
   @CONSTS@ its sizes, @PARTS@ the unrolled stage for the arm's sparsity patterns in functions of a
   few rows each, @BLOCKS@ their calls, @STEP@ the method's function and its interface (step_rk4.c or
   step_ros2.c with step_interface.c; fd_jacobian.c). */
/* ---- rscasadi: @NAME@, the structured step Jacobian (rscasadi/codegen/step_kernel.py) ---- */
#include <stdint.h>
@CONSTS@
/* gcc turns the block loops below into memset and memcpy calls, which keep t out of the registers */
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC optimize ("no-tree-loop-distribute-patterns")
#endif
/* X[0 .. W) = t */
#define RSK_ST(X, t, W) { casadi_real *x_ = (X); int c_; for (c_ = 0; c_ < (W); ++c_) x_[c_] = t[c_]; }
/* t += v X[0 .. W) */
#define RSK_AX(t, v, X, W) { const casadi_real v_ = (v), *x_ = (X); int c_; for (c_ = 0; c_ < (W); ++c_) t[c_] += v_ * x_[c_]; }

/* B = M^-1 ([-dr/dx | dQ/dtau] - s dr/dx [S; B1]), S = [0 1 0] + s2 B2 (B1, B2 NULL at the first
   stage, B2 NULL at the second), all stored by rows RSK_NP apart; jr holds the nonzeros of dr/dx' 4 apart
   (as the lanes left them).  L z = y is solved in place (z's row r in B's row perm[r], overwritten
   by L' x = z / d from the last row up: no scratch matrix).  Blocks of up to RSK_BK columns are
   independent: each goes through dr/dx's product, L and L' (their sparsity unrolled below, one
   block after the other) while it sits in the first-level cache. */
@PARTS@
static void rsk_stage(const casadi_real *jr, const casadi_real *d, const casadi_real *lt, const casadi_real *l,
                      const casadi_real *mu, const casadi_real *B1, const casadi_real *B2, casadi_real s,
                      casadi_real s2, casadi_real *B) {
  const casadi_real ms = -s, mss = -s * s2;
  casadi_real inv[RSK_NV];
  int r;
  for (r = 0; r < RSK_NV; ++r) inv[r] = 1.0 / d[r];
@BLOCKS@
}

#if RSK_CHAIN
/* out (RSK_NX x m) = M P (+ add), M (RSK_NX x RSK_NX), P (RSK_NX x m), column-major: a column of
   out accumulates in RSK_NX / 4 vectors over M's columns (and the last RSK_NX % 4 rows in scalars) */
#define RSK_NXV (RSK_NX / 4)
#define RSK_NXR (RSK_NX % 4)
static void rsk_chain(const casadi_real *M, const casadi_real *P, const casadi_real *add, int m, casadi_real *out) {
  int j, l, v;
  for (j = 0; j < m; ++j) {
    rsk_v t[RSK_NXV > 0 ? RSK_NXV : 1], mv, pv;
    casadi_real tr[4];
    for (v = 0; v < RSK_NXV; ++v)
      if (add) RSK_VLD(t[v], add + j * RSK_NX + 4 * v); else RSK_VBC(t[v], 0.0)
    for (v = 0; v < RSK_NXR; ++v) tr[v] = add ? add[j * RSK_NX + 4 * RSK_NXV + v] : 0.0;
    for (l = 0; l < RSK_NX; ++l) {
      const casadi_real p = P[j * RSK_NX + l];
      RSK_VBC(pv, p)
      for (v = 0; v < RSK_NXV; ++v) {
        RSK_VLD(mv, M + l * RSK_NX + 4 * v);
        t[v] = RSK_ADD(t[v], RSK_MUL(mv, pv));
      }
      for (v = 0; v < RSK_NXR; ++v) tr[v] += M[l * RSK_NX + 4 * RSK_NXV + v] * p;
    }
    for (v = 0; v < RSK_NXV; ++v) RSK_VST(out + j * RSK_NX + 4 * v, t[v]);
    for (v = 0; v < RSK_NXR; ++v) out[j * RSK_NX + 4 * RSK_NXV + v] = tr[v];
  }
}

/* the interval's sensitivities carried through this step (A_k, B_k): res[0] = A_k A0, res[1] = A_k B0 + B_k */
static void rsk_chain_out(casadi_real **res, const casadi_real *Ak, const casadi_real *Bk, const casadi_real *A0,
                          const casadi_real *B0) {
  if (res[0]) rsk_chain(Ak, A0, 0, RSK_NX, res[0]);
  if (res[1]) rsk_chain(Ak, B0, Bk, RSK_NU, res[1]);
}

/* whether A0 = I and B0 = 0: the first substep of an interval, nothing to chain onto */
static int rsk_start(const casadi_real *A0, const casadi_real *B0) {
  int i, j;
  for (j = 0; j < RSK_NX; ++j)
    for (i = 0; i < RSK_NX; ++i)
      if (A0[j * RSK_NX + i] != (i == j)) return 0;
  for (i = 0; i < RSK_NX * RSK_NU; ++i)
    if (B0[i] != 0.0) return 0;
  return 1;
}
#endif

#if RSK_STEP
/* A += [I hI; 0 I]: a step's A (column-major, RSK_NX square) from its stages' sums */
static void rsk_plus_identity(casadi_real *A, casadi_real h) {
  int r;
  for (r = 0; r < RSK_NV; ++r) {
    A[r * RSK_NX + r] += 1; A[(RSK_NV + r) * RSK_NX + r] += h; A[(RSK_NV + r) * RSK_NX + RSK_NV + r] += 1;
  }
}
#endif

@STEP@
