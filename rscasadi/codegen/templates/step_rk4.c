/* RK4's step and its Jacobian (rscasadi/codegen/step_kernel.py): the four stage points' forward
   dynamics and factors, dr/dx at all four in the lanes, then the four stages and their sums. */
int @NAME@(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w, int mem) {
  static const casadi_real c[4] = {0.0, 0.5, 0.5, 1.0};
  const casadi_real *x = arg[0], *tau = arg[1], h = arg[2] ? arg[2][0] : 0.0;
  const casadi_real **parg = arg + RSK_NIN, *jarg[3];
  casadi_real **pres = res + RSK_NOUT, *jres[1];
  /* stage point i: xi and a (the current one), X4 and A4 (all four, interleaved for the lanes:
     [4 r + i]), the factors D, LT, L (all four); JR4 dr/dx' at the four points, interleaved */
  casadi_real *xi = w + RSK_PT_W, *X4 = xi + RSK_NX, *A4 = X4 + 4 * RSK_NX, *kp = A4 + 4 * RSK_NV;
  casadi_real *a = kp + RSK_NX, *D = a + RSK_NV, *LT = D + 4 * RSK_NV, *L = LT + 4 * RSK_NLT;
  casadi_real *mu = L + 4 * RSK_NLT, *JR4 = mu + RSK_N;
  /* the row-stored matrices on a cache line: their rows (RSK_NP apart) then start on whole vectors
     (n = 12: the offset the point's work size left ran 6 % slower, interleaved A/B) */
  casadi_real *Bs = (casadi_real *)(((uintptr_t)(JR4 + 4 * RSK_NJR) + 63) & ~(uintptr_t)63);
  casadi_real *Ao = res[0], *Bo = res[1];
  int i, r, cc;
  (void)mem;
#if RSK_CHAIN
  /* RK4's sum of the stage derivatives k1 + 2 k2 + 2 k3 + k4; A and B of this step */
  static const casadi_real weight[4] = {1.0, 2.0, 2.0, 1.0};
  casadi_real *ks = Bs + 4 * RSK_NV * RSK_NP, *Ak = ks + RSK_NX, *Bk = Ak + RSK_NX * RSK_NX;
  const casadi_real *A0 = arg[RSK_NIN - 2], *B0 = arg[RSK_NIN - 1];
  const int chained = A0 && B0 && !rsk_start(A0, B0);
  if (chained) Ao = Ak, Bo = Bk;
  for (r = 0; r < RSK_NX; ++r) ks[r] = 0.0;
#endif
  for (i = 0; i < 4; ++i) {                 /* the stage points: forward dynamics and M's factors */
    for (r = 0; r < RSK_NX; ++r) xi[r] = (x ? x[r] : 0.0) + (i ? c[i] * h * kp[r] : 0.0);
    parg[0] = xi; parg[1] = tau;
    if (RSK_NPAR) parg[2] = arg[3];
    pres[0] = a; pres[1] = D + i * RSK_NV; pres[2] = LT + i * RSK_NLT; pres[3] = L + i * RSK_NLT; pres[4] = mu;
    if (RSK_FD(parg, pres, iw, w, 0)) return 1;
    for (r = 0; r < RSK_NV; ++r) { kp[r] = xi[RSK_NV + r]; kp[RSK_NV + r] = a[r]; }
#if RSK_CHAIN
    for (r = 0; r < RSK_NX; ++r) ks[r] += weight[i] * kp[r];
#endif
    for (r = 0; r < RSK_NX; ++r) X4[4 * r + i] = xi[r];
    for (r = 0; r < RSK_NV; ++r) A4[4 * r + i] = a[r];
  }
  jarg[0] = X4; jarg[1] = A4; jarg[2] = RSK_NPAR ? arg[3] : 0; jres[0] = JR4;
  rsk_jr4(jarg, jres);                      /* dr/dx' at the four points at once */
  for (i = 0; i < 4; ++i) {
    casadi_real *Bi = Bs + i * RSK_NV * RSK_NP;
    rsk_stage(JR4 + i, D + i * RSK_NV, LT + i * RSK_NLT, L + i * RSK_NLT, mu, i ? Bi - RSK_NV * RSK_NP : 0,
              i > 1 ? Bi - 2 * RSK_NV * RSK_NP : 0, c[i] * h, i ? c[i - 1] * h : 0.0, Bi);
  }
  {                              /* the sums, stored by columns as CasADi stores A and B: read once
                                    by rows, no intermediate matrix (2 % faster at n = 12) */
    const casadi_real *B1 = Bs, *B2 = Bs + RSK_NV * RSK_NP, *B3 = Bs + 2 * RSK_NV * RSK_NP, *B4 = Bs + 3 * RSK_NV * RSK_NP;
    const casadi_real h2 = h * h / 6, h6 = h / 6;
    for (r = 0; r < RSK_NV; ++r) {
      const casadi_real *b1 = B1 + r * RSK_NP, *b2 = B2 + r * RSK_NP, *b3 = B3 + r * RSK_NP, *b4 = B4 + r * RSK_NP;
      if (Ao)
        for (cc = 0; cc < RSK_NX; ++cc) {
          const casadi_real b23 = b2[cc] + b3[cc];
          Ao[cc * RSK_NX + r] = h2 * (b1[cc] + b23);
          Ao[cc * RSK_NX + RSK_NV + r] = h6 * (b1[cc] + 2 * b23 + b4[cc]);
        }
      if (Bo)
        for (cc = RSK_NX; cc < RSK_NC; ++cc) {
          const casadi_real b23 = b2[cc] + b3[cc];
          Bo[(cc - RSK_NX) * RSK_NX + r] = h2 * (b1[cc] + b23);
          Bo[(cc - RSK_NX) * RSK_NX + RSK_NV + r] = h6 * (b1[cc] + 2 * b23 + b4[cc]);
        }
    }
    if (Ao) rsk_plus_identity(Ao, h);
  }
#if RSK_CHAIN
  if (chained) rsk_chain_out(res, Ak, Bk, A0, B0);
  if (res[2])
    for (r = 0; r < RSK_NX; ++r) res[2][r] = (x ? x[r] : 0.0) + h / 6 * ks[r];
#endif
  return 0;
}

