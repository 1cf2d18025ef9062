#define _POSIX_C_SOURCE 200112L
#include <math.h>
#include <time.h>
#include "${header}"
#include "rscasadi_guard.h"
#include "${casadi_header}"
#if ${SYM}_RICCATI
#include <stdint.h>
#include "hpipm_d_ocp_qp_ipm.h"
#include "hpipm_d_ocp_qp_dim.h"
#include "hpipm_d_ocp_qp.h"
#include "hpipm_d_ocp_qp_sol.h"
#include "hpipm_d_part_cond.h"
#include "hpipm_d_cond.h"
#include "hpipm_d_cond_aux.h"
#endif
#if ${SYM}_THREADS > 1 && defined(_OPENMP)
#include <omp.h>
#include <pthread.h>
#define THREAD omp_get_thread_num()
/* GNU OpenMP's threads do not survive fork(): the child of a process that prepared on threads
 * would wait for them forever, so after a fork the loops run on the calling thread alone (the
 * one process-wide flag this library keeps) */
static volatile int forked_child = 0;
static void in_child(void) { forked_child = 1; }
static pthread_once_t watching = PTHREAD_ONCE_INIT;
static void watch_forks(void) { pthread_atfork(NULL, NULL, in_child); }
#define TEAM (forked_child ? 1 : ${SYM}_THREADS)
#define WATCH_FORKS() pthread_once(&watching, watch_forks)
#define PARALLEL_FOR _Pragma("omp parallel for schedule(static) num_threads(TEAM) reduction(|:bad)")
#else
#define THREAD 0
#define WATCH_FORKS() ((void)0)
#define PARALLEL_FOR
#endif
/* this thread's part of CasADi's work arrays */
#define W(c) ((c)->w + sizeof((c)->w) / sizeof(double) / ${SYM}_THREADS * THREAD)
#define IW(c) ((casadi_int *)(c)->iw + sizeof((c)->iw) / sizeof(long long) / ${SYM}_THREADS * THREAD)

#define NXP (${SYM}_NX * (${SYM}_HORIZON + 1))
#define NUP (${SYM}_NU * ${SYM}_HORIZON)
#define NROWS (${SYM}_NREF / ${SYM}_HORIZON)
#define MASS_INDEX ${mass_index}              /* the payload's mass in the parameters, or -1: none */
static const double NOMINAL[${SYM}_NP + 1] = {${nominal}};      /* the model's parameters (manifest.json) */
static const double TAU_MAX[${SYM}_NU] = {${tau_max}};          /* INFINITY: no limit */
static const double X_LO[${SYM}_NX] = {${x_lo}}, X_HI[${SYM}_NX] = {${x_hi}};      /* a plausible measurement */
static const double REF_LO[NROWS] = {${ref_lo}}, REF_HI[NROWS] = {${ref_hi}};  /* a reference column */
typedef char casadi_int_is_long_long[sizeof(casadi_int) == sizeof(long long) ? 1 : -1];
typedef char work_fits[sizeof(((${sym}_t *)0)->w) >= ${SYM}_THREADS * sizeof(casadi_real) * (${sz_w_check}) ? 1 : -1];
typedef char iwork_fits[sizeof(((${sym}_t *)0)->iw) >= ${SYM}_THREADS * sizeof(casadi_int) * (${sz_iw_check}) ? 1 : -1];
#define NPREPARED ${nprepared}
#if ${SYM}_SPLIT && !${SYM}_RICCATI
static const int PREP_OFF[NPREPARED + 1] = {${prep_offsets}};   /* each prepared output in c->prep */
#endif

size_t ${sym}_sizeof(void) { return sizeof(${sym}_t); }

double ${sym}_step_seconds(const ${sym}_t *c) { return c ? c->last_step_seconds : 0.0; }

double ${sym}_feedback_seconds(const ${sym}_t *c) { return c ? c->last_feedback_seconds : 0.0; }

int ${sym}_set_payload_mass(${sym}_t *c, double mass) {
  if (MASS_INDEX < 0) return ${SYM}_NO_PAYLOAD;
  if (!c || !isfinite(mass) || mass < 0) return ${SYM}_BAD_ARGUMENT;
  c->params[${SYM}_NJ + MASS_INDEX] = mass;
  return 0;
}

static int finite_all(const double *v, int n) {
  if (!v) return 0;
  for (int i = 0; i < n; ++i)
    if (!isfinite(v[i])) return 0;
  return 1;
}

int ${sym}_set_parameters(${sym}_t *c, const double *p) {
  if (${SYM}_NP == 0 || !c || !finite_all(p, ${SYM}_NP)) return ${SYM}_BAD_ARGUMENT;
  for (int i = 0; i < ${SYM}_NP; ++i) c->params[${SYM}_NJ + i] = p[i];
  return 0;
}

int ${sym}_set_posture(${sym}_t *c, const double *theta) {
  if (!c || !rscasadi_within(theta, X_LO, X_HI, ${SYM}_NJ)) return ${SYM}_BAD_ARGUMENT;
  for (int i = 0; i < ${SYM}_NJ; ++i) c->params[i] = theta[i];
  return 0;
}

/* ${sym}_hold at x into X, U: the arm held still at x over the horizon; 0 if that plan is finite */
static int hold(${sym}_t *c, const double *x, double *X, double *U) {
  const casadi_real *arg[${sym}_hold_SZ_ARG + 1] = {x, c->params};
  casadi_real *res[${sym}_hold_SZ_RES + 1] = {X, U};
  if (${sym}_hold(arg, res, IW(c), W(c), 0) != 0) return ${SYM}_FAILED;
  return finite_all(X, NXP) && finite_all(U, NUP) ? 0 : ${SYM}_NOT_FINITE;
}

/* the safe output: the holding torque of the last good state, within the limits */
static int refuse(${sym}_t *c, double *tau_out, int code) {
  if (hold(c, c->x_good, c->X_next, c->U_next) == 0)
    for (int i = 0; i < ${SYM}_NU; ++i) tau_out[i] = c->U_next[i];
  else
    rscasadi_zero(tau_out, ${SYM}_NU);
  rscasadi_clamp(tau_out, TAU_MAX, ${SYM}_NU);
  return code;
}

int ${sym}_init(${sym}_t *c, const double *x_measured) { return ${sym}_init_parameters(c, x_measured, NOMINAL); }

int ${sym}_init_parameters(${sym}_t *c, const double *x_measured, const double *p) {
  if (!c) return ${SYM}_BAD_ARGUMENT;
  c->ready = 0;
  c->prepared = 0;
  c->qp_owner = 0;
  c->last_step_seconds = c->last_feedback_seconds = 0.0;
  if (!finite_all(p, ${SYM}_NP)) return ${SYM}_BAD_ARGUMENT;
  if (!rscasadi_within(x_measured, X_LO, X_HI, ${SYM}_NX)) return ${SYM}_BAD_MEASUREMENT;
  for (int i = 0; i < ${SYM}_NJ; ++i) c->params[i] = x_measured[i];
  for (int i = 0; i < ${SYM}_NP; ++i) c->params[${SYM}_NJ + i] = p[i];
  const int code = hold(c, x_measured, c->X, c->U);
  if (code) return code;
  for (int i = 0; i < ${SYM}_NX; ++i) c->x_good[i] = x_measured[i];
  c->ready = RSCASADI_READY;
  return 0;
}

static int reference_ok(const double *reference) {
  if (!reference) return 0;
  for (int k = 0; k < ${SYM}_HORIZON; ++k)
    if (!rscasadi_within(reference + NROWS * k, REF_LO, REF_HI, NROWS)) return 0;
  return 1;
}

#if ${SYM}_RICCATI
#define NX ${SYM}_NX
#define NU ${SYM}_NU
#define NH ${SYM}_HORIZON
#define NR ${nr}                              /* rows of an interval end's residual */
#define NA ${na}                              /* rows of the soft state limits a sample on (0: none) */
#define NB ${blocks}                          /* HPIPM's stages after partial condensing (NH: none) */
static const double W_TAU = ${w_tau};       /* the torque's weight */
static const double SHIFT = ${shift};       /* the sample, in intervals: how far the plan moves */

typedef struct {
  struct d_ocp_qp_dim dim, bdim;          /* the intervals' QP; the blocks' (partially condensed) */
  struct d_ocp_qp qp, bqp;
  struct d_ocp_qp_sol sol, bsol;
  struct d_part_cond_qp_arg carg;
  struct d_part_cond_qp_ws cws;
  struct d_ocp_qp_ipm_arg arg;            /* the interior-point method on the blocks' QP */
  struct d_ocp_qp_ipm_ws ws;
  int block_size[NH + 1];
} hpipm_t;

#define FITS(size) if (p + (size) > end) return NULL

static char *aligned(char *p) { return (char *)(((uintptr_t)p + 63) & ~(uintptr_t)63); }

/* HPIPM's structures in c->qp_memory (placed once per controller address), or NULL if they do not fit */
static hpipm_t *qp_structures(${sym}_t *c) {
  char *p = aligned((char *)c->qp_memory), *end = (char *)c->qp_memory + sizeof(c->qp_memory);
  hpipm_t *h = (hpipm_t *)p;
  if (c->qp_owner == c) return h;
  int nx[NH + 1], nu[NH + 1], nbx[NH + 1], nbu[NH + 1], zero[NH + 1], idx[NU];
  for (int k = 0; k <= NH; ++k) {
    nx[k] = k == 0 ? 0 : NX;              /* x_0 is the measurement: eliminated into stage 0's b and r */
    nu[k] = k < NH ? NU : 0;
    nbx[k] = 0;
    nbu[k] = nu[k];
    zero[k] = 0;
  }
  p = aligned(p + sizeof(hpipm_t));
  FITS(d_ocp_qp_dim_memsize(NH));
  d_ocp_qp_dim_create(NH, &h->dim, p);
  p = aligned(p + d_ocp_qp_dim_memsize(NH));
  d_ocp_qp_dim_set_all(nx, nu, nbx, nbu, zero, zero, &h->dim);
  FITS(d_ocp_qp_memsize(&h->dim));
  d_ocp_qp_create(&h->dim, &h->qp, p);
  p = aligned(p + d_ocp_qp_memsize(&h->dim));
  FITS(d_ocp_qp_sol_memsize(&h->dim));
  d_ocp_qp_sol_create(&h->dim, &h->sol, p);
  p = aligned(p + d_ocp_qp_sol_memsize(&h->dim));
  FITS(d_ocp_qp_dim_memsize(NB));         /* the blocks: NH / NB intervals each, their torques stacked */
  d_ocp_qp_dim_create(NB, &h->bdim, p);
  p = aligned(p + d_ocp_qp_dim_memsize(NB));
  d_part_cond_qp_compute_block_size(NH, NB, h->block_size);
  d_part_cond_qp_compute_dim(&h->dim, h->block_size, &h->bdim);
  FITS(d_ocp_qp_memsize(&h->bdim));
  d_ocp_qp_create(&h->bdim, &h->bqp, p);
  p = aligned(p + d_ocp_qp_memsize(&h->bdim));
  FITS(d_ocp_qp_sol_memsize(&h->bdim));
  d_ocp_qp_sol_create(&h->bdim, &h->bsol, p);
  p = aligned(p + d_ocp_qp_sol_memsize(&h->bdim));
  FITS(d_part_cond_qp_arg_memsize(NB));
  d_part_cond_qp_arg_create(NB, &h->carg, p);
  p = aligned(p + d_part_cond_qp_arg_memsize(NB));
  d_part_cond_qp_arg_set_default(&h->carg);
  FITS(d_part_cond_qp_ws_memsize(&h->dim, h->block_size, &h->bdim, &h->carg));
  d_part_cond_qp_ws_create(&h->dim, h->block_size, &h->bdim, &h->carg, &h->cws, p);
  p = aligned(p + d_part_cond_qp_ws_memsize(&h->dim, h->block_size, &h->bdim, &h->carg));
  FITS(d_ocp_qp_ipm_arg_memsize(&h->bdim));
  d_ocp_qp_ipm_arg_create(&h->bdim, &h->arg, p);
  p = aligned(p + d_ocp_qp_ipm_arg_memsize(&h->bdim));
  d_ocp_qp_ipm_arg_set_default(SPEED, &h->arg);
  int iter_max = ${qp_iterations}, warm = 0;
  d_ocp_qp_ipm_arg_set_iter_max(&iter_max, &h->arg);    /* SPEED's tolerances: stationarity 1e-6, the rest 1e-8 */
  d_ocp_qp_ipm_arg_set_warm_start(&warm, &h->arg);
  FITS(d_ocp_qp_ipm_ws_memsize(&h->bdim, &h->arg));
  d_ocp_qp_ipm_ws_create(&h->bdim, &h->arg, &h->ws, p);
  for (int i = 0; i < NU; ++i) idx[i] = i;
  for (int k = 0; k < NH; ++k) d_ocp_qp_set_idxbu(k, idx, &h->qp);
  c->qp_owner = c;
  return h;
}

/* products on column-major arrays, the rows innermost (they vectorise) */
/* out (m x n) = A B, A (m x r), B (r x n) */
static void a_b(const double *A, const double *B, int m, int r, int n, double *out) {
  for (int j = 0; j < n; ++j) {
    for (int i = 0; i < m; ++i) out[i + m * j] = 0.0;
    for (int l = 0; l < r; ++l) {
      const double b = B[l + r * j];
      for (int i = 0; i < m; ++i) out[i + m * j] += A[i + m * l] * b;
    }
  }
}

/* out (m x n) = X Y', X (m x l), Y (n x l) */
static void a_bt(const double *X, const double *Y, int m, int n, int l, double *out) {
  for (int j = 0; j < m * n; ++j) out[j] = 0.0;
  for (int i = 0; i < l; ++i)
    for (int b = 0; b < n; ++b) {
      const double y = Y[b + n * i];
      for (int a = 0; a < m; ++a) out[a + m * b] += X[a + m * i] * y;
    }
}

/* out (cols x rows) = M' for M (rows x cols) */
static void transpose(const double *M, int rows, int cols, double *out) {
  for (int j = 0; j < cols; ++j)
    for (int i = 0; i < rows; ++i) out[j + cols * i] = M[i + rows * j];
}

/* out (m x NR) = (J M)' for a residual Jacobian J (NR x NX: each row a few states) and M (NX x m)
 * given as Mt = M' (m x NX): column i the rows of M that row i of J picks, J's zeros skipped */
static void residual_through(const double *J, const double *Mt, int m, double *out) {
  for (int i = 0; i < NR; ++i) {
    double *o = out + m * i;
    for (int a = 0; a < m; ++a) o[a] = 0.0;
    for (int l = 0; l < NX; ++l) {
      const double j = J[i + NR * l];
      if (j != 0.0)
        for (int a = 0; a < m; ++a) o[a] += j * Mt[a + m * l];
    }
  }
}

#if NA > 0
/* the soft state limits one sample after x_0 (rscasadi.mpc.formulation.sample_ahead: the state
 * the arm is in at the next torque), linear in (dx_0, du_0) through r + Jx dx_0 + Ju du_0: only
 * the first interval's R, S and r_u */
static int ahead(${sym}_t *c, const double *U, double *R, double *S, double *ru) {
  double r[NA], Jx[NA * NX], Ju[NA * NU], JuT[NU * NA], JxT[NX * NA], RA[NU * NU], SA[NU * NX], rA[NU];
  const casadi_real *arg[${sym}_ahead_SZ_ARG + 1] = {c->X, U, c->params + ${SYM}_NJ};
  casadi_real *res[${sym}_ahead_SZ_RES + 1] = {r, Jx, Ju};
  if (${sym}_ahead(arg, res, IW(c), W(c), 0) != 0) return 1;
  transpose(Ju, NA, NU, JuT);
  transpose(Jx, NA, NX, JxT);
  a_bt(JuT, JuT, NU, NU, NA, RA);
  a_bt(JuT, JxT, NU, NX, NA, SA);
  a_bt(JuT, r, NU, 1, NA, rA);
  for (int i = 0; i < NU * NU; ++i) R[i] += RA[i];
  for (int i = 0; i < NU * NX; ++i) S[i] += SA[i];
  for (int i = 0; i < NU; ++i) ru[i] += rA[i];
  return 0;
}
#endif

/* each interval's step from the plan and its Jacobians (x_{k+1} ~ xn + A dx_k + B du_k), then
 * the gaps e_k the plan's nodes leave, propagated: e_0 = 0, e_{k+1} = A_k e_k + xn_k - X_{k+1} */
#define LIN(c, k) ((c)->lin + (size_t)(k) * (NX + NX * NX + NX * NU))
#define GAP(c, k) ((c)->lin + (size_t)NH * (NX + NX * NX + NX * NU) + (size_t)(k) * NX)

static int linearise(${sym}_t *c, int k) {
  double *xn = LIN(c, k);
  const casadi_real *arg[${sym}_interval_SZ_ARG + 1] = {c->X + NX * k, c->U + NU * k, c->params + ${SYM}_NJ};
  casadi_real *res[${sym}_interval_SZ_RES + 1] = {xn, xn + NX, xn + NX + NX * NX};
  return ${sym}_interval(arg, res, IW(c), W(c), 0) != 0;
}

static void propagate_gaps(${sym}_t *c) {
  double *e = GAP(c, 0);
  for (int i = 0; i < NX; ++i) e[i] = 0.0;
  for (int k = 0; k < NH; ++k) {
    const double *xn = LIN(c, k);
    double *next = GAP(c, k + 1);
    a_b(xn + NX, GAP(c, k), NX, NX, 1, next);
    for (int i = 0; i < NX; ++i) next[i] += xn[i] - c->X[NX * (k + 1) + i];
  }
}

/* one interval's QP into HPIPM: the Gauss-Newton residual at X_{k+1} + e_{k+1}, written in
 * (dx_k, du_k) through dx_{k+1} = A dx_k + B du_k + b (rscasadi.mpc.formulation.stage_functions):
 * with Gx = Jx A and Gu = Jx B + Ju, Q = Gx' Gx, S = Gu' Gx, R = Gu' Gu + w I, q = Gx' r, r_u = Gu' r */
static int riccati_interval(${sym}_t *c, hpipm_t *h, int k, const double *reference) {
  const double *xn = LIN(c, k), *A = xn + NX, *B = A + NX * NX, *at_gap = GAP(c, k + 1);
  double b[NX], Ae[NX], at[NX], r[NR], Jx[NR * NX], Ju[NR * NU], JxAe[NR];
  double At[NX * NX], Bt[NU * NX], GxT[NX * NR], GuT[NU * NR], Q[NX * NX], S[NU * NX], R[NU * NU], q[NX], ru[NU];
  double lo[NU], hi[NU];
  const double *X = c->X + NX * k, *U = c->U + NU * k;
  a_b(A, GAP(c, k), NX, NX, 1, Ae);
  for (int i = 0; i < NX; ++i) {
    b[i] = xn[i] - X[NX + i];             /* the gap to the next node */
    at[i] = X[NX + i] + at_gap[i];
  }
  const casadi_real *arg2[${sym}_residual_SZ_ARG + 1] = {at, U, reference + NROWS * k, c->params};
  casadi_real *res2[${sym}_residual_SZ_RES + 1] = {r, Jx, Ju};
  if (${sym}_residual(arg2, res2, IW(c), W(c), 0) != 0) return ${SYM}_FAILED;
  a_b(Jx, Ae, NR, NX, 1, JxAe);
  for (int i = 0; i < NR; ++i) r[i] -= JxAe[i];     /* r + Jx (dx_{k+1} - e_{k+1}) = r - Jx A e_k + ... */
  transpose(A, NX, NX, At);
  transpose(B, NX, NU, Bt);
  residual_through(Jx, At, NX, GxT);
  residual_through(Jx, Bt, NU, GuT);
  for (int i = 0; i < NR; ++i)
    for (int a = 0; a < NU; ++a) GuT[a + NU * i] += Ju[i + NR * a];
  a_bt(GxT, GxT, NX, NX, NR, Q);
  a_bt(GuT, GxT, NU, NX, NR, S);
  a_bt(GuT, GuT, NU, NU, NR, R);
  a_bt(GxT, r, NX, 1, NR, q);
  a_bt(GuT, r, NU, 1, NR, ru);
  for (int i = 0; i < NU; ++i) {
    R[i + NU * i] += W_TAU;
    ru[i] += W_TAU * U[i];
    lo[i] = -TAU_MAX[i] - U[i];
    hi[i] = TAU_MAX[i] - U[i];
  }
  if (k == 0) {                           /* x_0 = X_0 + dx_0 enters only b_0 and r_0: kept for the feedback */
#if NA > 0
    if (ahead(c, U, R, S, ru)) return ${SYM}_FAILED;
#endif
    double *first = c->first;
    for (int i = 0; i < NX * NX; ++i) first[i] = A[i];
    for (int i = 0; i < NU * NX; ++i) first[NX * NX + i] = S[i];
    for (int i = 0; i < NX; ++i) first[NX * NX + NU * NX + i] = b[i];
    for (int i = 0; i < NU; ++i) first[NX * NX + NU * NX + NX + i] = ru[i];
  } else {
    d_ocp_qp_set_A(k, (double *)A, &h->qp);
    d_ocp_qp_set_Q(k, Q, &h->qp);
    d_ocp_qp_set_S(k, S, &h->qp);
    d_ocp_qp_set_q(k, q, &h->qp);
  }
  d_ocp_qp_set_B(k, (double *)B, &h->qp);
  d_ocp_qp_set_b(k, b, &h->qp);
  d_ocp_qp_set_R(k, R, &h->qp);
  d_ocp_qp_set_r(k, ru, &h->qp);
  d_ocp_qp_set_lbu(k, lo, &h->qp);
  d_ocp_qp_set_ubu(k, hi, &h->qp);
  return 0;
}

/* the blocks' dense QPs from the intervals' (d_part_cond_qp_cond's loop): each block condensed
 * on its own, with its own workspace, so the blocks share the threads.  Block b sees the stages
 * from its first interval on, as HPIPM's loop shows them to d_cond_*; on one thread, or where
 * this HPIPM's routines are not the ones called here (BLOCKS_APART 0), HPIPM's own loop */
#define BLOCKS_APART ${blocks_apart}
static void condense(hpipm_t *h) {
#if ${SYM}_THREADS > 1 && defined(_OPENMP) && BLOCKS_APART
  struct d_ocp_qp *q = &h->qp, *out = &h->bqp;
  int first[NB + 1], s = 0, bad = 0;
  for (int b = 0; b <= NB; ++b) {
    first[b] = s;
    s += h->cws.cond_workspace[b].bs;
  }
  PARALLEL_FOR
  for (int b = 0; b <= NB; ++b) {
    const int o = first[b];
    struct d_ocp_qp_dim dim = *q->dim;
    struct d_ocp_qp stages = *q;
    struct d_cond_qp_arg *arg = h->carg.cond_arg + b;
    struct d_cond_qp_ws *ws = h->cws.cond_workspace + b;
    dim.N = ws->bs;
    dim.nx += o, dim.nu += o, dim.nbx += o, dim.nbu += o, dim.nb += o, dim.ng += o, dim.ns += o;
    dim.nbxe += o, dim.nbue += o, dim.nge += o;
    stages.dim = &dim;
    stages.idxb += o, stages.BAbt += o, stages.b += o, stages.RSQrq += o, stages.rqz += o, stages.DCt += o;
    stages.d += o, stages.d_mask += o, stages.m += o, stages.Z += o, stages.idxs_rev += o, stages.idxe += o;
    stages.diag_H_flag += o;
    d_cond_BAbt(&stages, out->BAbt + b, out->b + b, arg, ws);
    d_cond_RSQrq(&stages, out->RSQrq + b, out->rqz + b, arg, ws);
    d_cond_DCtd(&stages, out->idxb[b], out->DCt + b, out->d + b, out->d_mask + b, out->idxs_rev[b], out->Z + b,
                out->rqz + b, arg, ws);
  }
  (void)bad;
#else
  d_part_cond_qp_cond(&h->qp, &h->bqp, &h->carg, &h->cws);
#endif
}

/* the intervals are independent but for the gaps, a cheap sequential pass between the two loops */
static int riccati_prepare(${sym}_t *c, const double *reference) {
  hpipm_t *h = qp_structures(c);
  if (!h) return ${SYM}_FAILED;
  double zero[NX * NX] = {0.0};
  int bad = 0;
  WATCH_FORKS();
  PARALLEL_FOR
  for (int k = 0; k < NH; ++k) bad |= linearise(c, k);
  if (bad) return ${SYM}_FAILED;
  propagate_gaps(c);
  PARALLEL_FOR
  for (int k = 0; k < NH; ++k) bad |= riccati_interval(c, h, k, reference) != 0;
  if (bad) return ${SYM}_FAILED;
  d_ocp_qp_set_Q(NH, zero, &h->qp);       /* the last node's cost is the last interval's */
  d_ocp_qp_set_q(NH, zero, &h->qp);
  condense(h);                            /* at dx_0 = 0; the feedback moves b_0, r_0 */
  return 0;
}

/* the QP from the measured state; the plan stepped (x_0 the measurement) and shifted by a sample */
static int riccati_feedback(${sym}_t *c, const double *x_measured, double *tau_out) {
  if (c->qp_owner != c) return ${SYM}_NOT_PREPARED;
  hpipm_t *h = qp_structures(c);
  double dx0[NX], v[NX], b0[NX], r0[NU], Xs[NXP], Us[NUP];
  const double *A0 = c->first, *S0 = A0 + NX * NX;
  for (int i = 0; i < NX; ++i) dx0[i] = x_measured[i] - c->X[i];
  a_b(A0, dx0, NX, NX, 1, b0);            /* b_0 + A_0 dx_0, r_0 + S_0 dx_0 */
  a_b(S0, dx0, NU, NX, 1, r0);
  for (int i = 0; i < NX; ++i) b0[i] += S0[NU * NX + i];
  for (int i = 0; i < NU; ++i) r0[i] += S0[NU * NX + NX + i];
  d_ocp_qp_set_b(0, b0, &h->qp);
  d_ocp_qp_set_r(0, r0, &h->qp);
  d_part_cond_qp_cond_rhs(&h->qp, &h->bqp, &h->carg, &h->cws);   /* the vectors only: the matrices are the prepare's */
  d_ocp_qp_ipm_solve(&h->bqp, &h->bsol, &h->arg, &h->ws);
  int status = 0;
  d_ocp_qp_ipm_get_status(&h->ws, &status);
  if (status == 3) return ${SYM}_NOT_FINITE;   /* HPIPM met NaN */
  d_part_cond_qp_expand_sol(&h->qp, &h->bsol, &h->sol, &h->carg, &h->cws);
  for (int i = 0; i < NX; ++i) Xs[i] = x_measured[i];
  for (int k = 1; k <= NH; ++k) {
    d_ocp_qp_sol_get_x(k, &h->sol, v);
    for (int i = 0; i < NX; ++i) Xs[NX * k + i] = c->X[NX * k + i] + v[i];
  }
  for (int k = 0; k < NH; ++k) {
    d_ocp_qp_sol_get_u(k, &h->sol, v);
    for (int i = 0; i < NU; ++i) {
      const double u = c->U[NU * k + i], du = fmin(fmax(v[i], -TAU_MAX[i] - u), TAU_MAX[i] - u);
      Us[NU * k + i] = u + du;
    }
  }
  for (int i = 0; i < NU; ++i) tau_out[i] = Us[i];
  for (int k = 0; k <= NH; ++k)           /* shifted: (1 - s) Z_k + s Z_{k+1}, the last node held */
    for (int i = 0; i < NX; ++i)
      c->X_next[NX * k + i] = (1 - SHIFT) * Xs[NX * k + i] + SHIFT * Xs[NX * (k < NH ? k + 1 : NH) + i];
  for (int k = 0; k < NH; ++k)
    for (int i = 0; i < NU; ++i)
      c->U_next[NU * k + i] = (1 - SHIFT) * Us[NU * k + i] + SHIFT * Us[NU * (k < NH - 1 ? k + 1 : NH - 1) + i];
  return 0;
}
#endif

int ${sym}_prepare(${sym}_t *c, const double *reference) {
  if (!c || c->ready != RSCASADI_READY) return ${SYM}_NOT_INITIALISED;
  int code = reference_ok(reference) ? 0 : ${SYM}_BAD_REFERENCE;
#if ${SYM}_RICCATI
  if (!code) code = riccati_prepare(c, reference);
#elif ${SYM}_SPLIT
  if (!code) {
    const casadi_real *arg[${sym}_rti_prepare_SZ_ARG + 1] = {reference, c->X, c->U, c->params};
    casadi_real *res[${sym}_rti_prepare_SZ_RES + 1];
    for (int i = 0; i < NPREPARED; ++i) res[i] = c->prep + PREP_OFF[i];
    if (${sym}_rti_prepare(arg, res, IW(c), W(c), 0) != 0) code = ${SYM}_FAILED;
    else if (!finite_all(c->prep, PREP_OFF[NPREPARED])) code = ${SYM}_NOT_FINITE;
  }
#else
  if (!code)
    for (int i = 0; i < ${SYM}_NREF; ++i) c->reference[i] = reference[i];
#endif
  c->prepared = code ? code : RSCASADI_READY;
  return code;
}

static int feedback(${sym}_t *c, const double *x_measured, double *tau_out) {
  if (!c || c->ready != RSCASADI_READY) {
    rscasadi_zero(tau_out, ${SYM}_NU);
    return ${SYM}_NOT_INITIALISED;
  }
  if (!rscasadi_within(x_measured, X_LO, X_HI, ${SYM}_NX)) return refuse(c, tau_out, ${SYM}_BAD_MEASUREMENT);
  for (int i = 0; i < ${SYM}_NX; ++i) c->x_good[i] = x_measured[i];
  int code = c->prepared == RSCASADI_READY ? 0 : (c->prepared ? c->prepared : ${SYM}_NOT_PREPARED);
  c->prepared = 0;                        /* a preparation serves one feedback */
  if (code == ${SYM}_BAD_REFERENCE || code == ${SYM}_NOT_PREPARED) return refuse(c, tau_out, code);
  if (!code) {
#if ${SYM}_RICCATI
    code = riccati_feedback(c, x_measured, tau_out);
#elif ${SYM}_SPLIT
    const casadi_real *arg[${sym}_rti_feedback_SZ_ARG + 1] = {x_measured, c->X, c->U};
    for (int i = 0; i < NPREPARED; ++i) arg[3 + i] = c->prep + PREP_OFF[i];
    casadi_real *res[${sym}_rti_feedback_SZ_RES + 1] = {tau_out, c->X_next, c->U_next};
    code = ${sym}_rti_feedback(arg, res, IW(c), W(c), 0) != 0 ? ${SYM}_FAILED : 0;
#else
    const casadi_real *arg[${sym}_rti_SZ_ARG + 1] = {x_measured, c->reference, c->X, c->U, c->params};
    casadi_real *res[${sym}_rti_SZ_RES + 1] = {tau_out, c->X_next, c->U_next};
    code = ${sym}_rti(arg, res, IW(c), W(c), 0) != 0 ? ${SYM}_FAILED : 0;
#endif
  }
  if (!code && !(finite_all(c->X_next, NXP) && finite_all(c->U_next, NUP) && finite_all(tau_out, ${SYM}_NU)))
    code = ${SYM}_NOT_FINITE;
  if (code) {                             /* the plan restarts from the arm held here */
    refuse(c, tau_out, code);
    if (hold(c, x_measured, c->X, c->U) != 0) c->ready = 0;
    return code;
  }
  for (int i = 0; i < NXP; ++i) c->X[i] = c->X_next[i];
  for (int i = 0; i < NUP; ++i) c->U[i] = c->U_next[i];
  rscasadi_clamp(tau_out, TAU_MAX, ${SYM}_NU);
  return 0;
}

int ${sym}_feedback(${sym}_t *c, const double *x_measured, double *tau_out) {
  if (!tau_out) return ${SYM}_BAD_ARGUMENT;
  const double t0 = rscasadi_now();
  const int flag = feedback(c, x_measured, tau_out);
  if (c) c->last_feedback_seconds = rscasadi_now() - t0;
  return flag;
}

int ${sym}_step(${sym}_t *c, const double *x_measured, const double *reference, double *tau_out) {
  if (!tau_out) return ${SYM}_BAD_ARGUMENT;
  const double t0 = rscasadi_now();
  ${sym}_prepare(c, reference);           /* its code, if any, is the feedback's */
  const int flag = ${sym}_feedback(c, x_measured, tau_out);
  if (c) c->last_step_seconds = rscasadi_now() - t0;
  return flag;
}

/* the target held over the horizon at rest: joint space theta (n) and zero speeds; task space,
 * per frame, p (3), zero velocity, and R (9, column-major) when the rotation is followed */
int ${sym}_step_to(${sym}_t *c, const double *x_measured, const double *target, double *tau_out) {
  if (!tau_out) return ${SYM}_BAD_ARGUMENT;
  if (!c) {
    rscasadi_zero(tau_out, ${SYM}_NU);
    return ${SYM}_NOT_INITIALISED;
  }
  if (!target) return ${sym}_step(c, x_measured, NULL, tau_out);
  for (int k = 0; k < ${SYM}_HORIZON; ++k) {
    double *col = c->target_reference + NROWS * k;
    for (int i = 0; i < NROWS; ++i) col[i] = 0.0;
    if (${SYM}_TASK_SPACE) {
      const int block = NROWS / ${SYM}_NFRAMES, given = ${SYM}_NTARGET / ${SYM}_NFRAMES;
      for (int f = 0; f < ${SYM}_NFRAMES; ++f) {
        for (int i = 0; i < 3; ++i) col[block * f + i] = target[given * f + i];
        for (int i = 0; i < block - 6; ++i) col[block * f + 6 + i] = target[given * f + 3 + i];
      }
    } else {
      for (int i = 0; i < ${SYM}_NJ; ++i) col[i] = target[i];
    }
  }
  return ${sym}_step(c, x_measured, c->target_reference, tau_out);
}
