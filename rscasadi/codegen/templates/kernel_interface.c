/* The CasADi-style interface every structured kernel shares (rscasadi/codegen/step_kernel.py):
   memory, sizes and work; the method's own names and sparsity before it. */
int @NAME@_checkout(void) { return 0; }
void @NAME@_release(int mem) { (void)mem; }
void @NAME@_incref(void) {}
void @NAME@_decref(void) {}
casadi_int @NAME@_n_in(void) { return RSK_NIN; }
casadi_int @NAME@_n_out(void) { return RSK_NOUT; }
casadi_real @NAME@_default_in(casadi_int i) { (void)i; return 0.0; }
int @NAME@_work(casadi_int *sz_arg, casadi_int* sz_res, casadi_int *sz_iw, casadi_int *sz_w) {
  if (sz_arg) *sz_arg = RSK_NIN + RSK_PT_ARG;
  if (sz_res) *sz_res = RSK_NOUT + RSK_PT_RES;
  if (sz_iw) *sz_iw = RSK_PT_IW;
  if (sz_w) *sz_w = RSK_SZ_W;
  return 0;
}
int @NAME@_work_bytes(casadi_int *sz_arg, casadi_int* sz_res, casadi_int *sz_iw, casadi_int *sz_w) {
  @NAME@_work(sz_arg, sz_res, sz_iw, sz_w);
  if (sz_arg) *sz_arg *= sizeof(void*);
  if (sz_res) *sz_res *= sizeof(void*);
  if (sz_iw) *sz_iw *= sizeof(casadi_int);
  if (sz_w) *sz_w *= sizeof(casadi_real);
  return 0;
}
