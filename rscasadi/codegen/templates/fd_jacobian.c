/* The forward dynamics' Jacobian (rscasadi/codegen/step_kernel.py, method "fd_jacobian"): at x, the
   implicit-function theorem on the residual r(x, a, tau) = M a + c - Q,

     d a / d(x, tau) = M^-1 [-dr/dx | dQ/dtau]

   which is one rsk_stage with no earlier stage (s = 0), from the forward dynamics' LDL^T factors of
   M and dr/dx at (x, a).  Interface as the Function it replaces: (theta, phi, dtheta, dphi, tau[, p])
   -> jacobian (RSK_NV x RSK_NC, dense, by columns). */
int @NAME@(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w, int mem) {
  const casadi_real **parg = arg + RSK_NIN;
  casadi_real **pres = res + RSK_NOUT;
  casadi_real *x = w + RSK_PT_W, *a = x + RSK_NX, *D = a + RSK_NV, *LT = D + RSK_NV, *L = LT + RSK_NLT;
  casadi_real *mu = L + RSK_NLT, *JR = mu + RSK_N;
  casadi_real *F = (casadi_real *)(((uintptr_t)(JR + RSK_NJR) + 63) & ~(uintptr_t)63);
  static const int size[4] = {RSK_N, RSK_NV - RSK_N, RSK_N, RSK_NV - RSK_N};
  int i, r, c, k = 0;
  (void)mem;
  if (!res[0]) return 0;
  for (i = 0; i < 4; ++i)                    /* x = (theta, phi, dtheta, dphi) */
    for (r = 0; r < size[i]; ++r) x[k++] = arg[i] ? arg[i][r] : 0.0;
  parg[0] = x; parg[1] = arg[4];
  if (RSK_NPAR) parg[2] = arg[5];
  pres[0] = a; pres[1] = D; pres[2] = LT; pres[3] = L; pres[4] = mu;
  if (RSK_FD(parg, pres, iw, w, 0)) return 1;
  parg[0] = x; parg[1] = a;
  if (RSK_NPAR) parg[2] = arg[5];
  pres[0] = JR;
  if (RSK_JR(parg, pres, iw, w, 0)) return 1;
  rsk_stage(JR, D, LT, L, mu, 0, 0, 0.0, 0.0, F);
  for (c = 0; c < RSK_NC; ++c)
    for (r = 0; r < RSK_NV; ++r) res[0][c * RSK_NV + r] = F[r * RSK_NP + c];
  return 0;
}

static const casadi_int rsk_sp_q[3] = {RSK_N, 1, 1}, rsk_sp_m[3] = {RSK_NV - RSK_N, 1, 1};
static const casadi_int rsk_sp_tau[3] = {RSK_NU, 1, 1}, rsk_sp_p[3] = {RSK_NPAR, 1, 1};
static const casadi_int rsk_sp_J[3] = {RSK_NV, RSK_NC, 1};
const char* @NAME@_name_in(casadi_int i) {
  switch (i) {
    case 0: return "theta"; case 1: return "phi"; case 2: return "dtheta"; case 3: return "dphi";
    case 4: return "tau"; case 5: return RSK_NPAR ? "p" : 0; default: return 0;
  }
}
const char* @NAME@_name_out(casadi_int i) { return i == 0 ? "jacobian" : 0; }
const casadi_int* @NAME@_sparsity_in(casadi_int i) {
  switch (i) {
    case 0: case 2: return rsk_sp_q; case 1: case 3: return rsk_sp_m; case 4: return rsk_sp_tau;
    case 5: return RSK_NPAR ? rsk_sp_p : 0; default: return 0;
  }
}
const casadi_int* @NAME@_sparsity_out(casadi_int i) { return i == 0 ? rsk_sp_J : 0; }
