/* The condensing kernel (rscasadi/ocp/condensing.py): after CasADi's generated functions and the
   problem's sizes and index arrays; @SITES@ is where the call sites' evaluations go. */
/* Per thread: the SX functions' work arrays and, per interval, the last solution.  Nothing in
   the result depends on the cache beyond Newton's tolerance: it only chooses the starting point
   and skips the solve when the inputs are bitwise those of the last call. */
/* the dense loops vectorised even when the generated SX code around them is built at -O1
   (its size makes -O2 cost minutes) */
#if defined(__GNUC__) && !defined(__clang__)
#define DENSE __attribute__((optimize("O3")))
#else
#define DENSE
#endif
typedef struct { long generation; int seen, valid, factored, derived; casadi_real key[NKEY]; casadi_real y[NY];
                 casadi_real lu[NY * NY]; int piv[NY]; casadi_real S[NY * NS], Gs[NY * NS];
                 casadi_real Y[NYALL], F[NFALL], Fy[NFY]; } entry_t;     /* the call sites at the last linearisation */
static long generation = 1;            /* reset() starts a new one: every thread's entries go stale */
static __thread entry_t* cache = 0;
static __thread long cache_size = 0;
/* the thread's arrays are read through local pointers taken once (OPAQUE): in a shared library
   each access to a __thread variable is a call (__tls_get_addr), which gcc otherwise repeats in
   every pass of a loop (2.5 % of the Panda's minimum-time solve) */
static inline void* opaque_(void* p) { __asm__("" : "+r"(p)); return p; }
#define OPAQUE(p) opaque_((void*)(p))
static __thread const casadi_real* tls_w_arg[SZ_ARG];
static __thread casadi_real* tls_w_res[SZ_RES];
static __thread casadi_int tls_w_iw[SZ_IW];
static __thread casadi_real tls_w_w[SZ_W];
static __thread casadi_real tls_zf[NZ];

static entry_t* entry(long k) {
  if (k < 0) return 0;
  if (k >= cache_size) {
    long size = k + 1 > 2 * cache_size ? k + 1 : 2 * cache_size;
    entry_t* grown = (entry_t*)realloc(cache, (size_t)size * sizeof(entry_t));
    if (!grown) return 0;
    memset(grown + cache_size, 0, (size_t)(size - cache_size) * sizeof(entry_t));
    cache = grown;
    cache_size = size;
  }
  return cache + k;
}

/* LU with partial pivoting of the dense column-major n x n matrix a, in place. */
DENSE static int lu_factor(casadi_real* a, int* piv, int n) {
  int i, j, k;
  for (k = 0; k < n; ++k) {
    int p = k;
    casadi_real big = fabs(a[k + k * n]);
    for (i = k + 1; i < n; ++i) if (fabs(a[i + k * n]) > big) { big = fabs(a[i + k * n]); p = i; }
    if (!(big > 0)) return 1;
    piv[k] = p;
    if (p != k) for (j = 0; j < n; ++j) { casadi_real t = a[k + j * n]; a[k + j * n] = a[p + j * n]; a[p + j * n] = t; }
    for (i = k + 1; i < n; ++i) a[i + k * n] /= a[k + k * n];
    for (j = k + 1; j < n; ++j) {
      casadi_real akj = a[k + j * n];
      if (akj != 0) for (i = k + 1; i < n; ++i) a[i + j * n] -= a[i + k * n] * akj;
    }
  }
  return 0;
}

/* C += alpha A B, column-major (A m x k, B k x n): blocks of 12 x 4 and 4 x 4 held in registers
   as 4-wide vectors (three loads and four broadcasts per twelve multiply-adds), scalar at the
   edges.  Why: loops over one output column at a time wait on loads and stores; at the Panda's
   sizes Z' H Z takes 7.4 us so against 12.9 us (2-core Xeon VM, 2026-11-28). */
#if defined(__GNUC__)
typedef casadi_real v4_t __attribute__((vector_size(32)));
typedef casadi_real v4u_t __attribute__((vector_size(32), aligned(sizeof(casadi_real))));
#define V4(p) (*(const v4u_t*)(p))
#define V4_ADD(p, v) (*(v4u_t*)(p) = V4(p) + (v))
#define BCAST(x) ((v4_t){(x), (x), (x), (x)})
#endif
DENSE static void gemm_nn(int m, int n, int k, casadi_real alpha, const casadi_real* A, int lda,
                          const casadi_real* B, int ldb, casadi_real* C, int ldc) {
  int i = 0, j = 0, p, jj;
#if defined(__GNUC__)
  for (j = 0; j + 4 <= n; j += 4) {
    const casadi_real *b0 = B + j * ldb, *b1 = b0 + ldb, *b2 = b1 + ldb, *b3 = b2 + ldb;
    for (i = 0; i + 12 <= m; i += 12) {
      v4_t c[4][3] = {{{0}}};
      casadi_real* o = C + i + j * ldc;
      for (p = 0; p < k; ++p) {
        const casadi_real* a = A + i + p * lda;
        const v4_t a0 = V4(a), a1 = V4(a + 4), a2 = V4(a + 8);
        v4_t b = BCAST(b0[p]);
        c[0][0] += a0 * b; c[0][1] += a1 * b; c[0][2] += a2 * b;
        b = BCAST(b1[p]); c[1][0] += a0 * b; c[1][1] += a1 * b; c[1][2] += a2 * b;
        b = BCAST(b2[p]); c[2][0] += a0 * b; c[2][1] += a1 * b; c[2][2] += a2 * b;
        b = BCAST(b3[p]); c[3][0] += a0 * b; c[3][1] += a1 * b; c[3][2] += a2 * b;
      }
      for (jj = 0; jj < 4; ++jj, o += ldc) { V4_ADD(o, alpha * c[jj][0]); V4_ADD(o + 4, alpha * c[jj][1]); V4_ADD(o + 8, alpha * c[jj][2]); }
    }
    for (; i + 4 <= m; i += 4) {
      v4_t c[4] = {{0}};
      casadi_real* o = C + i + j * ldc;
      for (p = 0; p < k; ++p) {
        const v4_t a0 = V4(A + i + p * lda);
        c[0] += a0 * BCAST(b0[p]); c[1] += a0 * BCAST(b1[p]); c[2] += a0 * BCAST(b2[p]); c[3] += a0 * BCAST(b3[p]);
      }
      for (jj = 0; jj < 4; ++jj, o += ldc) V4_ADD(o, alpha * c[jj]);
    }
    for (; i < m; ++i) for (jj = j; jj < j + 4; ++jj) {
      casadi_real s = 0;
      for (p = 0; p < k; ++p) s += A[i + p * lda] * B[p + jj * ldb];
      C[i + jj * ldc] += alpha * s;
    }
  }
#endif
  for (; j < n; ++j) for (i = 0; i < m; ++i) {
    casadi_real s = 0;
    for (p = 0; p < k; ++p) s += A[i + p * lda] * B[p + j * ldb];
    C[i + j * ldc] += alpha * s;
  }
}

/* x := A^{-1} x (trans = 0) or A^{-T} x (trans = 1) with the factors of lu_factor. */
DENSE static void lu_solve(const casadi_real* a, const int* piv, int n, casadi_real* x, int trans) {
  int i, j;
  if (!trans) {
    for (i = 0; i < n; ++i) if (piv[i] != i) { casadi_real t = x[i]; x[i] = x[piv[i]]; x[piv[i]] = t; }
    for (j = 0; j < n; ++j) for (i = j + 1; i < n; ++i) x[i] -= a[i + j * n] * x[j];
    for (j = n - 1; j >= 0; --j) { x[j] /= a[j + j * n]; for (i = 0; i < j; ++i) x[i] -= a[i + j * n] * x[j]; }
  } else {
    for (j = 0; j < n; ++j) { for (i = 0; i < j; ++i) x[j] -= a[i + j * n] * x[i]; x[j] /= a[j + j * n]; }
    for (j = n - 1; j >= 0; --j) for (i = j + 1; i < n; ++i) x[j] -= a[i + j * n] * x[i];
    for (i = n - 1; i >= 0; --i) if (piv[i] != i) { casadi_real t = x[i]; x[i] = x[piv[i]]; x[piv[i]] = t; }
  }
}

/* S := -G_y^{-1} Gs (NY x NS, column-major) with the factors of lu_factor: rows of a row-major
   copy updated as vectors (the NS right-hand sides at once) */
DENSE static void sensitivities(const casadi_real* a, const int* piv, const casadi_real* Gs, casadi_real* S) {
  casadi_real T[NY][NS], t;
  int i, j, c;
  for (i = 0; i < NY; ++i) for (c = 0; c < NS; ++c) T[i][c] = -Gs[i + c * NY];
  for (i = 0; i < NY; ++i) if (piv[i] != i) for (c = 0; c < NS; ++c) { t = T[i][c]; T[i][c] = T[piv[i]][c]; T[piv[i]][c] = t; }
  for (j = 0; j < NY; ++j) for (i = j + 1; i < NY; ++i) {
    casadi_real l = a[i + j * NY];
    if (l != 0) for (c = 0; c < NS; ++c) T[i][c] -= l * T[j][c];
  }
  for (j = NY - 1; j >= 0; --j) {
    casadi_real d = 1 / a[j + j * NY];
    for (c = 0; c < NS; ++c) T[j][c] *= d;
    for (i = 0; i < j; ++i) {
      casadi_real u = a[i + j * NY];
      if (u != 0) for (c = 0; c < NS; ++c) T[i][c] -= u * T[j][c];
    }
  }
  for (i = 0; i < NY; ++i) for (c = 0; c < NS; ++c) S[i + c * NY] = T[i][c];
}

/* the full variables z from the kept w and the entry's y */
static void full_z(const casadi_real* w, const casadi_real* y) {
  casadi_real* zf = OPAQUE(tls_zf);
  int i;
  for (i = 0; i < NK; ++i) zf[KEEP[i]] = w ? w[i] : 0;
  for (i = 0; i < NY; ++i) zf[ELIM[i]] = y[i];
}

/* call an SX function: z, the piece's arguments, then `extra` inputs */
static int call(int (*f)(const casadi_real**, casadi_real**, casadi_int*, casadi_real*, int),
                const casadi_real** args, const casadi_real** extra, int n_extra, casadi_real** res, int n_res) {
  const casadi_real** w_arg = OPAQUE(tls_w_arg);
  casadi_real** w_res = OPAQUE(tls_w_res);
  int i;
  w_arg[0] = OPAQUE(tls_zf);
  for (i = 0; i < NA; ++i) w_arg[1 + i] = args[i];
  for (i = 0; i < n_extra; ++i) w_arg[1 + NA + i] = extra[i];
  for (i = 0; i < SZ_RES; ++i) w_res[i] = i < n_res ? res[i] : 0;          /* outputs not asked for: none */
  return f(w_arg, w_res, tls_w_iw, tls_w_w, 0);
}

/* call a model Function (value or curvature at a call site): two inputs, two outputs */
static int raw(int (*f)(const casadi_real**, casadi_real**, casadi_int*, casadi_real*, int),
               const casadi_real* a0, const casadi_real* a1, casadi_real* r0, casadi_real* r1) {
  const casadi_real** w_arg = OPAQUE(tls_w_arg);
  casadi_real** w_res = OPAQUE(tls_w_res);
  int i;
  for (i = 0; i < SZ_RES; ++i) w_res[i] = 0;
  w_arg[0] = a0; w_arg[1] = a1; w_res[0] = r0; w_res[1] = r1;
  return f(w_arg, w_res, tls_w_iw, tls_w_w, 0);
}
@SITES@

/* the key of a call: the kept variables and the piece's arguments, bitwise */
static void make_key(casadi_real* key, const casadi_real* w, const casadi_real** args) {
  int i, j, off = NK;
  for (i = 0; i < NK; ++i) key[i] = w ? w[i] : 0;
  for (j = 0; j < NA; ++j) { for (i = 0; i < ARGNNZ[j]; ++i) key[off + i] = args[j] ? args[j][i] : 0; off += ARGNNZ[j]; }
}

/* G_y (factored into e->lu) and G_w at (w, e->y); G the residual there */
static int linearise(entry_t* e, const casadi_real* w, const casadi_real** args, casadi_real* G, casadi_real* Gs) {
  const casadi_real* extra[2];
  casadi_real* out[3];
  full_z(w, e->y);
  out[0] = e->Y;                                 /* the call sites' values and Jacobians, kept */
  if (call(P(y), args, 0, 0, out, 1) || site_values(e->Y, e->F, e->Fy)) return 1;
  extra[0] = e->F; extra[1] = e->Fy;
  out[0] = G; out[1] = e->lu; out[2] = Gs;
  if (call(P(lin), args, extra, 2, out, 3)) return 1;
  e->factored = 1;
  return lu_factor(e->lu, e->piv, NY);
}

/* Newton from e->y: steps with the last factors of G_y (a chord method: each step one residual,
   no Jacobian), linearised afresh when there are none or the steps stop shrinking fast; 0 when
   converged */
static int newton(entry_t* e, const casadi_real* w, const casadi_real** args) {
  casadi_real G[NY], Gs[NY * NS];
  casadi_real* out[1];
  casadi_real last = 0;
  int i, it, fresh = 0;
  out[0] = G;
  for (it = 0; it < MAXIT; ++it) {
    casadi_real step = 0, size = 0;
    if (!e->factored || fresh) {
      if (linearise(e, w, args, G, Gs)) { e->factored = 0; return 1; }
      fresh = 0;
    } else {
      full_z(w, e->y);
      if (call(P(residual), args, 0, 0, out, 1)) return 1;
    }
    lu_solve(e->lu, e->piv, NY, G, 0);
    for (i = 0; i < NY; ++i) {
      if (!(fabs(G[i]) < 1e300)) return 1;                          /* not finite */
      e->y[i] -= G[i];
      step = fabs(G[i]) > step ? fabs(G[i]) : step;
      size = fabs(e->y[i]) > size ? fabs(e->y[i]) : size;
    }
    if (step <= STEPTOL * (1 + size)) return 0;
    if (it > 0 && step > 0.25 * last) fresh = 1;                      /* slow contraction: new factors */
    last = step;
  }
  return 1;
}

/* Whether a root has a scaled acceleration no motion within the limits could have. */
static int spurious(const entry_t* e) {
  int i;
  for (i = 0; i < NY; ++i) if (fabs(e->y[i]) > SPURIOUS) return 1;
  return 0;
}

/* The entry of interval k with y solved from G(y; w) = 0 at (w, args), or 0 if Newton failed.
   Start: the last solution moved along its sensitivity S (first order in the change of w); if
   Newton fails from there (a far jump of w), once more from y = 0 with fresh factors. */
static entry_t* solved(const casadi_real* w, const casadi_real** args, long k) {
  casadi_real key[NKEY], dw[NS];
  int i, j, cold;
  entry_t* e = entry(k);
  if (!e) return 0;
  if (e->generation != __atomic_load_n(&generation, __ATOMIC_RELAXED)) {
    e->generation = __atomic_load_n(&generation, __ATOMIC_RELAXED);
    e->seen = e->valid = e->factored = e->derived = 0;
  }
  make_key(key, w, args);
  if (e->valid && !memcmp(key, e->key, sizeof key)) return e;
  cold = !e->seen;
  if (cold) { memset(e->y, 0, sizeof e->y); e->seen = 1; e->factored = 0; }
  else if (e->derived) {                                              /* y += S dw */
    for (j = 0; j < NS; ++j) dw[j] = (w ? w[SCOLS[j]] : 0) - e->key[SCOLS[j]];
    for (j = 0; j < NS; ++j) for (i = 0; i < NY; ++i) e->y[i] += e->S[i + j * NY] * dw[j];
  }
  e->valid = e->derived = 0;
  if (newton(e, w, args) || (!cold && spurious(e))) {              /* from y = 0, with fresh factors */
    memset(e->y, 0, sizeof e->y);
    e->factored = 0;
    if (cold || newton(e, w, args)) { e->seen = 0; return 0; }
  }
  memcpy(e->key, key, sizeof key);
  e->valid = 1;
  return e;
}

/* ... and with G_y factored and S = -G_y^{-1} G_w at that y (for the derivatives) */
static entry_t* derived(const casadi_real* w, const casadi_real** args, long k) {
  casadi_real G[NY];
  entry_t* e = solved(w, args, k);
  if (!e || e->derived) return e;
  if (linearise(e, w, args, G, e->Gs)) return 0;
  sensitivities(e->lu, e->piv, e->Gs, e->S);
  e->derived = 1;
  return e;
}

/* forget every thread's solutions: the next solve starts from scratch, its results independent
   of earlier solves in the process */
CASADI_SYMBOL_EXPORT void P(reset)(void) { __atomic_add_fetch(&generation, 1, __ATOMIC_RELAXED); }

/* Each external returns with the upper halves of the AVX registers clear.  Its callers (fatrop,
   IPOPT, CasADi) are SSE code, which runs many times slower while they are in use, and gcc 12
   with AVX-512 leaves some of this file's functions without the vzeroupper that must end AVX
   code (solved()'s key copied by 512-bit moves). */
#if defined(__AVX__) && defined(__GNUC__)
#define CLEAR_UPPER() __builtin_ia32_vzeroupper()
#else
#define CLEAR_UPPER() ((void)0)
#endif
#define EXTERNAL(name) \
  static int name##_body(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w, int mem); \
  CASADI_SYMBOL_EXPORT int P(name)(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w, \
                                   int mem) { \
    int r = name##_body(arg, res, iw, w, mem); \
    CLEAR_UPPER(); \
    return r; \
  } \
  static int name##_body(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w, int mem)
static long index_of(const casadi_real** arg) { return arg[1 + NA] ? (long)arg[1 + NA][0] : 0; }
/* the externals take CasADi's work arrays and memory, and use their own */
#define UNUSED_WORK (void)iw; (void)w; (void)mem

EXTERNAL(ext_newton) {
  UNUSED_WORK;
  entry_t* e = solved(arg[0], arg + 1, index_of(arg));
  if (!e) return 1;
  if (res[0]) memcpy(res[0], e->y, sizeof e->y);
  return 0;
}

EXTERNAL(ext_rows) {
  UNUSED_WORK;
  entry_t* e = solved(arg[0], arg + 1, index_of(arg));
  if (!e) return 1;
  full_z(arg[0], e->y);
  return call(P(rows), arg + 1, 0, 0, res, 2);
}

/* an SX function of (z, args, S) at the solved and derived entry of this call */
static int with_sensitivities(int (*f)(const casadi_real**, casadi_real**, casadi_int*, casadi_real*, int),
                              const casadi_real** arg, casadi_real** res) {
  const casadi_real* extra[1];
  entry_t* e = derived(arg[0], arg + 1, index_of(arg));
  if (!e) return 1;
  full_z(arg[0], e->y);
  extra[0] = e->S;
  return call(f, arg + 1, extra, 1, res, 2);
}

/* J_r Z = J_K + J_E S~ on its pattern (out), column by column of a dense NR x NK block */
DENSE static void condensed_jacobian(const casadi_real* JK, const casadi_real* JE, const casadi_real* S, casadi_real* out) {
  static __thread casadi_real tls_Jd[NR * NK], tls_St[NY * NS];
  casadi_real *Jd = OPAQUE(tls_Jd), *St = OPAQUE(tls_St);
  int i, r, s;
  for (i = 0; i < NY; ++i) for (s = 0; s < NS; ++s) St[s + i * NS] = S[i + s * NY];     /* S by rows */
  memset(Jd, 0, sizeof tls_Jd);
  for (i = 0; i < JK_NNZ; ++i) Jd[JK_ROW[i] + JK_COL[i] * NR] = JK[i];
  for (r = 0; r < NR; ++r) {              /* J_E by rows, all of S's columns at once (independent sums) */
    casadi_real acc[NS];
    if (JE_START[r] == JE_START[r + 1]) continue;
    for (s = 0; s < NS; ++s) acc[s] = 0;
    for (i = JE_START[r]; i < JE_START[r + 1]; ++i) {
      const casadi_real v = JE[JE_ORDER[i]], *Si = St + JE_OCOL[i] * NS;
      for (s = 0; s < NS; ++s) acc[s] += v * Si[s];
    }
    for (s = 0; s < NS; ++s) Jd[r + SCOLS[s] * NR] += acc[s];
  }
  for (i = 0; i < NJP; ++i) out[i] = Jd[JP_ROW[i] + JP_COL[i] * NR];
}

/* the rows and their condensed Jacobian: the rows' Jacobian at the solved point (the call sites'
   values and Jacobians the entry's), then the sparse times dense product */
EXTERNAL(ext_first) {
  static __thread casadi_real JK[NJK], JE[NJE];
  const casadi_real* extra[2];
  casadi_real* out[3];
  entry_t* e = derived(arg[0], arg + 1, index_of(arg));
  UNUSED_WORK;
  if (!e) return 1;
  full_z(arg[0], e->y);
  extra[0] = e->F; extra[1] = e->Fy;
  out[0] = res[0]; out[1] = JK; out[2] = JE;
  if (call(P(jac), arg + 1, extra, 2, out, 3)) return 1;
  if (res[1]) condensed_jacobian(JK, JE, e->S, res[1]);
  return 0;
}

EXTERNAL(ext_objective) {
  UNUSED_WORK;
  return with_sensitivities(P(objective), arg, res);
}

/* the lifted Hessian's blocks at a derived entry: the multipliers mu of the call sites' outputs,
   their curvatures (the sites' values and Jacobians are the entry's), then the glue
   (assembly.SplitHessian) */
static int split_hessian(const entry_t* e, const casadi_real** args, const casadi_real** lam, casadi_real* Hdd,
                         casadi_real* Hyd, casadi_real* Hyy) {
  static __thread casadi_real MU[NFALL], C[NC];
  const casadi_real* extra[5];
  casadi_real* out[3];
  extra[0] = lam[0]; extra[1] = lam[1]; extra[2] = e->F; extra[3] = e->Fy; extra[4] = C;
  out[0] = MU;
  if (call(P(mu), args, extra, 3, out, 1) || site_curvatures(e->Y, MU, C)) return 1;
  out[0] = Hdd; out[1] = Hyd; out[2] = Hyy;
  return call(P(glue), args, extra, 5, out, 3);
}

/* Hc = H_DD + M + M' on the curved columns D, M = S~' (H_YY S~ / 2 + H_YD): Z' H Z with Z = [I; S~],
   S~ = S on D (zero where y does not depend on the column); two dense products */
DENSE static void condensed_hessian(const casadi_real* Hdd, const casadi_real* Hyd, const casadi_real* Hyy,
                              const casadi_real* S, casadi_real* Hc) {
  static __thread casadi_real tls_V[NY * ND], tls_Sd[NY * ND], tls_St[ND * NY], tls_M[ND * ND];
  casadi_real *V = OPAQUE(tls_V), *Sd = OPAQUE(tls_Sd), *St = OPAQUE(tls_St), *M = OPAQUE(tls_M);
  int i, a, b, k;
  for (b = 0; b < ND; ++b)                                     /* S~ */
    for (i = 0; i < NY; ++i) Sd[i + b * NY] = DS[b] < 0 ? 0 : S[i + DS[b] * NY];
  memcpy(V, Hyd, sizeof tls_V);                                /* V = H_YD + H_YY S~ / 2 */
  gemm_nn(NY, ND, NY, 0.5, Hyy, NY, Sd, NY, V, NY);
  for (i = 0; i < NY; ++i) for (a = 0; a < ND; ++a) St[a + i * ND] = Sd[i + a * NY];
  memset(M, 0, sizeof tls_M);                                  /* M = S~' V */
  gemm_nn(ND, ND, NY, 1, St, ND, V, NY, M, ND);
  for (k = 0; k < NHC; ++k) {                                   /* the pattern's entries, in order */
    a = HROW[k]; b = HCOL[k];
    Hc[k] = (a <= b ? Hdd[a + b * ND] : Hdd[b + a * ND]) + M[a + b * ND] + M[b + a * ND];
  }
}

/* the Hessian of lam' R + lam_f f: nu from the adjoint equation, then Z' H(lam, nu) Z */
EXTERNAL(ext_second) {
  static __thread casadi_real Hdd[ND * ND], Hyd[NY * ND], Hyy[NY * NY];
  casadi_real g[NZ], nu[NY], lam[NROWS], zero = 0;
  const casadi_real* extra[3];
  casadi_real* out[3];
  int i, j;
  entry_t* e = derived(arg[0], arg + 1, index_of(arg));
  UNUSED_WORK;
  if (!e) return 1;
  full_z(arg[0], e->y);
  extra[0] = arg[2 + NA];
  extra[1] = arg[3 + NA] ? arg[3 + NA] : &zero;
  out[0] = g;
  if (call(P(adjoint), arg + 1, extra, 2, out, 1)) return 1;
  for (i = 0; i < NY; ++i) nu[i] = -g[ELIM[i]];
  lu_solve(e->lu, e->piv, NY, nu, 1);                        /* nu = -G_y^-T (R_y' lam + lam_f f_y) */
  if (res[0]) {                                              /* grad_w L = its kept part + G_w' nu */
    for (i = 0; i < NK; ++i) res[0][i] = g[KEEP[i]];
    for (j = 0; j < NS; ++j) for (i = 0; i < NY; ++i) res[0][SCOLS[j]] += e->Gs[i + j * NY] * nu[i];
  }
  if (!res[1]) return 0;
  for (i = 0; i < NR; ++i) lam[RKEEP[i]] = arg[2 + NA] ? arg[2 + NA][i] : 0;
  for (i = 0; i < NY; ++i) lam[GROWS[i]] = nu[i];
  extra[0] = lam;
  if (split_hessian(e, arg + 1, extra, Hdd, Hyd, Hyy)) return 1;
  condensed_hessian(Hdd, Hyd, Hyy, e->S, res[1]);
  return 0;
}
