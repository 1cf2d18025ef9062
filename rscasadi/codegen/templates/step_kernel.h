/* The structured step-Jacobian kernel's declarations (rscasadi/codegen/step_kernel.py fills @NAME@). */
int @NAME@(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w, int mem);
int @NAME@_checkout(void);
void @NAME@_release(int mem);
void @NAME@_incref(void);
void @NAME@_decref(void);
casadi_int @NAME@_n_in(void);
casadi_int @NAME@_n_out(void);
casadi_real @NAME@_default_in(casadi_int i);
const char* @NAME@_name_in(casadi_int i);
const char* @NAME@_name_out(casadi_int i);
const casadi_int* @NAME@_sparsity_in(casadi_int i);
const casadi_int* @NAME@_sparsity_out(casadi_int i);
int @NAME@_work(casadi_int *sz_arg, casadi_int* sz_res, casadi_int *sz_iw, casadi_int *sz_w);
int @NAME@_work_bytes(casadi_int *sz_arg, casadi_int* sz_res, casadi_int *sz_iw, casadi_int *sz_w);
