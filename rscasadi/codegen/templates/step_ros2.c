/* ROS2's step and its Jacobian (rscasadi/codegen/step_kernel.py, rscasadi/codegen/rosenbrock.py):

     S = I - g Fv - g^2 Fq (g = gamma h; Fq, Fv: F1's angle and speed columns, F1 = M^-1 [-dr/dx | dQ/dtau] at x)
     k1:  k_v = S^-1 (a1 + g Fq v),                       k_q = v + g k_v
     k2:  k_v = S^-1 (a2 - 2 k1_v + g Fq (v2 - 2 k1_q)),  k_q = v2 - 2 k1_q + g k_v      (a2, v2 at x2 = x + h k1)
     x_next = x + 3/2 h k1 + 1/2 h k2

   and with W held fixed (the matrices by rows, RSK_NP apart, columns (x, tau)):

     K1 = S^-1 (F1 + g Fq [0 I 0])                                  dk1 = [[0 I 0] + g K1; K1]
     P2 = M2^-1 ([-dr/dx | dQ/dtau] - h dr/dx [[0 I 0] + g K1; K1])  the dynamics' Jacobian along x2
     K2 = S^-1 (P2 - 2 K1 - g Fq [0 I 0] + g (h - 2 g) Fq K1)       dk2 = [-[0 I 0] + (h - 2 g) K1 + g K2; K2]
     A, B = [[I hI 0] + h/2 (g + h) K1 + h g/2 K2;  [0 I 0] + 3/2 h K1 + 1/2 h K2]

   P2 is rsk_stage with s = h, s2 = g and B1 = B2 = K1.  S is dense (RSK_NV square): an LU with
   partial pivoting, its solves row operations on whole rows.  Without A and B (res[0], res[1]
   NULL) neither K1, K2 nor dr/dx at x2 are formed: the step alone needs F1's state columns. */

/* S = P L U in place (RSK_NV square, by rows): piv[k] the row swapped with row k at column k */
static void rsk_lu(casadi_real *S, int *piv) {
  int i, j, k;
  for (k = 0; k < RSK_NV; ++k) {
    int p = k;
    for (i = k + 1; i < RSK_NV; ++i)
      if (fabs(S[i * RSK_NV + k]) > fabs(S[p * RSK_NV + k])) p = i;
    piv[k] = p;
    if (p != k)
      for (j = 0; j < RSK_NV; ++j) { casadi_real t = S[k * RSK_NV + j]; S[k * RSK_NV + j] = S[p * RSK_NV + j]; S[p * RSK_NV + j] = t; }
    for (i = k + 1; i < RSK_NV; ++i) {
      const casadi_real f = S[i * RSK_NV + k] /= S[k * RSK_NV + k];
      for (j = k + 1; j < RSK_NV; ++j) S[i * RSK_NV + j] -= f * S[k * RSK_NV + j];
    }
  }
}

/* X = S^-1 X from rsk_lu's factors: X RSK_NV rows of m entries, ld apart */
static void rsk_lu_solve(const casadi_real *LU, const int *piv, casadi_real *X, int m, int ld) {
  int i, k, c;
  for (k = 0; k < RSK_NV; ++k)
    if (piv[k] != k)
      for (c = 0; c < m; ++c) { casadi_real t = X[k * ld + c]; X[k * ld + c] = X[piv[k] * ld + c]; X[piv[k] * ld + c] = t; }
  for (i = 1; i < RSK_NV; ++i)
    for (k = 0; k < i; ++k) {
      const casadi_real f = LU[i * RSK_NV + k];
      for (c = 0; c < m; ++c) X[i * ld + c] -= f * X[k * ld + c];
    }
  for (i = RSK_NV - 1; i >= 0; --i) {
    const casadi_real inv = 1.0 / LU[i * RSK_NV + i];
    for (k = i + 1; k < RSK_NV; ++k) {
      const casadi_real f = LU[i * RSK_NV + k];
      for (c = 0; c < m; ++c) X[i * ld + c] -= f * X[k * ld + c];
    }
    for (c = 0; c < m; ++c) X[i * ld + c] *= inv;
  }
}

/* y (RSK_NV, or rows ld apart of m entries) += s Fq X: Fq F1's first RSK_NV columns */
static void rsk_fq(const casadi_real *F1, casadi_real s, const casadi_real *X, int m, int ld, casadi_real *Y) {
  int i, k, c;
  for (i = 0; i < RSK_NV; ++i)
    for (k = 0; k < RSK_NV; ++k) {
      const casadi_real f = s * F1[i * RSK_NP + k];
      for (c = 0; c < m; ++c) Y[i * ld + c] += f * X[k * ld + c];
    }
}

/* the forward dynamics and M's factors at xi: a, D, LT, L, mu */
static int rsk_point(const casadi_real **arg, casadi_real **res, casadi_int *iw, casadi_real *w, const casadi_real *xi,
                     casadi_real *a, casadi_real *D, casadi_real *LT, casadi_real *L, casadi_real *mu) {
  const casadi_real **parg = arg + RSK_NIN;
  casadi_real **pres = res + RSK_NOUT;
  parg[0] = xi; parg[1] = arg[1];
  if (RSK_NPAR) parg[2] = arg[3];
  pres[0] = a; pres[1] = D; pres[2] = LT; pres[3] = L; pres[4] = mu;
  return RSK_FD(parg, pres, iw, w, 0);
}

/* dr/dx' at (xi, a) into JR */
static int rsk_jr(const casadi_real **arg, casadi_real **res, casadi_int *iw, casadi_real *w, const casadi_real *xi,
                  const casadi_real *a, casadi_real *JR) {
  const casadi_real **parg = arg + RSK_NIN;
  casadi_real **pres = res + RSK_NOUT;
  parg[0] = xi; parg[1] = a;
  if (RSK_NPAR) parg[2] = arg[3];
  pres[0] = JR;
  return RSK_JR(parg, pres, iw, w, 0);
}

int @NAME@(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w, int mem) {
  const casadi_real *x = arg[0], h = arg[2] ? arg[2][0] : 0.0, g = RSK_GAMMA * h;
  casadi_real *x2 = w + RSK_PT_W, *k1 = x2 + RSK_NX, *k2 = k1 + RSK_NX, *a1 = k2 + RSK_NX, *a2 = a1 + RSK_NV;
  casadi_real *D = a2 + RSK_NV, *LT = D + 2 * RSK_NV, *L = LT + 2 * RSK_NLT, *mu = L + 2 * RSK_NLT;
  casadi_real *JR = mu + RSK_N, *S = JR + RSK_NJR;
  casadi_real *F1 = (casadi_real *)(((uintptr_t)(S + RSK_NV * RSK_NV) + 63) & ~(uintptr_t)63);
  casadi_real *K1 = F1 + RSK_NV * RSK_NP, *K2 = K1 + RSK_NV * RSK_NP;
  casadi_real *Ao = res[0], *Bo = res[1];
  int piv[RSK_NV], r, cc, jac;
#if RSK_CHAIN
  casadi_real *Ak = K2 + RSK_NV * RSK_NP, *Bk = Ak + RSK_NX * RSK_NX;
  const casadi_real *A0 = arg[RSK_NIN - 2], *B0 = arg[RSK_NIN - 1];
  const int chained = A0 && B0 && !rsk_start(A0, B0);
  if (chained) Ao = res[0] || res[1] ? Ak : 0, Bo = res[1] ? Bk : 0;     /* A_k B0 needs A_k */
#endif
  (void)mem;
  jac = Ao || Bo;
  for (r = 0; r < RSK_NX; ++r) x2[r] = x ? x[r] : 0.0;
  if (rsk_point(arg, res, iw, w, x2, a1, D, LT, L, mu)) return 1;
  if (rsk_jr(arg, res, iw, w, x2, a1, JR)) return 1;
  rsk_stage(JR, D, LT, L, mu, 0, 0, 0.0, 0.0, F1);
  for (r = 0; r < RSK_NV; ++r)
    for (cc = 0; cc < RSK_NV; ++cc)
      S[r * RSK_NV + cc] = (r == cc) - g * F1[r * RSK_NP + RSK_NV + cc] - g * g * F1[r * RSK_NP + cc];
  rsk_lu(S, piv);
  for (r = 0; r < RSK_NV; ++r) k1[RSK_NV + r] = a1[r];            /* k1 */
  rsk_fq(F1, g, x2 + RSK_NV, 1, 1, k1 + RSK_NV);
  rsk_lu_solve(S, piv, k1 + RSK_NV, 1, 1);
  for (r = 0; r < RSK_NV; ++r) k1[r] = x2[RSK_NV + r] + g * k1[RSK_NV + r];
  for (r = 0; r < RSK_NX; ++r) x2[r] += h * k1[r];
  if (rsk_point(arg, res, iw, w, x2, a2, D + RSK_NV, LT + RSK_NLT, L + RSK_NLT, mu)) return 1;
  for (r = 0; r < RSK_NV; ++r) { k2[r] = x2[RSK_NV + r] - 2 * k1[r]; k2[RSK_NV + r] = a2[r] - 2 * k1[RSK_NV + r]; }
  rsk_fq(F1, g, k2, 1, 1, k2 + RSK_NV);                              /* k2 */
  rsk_lu_solve(S, piv, k2 + RSK_NV, 1, 1);
  for (r = 0; r < RSK_NV; ++r) k2[r] += g * k2[RSK_NV + r];
  if (jac) {
    const casadi_real c1 = 0.5 * h * (g + h), c2 = 0.5 * h * g;
    for (r = 0; r < RSK_NV * RSK_NP; ++r) K1[r] = F1[r];             /* K1 */
    for (r = 0; r < RSK_NV; ++r)
      for (cc = 0; cc < RSK_NV; ++cc) K1[r * RSK_NP + RSK_NV + cc] += g * F1[r * RSK_NP + cc];
    rsk_lu_solve(S, piv, K1, RSK_NC, RSK_NP);
    if (rsk_jr(arg, res, iw, w, x2, a2, JR)) return 1;               /* P2, then K2 in its place */
    rsk_stage(JR, D + RSK_NV, LT + RSK_NLT, L + RSK_NLT, mu, K1, K1, h, g, K2);
    for (r = 0; r < RSK_NV; ++r) {
      for (cc = 0; cc < RSK_NC; ++cc) K2[r * RSK_NP + cc] -= 2 * K1[r * RSK_NP + cc];
      for (cc = 0; cc < RSK_NV; ++cc) K2[r * RSK_NP + RSK_NV + cc] -= g * F1[r * RSK_NP + cc];
    }
    rsk_fq(F1, g * (h - 2 * g), K1, RSK_NC, RSK_NP, K2);
    rsk_lu_solve(S, piv, K2, RSK_NC, RSK_NP);
    for (r = 0; r < RSK_NV; ++r) {                                   /* A and B by columns, as CasADi stores them */
      const casadi_real *b1 = K1 + r * RSK_NP, *b2 = K2 + r * RSK_NP;
      if (Ao)
        for (cc = 0; cc < RSK_NX; ++cc) {
          Ao[cc * RSK_NX + r] = c1 * b1[cc] + c2 * b2[cc];
          Ao[cc * RSK_NX + RSK_NV + r] = 0.5 * h * (3 * b1[cc] + b2[cc]);
        }
      if (Bo)
        for (cc = RSK_NX; cc < RSK_NC; ++cc) {
          Bo[(cc - RSK_NX) * RSK_NX + r] = c1 * b1[cc] + c2 * b2[cc];
          Bo[(cc - RSK_NX) * RSK_NX + RSK_NV + r] = 0.5 * h * (3 * b1[cc] + b2[cc]);
        }
    }
    if (Ao) rsk_plus_identity(Ao, h);
  }
#if RSK_CHAIN
  if (chained) rsk_chain_out(res, Ak, Bk, A0, B0);
  if (res[2])
    for (r = 0; r < RSK_NX; ++r) res[2][r] = (x ? x[r] : 0.0) + 0.5 * h * (3 * k1[r] + k2[r]);
#endif
  return 0;
}

