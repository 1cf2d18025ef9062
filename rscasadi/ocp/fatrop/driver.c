/* fatrop through its own C interface (fatrop/ocp/OCPCInterface.h, shipped in the CasADi wheel),
   stage by stage, on the NLP's compiled functions: what CasADi's fatrop plugin does, without its
   per-call sparse projections and function-call layers (rscasadi/ocp/fatrop/driver.py).

   The NLP is ordered as CasADi's manual structure: variables x_0 u_0 x_1 u_1 ... x_N; rows per
   stage k the nx[k+1] gap rows x_{k+1} - F_k(x_k, u_k) then the stage's path rows.  fatrop's
   per stage data (u first, then x; its dynamics x_{k+1} = F_k):
     BAbt_k = [B' ; A' ; b'] with b = F_k - x_{k+1},  Ggt_k = [G' ; g'] for equalities (g - lb),
     Ggt_ineq_k = [G' ; g'] for inequalities,  RSQrqt_k = [H ; grad L'] (u first).
   The Jacobian's and Hessian's nonzeros go to these blocks by index maps made once in Python
   (places in column-major blocks) and turned here, once per solver, into places in fatrop's
   panel-major memory (BLASFEO_DMATEL): each call writes them there directly.  The blocks' other
   entries are zeroed then and stay zero (fatrop itself writes only their last rows).
   The full_eval callbacks return 1: done, no per-stage callbacks, and (unlike 2) fatrop still
   subtracts the slacks from the inequality rows of the constraint violation. */
#include <stdlib.h>
#include <string.h>
#include <math.h>
#include <stdio.h>
#include <blasfeo.h>
#include <fatrop/ocp/OCPCInterface.h>

typedef long long casadi_int;
typedef int (*fn_t)(const double**, double**, casadi_int*, double*, int);

/* A piece of the NLP evaluated by the driver itself (pieces mode): `count` instances of functions of
   nz variables (instance k's: x[cols[k nz + j]]) and its parameters, with nr rows (rows[k nr + i]).
   Parameter a of instance k is p[arg_off[a] + k arg_step[a]] .. (arg_len[a] numbers), or, where
   arg_step[a] < 0, the number k itself (the condensing kernel's interval).  Its functions:
   value (z, par) -> (rows, f), first -> (rows, J), objective -> (f, grad f), second (z, par, lam,
   lam_f) -> (grad L, H); a vector output's nonzeros are the entries *_nz lists; J's and H's
   nonzeros go out as they are, instance after instance (the places driver.py computed for them). */
typedef struct {
  int count, nz, nr, n_args;
  const int *cols, *rows;
  const int *arg_off, *arg_len, *arg_step;
  fn_t value, first, objective, second;
  const int *rows_nz, *grad_f_nz, *grad_l_nz;
  int n_rows_nz, n_f_nz, n_grad_f_nz, n_grad_l_nz, nnz_j, nnz_h;
} rsf_piece;

typedef struct {
  int K, nv, ng;                           /* stages (N + 1), NLP variables, NLP rows */
  const int *nx, *nu, *xoff, *roff;        /* per stage: sizes, first variable, first row */
  const int *a_eq, *a_eq_idx, *a_in, *a_in_idx;    /* path rows: equalities, inequalities */
  const int *x_eq, *x_eq_idx, *x_in, *x_in_idx;    /* bounded variables, likewise */
  int nnz_j, nnz_h;
  int n_jparts, n_hparts;                  /* the derivative functions' outputs of nonzeros */
  const int *jt, *ht;                      /* block index of each Jacobian / Hessian nonzero
                                              (-1: none, -2: x_{k+1} in a gap row, must be 1;
                                              Hessian -1: added after, by hadd) */
  const double* js;                        /* its sign (-1: A, B of the gap rows) */
  const int *jpart, *hpart;                /* where each output's nonzeros start in a, h */
  const int *jorder, *jstart;              /* the Jacobian's nonzeros stage by stage: stage k's are
                                              jorder[jstart[k] .. jstart[k + 1]) */
  const int *horder, *hstart;              /* the Hessian's written ones, likewise */
  const int *hadd, *hadd_to, *hadd_start;  /* its nonzeros that share a place with another (added),
                                              likewise by stage */
  const int *bab_off, *geq_off, *gin_off, *rsq_off;
  fn_t f, g, grad_f, jac_g, hess_l;
  fn_t fg;                                 /* (x, p) -> (f, g), or NULL: then jac_g's first output is g */
  int sz_arg, sz_res, sz_iw, sz_w;
  int n_pieces;                            /* > 0: the pieces below instead of f, g, ... (no NLP library) */
  const rsf_piece* pieces;
} rsf_problem;

typedef struct {
  const rsf_problem* P;
  const double *p, *lbx, *ubx, *lbg, *ubg, *x0;
  double *x, *gv, *a, *h, *lam, *grad;
  int *jpm, *hpm, *hapm;                   /* the places in fatrop's blocks (panel_places) */
  double **jseen, **hseen;                 /* the blocks' memory seen (seen_before) */
  int n_jblocks, jnext, hnext;
  double *gx, fv;                          /* with fg: f and g (gv) are those at gx */
  int g_valid;
  const double** arg;
  double** res;
  casadi_int* iw;
  double* w;
  int failed, bad_gap;
  double *pbuf, *pf;                       /* pieces mode: per-instance vectors and objectives */
  double* tbuf;                            /* per thread: z, parameters' k, rows, vector, lam, f */
  const double*** targ;
  double*** tres;
  casadi_int** tiw;
  double** tw;
  int tsize, nthreads;                     /* pieces mode: the threads it has memory for */
  int team;                                /* the threads of this solve's last loop over the stages */
} rsf_data;

#define D ((rsf_data*)user_data)
#define FG(P) ((P)->fg || (P)->n_pieces)       /* f and g from one evaluation */

static int pos(const rsf_problem* P, int k, int v) {      /* a stage variable's place: u, then x */
  int i = v - P->xoff[k];
  return i < P->nx[k] ? P->nu[k] + i : i - P->nx[k];
}

static void read_primal(rsf_data* d, const double* primal, const struct FatropOcpCDims* s) {
  const rsf_problem* P = d->P;
  int k;
  for (k = 0; k < P->K; ++k) {
    memcpy(d->x + P->xoff[k] + P->nx[k], primal + s->ux_offs[k], sizeof(double) * P->nu[k]);
    memcpy(d->x + P->xoff[k], primal + s->ux_offs[k] + P->nu[k], sizeof(double) * P->nx[k]);
  }
}

/* A stop asked for from another thread (Ctrl-C: driver.py): every later evaluation of the
   running solve gives NaN, which fatrop cannot step on, so it returns within an iteration. */
static volatile int rsf_stop = 0;
void rsf_request_stop(void) { rsf_stop = 1; }

/* one NLP function with outputs of sizes n[]; an error (e.g. the kernel's Newton failing) or a
   stop leaves NaN in every output for fatrop to reject */
static void call(rsf_data* d, fn_t f, const double** in, int n_in, double** out, const int* n, int n_out) {
  int i, j;
  for (i = 0; i < n_in; ++i) d->arg[i] = in[i];
  for (i = 0; i < n_out; ++i) d->res[i] = out[i];
  if (rsf_stop || f(d->arg, d->res, d->iw, d->w, 0)) {
    d->failed = 1;
    for (i = 0; i < n_out; ++i) for (j = 0; j < n[i]; ++j) out[i][j] = NAN;
  }
}

#ifdef _OPENMP
#include <omp.h>
#define THREAD omp_get_thread_num()
#define TEAM_NOW omp_get_num_threads()
#define PROCS (omp_get_num_procs() > omp_get_max_threads() ? omp_get_num_procs() : omp_get_max_threads())
#define TEAM(d) (omp_get_max_threads() < (d)->nthreads ? omp_get_max_threads() : (d)->nthreads)
#else
#define THREAD 0
#define TEAM_NOW 1
#define PROCS 1
#define TEAM(d) 1
#endif

/* instance k of piece q on this thread's memory: fn's inputs z, the parameters (and lam, lam_f
   for the Hessian), outputs out[0..1]; nonzero on failure */
static int piece_call(rsf_data* d, const rsf_piece* q, int k, fn_t fn, const double* lam_f, double* out0, double* out1) {
  int t = THREAD, a, j;
  double* b = d->tbuf + (size_t)t * d->tsize;
  double *z = b, *kk = b + q->nz, *lam = kk + 1;
  const double** arg = d->targ[t];
  double** res = d->tres[t];
  for (j = 0; j < q->nz; ++j) z[j] = d->x[q->cols[(size_t)k * q->nz + j]];
  *kk = k;
  arg[0] = z;
  for (a = 0; a < q->n_args; ++a) arg[1 + a] = q->arg_step[a] < 0 ? kk : d->p + q->arg_off[a] + (size_t)k * q->arg_step[a];
  if (lam_f) {
    for (j = 0; j < q->nr; ++j) lam[j] = d->lam[q->rows[(size_t)k * q->nr + j]];
    arg[1 + q->n_args] = lam;
    arg[2 + q->n_args] = lam_f;
  }
  res[0] = out0; res[1] = out1;
  return rsf_stop || fn(arg, res, d->tiw[t], d->tw[t], 0);
}

/* this thread's output space after z, k and lam */
static double* piece_out(rsf_data* d, const rsf_piece* q) {
  return d->tbuf + (size_t)THREAD * d->tsize + q->nz + 1 + q->nr;
}

static void fail_all(double* v, int n) { int i; for (i = 0; i < n; ++i) v[i] = NAN; }

/* f and g from the pieces; instance objectives summed in order (the same on any number of threads) */
static void pieces_fg(rsf_data* d) {
  const rsf_problem* P = d->P;
  int q, k, i, bad = 0;
  memset(d->gv, 0, sizeof(double) * P->ng);
  d->fv = 0;
  for (q = 0; q < P->n_pieces; ++q) {
    const rsf_piece* Q = P->pieces + q;
    #pragma omp parallel for schedule(static) private(i) reduction(|:bad) num_threads(TEAM(d))
    for (k = 0; k < Q->count; ++k) {
      double* r = piece_out(d, Q);
      d->pf[k] = 0;
      if (piece_call(d, Q, k, Q->value, 0, r, Q->n_f_nz ? d->pf + k : r + Q->n_rows_nz)) { bad = 1; continue; }
      for (i = 0; i < Q->n_rows_nz; ++i) d->gv[Q->rows[(size_t)k * Q->nr + Q->rows_nz[i]]] = r[i];
    }
    for (k = 0; k < Q->count; ++k) d->fv += d->pf[k];
  }
  if (bad) { d->failed = 1; d->fv = NAN; fail_all(d->gv, P->ng); }
}

/* a gradient into d->grad, each instance's written apart and summed in order (the same on any
   number of threads): of f (lam_f 0: each piece's objective -> (f, grad f)) or of the Lagrangian
   (its second -> (grad L, H), the Hessian's nonzeros to d->h); nonzero if an evaluation failed */
static int pieces_gradient(rsf_data* d, const double* lam_f) {
  const rsf_problem* P = d->P;
  int q, k, i, bad = 0;
  memset(d->grad, 0, sizeof(double) * P->nv);
  for (q = 0; q < P->n_pieces; ++q) {
    const rsf_piece* Q = P->pieces + q;
    const int* nz = lam_f ? Q->grad_l_nz : Q->grad_f_nz;
    const int n_nz = lam_f ? Q->n_grad_l_nz : Q->n_grad_f_nz;
    #pragma omp parallel for schedule(static) private(i) reduction(|:bad) num_threads(TEAM(d))
    for (k = 0; k < Q->count; ++k) {
      double* v = d->pbuf + (size_t)k * Q->nz;
      double* r = piece_out(d, Q);
      double f;
      if (lam_f ? piece_call(d, Q, k, Q->second, lam_f, r, d->h + P->hpart[q] + (size_t)k * Q->nnz_h)
                : piece_call(d, Q, k, Q->objective, 0, &f, r)) { bad = 1; continue; }
      memset(v, 0, sizeof(double) * Q->nz);
      for (i = 0; i < n_nz; ++i) v[nz[i]] = r[i];
    }
    for (k = 0; k < Q->count; ++k)
      for (i = 0; i < Q->nz; ++i) d->grad[Q->cols[(size_t)k * Q->nz + i]] += d->pbuf[(size_t)k * Q->nz + i];
  }
  return bad;
}

/* the gradient of f (into d->grad) */
static void pieces_grad_f(rsf_data* d) {
  if (pieces_gradient(d, 0)) { d->failed = 1; fail_all(d->grad, d->P->nv); }
}

/* the Jacobian's nonzeros, piece after piece, instance after instance (d->a) */
static void pieces_jac(rsf_data* d) {
  const rsf_problem* P = d->P;
  int q, k, bad = 0;
  for (q = 0; q < P->n_pieces; ++q) {
    const rsf_piece* Q = P->pieces + q;
    #pragma omp parallel for schedule(static) reduction(|:bad) num_threads(TEAM(d))
    for (k = 0; k < Q->count; ++k)
      if (piece_call(d, Q, k, Q->first, 0, piece_out(d, Q), d->a + P->jpart[q] + (size_t)k * Q->nnz_j)) bad = 1;
  }
  if (bad) { d->failed = 1; fail_all(d->a, P->nnz_j); }
}

/* the Lagrangian's gradient (d->grad) and Hessian nonzeros (d->h) at multipliers d->lam, lam_f */
static void pieces_hess(rsf_data* d, const double* lam_f) {
  if (pieces_gradient(d, lam_f)) { d->failed = 1; fail_all(d->grad, d->P->nv); fail_all(d->h, d->P->nnz_h); }
}

/* f and g at d->x, evaluated together once per point: fatrop asks for g at a trial point, then f
   there, and (accepted) for the Jacobian there, whose constant terms are g again */
static void eval_fg(rsf_data* d) {
  const rsf_problem* P = d->P;
  const double* in[2] = {d->x, d->p};
  double* out[2] = {&d->fv, d->gv};
  const int n[2] = {1, P->ng};
  if (d->g_valid && !memcmp(d->gx, d->x, sizeof(double) * P->nv)) return;
  if (P->n_pieces) pieces_fg(d);
  else call(d, P->fg, in, 2, out, n, 2);
  memcpy(d->gx, d->x, sizeof(double) * P->nv);
  d->g_valid = 1;
}

static fatrop_int get_nx(fatrop_int k, void* user_data) { return D->P->nx[k < D->P->K ? k : D->P->K - 1]; }
static fatrop_int get_nu(fatrop_int k, void* user_data) { return D->P->nu[k]; }
static fatrop_int get_ng(fatrop_int k, void* user_data) {
  const rsf_problem* P = D->P;
  return P->a_eq_idx[k + 1] - P->a_eq_idx[k] + P->x_eq_idx[k + 1] - P->x_eq_idx[k];
}
static fatrop_int get_ng_ineq(fatrop_int k, void* user_data) {
  const rsf_problem* P = D->P;
  return P->a_in_idx[k + 1] - P->a_in_idx[k] + P->x_in_idx[k + 1] - P->x_in_idx[k];
}
static fatrop_int get_horizon(void* user_data) { return D->P->K; }

static fatrop_int get_bounds(double* lo, double* up, fatrop_int k, void* user_data) {
  const rsf_problem* P = D->P;
  int i, c = 0;
  if (!D->lbg) {                           /* while the solver is built: every solve reads them again */
    for (i = 0; i < get_ng_ineq(k, user_data); ++i) { lo[i] = -INFINITY; up[i] = INFINITY; }
    return 0;
  }
  for (i = P->a_in_idx[k]; i < P->a_in_idx[k + 1]; ++i, ++c) { lo[c] = D->lbg[P->a_in[i]]; up[c] = D->ubg[P->a_in[i]]; }
  for (i = P->x_in_idx[k]; i < P->x_in_idx[k + 1]; ++i, ++c) { lo[c] = D->lbx[P->x_in[i]]; up[c] = D->ubx[P->x_in[i]]; }
  return 0;
}
static fatrop_int initial_xk(double* xk, fatrop_int k, void* user_data) {
  memcpy(xk, D->x0 + D->P->xoff[k], sizeof(double) * D->P->nx[k]);
  return 0;
}
static fatrop_int initial_uk(double* uk, fatrop_int k, void* user_data) {
  memcpy(uk, D->x0 + D->P->xoff[k] + D->P->nx[k], sizeof(double) * D->P->nu[k]);
  return 0;
}

/* element (r, c) of fatrop's block A: BLASFEO's panel-major place */
#define EL(A, r, c) BLASFEO_DMATEL(A, r, c)
#define AT(A, r, c) ((int)(&BLASFEO_DMATEL(A, r, c) - (A)->pA))

/* fatrop keeps two sets of Jacobian blocks and alternates between them (the last iterate's and the
   new one): every set of block memory it has passed is remembered, up to SEEN sets */
#define SEEN 4

/* Whether fatrop's blocks (A[b] + k with n[3k + b] columns) are memory seen before; if not, it is
   remembered (over the oldest set) and 0 returned.  seen: SEEN sets of the n_blocks blocks' pA */
static int seen_before(double** seen, int n_blocks, struct blasfeo_dmat* const* A, const int* n, int K, int* next) {
  int set, k, b, i;
  for (set = 0; set < SEEN; ++set) {
    double** s = seen + (size_t)set * n_blocks;
    int same = 1;
    for (k = 0, i = 0; k < K && same; ++k)
      for (b = 0; b < 3; ++b) if (A[b] && n[3 * k + b] && s[i++] != A[b][k].pA) { same = 0; break; }
    if (same) return 1;
  }
  seen += (size_t)*next * n_blocks;
  *next = (*next + 1) % SEEN;
  for (k = 0, i = 0; k < K; ++k)
    for (b = 0; b < 3; ++b) if (A[b] && n[3 * k + b]) seen[i++] = A[b][k].pA;
  return 0;
}

/* a block-buffer place (driver.py: stage k's blocks column-major, ld rows, at off[] in turn)
   as a place in fatrop's block: (its place << 3) | (block << 1) | negated */
static int panel_place(struct blasfeo_dmat* const* A, const int* off, int k, int ld, int place, int neg) {
  int b = place < off[1] ? 0 : place < off[2] ? 1 : 2, local = place - off[b];
  return (AT(A[b] + k, local % ld, local / ld) << 3) | (b << 1) | (neg ? 1 : 0);
}

/* The Jacobian's places in fatrop's blocks, made when its blocks are memory not seen before: the
   blocks zeroed, each nonzero's place, in the order the stages write them (jorder) */
static void jac_places(rsf_data* d, struct blasfeo_dmat* const* A, const int* n) {
  const rsf_problem* P = d->P;
  int k, b, i;
  if (seen_before(d->jseen, d->n_jblocks, A, n, P->K, &d->jnext)) return;
  for (k = 0; k < P->K; ++k) {
    int off[3] = {P->bab_off[k], P->geq_off[k], P->gin_off[k]}, ld = P->nx[k] + P->nu[k] + 1;
    for (b = 0; b < 3; ++b) if (n[3 * k + b]) { blasfeo_dgese(ld, n[3 * k + b], 0.0, A[b] + k, 0, 0); A[b][k].use_dA = 0; }
    for (i = P->jstart[k]; i < P->jstart[k + 1]; ++i) {
      int e = P->jorder[i];
      d->jpm[i] = P->jt[e] >= 0 ? panel_place(A, off, k, ld, P->jt[e], P->js[e] < 0) : P->jt[e];
    }
  }
}

/* stage k's blocks of the Jacobian in fatrop's memory: the nonzeros, the gap rows' constants, the
   identity rows of bounded variables (each stage its own blocks: the stages run on threads);
   nonzero if a gap row's x_{k+1} coefficient is not 1 */
static int jac_stage(rsf_data* d, int k, struct blasfeo_dmat* const* A) {
  const rsf_problem* P = d->P;
  struct blasfeo_dmat *B = A[0] + k, *G = A[1] + k, *I = A[2] + k;
  double* pA[3] = {k < P->K - 1 ? B->pA : 0, G->pA, I->pA};
  int i, c, bad = 0, last = P->nx[k] + P->nu[k];
  for (i = P->jstart[k]; i < P->jstart[k + 1]; ++i) {
    int m = d->jpm[i];
    double v = d->a[P->jorder[i]];
    if (m >= 0) pA[(m >> 1) & 3][m >> 3] = m & 1 ? -v : v;
    else if (m == -2 && v != 1) bad = 1;                              /* x_{k+1}'s coefficient */
  }
  if (k < P->K - 1)
    for (i = 0; i < P->nx[k + 1]; ++i) EL(B, last, i) = d->lbg[P->roff[k] + i] - d->gv[P->roff[k] + i];
  c = 0;
  for (i = P->a_eq_idx[k]; i < P->a_eq_idx[k + 1]; ++i, ++c) EL(G, last, c) = d->gv[P->a_eq[i]] - d->lbg[P->a_eq[i]];
  for (i = P->x_eq_idx[k]; i < P->x_eq_idx[k + 1]; ++i, ++c) {
    EL(G, pos(P, k, P->x_eq[i]), c) = 1;
    EL(G, last, c) = d->x[P->x_eq[i]] - d->lbx[P->x_eq[i]];
  }
  c = 0;
  for (i = P->a_in_idx[k]; i < P->a_in_idx[k + 1]; ++i, ++c) EL(I, last, c) = d->gv[P->a_in[i]];
  for (i = P->x_in_idx[k]; i < P->x_in_idx[k + 1]; ++i, ++c) {
    EL(I, pos(P, k, P->x_in[i]), c) = 1;
    EL(I, last, c) = d->x[P->x_in[i]];
  }
  return bad;
}

/* the columns of stage k's Jacobian blocks (BAbt, Ggt, Ggt_ineq) */
static void jac_columns(const rsf_problem* P, int k, int* n) {
  n[0] = k < P->K - 1 ? P->nx[k + 1] : 0;
  n[1] = P->a_eq_idx[k + 1] - P->a_eq_idx[k] + P->x_eq_idx[k + 1] - P->x_eq_idx[k];
  n[2] = P->a_in_idx[k + 1] - P->a_in_idx[k] + P->x_in_idx[k + 1] - P->x_in_idx[k];
}

static fatrop_int constr_jac(const double* primal, const double* sp, const double* gp, struct blasfeo_dmat* BAbt,
                             struct blasfeo_dmat* Ggt, struct blasfeo_dmat* Ggt_ineq,
                             const struct FatropOcpCDims* s, void* user_data) {
  rsf_data* d = D;
  const rsf_problem* P = d->P;
  const double* in[2] = {d->x, d->p};
  double* out[1 + P->n_jparts];
  int n[1 + P->n_jparts];
  struct blasfeo_dmat* A[3] = {BAbt, Ggt, Ggt_ineq};
  int cols[3 * P->K];
  int k, bad = 0, g = FG(P) ? 0 : 1;         /* outputs before the Jacobian's parts: g, or none */
  out[0] = d->gv; n[0] = P->ng;
  for (k = 0; k < P->n_jparts; ++k) { out[g + k] = d->a + P->jpart[k]; n[g + k] = P->jpart[k + 1] - P->jpart[k]; }
  for (k = 0; k < P->K; ++k) jac_columns(P, k, cols + 3 * k);
  jac_places(d, A, cols);
  read_primal(d, primal, s);
  if (FG(P)) eval_fg(d);
  if (P->n_pieces) pieces_jac(d);
  else call(d, P->jac_g, in, 2, out, n, g + P->n_jparts);
  #pragma omp parallel for schedule(static) reduction(|:bad)
  for (k = 0; k < P->K; ++k) {
    if (k == 0) d->team = TEAM_NOW;
    bad |= jac_stage(d, k, A);
  }
  if (bad) d->bad_gap = 1;
  return 1;
}

static fatrop_int constr_viol(const double* primal, const double* sp, const double* gp, double* res,
                              const struct FatropOcpCDims* s, void* user_data) {
  rsf_data* d = D;
  const rsf_problem* P = d->P;
  const double* in[2] = {d->x, d->p};
  double* out[1] = {d->gv};
  int k, i, c;
  read_primal(d, primal, s);
  if (FG(P)) eval_fg(d);
  else call(d, P->g, in, 2, out, &P->ng, 1);
  for (k = 0; k < P->K; ++k) {
    c = 0;
    for (i = P->a_in_idx[k]; i < P->a_in_idx[k + 1]; ++i) res[s->g_ineq_offs[k] + c++] = d->gv[P->a_in[i]];
    for (i = P->x_in_idx[k]; i < P->x_in_idx[k + 1]; ++i) res[s->g_ineq_offs[k] + c++] = d->x[P->x_in[i]];
    c = 0;
    for (i = P->a_eq_idx[k]; i < P->a_eq_idx[k + 1]; ++i) res[s->g_offs[k] + c++] = d->gv[P->a_eq[i]] - d->lbg[P->a_eq[i]];
    for (i = P->x_eq_idx[k]; i < P->x_eq_idx[k + 1]; ++i) res[s->g_offs[k] + c++] = d->x[P->x_eq[i]] - d->lbx[P->x_eq[i]];
    if (k < P->K - 1)
      for (i = 0; i < P->nx[k + 1]; ++i) res[s->dyn_eq_offs[k] + i] = d->lbg[P->roff[k] + i] - d->gv[P->roff[k] + i];
  }
  return 1;
}

static fatrop_int obj_grad(double scale, const double* primal, const double* sp, const double* gp, double* res,
                           const struct FatropOcpCDims* s, void* user_data) {
  rsf_data* d = D;
  const rsf_problem* P = d->P;
  const double* in[2] = {d->x, d->p};
  double* out[1] = {d->grad};
  int k, i;
  read_primal(d, primal, s);
  if (P->n_pieces) pieces_grad_f(d);
  else call(d, P->grad_f, in, 2, out, &P->nv, 1);
  for (k = 0; k < P->K; ++k) {
    for (i = 0; i < P->nu[k]; ++i) res[s->ux_offs[k] + i] = scale * d->grad[P->xoff[k] + P->nx[k] + i];
    for (i = 0; i < P->nx[k]; ++i) res[s->ux_offs[k] + P->nu[k] + i] = scale * d->grad[P->xoff[k] + i];
  }
  return 1;
}

static fatrop_int obj(double scale, const double* primal, const double* sp, const double* gp, double* res,
                      const struct FatropOcpCDims* s, void* user_data) {
  rsf_data* d = D;
  const double* in[2] = {d->x, d->p};
  double* out[1] = {res};
  const int one = 1;
  read_primal(d, primal, s);
  if (FG(d->P)) {
    eval_fg(d);
    *res = d->fv;
  } else call(d, d->P->f, in, 2, out, &one, 1);
  *res *= scale;
  return 1;
}

/* The Hessian's places in fatrop's blocks (as jac_places): the written nonzeros', then the added ones' */
static void hess_places(rsf_data* d, struct blasfeo_dmat* RSQrqt) {
  const rsf_problem* P = d->P;
  struct blasfeo_dmat* const A[3] = {RSQrqt, 0, 0};
  int k, i, n[3 * P->K];
  for (k = 0; k < P->K; ++k) { n[3 * k] = P->nx[k] + P->nu[k]; n[3 * k + 1] = n[3 * k + 2] = 0; }
  if (seen_before(d->hseen, P->K, A, n, P->K, &d->hnext)) return;
  for (k = 0; k < P->K; ++k) {
    int ld = P->nx[k] + P->nu[k] + 1;
    struct blasfeo_dmat* R = RSQrqt + k;
    blasfeo_dgese(ld, ld - 1, 0.0, R, 0, 0);
    R->use_dA = 0;
    for (i = P->hstart[k]; i < P->hstart[k + 1]; ++i) {
      int local = P->ht[P->horder[i]] - P->rsq_off[k];
      d->hpm[i] = AT(R, local % ld, local / ld);
    }
    for (i = P->hadd_start[k]; i < P->hadd_start[k + 1]; ++i) {
      int local = P->hadd_to[i] - P->rsq_off[k];
      d->hapm[i] = AT(R, local % ld, local / ld);
    }
  }
}

/* fatrop's Lagrangian: scale f + lam_dyn' F_k + lam_eq' g_eq + lam_ineq' g_ineq (+ bound rows);
   the NLP's gap rows are x_{k+1} - F_k, so they take -lam_dyn and x_{k+1} gets lam_dyn back.
   The last row (the Lagrangian's gradient) is written as CasADi's plugin writes it; fatrop 1.1.8
   sets that row itself before it uses it (a wrong one here changes no iterate: tested). */
static fatrop_int lag_hess(double scale, const double* primal, const double* lam_data, const double* sp,
                           const double* gp, struct blasfeo_dmat* RSQrqt, const struct FatropOcpCDims* s,
                           void* user_data) {
  rsf_data* d = D;
  const rsf_problem* P = d->P;
  const double* in[4] = {d->x, d->p, &scale, d->lam};
  double* out[1 + P->n_hparts];
  int n[1 + P->n_hparts];
  int k, i, c;
  out[0] = d->grad; n[0] = P->nv;
  for (k = 0; k < P->n_hparts; ++k) { out[1 + k] = d->h + P->hpart[k]; n[1 + k] = P->hpart[k + 1] - P->hpart[k]; }
  read_primal(d, primal, s);
  memset(d->lam, 0, sizeof(double) * P->ng);
  for (k = 0; k < P->K; ++k) {
    c = 0;
    for (i = P->a_in_idx[k]; i < P->a_in_idx[k + 1]; ++i) d->lam[P->a_in[i]] = lam_data[s->g_ineq_offs[k] + c++];
    c = 0;
    for (i = P->a_eq_idx[k]; i < P->a_eq_idx[k + 1]; ++i) d->lam[P->a_eq[i]] = lam_data[s->g_offs[k] + c++];
    if (k < P->K - 1)
      for (i = 0; i < P->nx[k + 1]; ++i) d->lam[P->roff[k] + i] = -lam_data[s->dyn_eq_offs[k] + i];
  }
  if (P->n_pieces) pieces_hess(d, &scale);
  else call(d, P->hess_l, in, 4, out, n, 1 + P->n_hparts);
  for (k = 0; k < P->K; ++k) {
    if (k < P->K - 1)
      for (i = 0; i < P->nx[k + 1]; ++i) d->grad[P->xoff[k + 1] + i] += lam_data[s->dyn_eq_offs[k] + i];
    c = P->a_in_idx[k + 1] - P->a_in_idx[k];
    for (i = P->x_in_idx[k]; i < P->x_in_idx[k + 1]; ++i) d->grad[P->x_in[i]] += lam_data[s->g_ineq_offs[k] + c++];
    c = P->a_eq_idx[k + 1] - P->a_eq_idx[k];
    for (i = P->x_eq_idx[k]; i < P->x_eq_idx[k + 1]; ++i) d->grad[P->x_eq[i]] += lam_data[s->g_offs[k] + c++];
  }
  hess_places(d, RSQrqt);
  #pragma omp parallel for schedule(static) private(i)
  for (k = 0; k < P->K; ++k) {
    int n = P->nx[k] + P->nu[k];
    double* R = RSQrqt[k].pA;
    for (i = P->hstart[k]; i < P->hstart[k + 1]; ++i) R[d->hpm[i]] = d->h[P->horder[i]];
    for (i = P->hadd_start[k]; i < P->hadd_start[k + 1]; ++i) R[d->hapm[i]] += d->h[P->hadd[i]];
    for (i = 0; i < n; ++i) EL(RSQrqt + k, n, i) = d->grad[P->xoff[k] + (i < P->nu[k] ? P->nx[k] + i : i - P->nu[k])];
  }
  return 1;
}

/* where this driver's BLASFEO calls go (libfatrop's bind alike): blasfeo.py names the library */
void* rsf_blasfeo_function(void) { return (void*)&blasfeo_dgese; }

/* fatrop keeps the last writer it was given for the process (a global stream): every solver gets
   this one, which prints only while a verbose solve runs (solves are one at a time, driver.py) */
static int rsf_verbose = 0;
static void writer(const char* msg, int n) { if (rsf_verbose) fwrite(msg, 1, (size_t)n, stdout); }
static void flusher(void) { if (rsf_verbose) fflush(stdout); }

/* A session: one solver (built once: its build took 3 ms of a 57 ms solve of (b)) and its data,
   for one problem layout P, solved again and again (fatrop resets its iterates, bounds and barrier
   rule on every solve; tested: the same iterates as a new solver). */
typedef struct {
  rsf_data d;
  struct FatropOcpCInterface ocp;
  void* solver;
} rsf_session;

void rsf_close(rsf_session* S) {
  rsf_data* d;
  if (!S) return;
  d = &S->d;
  if (S->solver) fatrop_ocp_c_destroy(S->solver);
  free(d->x); free(d->gx); free(d->gv); free(d->a); free(d->h); free(d->lam); free(d->grad);
  free(d->jpm); free(d->hpm); free(d->hapm); free(d->jseen); free(d->hseen);
  free(d->arg); free(d->res); free(d->iw); free(d->w);
  if (d->targ) {
    int t;
    for (t = 0; t < d->nthreads; ++t) { free(d->targ[t]); free(d->tres[t]); free(d->tiw[t]); free(d->tw[t]); }
  }
  free(d->targ); free(d->tres); free(d->tiw); free(d->tw); free(d->tbuf); free(d->pbuf); free(d->pf);
  free(S);
}

rsf_session* rsf_open(const rsf_problem* P) {
  rsf_session* S = calloc(1, sizeof(rsf_session));
  rsf_data* d;
  if (!S) return 0;
  d = &S->d;
  d->P = P;
  d->x = calloc(P->nv, sizeof(double)); d->gx = calloc(P->nv, sizeof(double)); d->gv = calloc(P->ng + 1, sizeof(double));
  d->a = calloc(P->nnz_j + 1, sizeof(double)); d->h = calloc(P->nnz_h + 1, sizeof(double));
  d->lam = calloc(P->ng + 1, sizeof(double)); d->grad = calloc(P->nv, sizeof(double));
  d->jpm = calloc(P->jstart[P->K] + 1, sizeof(int)); d->hpm = calloc(P->hstart[P->K] + 1, sizeof(int));
  d->hapm = calloc(P->hadd_start[P->K] + 1, sizeof(int));
  {
    int k, n[3];
    for (k = 0; k < P->K; ++k) { jac_columns(P, k, n); d->n_jblocks += (n[0] > 0) + (n[1] > 0) + (n[2] > 0); }
  }
  d->jseen = calloc((size_t)SEEN * d->n_jblocks + 1, sizeof(double*)); d->hseen = calloc((size_t)SEEN * P->K + 1, sizeof(double*));
  d->arg = calloc(P->sz_arg + 4, sizeof(double*)); d->res = calloc(P->sz_res + 2, sizeof(double*));
  d->iw = calloc(P->sz_iw + 1, sizeof(casadi_int)); d->w = calloc(P->sz_w + 1, sizeof(double));
  if (P->n_pieces) {                       /* each thread its own z, k, lam, outputs and work memory */
    int q, t, most = 1, count = 1;
    for (q = 0; q < P->n_pieces; ++q) {
      const rsf_piece* Q = P->pieces + q;
      int need = Q->nz + 1 + Q->nr + Q->nz + Q->nr + 2;
      if (need > most) most = need;
      if (Q->count * Q->nz > count) count = Q->count * Q->nz;
      if (Q->count > count) count = Q->count;
    }
    d->tsize = most;
    d->nthreads = PROCS;
    d->tbuf = calloc((size_t)most * d->nthreads, sizeof(double));
    d->pbuf = calloc((size_t)count, sizeof(double));
    d->pf = calloc((size_t)count, sizeof(double));
    d->targ = calloc(d->nthreads, sizeof(double*)); d->tres = calloc(d->nthreads, sizeof(double*));
    d->tiw = calloc(d->nthreads, sizeof(casadi_int*)); d->tw = calloc(d->nthreads, sizeof(double*));
    for (t = 0; t < d->nthreads; ++t) {
      d->targ[t] = calloc(P->sz_arg + 4, sizeof(double*)); d->tres[t] = calloc(P->sz_res + 2, sizeof(double*));
      d->tiw[t] = calloc(P->sz_iw + 1, sizeof(casadi_int)); d->tw[t] = calloc(P->sz_w + 1, sizeof(double));
    }
  }
  S->ocp.get_nx = get_nx; S->ocp.get_nu = get_nu; S->ocp.get_ng = get_ng; S->ocp.get_ng_ineq = get_ng_ineq;
  S->ocp.get_horizon_length = get_horizon; S->ocp.get_bounds = get_bounds;
  S->ocp.get_initial_xk = initial_xk; S->ocp.get_initial_uk = initial_uk;
  S->ocp.full_eval_constr_jac = constr_jac; S->ocp.full_eval_contr_viol = constr_viol;
  S->ocp.full_eval_obj_grad = obj_grad; S->ocp.full_eval_obj = obj; S->ocp.full_eval_lag_hess = lag_hess;
  S->ocp.user_data = d;
  S->solver = fatrop_ocp_c_create(&S->ocp, writer, flusher);
  return S;
}

/* Options: names[i] with values[i] (double, int or bool by fatrop's type) or strings[i]; set
   before every solve (some, as print_level, are fatrop's process-wide state).  0, or -1000 - i if
   option i is unknown or refused. */
int rsf_options(rsf_session* S, int n_opt, const char** names, const double* values, const char** strings) {
  int i;
  for (i = 0; i < n_opt; ++i) {
    int type = fatrop_ocp_c_option_type(names[i]), bad = 1;
    if (type == 0) bad = fatrop_ocp_c_set_option_double(S->solver, names[i], values[i]);
    else if (type == 1) bad = fatrop_ocp_c_set_option_int(S->solver, names[i], (int)values[i]);
    else if (type == 2) bad = fatrop_ocp_c_set_option_bool(S->solver, names[i], values[i] != 0);
    else if (type == 3) bad = fatrop_ocp_c_set_option_string(S->solver, names[i], strings[i]);
    if (bad) return -1000 - i;
  }
  return 0;
}

/* One solve of the session's problem from x0 with parameters p and these bounds (their
   classification into equalities, inequalities and free is the session's layout).
   Returns 0 on success, 1 otherwise, -1 on an exception inside fatrop (then close the session);
   `threads`: its loops' threads.  stats[19]: FatropOcpCStats in order, whether an evaluation
   failed, whether a gap row's x_{k+1} coefficient was not 1, the threads its loops ran on. */
int rsf_run(rsf_session* S, const double* x0, const double* p, const double* lbx, const double* ubx,
            const double* lbg, const double* ubg, int verbose, int threads, double* x_out, double* lam_g,
            double* lam_x, double* stats) {
  rsf_data* d = &S->d;
  const rsf_problem* P = d->P;
  const struct FatropOcpCDims* s;
  const struct FatropOcpCStats* st;
  const double *primal, *dual;
  int i, k, c, ret;
  d->p = p; d->lbx = lbx; d->ubx = ubx; d->lbg = lbg; d->ubg = ubg; d->x0 = x0;
  d->failed = d->bad_gap = d->g_valid = d->team = 0;
#ifdef _OPENMP
  /* the threads of this solve's loops (the library's own too): set on the thread that runs the
     solve, since a thread's OpenMP setting is its own and a new thread starts from the default */
  omp_set_num_threads(threads > 0 ? threads : 1);
#else
  (void)threads;
#endif
  rsf_stop = 0;
  rsf_verbose = verbose;
  ret = fatrop_ocp_c_solve(S->solver);
  rsf_verbose = 0;
  primal = fatrop_ocp_c_get_primal(S->solver)->pa;
  dual = fatrop_ocp_c_get_dual(S->solver)->pa;
  s = fatrop_ocp_c_get_dims(S->solver);
  st = fatrop_ocp_c_get_stats(S->solver);
  read_primal(d, primal, s);
  memcpy(x_out, d->x, sizeof(double) * P->nv);
  memset(lam_g, 0, sizeof(double) * P->ng);
  memset(lam_x, 0, sizeof(double) * P->nv);
  for (k = 0; k < P->K; ++k) {
    c = 0;
    for (i = P->a_in_idx[k]; i < P->a_in_idx[k + 1]; ++i) lam_g[P->a_in[i]] = dual[s->g_ineq_offs[k] + c++];
    for (i = P->x_in_idx[k]; i < P->x_in_idx[k + 1]; ++i) lam_x[P->x_in[i]] = dual[s->g_ineq_offs[k] + c++];
    c = 0;
    for (i = P->a_eq_idx[k]; i < P->a_eq_idx[k + 1]; ++i) lam_g[P->a_eq[i]] = dual[s->g_offs[k] + c++];
    for (i = P->x_eq_idx[k]; i < P->x_eq_idx[k + 1]; ++i) lam_x[P->x_eq[i]] = dual[s->g_offs[k] + c++];
    if (k < P->K - 1)
      for (i = 0; i < P->nx[k + 1]; ++i) lam_g[P->roff[k] + i] = -dual[s->dyn_eq_offs[k] + i];
  }
  stats[0] = st->compute_sd_time; stats[1] = st->duinf_time; stats[2] = st->eval_hess_time;
  stats[3] = st->eval_jac_time; stats[4] = st->eval_cv_time; stats[5] = st->eval_grad_time;
  stats[6] = st->eval_obj_time; stats[7] = st->initialization_time; stats[8] = st->time_total;
  stats[9] = st->eval_hess_count; stats[10] = st->eval_jac_count; stats[11] = st->eval_cv_count;
  stats[12] = st->eval_grad_count; stats[13] = st->eval_obj_count; stats[14] = st->iterations_count;
  stats[15] = st->return_flag; stats[16] = d->failed; stats[17] = d->bad_gap;
  stats[18] = d->team;
  d->p = d->lbx = d->ubx = d->lbg = d->ubg = d->x0 = 0;      /* the caller's arrays: this solve's only */
  return ret;
}
