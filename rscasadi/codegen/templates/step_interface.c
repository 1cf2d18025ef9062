/* A step kernel's CasADi-style interface: (x, tau, h[, p][, A0, B0]) -> (A, B[, x_next])
   (rscasadi/codegen/step_kernel.py). */
static const casadi_int rsk_sp_x[3] = {RSK_NX, 1, 1}, rsk_sp_tau[3] = {RSK_NU, 1, 1}, rsk_sp_h[3] = {1, 1, 1};
static const casadi_int rsk_sp_p[3] = {RSK_NPAR, 1, 1};
static const casadi_int rsk_sp_A[3] = {RSK_NX, RSK_NX, 1}, rsk_sp_B[3] = {RSK_NX, RSK_NU, 1};
const char* @NAME@_name_in(casadi_int i) {
  if (RSK_CHAIN && i == RSK_NIN - 2) return "A0";
  if (RSK_CHAIN && i == RSK_NIN - 1) return "B0";
  switch (i) { case 0: return "x"; case 1: return "tau"; case 2: return "h"; case 3: return RSK_NPAR ? "p" : 0; default: return 0; }
}
const char* @NAME@_name_out(casadi_int i) {
  switch (i) { case 0: return "A"; case 1: return "B"; case 2: return RSK_CHAIN ? "x_next" : 0; default: return 0; }
}
const casadi_int* @NAME@_sparsity_in(casadi_int i) {
  if (RSK_CHAIN && i == RSK_NIN - 2) return rsk_sp_A;
  if (RSK_CHAIN && i == RSK_NIN - 1) return rsk_sp_B;
  switch (i) { case 0: return rsk_sp_x; case 1: return rsk_sp_tau; case 2: return rsk_sp_h; case 3: return RSK_NPAR ? rsk_sp_p : 0; default: return 0; }
}
const casadi_int* @NAME@_sparsity_out(casadi_int i) {
  switch (i) { case 0: return rsk_sp_A; case 1: return rsk_sp_B; case 2: return RSK_CHAIN ? rsk_sp_x : 0; default: return 0; }
}
